"""`lennard_jones_fused` on the Warp engine (``Cell(kernel="warp")``,
`jaxrt.energy.listfree.warp_cell`) against ``backend="brute"`` in float64
(every pair, the reference arithmetic): energies, forces, pair counts,
sigma / epsilon gradients and radii; periodic, free and slab boxes,
periodic boxes of 2 to 7 cutoffs whose stencils alias, coincident
particles and pairs at the cutoff, ``jit``, ``lax.scan`` and 2D.

The engine runs where JAX runs: Warp's CPU device here, CUDA where JAX's
default backend is a GPU (the GPU hosts' Warp has no CPU compiler).

Tolerances: in float64 both sides add the same pair terms in different
orders (per sorted particle vs per row block), so they agree to a few ulps
of the largest terms: ``rtol = 1e-12`` of the energy and ``1e-10`` of the
largest force (single pairs reach O(1e3) at the closest distances of these
fluids while the sums are O(10)). float32 against the float64 reference:
``rtol = 1e-4`` on energies (sums of ~10^3 terms of mixed sign) and
``2e-3`` of the largest force, as tests/energy/test_fused.py. Pair counts
are integers and equal exactly.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax_md import space
from scenes import GEOMETRIES, fluid

pytest.importorskip("warp")

import jaxrt  # noqa: E402
from jaxrt.energy import lennard_jones_fused, lennard_jones_truncated  # noqa: E402

from jaxrt.energy.listfree.lj import CellSums  # noqa: E402
from lj_cases import check_descent_in_scan_2d, check_sums, close  # noqa: E402

WARP = jaxrt.backends.Cell(kernel="warp")
# The default: cells a quarter of the cutoff along x and half across (a
# 9 x 5 x 5 stencil); COARSE: cells a cutoff wide (3 x 3 x 3).
COARSE = CellSums(kernel="warp", reach=(1, 1))
E_RTOL, F_RTOL = 1e-12, 1e-10


def pair(geometry, side, engine=WARP, **kw):
    displacement, box, periodic = GEOMETRIES[geometry](side)
    return tuple(lennard_jones_fused(displacement, box, backend=b,
                                     periodic=periodic, **kw)
                 for b in (engine, "brute"))


@pytest.mark.parametrize("geometry, engine", [
    ("periodic", WARP), ("free", WARP), ("slab", WARP), ("periodic", COARSE),
    ("free", COARSE)])
def test_matches_brute_float64(x64, geometry, engine):
    R, side = fluid()
    R = jnp.asarray(R)
    warp, brute = pair(geometry, side, engine)
    s, t = warp.sums(R), brute.sums(R)
    assert int(t.count) > 0
    check_sums(s, t, E_RTOL, F_RTOL)
    close(jax.grad(warp)(R), -t.forces, F_RTOL)


def test_float32_within_tolerance(x64):
    R, side = fluid(n_side=7)
    warp, brute = pair("periodic", side)
    R32 = jnp.asarray(R, jnp.float32)
    e, g = jax.value_and_grad(warp)(R32)
    assert e.dtype == g.dtype == jnp.float32
    t = brute.sums(jnp.asarray(R))
    np.testing.assert_allclose(float(e), float(t.energy), rtol=1e-4)
    close(-g, t.forces, 2e-3)


@pytest.mark.parametrize("side_over_cutoff, engine", [
    (2.05, WARP), (2.6, WARP), (3.4, WARP), (7.0, WARP), (2.05, COARSE),
    (2.6, COARSE), (3.4, COARSE)])
def test_small_periodic_boxes_alias_no_pair(x64, side_over_cutoff, engine):
    """One to a few cells per axis: each distinct cell walked once, every
    pair met once from each side (a doubled cell doubles the count)."""
    side = side_over_cutoff * 2.5
    n = max(8, int(0.5 * side ** 3))
    R = jnp.asarray(np.random.default_rng(3).uniform(0, side, (n, 3)))
    warp, brute = pair("periodic", side, engine)
    s, t = warp.sums(R), brute.sums(R)
    assert int(s.count) == int(t.count)
    close(s.energy, t.energy, E_RTOL)
    close(s.forces, t.forces, F_RTOL)


def test_coincident_and_exact_cutoff_pairs(x64):
    side = 10.0
    R = jnp.asarray([[1.0, 1.0, 1.0], [1.0, 1.0, 1.0],   # coincident
                     [5.0, 5.0, 5.0], [7.5, 5.0, 5.0],   # exactly r_cutoff
                     [1.0, 6.0, 6.0], [2.2, 6.0, 6.0],   # inside the switch
                     [9.9, 3.0, 3.0], [0.3, 3.0, 3.0]])  # across the x face
    warp, brute = pair("periodic", side)
    g = jax.grad(warp)(R)
    assert np.all(np.isfinite(g))
    np.testing.assert_array_equal(np.asarray(g[:4]), 0.0)
    assert int(warp.sums(R).count) == int(brute.sums(R).count) == 3
    close(warp(R), brute(R), E_RTOL)
    close(g, jax.grad(brute)(R), F_RTOL)
    r = jnp.asarray(1.2)
    close(g[5, 0], jax.grad(lennard_jones_truncated)(r, r_onset=2.0,
                                                      r_cutoff=2.5), F_RTOL)


def test_jit_scan_and_2d(x64):
    warp, brute, R_end, _, _ = check_descent_in_scan_2d(WARP, E_RTOL)
    close(jax.grad(warp)(R_end), jax.grad(brute)(R_end), F_RTOL)


def test_radii_and_parameter_gradients(x64):
    R, side = fluid(n_side=5, density=0.4)
    R = jnp.asarray(R)
    radii = jnp.asarray(np.random.default_rng(1).uniform(0.8, 2.6, len(R)))
    warp, brute = pair("slab", side, radii=radii)
    close(warp(R), brute(R), E_RTOL)
    close(jax.grad(warp)(R), jax.grad(brute)(R), F_RTOL)
    small = radii * 0.9
    close(warp(R, radii=small), brute(R, radii=small), E_RTOL)
    for name in ("sigma", "epsilon"):
        value = jnp.asarray(0.95 if name == "sigma" else 1.3)
        g = jax.grad(lambda v: warp(R, **{name: v}))(value)
        close(g, jax.grad(lambda v: brute(R, **{name: v}))(value), E_RTOL)


@pytest.mark.parametrize("reach", [(1, 1), (4, 2)])
def test_flat_free_cloud_fits_the_table(x64, reach):
    """A free 3D cloud flat along z (one cell there): the other free axes'
    cells still fit the cell table (the even coarsening alone overflowed
    it, writing past the table), and the sums stay right."""
    from jaxrt.energy.listfree import warp_cell
    from jaxrt.energy.listfree.lj import Params
    rng = np.random.default_rng(4)
    R = np.concatenate([rng.uniform(0, 12, (60, 2)), np.zeros((60, 1))], 1)
    R = jnp.asarray(R)
    params = Params(0.0, 1.0, 1.0, (False,) * 3, (1.0,) * 3, 3)
    _, cells, table = warp_cell.grid(
        R, params, warp_cell.stencil_reach(params, reach))
    assert int(np.prod(np.asarray(cells[:3]))) <= table
    displacement, _ = space.free()
    got, ref = (lennard_jones_fused(displacement, None, backend=b)
                for b in (CellSums(kernel="warp", reach=reach), "brute"))
    close(got(R), ref(R), E_RTOL)
    close(jax.grad(got)(R), jax.grad(ref)(R), F_RTOL)


@pytest.mark.parametrize("geometry, side_over_cutoff", [
    ("periodic", None), ("slab", None), ("free", None), ("periodic", 2.05),
    ("periodic", 3.4), ("periodic", 7.0)])
def test_trimmed_stencil_rows_match_brute_float64(x64, monkeypatch, geometry,
                                                  side_over_cutoff):
    """The walk with each stencil row cut to the sphere it covers
    (`warp_kernels.trim_functions`): the same pairs and sums as the brute
    force, in large periodic boxes, slabs and free clouds (not trimmed on
    free axes) and small periodic boxes (rounded axes, not trimmed)."""
    from jaxrt.backends.cell import warp_kernels
    monkeypatch.setattr(warp_kernels, "TRIM", True)
    if side_over_cutoff is None:
        R, side = fluid()
    else:
        side = side_over_cutoff * 2.5
        n = max(8, int(0.5 * side ** 3))
        R = np.random.default_rng(5).uniform(0, side, (n, 3))
    R = jnp.asarray(R)
    warp, brute = pair(geometry, side)
    s, t = warp.sums(R), brute.sums(R)
    assert int(t.count) > 0
    assert int(s.count) == int(t.count)
    check_sums(s, t, E_RTOL, F_RTOL)
