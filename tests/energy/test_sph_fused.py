"""List-free SPH (`jaxrt.energy.listfree.sph`) against the list path
(`jaxrt.energy.sph` on a jax-md all-pairs Dense list: an independent
search, and a tenth of the compile time of a cell list's).

Tolerances: in float64 both paths add the same pair terms in different
orders (per particle along the cell runs vs along the list's rows), so
they agree to a few ulps of the largest terms: ``1e-12`` of the largest
entry on densities, accelerations and gradients (pressure terms of ~10^3
cancel to O(1) sums; the worst seen is ~5e-14).

The default run keeps one case per property; the other geometries and
backends run with ``-m slow``.

``"pallas"`` in the parameter lists is the cell walk as one kernel
(`jaxrt.backends.cell.kernel.pair_sums`): compiled on a GPU, in Pallas'
interpreter elsewhere (small systems: it is slow there). On the GPU,
``-k pallas`` runs them all compiled.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax_md import space

from jaxrt.backends import Cell
from jaxrt.energy import (FusedInputError, HigherOrderError,
                          acceleration_fused, density_fused, sph)
from scenes import slab_displacement
from sph_cases import (EOS, KERNEL, check_coincident_and_exact_support,
                       check_every_input_gradient, check_momentum,
                       check_scan_steps_match_list, close, fluid_state,
                       neighbour_fn)

SLOW = pytest.mark.slow
ON_GPU = jax.default_backend() in ("gpu", "cuda")
WALKS = {"pallas": Cell(kernel="pallas" if ON_GPU else "interpret"),
         "xla": Cell(kernel="xla")}


def pick(backend):
    """A test's backend label -> ``backend=``: "pallas" and "xla" are the
    cell walk as the kernel and as array programs."""
    return WALKS.get(backend, backend)


GEOMETRIES = {
    "periodic": lambda side, dim: (space.periodic(side)[0], side, None),
    "free": lambda side, dim: (space.free()[0], None, None),
    "slab": lambda side, dim: (slab_displacement(side, 1), side,
                               (True,) + (False,) * (dim - 1)),
}


def neighbours(displacement, box, periodic, R, cutoff):
    """jax-md's all-pairs Dense list at R, the reference's."""
    return neighbour_fn(displacement, box, cutoff).allocate(R)


def system(dim, geometry, n_side=None, seed=0):
    n_side = n_side or (11 if dim == 2 else 6)
    if geometry == "slab" and dim == 2:
        n_side = 20  # brute's row blocks: two, the second padded
    R, V, mass, side = fluid_state(n_side, dim, seed=seed)
    return (R, V, mass, *GEOMETRIES[geometry](side, dim))


@pytest.mark.parametrize("dim, geometry, backend", [
    (2, "periodic", "cell"), (2, "slab", "brute"),
    (2, "periodic", "pallas"), pytest.param(3, "slab", "pallas", marks=SLOW),
    pytest.param(2, "free", "pallas", marks=SLOW),
    pytest.param(2, "slab", "pallas", marks=SLOW),
    pytest.param(3, "periodic", "pallas", marks=SLOW),
    pytest.param(3, "free", "pallas", marks=SLOW),
    # 3D free space: test_density_gradients_and_given_pressure.
    pytest.param(3, "free", "cell", marks=SLOW),
    pytest.param(3, "periodic", "cell", marks=SLOW),
    pytest.param(2, "free", "cell", marks=SLOW),
    pytest.param(3, "slab", "cell", marks=SLOW),
    pytest.param(3, "periodic", "brute", marks=SLOW)])
def test_density_and_acceleration_match_list_path(x64, dim, geometry,
                                                  backend):
    R, V, mass, displacement, box, periodic = system(dim, geometry)
    kernel = KERNEL[dim]
    nbrs = neighbours(displacement, box, periodic, R, float(kernel.cutoff))
    kw = dict(mass=mass, alpha=0.5, beta=0.4)
    rho = density_fused(displacement, box, kernel, mass=mass,
                        backend=pick(backend), periodic=periodic)(R)
    assert rho.dtype == jnp.float64 and rho.shape == (len(R),)
    close(rho, jax.jit(sph.density(displacement, kernel, mass=mass))(R, nbrs))
    acc = acceleration_fused(displacement, box, kernel, EOS,
                             backend=pick(backend), periodic=periodic,
                             **kw)(R, V)
    ref = jax.jit(sph.acceleration(displacement, kernel, EOS, **kw))(R, V,
                                                                      nbrs)
    for a, b in zip(acc, ref):
        close(a, b)
    if backend == "pallas":
        # The kernel and the array walk: the same terms, to rounding.
        xla = acceleration_fused(displacement, box, kernel, EOS,
                                 backend=pick("xla"), periodic=periodic,
                                 **kw)(R, V)
        for a, b in zip(acc, xla):
            close(a, b)
    check_momentum(mass, acc)


@pytest.mark.parametrize("dim, backend", [
    (2, "cell"), (2, "pallas"), pytest.param(3, "pallas", marks=SLOW)])
def test_gradients_match_list_path(x64, dim, backend):
    """Every differentiable input at once: positions, velocities, h,
    per-particle masses, alpha, beta and the Tait parameters, through the
    densities into the forces (the kernel: through its VJP walks too)."""
    R, V, mass, displacement, box, periodic = system(
        dim, "periodic", n_side=9 if dim == 2 else 6)
    kernel = KERNEL[dim]
    nbrs = neighbours(displacement, box, periodic, R, float(kernel.cutoff))
    fused = acceleration_fused(displacement, box, kernel, EOS,
                               backend=pick(backend))
    ref = sph.acceleration(displacement, kernel, EOS)
    check_every_input_gradient(fused, ref, nbrs, R, V, mass)


@pytest.mark.parametrize("backend", [
    "cell", pytest.param("pallas", marks=SLOW),
    pytest.param("brute", marks=SLOW)])
def test_density_gradients_and_given_pressure(x64, backend):
    """density_fn's own VJP (R, h, scalar mass), and accel_fn with given
    rho and pressure (their gradients)."""
    R, V, _, displacement, box, periodic = system(3, "free")
    kernel = KERNEL[3]
    nbrs = neighbours(displacement, box, periodic, R, float(kernel.cutoff))
    fused = density_fused(displacement, box, kernel, backend=pick(backend))
    ref = sph.density(displacement, kernel)

    def loss(fn, R, h, m):
        return jnp.sum(jnp.cos(fn(R, h=h, mass=m)))
    g = jax.jit(jax.grad(lambda *a: loss(fused, *a), argnums=(0, 1, 2)))(
        R, 1.25, 1.1)
    g_ref = jax.jit(jax.grad(
        lambda *a: loss(lambda R, **k: ref(R, nbrs, **k), *a),
        argnums=(0, 1, 2)))(R, 1.25, 1.1)
    for x, y in zip(g, g_ref):
        close(x, y)

    accel = acceleration_fused(displacement, box, kernel, EOS,
                               backend=pick(backend))
    accel_ref = sph.acceleration(displacement, kernel, EOS)
    rho = jax.jit(ref)(R, nbrs)
    pressure = jnp.maximum(EOS.pressure(rho), 0)

    def loss2(fn, rho, pressure):
        return jnp.sum(jnp.tanh(fn(rho=rho, pressure=pressure).total))
    g = jax.jit(jax.grad(lambda *a: loss2(lambda **k: accel(R, V, **k), *a),
                         argnums=(0, 1)))(rho, pressure)
    g_ref = jax.jit(jax.grad(
        lambda *a: loss2(lambda **k: accel_ref(R, V, nbrs, **k), *a),
        argnums=(0, 1)))(rho, pressure)
    for x, y in zip(g, g_ref):
        close(x, y)


@pytest.mark.parametrize("backend", ["cell", "pallas",
                                     pytest.param("brute", marks=SLOW)])
def test_coincident_and_exact_support_pairs(x64, backend):
    accel, ref, nbrs, R, V = check_coincident_and_exact_support(
        2, pick(backend))

    def loss(out):
        return jnp.sum(out.total ** 2) + jnp.sum(out.density)
    g = jax.jit(jax.grad(lambda R, V: loss(accel(R, V)), argnums=(0, 1)))(
        R, V)
    g_ref = jax.jit(jax.grad(lambda R, V: loss(ref(R, V, nbrs)),
                             argnums=(0, 1)))(R, V)
    for x, y in zip(g, g_ref):
        assert np.all(np.isfinite(x))
        close(x, y)


def test_jit_scan_steps_match_list_path(x64):
    check_scan_steps_match_list(2, n_side=10)


def test_float32(x64):
    """float32 positions: results in float32, close to the float64 ones."""
    R, V, _, displacement, box, periodic = system(2, "periodic")
    kernel = KERNEL[2]
    accel = acceleration_fused(displacement, box, kernel, EOS)
    out64 = accel(R, V)
    out32 = accel(R.astype(jnp.float32), V.astype(jnp.float32))
    assert out32.pressure.dtype == jnp.float32
    close(out32.density, out64.density, 1e-5)
    close(out32.total, out64.total, 1e-3)


def test_higher_order_raises(x64):
    R, V, _, displacement, box, _ = system(2, "periodic", n_side=6)
    kernel = KERNEL[2]
    density = density_fused(displacement, box, kernel)
    with pytest.raises(HigherOrderError, match="sph.density"):
        jax.hessian(lambda R: jnp.sum(density(R)))(R)
    accel = acceleration_fused(displacement, box, kernel, EOS)
    with pytest.raises(HigherOrderError):
        jax.grad(lambda R: jnp.sum(jax.grad(
            lambda R: jnp.sum(accel(R, V).total))(R) ** 2))(R)


def test_bad_arguments(x64):
    R, V, _, displacement, box, _ = system(2, "periodic", n_side=6)
    kernel = KERNEL[2]
    accel = acceleration_fused(displacement, box, kernel, EOS)
    density = density_fused(displacement, box, kernel)
    with pytest.raises(TypeError, match="'alpah'.*'alpha'"):
        accel(R, V, alpah=0.3)
    with pytest.raises(TypeError, match="masss"):
        density(R, masss=2.0)
    # h above the factory's: the cells would miss pairs.
    with pytest.raises(ValueError, match="larger than the factory"):
        density(R, h=1.5)
    assert np.all(np.isnan(jax.jit(lambda h: density(R, h=h))(1.5)))
    assert np.all(np.isfinite(jax.jit(lambda h: density(R, h=h))(1.2)))
    with pytest.raises(ValueError, match="h must be finite and > 0"):
        density(R, h=-1.0)
    bad = R.at[3, 0].set(jnp.nan)
    with pytest.raises(FusedInputError, match="NaN"):
        accel(bad, V)
    assert np.all(np.isnan(jax.jit(density)(bad)))
    with pytest.raises(ValueError, match="negative"):
        accel(R, V, rho=-jnp.ones(len(R)))
    with pytest.raises(ValueError, match="mass has shape"):
        density(R, mass=jnp.ones(3))
    with pytest.raises(ValueError, match="V has shape"):
        accel(R, V[:-1])
    with pytest.raises(ValueError, match="kernel has dim=2"):
        density(jnp.zeros((4, 3)))
    with pytest.raises(ValueError, match="backend"):
        density_fused(displacement, box, kernel, backend="bvh")
    # The walk: an unknown program, or a name that is not a backend.
    with pytest.raises(ValueError, match=r"kernel='cuda'.*choose one of"):
        density_fused(displacement, box, kernel, backend=Cell(kernel="cuda"))
    with pytest.raises(ValueError, match=r"backend='pallas' is not known.*"
                       r"Cell\(kernel=\.\.\.\)"):
        acceleration_fused(displacement, box, kernel, EOS, backend="pallas")
    with pytest.raises(ValueError, match="radius_classes"):
        density_fused(displacement, box, kernel,
                      backend=Cell(radius_classes=2))
    if not ON_GPU:
        with pytest.raises(ValueError, match="kernel='pallas'.*CUDA"):
            acceleration_fused(displacement, box, kernel, EOS,
                               backend=Cell(kernel="pallas"))
    with pytest.raises(ValueError, match="alpha"):
        acceleration_fused(displacement, box, kernel, EOS, alpha=-1.0)
    with pytest.raises(ValueError, match="half"):
        density_fused(space.periodic(4.0)[0], 4.0, kernel)
    with pytest.raises(ValueError, match="disagrees"):
        density_fused(space.free()[0], box, kernel, periodic=True)


def test_scene_list_free_matches_list():
    """The dam break with ``list_free = true`` on its SPH effects: no
    neighbour list, the same trajectory (float32, 10 steps)."""
    import dataclasses

    from jaxrt import sim
    from jaxrt.sim.builtin import dam_break
    from jaxrt.sim.spec import SceneError
    scene = dam_break(dx=0.1)
    free = dataclasses.replace(scene, effects=tuple(
        dataclasses.replace(e, list_free=True) if e.kind.startswith("sph")
        else e for e in scene.effects))
    runs = []
    for s in (scene, free):
        compiled = sim.compile_scene(s)
        state, nbrs = compiled.init()
        state, nbrs, _ = compiled.chunk(state, nbrs, steps=10)
        runs.append((compiled, state))
    (listed, a), (fused, b) = runs
    assert listed.neighbor_fn is not None and fused.neighbor_fn is None
    assert any("no neighbour list" in line for line in fused.plan)
    close(b.position, a.position, 1e-5)
    close(b.rho, a.rho, 1e-5)
    with pytest.raises(SceneError, match="list_free"):
        dataclasses.replace(scene, effects=tuple(
            dataclasses.replace(e, list_free=True) if e.kind == "sph_density"
            else e for e in scene.effects))


def test_scene_walk_key():
    """sph_density's ``walk``: read from TOML and written back, checked,
    and handed to the list-free factories as ``Cell(kernel=walk)``."""
    import dataclasses

    from jaxrt import sim
    from jaxrt.sim.builtin import dam_break
    from jaxrt.sim.spec import SceneError
    scene = dam_break(dx=0.1)

    def with_density(**kw):
        return dataclasses.replace(scene, effects=tuple(
            dataclasses.replace(e, list_free=True,
                                **(kw if e.kind == "sph_density" else {}))
            if e.kind.startswith("sph") else e for e in scene.effects))
    xla = with_density(walk="xla")
    text = sim.to_toml(xla)
    assert 'walk = "xla"' in text
    assert sim.from_toml(text).effect("sph_density").walk == "xla"
    assert xla.effect("sph_density").walk_backend() == Cell(kernel="xla")
    assert any("walk 'xla'" in line for line in sim.compile_scene(xla).plan)
    with pytest.raises(SceneError, match=r"walk.*one of \['auto'"):
        with_density(walk="cuda")
    with pytest.raises(SceneError, match="walk.*needs list_free"):
        dataclasses.replace(scene, effects=tuple(
            dataclasses.replace(e, walk="xla") if e.kind == "sph_density"
            else e for e in scene.effects))
    if not ON_GPU:
        with pytest.raises(ValueError, match="kernel='pallas'.*CUDA"):
            sim.compile_scene(with_density(walk="pallas"))


@pytest.mark.parametrize("table, wide", [(1000, False), (2 ** 40, True),
                                         (2 ** 40, False)])
def test_sort_by_key_branches(table, wide):
    """`fused.cell_runs`'s sort: key and index packed in 32 bits, in 64
    (x64 on), or the two-operand sort (neither fits)."""
    from jaxrt.energy.listfree.lj import sort_by_key
    key = np.random.default_rng(0).integers(0, 1000, 500).astype(np.int32)
    with jax.enable_x64(wide):
        order, sorted_key = sort_by_key(jnp.asarray(key), table)
    order, sorted_key = np.asarray(order), np.asarray(sorted_key)
    np.testing.assert_array_equal(sorted_key, np.sort(key))
    np.testing.assert_array_equal(key[order], sorted_key)
    np.testing.assert_array_equal(np.sort(order), np.arange(len(key)))


def test_vmap(x64):
    """A batch of configurations: each its own grid and loop length."""
    R = jnp.asarray(np.random.default_rng(0).uniform(0, 8, (3, 50, 2)))
    displacement, _ = space.periodic(8.0)
    density = density_fused(displacement, 8.0, sph.CubicSpline(1.0, dim=2))

    def loss(R):
        return jnp.sum(density(R) ** 2)
    batched = jax.vmap(jax.value_and_grad(loss))(R)
    for b in range(3):
        one = jax.value_and_grad(loss)(R[b])
        close(batched[0][b], one[0])
        close(batched[1][b], one[1])


@pytest.mark.parametrize("dim, dtype", [(2, jnp.float32), (3, jnp.float64)])
def test_kernel_walks_lower_for_cuda(x64, dim, dtype):
    """Density, forces and both VJP walks lower to Triton (four kernels):
    on a CPU too, by exporting for CUDA (no GPU needed to find a primitive
    Pallas' Triton lowering lacks)."""
    from jax import export

    from jaxrt.backends.cell import kernel as _cell_kernel
    if _cell_kernel.pl is None:
        pytest.skip("this JAX has no Pallas Triton backend")
    # Boxes of 4 and 3 supports: the walks add the runs' images on every
    # axis (`test_kernel_walks_take_run_images`).
    R, V, _, displacement, box, periodic = system(
        dim, "periodic", n_side=11 if dim == 2 else 8)
    accel = acceleration_fused(displacement, box, KERNEL[dim], EOS,
                               backend=Cell(kernel="auto"))

    def loss(R, V, h):
        out = accel(R, V, h=h)
        return jnp.sum(out.total ** 2) + jnp.sum(jnp.sin(out.density))
    exported = export.export(
        jax.jit(jax.grad(loss, argnums=(0, 1, 2))), platforms=["cuda"],
        disabled_checks=[export.DisabledSafetyCheck.custom_call(
            "__gpu$xla.gpu.triton")])(R.astype(dtype), V.astype(dtype),
                                      dtype(1.2))
    module = exported.mlir_module()
    assert module.count("xla.gpu.triton") == 4
    assert module.count('name = "jaxrt_cell_pair_sums"') == 4


def test_kernel_walks_take_run_images():
    """Which axes the kernel walks of these tests' systems take the runs'
    images on (`jaxrt.energy.listfree.lj.run_image_axes`; elsewhere they round
    every candidate's difference): all axes of the 2D periodic boxes and
    of the 3D export's, none in the 3D box of 6 (9 cells along x, the
    whole row a run; 2 across, aliased) nor in a slab (its free axes can
    coarsen the grid)."""
    from jaxrt.energy.listfree import lj as fused
    from jaxrt.energy.listfree import sph as sph_fused

    def axes(dim, geometry, n_side):
        R, _, _, displacement, box, periodic = system(dim, geometry, n_side)
        grid, _ = sph_fused._grid(displacement, box, KERNEL[dim], periodic)
        return fused.run_image_axes(grid, len(R))

    assert axes(2, "periodic", 11) == (True, True)
    assert axes(2, "periodic", 9) == (True, True)
    assert axes(3, "periodic", 8) == (True, True, True)
    assert axes(3, "periodic", 6) == (False, False, False)
    assert axes(3, "slab", 6) == (False, False, False)
