"""Coincident and nearly coincident particles.

Danger: a zero (or one-ulp) separation turns a distance into 0/0 or its
gradient into sqrt'(0) = inf, or hides a pair from a search that tests
``d > eps``. Every backend must list such pairs as the metric decides
(``0 < cutoff``), and the LJ forces on those lists must stay finite; the
sphere method, which documents a blind zone below 2ε (seed 001,
Appendix 7), must raise its error instead, at ``allocate`` and under
``jit``.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax_md import partition, space

import jaxrt
from jaxrt import energy
from oracle import assert_layout, brute_pairs, expected_pairs, list_pairs
from stability_common import BACKENDS_3D, grid, jax_md_pairs

EXACT = [b for b in BACKENDS_3D if b != "spheres"]
CUTOFF = 1.2


def scene(dtype):
    """60 random particles in a 6-box, then groups at (or next to) one
    point: three exactly coincident (0, 1, 2), one a single ulp away (3),
    one 1e-6 away (4, a float32 separation of a few ulps)."""
    R = np.random.default_rng(0).uniform(0.5, 5.5, (60, 3)).astype(dtype)
    p = R[0].copy()
    R[1] = R[2] = p
    R[3] = p
    R[3, 0] = np.nextafter(p[0], dtype(np.inf))
    R[4] = p + dtype(1e-6)
    return R


@pytest.mark.parametrize(*grid(
    lambda backend, dtype, fmt: (dtype is np.float32 and fmt is partition.Dense
                                and backend != "cell"),
    backend=EXACT, dtype=[np.float32, np.float64],
    fmt=[partition.Dense, partition.Sparse]))
def test_coincident_pairs_are_listed_as_the_metric_decides(backend, dtype,
                                                           fmt, request):
    if dtype is np.float64:
        request.getfixturevalue("x64")
    """Bound: set equality (integers, exact) with jax-md's all-pairs list
    and with the float64 oracle; the five particles at one point form all
    20 ordered pairs (distance <= 1e-6 * sqrt(3) << cutoff, so no rounding
    can decide otherwise)."""
    R = jnp.asarray(scene(dtype))
    disp, _ = space.periodic(6.0)
    nbrs = jaxrt.neighbor_list(disp, 6.0, CUTOFF, format=fmt,
                               backend=backend).allocate(R)
    assert not nbrs.did_buffer_overflow
    assert_layout(nbrs)
    got = list_pairs(nbrs)
    assert {(i, j) for i in range(5) for j in range(5) if i != j} <= got
    assert got == jax_md_pairs(disp, 6.0, CUTOFF, R, fmt)
    assert got == expected_pairs(fmt, brute_pairs(R, CUTOFF, 6.0, True))
    # A jitted update that moves a sixth particle onto the point.
    moved = R.at[5].set(R[0])
    nbrs = jax.jit(nbrs.update)(moved)
    assert not nbrs.did_buffer_overflow or int(nbrs.error.code) == 1
    if not nbrs.did_buffer_overflow:
        assert list_pairs(nbrs) == jax_md_pairs(disp, 6.0, CUTOFF, moved, fmt)


@pytest.mark.skipif("spheres" not in BACKENDS_3D, reason="needs Warp")
def test_spheres_raise_on_coincident_particles_never_a_silent_miss():
    """The sphere method cannot see pairs closer than 2ε (`jaxrt.backends.rt.epsilon`)
    and documents an error: it must come at allocate and under jit, naming
    the pair, never a list that silently lacks it."""
    R = jnp.asarray(scene(np.float32))
    disp, _ = space.periodic(6.0)
    fns = jaxrt.neighbor_list(disp, 6.0, CUTOFF, backend="spheres")
    with pytest.raises(Exception, match=r"particles \d and \d are closer than"):
        fns.allocate(R)
    apart = R.at[1:5].set(R[1:5] + 0.3 * jnp.arange(1, 5)[:, None])
    nbrs = fns.allocate(apart)
    with pytest.raises(Exception, match="closer than .*2ε"):
        jax.block_until_ready(jax.jit(fns.update)(R, nbrs).idx)


@pytest.mark.parametrize(*grid(
    lambda backend, fmt: backend == "bvh" and fmt is partition.Dense,
    backend=EXACT, fmt=[partition.Dense, partition.Sparse]))
def test_lj_forces_stay_finite_at_coincidence(backend, fmt):
    """jaxrt's LJ gives a coincident pair zero energy and zero force (its
    documented rule, the double-where), on every backend's list (Dense
    rows gradient, Sparse autodiff, self pairs and padding included).

    Bounds: forces finite everywhere; on an isolated coincident pair
    exactly 0 (no other particle within the cutoff, so every term is 0).
    A pair at r = 0.05 sigma: (sigma/r)^12 = 4.1e15 and its force
    48 (sigma/r)^13 / sigma = 3.9e18, far below float32's 3.4e38: finite,
    and equal to the closed form.
    """
    disp, _ = space.periodic(12.0)
    base = np.random.default_rng(1).uniform(0.5, 5.5, (40, 3))
    isolated = np.array([[9.0, 9.0, 9.0], [9.0, 9.0, 9.0],
                         [9.0, 3.0, 9.0], [9.05, 3.0, 9.0]])
    R = jnp.asarray(np.concatenate([base, isolated]), jnp.float32)
    mask_self = fmt is partition.Dense  # Sparse: self pairs kept
    if True:
        nbrs = jaxrt.neighbor_list(disp, 12.0, 2.5, format=fmt,
                                   mask_self=mask_self,
                                   backend=backend).allocate(R)
        e_fn = energy.lennard_jones_pair_neighbor_list(
            disp, r_onset=2.0, r_cutoff=2.5)
        e, g = jax.value_and_grad(e_fn)(R, nbrs)
        g = np.asarray(g)
        assert np.isfinite(float(e)) and np.all(np.isfinite(g))
        assert np.all(g[40:42] == 0.0)
        # The close pair: the closed form at the float32 separation
        # (evaluated in float64); rtol 1e-4 = float32 rounding (6e-8) of
        # the ~15 operations of r**-13, with a wide margin.
        r = float(np.float32(9.05) - np.float32(9.0))
        force = 24 * (2 * r ** -13 - r ** -7)
        np.testing.assert_allclose(g[42:44, 0], [force, -force], rtol=1e-4)
        assert np.all(g[42:44, 1:] == 0.0)


def test_lj_overlap_past_float32_range_is_loud_not_hidden():
    """Below r = sigma 10^(-38.53/12) = 6.2e-4 sigma, (sigma/r)^12 overflows
    float32 (max 3.4e38): the energy is +inf (documented), never the
    largest float with a zero force as jax-md's nan_to_num gives."""
    disp, _ = space.free()
    R = jnp.asarray([[1.0, 1.0, 1.0], [1.0 + 1e-4, 1.0, 1.0]], jnp.float32)
    nbrs = jaxrt.neighbor_list(disp, None, 2.5).allocate(R)
    e = energy.lennard_jones_pair_neighbor_list(disp, r_onset=2.0,
                                                r_cutoff=2.5)(R, nbrs)
    assert float(e) == np.inf
