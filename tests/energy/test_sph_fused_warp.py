"""List-free SPH on the Warp engine (``Cell(kernel="warp")``,
`jaxrt.backends.cell.warp_sph`) against the list path (`jaxrt.energy.sph`
on jax-md's all-pairs Dense list) and the array cell walk
(``Cell(kernel="xla")``): densities, pressure and viscosity accelerations,
their gradients; periodic, small periodic, free and slab boxes in 3D (and
2D), pairs exactly at the support and coincident particles, ``jit`` and
``lax.scan``.

The engine runs where JAX runs: Warp's CPU device here, CUDA where JAX's
default backend is a GPU.

Tolerances: in float64 the paths add the same pair terms in different
orders (per sorted particle along the Warp grid's rows, per list row, per
jaxrt grid run), and the Warp walk writes the kernel's derivative out
(``f'``) where the others differentiate ``f``, a few ulps apart: ``1e-12``
of the largest entry (pressure terms of ~10^3 cancel to O(1) sums), as
tests/energy/test_sph_fused.py. float32 against float64: ``1e-5`` of the
largest density (sums of ~30 positive terms, relative rounding ~1e-7 per
term) and ``1e-3`` of the largest acceleration (the pressure sums cancel
three orders of magnitude, leaving ~1e-4 relative), test_sph_fused.py's
float32 bounds.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax_md import space

pytest.importorskip("warp")

from jaxrt.backends import Cell  # noqa: E402
from jaxrt.energy import (FusedInputError, acceleration_fused,  # noqa: E402
                          density_fused, sph)
from jaxrt.energy.listfree.lj import CellSums  # noqa: E402
from scenes import slab_displacement  # noqa: E402
from sph_cases import (EOS, KERNEL,  # noqa: E402
                       check_coincident_and_exact_support,
                       check_every_input_gradient, check_momentum,
                       check_scan_steps_match_list, close, fluid_state,
                       loss_of_every_input, neighbour_fn)

WARP = Cell(kernel="warp")
XLA = Cell(kernel="xla")


GEOMETRIES = {
    "periodic": lambda side, dim: (space.periodic(side)[0], side, None),
    "free": lambda side, dim: (space.free()[0], None, None),
    "slab": lambda side, dim: (slab_displacement(side, 2), side,
                               (True, True) + (False,) * (dim - 2)),
}


def system(dim, geometry, n_side, seed=0):
    R, V, mass, side = fluid_state(n_side, dim, seed=seed)
    return (R, V, mass, *GEOMETRIES[geometry](side, dim))


def check_against_references(R, V, mass, displacement, box, periodic,
                             kernel, engine=WARP, **kw):
    """Warp's density and accelerations == the list path's and the array
    walk's (float64, `RTOL`); momentum conserved."""
    nbrs = neighbour_fn(displacement, box, float(kernel.cutoff)).allocate(R)
    rho = density_fused(displacement, box, kernel, mass=mass,
                        backend=engine, periodic=periodic)(R)
    assert rho.dtype == R.dtype and rho.shape == (len(R),)
    close(rho, jax.jit(sph.density(displacement, kernel, mass=mass))(R, nbrs))
    close(rho, density_fused(displacement, box, kernel, mass=mass,
                             backend=XLA, periodic=periodic)(R))
    kw = dict(mass=mass, alpha=0.5, beta=0.4, **kw)
    acc = acceleration_fused(displacement, box, kernel, EOS, backend=engine,
                             periodic=periodic, **kw)(R, V)
    ref = jax.jit(sph.acceleration(displacement, kernel, EOS, **kw))(
        R, V, nbrs)
    xla = acceleration_fused(displacement, box, kernel, EOS, backend=XLA,
                             periodic=periodic, **kw)(R, V)
    for a, b, c in zip(acc, ref, xla):
        assert a.shape == b.shape and a.dtype == R.dtype
        close(a, b)
        close(a, c)
    check_momentum(mass, acc)
    return acc


@pytest.mark.parametrize("dim, geometry", [
    (3, "periodic"), (3, "free"), (3, "slab"), (2, "periodic")])
def test_matches_list_path_and_cell_walk(x64, dim, geometry):
    R, V, mass, displacement, box, periodic = system(
        dim, geometry, n_side=7 if dim == 3 else 12)
    check_against_references(R, V, mass, displacement, box, periodic,
                             KERNEL[dim])


@pytest.mark.parametrize("name", sorted(sph.KERNELS))
def test_every_kernel(x64, name):
    """The kernels' shapes and derivatives, written out in the walk."""
    kernel = sph.kernel(name, 1.1, dim=3)
    n_side = 8 if kernel.support > 2 else 7
    R, V, mass, displacement, box, periodic = system(3, "periodic", n_side,
                                                     seed=3)
    check_against_references(R, V, mass, displacement, box, periodic, kernel)


@pytest.mark.parametrize("n_side, reach", [
    (6, (4, 2)), (6, (1, 1)), (8, (1, 1)), (9, (4, 2))])
def test_small_periodic_boxes(x64, n_side, reach):
    """Boxes of 2.3 to 3.5 supports: stencils that alias cells (rounded
    differences) and ones that wrap with images, both stencil shapes."""
    R, V, mass, displacement, box, periodic = system(3, "periodic", n_side,
                                                     seed=n_side)
    check_against_references(R, V, mass, displacement, box, periodic,
                             KERNEL[3], engine=CellSums(kernel="warp",
                                                        reach=reach))


@pytest.mark.parametrize("dim", [2, 3])
def test_coincident_and_exact_support_pairs(x64, dim):
    check_coincident_and_exact_support(dim, WARP)


def test_periodic_pair_at_the_support_across_the_boundary(x64):
    """A pair exactly one support apart through the periodic boundary
    counts nothing; one just inside counts through its image."""
    kernel = sph.CubicSpline(0.5, dim=3)  # support 1.0
    side = 4.0
    R = jnp.asarray([[0.25, 2.0, 2.0], [3.25, 2.0, 2.0],    # 1.0 apart
                     [0.5, 0.2, 1.0], [0.5, 3.4, 1.0]])     # 0.8 apart
    displacement, _ = space.periodic(side)
    rho = density_fused(displacement, side, kernel, backend=WARP)(R)
    w0, w = kernel.w(jnp.zeros(())), kernel.w(jnp.asarray(0.8))
    close(rho, jnp.asarray([w0, w0, w0 + w, w0 + w]), 1e-12)


def test_gradients_and_traced_keywords(x64):
    """The VJP (the cell walk's, on the same positions) and call-time
    keywords: h below the factory's, masses, alpha, beta, the EOS."""
    R, V, mass, displacement, box, periodic = system(3, "periodic", 6)
    kernel = KERNEL[3]
    nbrs = neighbour_fn(displacement, box, float(kernel.cutoff)).allocate(R)
    fused = acceleration_fused(displacement, box, kernel, EOS, backend=WARP)
    ref = sph.acceleration(displacement, kernel, EOS)
    weights = jnp.asarray(np.random.default_rng(5).normal(size=R.shape))
    args = (R, V, 1.2, mass, 0.5, 0.3, 1.1, 9.0, 7.0)
    close(loss_of_every_input(fused, weights, *args), loss_of_every_input(
        lambda R, V, **k: ref(R, V, nbrs, **k), weights, *args))
    check_every_input_gradient(fused, ref, nbrs, R, V, mass)

    density = density_fused(displacement, box, kernel, backend=WARP)
    dref = sph.density(displacement, kernel)
    g = jax.grad(lambda R, h: jnp.sum(jnp.cos(density(R, h=h))),
                 argnums=(0, 1))(R, 1.25)
    g_ref = jax.grad(lambda R, h: jnp.sum(jnp.cos(dref(R, nbrs, h=h))),
                     argnums=(0, 1))(R, 1.25)
    for x, y in zip(g, g_ref):
        close(x, y)

    # Given densities and pressures skip the density pass and the EOS.
    rho = jax.jit(dref)(R, nbrs)
    pressure = jnp.maximum(EOS.pressure(rho), 0)
    got = fused(R, V, rho=rho, pressure=pressure)
    want = ref(R, V, nbrs, rho=rho, pressure=pressure)
    for a, b in zip(got, want):
        close(a, b)


def test_jit_scan_steps_match_list_path(x64):
    check_scan_steps_match_list(3, n_side=6, backend=WARP)


def test_float32(x64):
    """float32 positions: results in float32, close to the float64 list
    path's (the module docstring's bounds)."""
    R, V, mass, displacement, box, periodic = system(3, "periodic", 7)
    kernel = KERNEL[3]
    nbrs = neighbour_fn(displacement, box, float(kernel.cutoff)).allocate(R)
    ref = jax.jit(sph.acceleration(displacement, kernel, EOS, mass=mass,
                                   alpha=0.5))(R, V, nbrs)
    accel = acceleration_fused(displacement, box, kernel, EOS, mass=mass,
                               alpha=0.5, backend=WARP)
    out32 = jax.jit(accel)(R.astype(jnp.float32), V.astype(jnp.float32))
    assert out32.pressure.dtype == jnp.float32
    close(out32.density, ref.density, 1e-5)
    close(out32.total, ref.total, 1e-3)


def test_bad_positions_raise(x64):
    R, V, mass, displacement, box, periodic = system(3, "periodic", 6)
    accel = acceleration_fused(displacement, box, KERNEL[3], EOS,
                               backend=WARP)
    with pytest.raises(FusedInputError):
        accel(R.at[3, 1].set(jnp.nan), V)
    out = jax.jit(accel)(R.at[3, 1].set(jnp.inf), V)
    assert np.all(np.isnan(np.asarray(out.pressure)))


def test_second_derivatives_raise(x64):
    from jaxrt.energy import HigherOrderError
    R, V, _, displacement, box, periodic = system(3, "periodic", 6)
    accel = acceleration_fused(displacement, box, KERNEL[3], EOS,
                               backend=WARP)

    def loss(R):
        return jnp.sum(accel(R, V).total ** 2)
    with pytest.raises(HigherOrderError):
        jax.hessian(loss)(R[:, :]).block_until_ready()
