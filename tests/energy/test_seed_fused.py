"""Seed 001's fused (list-free) mode, `jaxrt.rt.FusedEnergy`: per-particle
LJ energies summed during the traversal of the custom AABB (sorted and
not), sphere and double-square methods, under ``jax.jit``, against

* a float64 brute force (every pair by numpy), and
* the energy summed in JAX from the same method's own Dense list
  (``jaxrt.neighbor_list(..., backend=<the same method>)``),

on uniform random points, periodic boxes (unwrapped positions), pairs at
exactly the cutoff and one ulp either side, and coincident particles.

Tolerance (`tolerance`). Per pair, with ``s = sigma^2 / r2`` and unit
roundoff u (2**-24 in float32, 2**-53 in float64): in free space ``r2``
is a sum of three squares of correctly rounded differences (<= 4u
relative); ``s`` adds the division and the rounding of sigma^2 (~6u);
``s^3`` triples it and rounds twice (~20u), ``s^6`` ~41u; so
``U = 4 eps (s^6 - s^3)`` is off by at most ~42u * 4 eps (s^6 + s^3) (the
difference can cancel, so the bound is on the magnitudes, not on |U|).
Summing k terms adds k u times the same magnitudes. Hence, per particle,
``|E_i - E_i(float64)| <= (48 + k_i) u A_i`` with
``A_i = sum_j 4 eps (s^6 + s^3)`` from the oracle: a first-order bound
with ~15% margin, one formula for both precisions. On periodic axes the
displacement is wrapped (jax-md's ``mod`` arithmetic, in the positions'
precision for the custom AABB), so its components carry an absolute error
``delta`` of a few ulp of the side instead: r2 gains ``2 sqrt(3) delta / r``
relatively, U twelve times that, which adds ``42 delta B_i`` with
``B_i = sum_j 4 eps (s^6 + s^3) / r_ij``. Counts must match exactly (a
missing, extra or doubled pair fails there whatever its energy).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax_md import partition, space

import jaxrt
from jaxrt.sim import distributions as scenes
from jaxrt.backends.rt import Bvh, FusedEnergy
from jaxrt.backends.rt.epsilon import ParticlesTooCloseError
from oracle import brute_pairs, list_pairs

pytest.importorskip("warp")

METHODS = ["aabb", "aabb-unsorted", "spheres", "squares"]
DTYPES = [np.float32, np.float64]


@pytest.fixture(params=METHODS)
def method(request):
    return request.param


@pytest.fixture(params=DTYPES, ids=["float32", "float64"])
def dtype(request):
    if request.param == np.float64:
        with jax.enable_x64(True):
            yield request.param
    else:
        yield request.param


def oracle(position, pairs, sigma, epsilon=1.0, r_min=None, side=None):
    """float64 ``(E, A, B, k)``, each ``(N,)``, over the ordered ``pairs``:
    energies, magnitudes ``sum 4 eps (s^6 + s^3)``, the same over ``r_ij``,
    and counts. ``side``: per-axis periodic sides (None or inf: free)."""
    r = np.asarray(position, np.float64)
    n = r.shape[0]
    r_min = 0.1 * sigma if r_min is None else r_min
    e, a, b, k = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n, np.int64)
    if not pairs:
        return e, a, b, k
    i, j = np.array(sorted(pairs)).T
    d = r[i] - r[j]
    if side is not None:
        side = np.broadcast_to(np.asarray(side, np.float64), (r.shape[1],))
        periodic = np.isfinite(side)
        safe = np.where(periodic, side, 1.0)
        d = np.where(periodic, d - safe * np.round(d / safe), d)
    d2 = np.sum(d * d, axis=1)
    r2 = np.maximum(d2, r_min ** 2)
    s3 = (sigma * sigma / r2) ** 3
    np.add.at(e, i, 4.0 * epsilon * (s3 * s3 - s3))
    np.add.at(a, i, 4.0 * epsilon * (s3 * s3 + s3))
    np.add.at(b, i, 4.0 * epsilon * (s3 * s3 + s3) / np.sqrt(r2))
    np.add.at(k, i, 1)
    return e, a, b, k


def tolerance(dtype, magnitude, k, over_r=0.0, side=0.0):
    """The module docstring's bound: ``(48 + k_i) u A_i``, plus
    ``42 delta B_i`` on periodic boxes (``delta = 4 u side``, the largest
    periodic ``side``), plus the smallest normal number (particles without
    pairs)."""
    u = np.finfo(dtype).eps / 2
    delta = 4 * u * side
    return (48 + k) * u * magnitude + 42 * delta * over_r + np.finfo(dtype).tiny


def list_energy(position, idx, sigma, epsilon=1.0, r_min=None, side=None):
    """The study's list path (`benchmarks/seed_rt/worker.py`): U summed
    over each Dense row in JAX, in the positions' dtype."""
    n = position.shape[0]
    r_min = 0.1 * sigma if r_min is None else r_min
    dr = position[:, None, :] - position[jnp.minimum(idx, n - 1)]
    if side is not None:
        dr = dr - side * jnp.round(dr / side)
    r2 = jnp.maximum(jnp.sum(dr * dr, axis=-1), r_min ** 2)
    s6 = (sigma * sigma / r2) ** 3
    return jnp.sum(jnp.where(idx < n, 4.0 * epsilon * (s6 * s6 - s6), 0.0), axis=1)


def method_list(fused: FusedEnergy, position, box, periodic):
    """The same method's Dense list (its own pair test, its own rounding)."""
    if periodic:
        disp, _ = space.periodic(jnp.asarray(box, position.dtype))
    else:
        disp, _ = space.free()
    fns = jaxrt.neighbor_list(disp, box, fused.cutoff, dr_threshold=0.0,
                              format=partition.Dense, backend=fused.options)
    return fns.allocate(position)


def check(method, positions, cutoff, *, sigma, box=1.0, periodic=False,
          expect_pairs=None):
    """Fused energy (jit) == float64 oracle == the method's own list energy,
    within `tolerance`; counts exact. Returns the list's pairs."""
    positions = np.asarray(positions)
    dtype = positions.dtype
    fused = FusedEnergy(method, cutoff=cutoff, sigma=sigma,
                        box=box if periodic else None, periodic=periodic)
    R = jnp.asarray(positions)
    energy, count = jax.jit(fused)(R)
    energy, count = np.asarray(energy), np.asarray(count)
    assert energy.dtype == dtype and count.dtype == np.int32
    assert np.all(np.isfinite(energy))

    nbrs = method_list(fused, R, box, periodic)
    pairs = list_pairs(nbrs)
    if expect_pairs is not None:
        assert pairs == expect_pairs
    side = np.broadcast_to(box, (3,)) if periodic else None
    e64, magnitude, over_r, k = oracle(positions, pairs, sigma, side=side)
    np.testing.assert_array_equal(count, k)
    tol = tolerance(dtype, magnitude, k, over_r, np.max(side) if periodic else 0.0)
    err = np.abs(energy - e64)
    assert np.all(err <= tol), (
        f"{method}: fused energy off the float64 oracle by up to "
        f"{np.max(err / tol):.2f} x the bound (particle {np.argmax(err / tol)})")
    listed = np.asarray(list_energy(R, nbrs.idx, sigma,
                                    side=jnp.asarray(side, dtype) if periodic else None))
    assert np.all(np.abs(listed - e64) <= tol)
    return pairs


def test_uniform_random(method, dtype):
    positions, cutoff = scenes.uniform(beta=8, p=2, seed=3)  # N = 1024, k ~ 8
    positions = positions.astype(dtype)
    expected = brute_pairs(positions, cutoff)
    check(method, positions, cutoff, sigma=0.5 * cutoff, expect_pairs=expected)


def test_dense_random(method):
    """k ~ 130, the study's p = 32 (float32, the study's precision)."""
    positions, cutoff = scenes.uniform(beta=4, p=32, seed=4)  # N = 2048
    positions = positions.astype(np.float32)
    check(method, positions, cutoff, sigma=0.5 * cutoff,
          expect_pairs=brute_pairs(positions, cutoff))


@pytest.mark.parametrize("periodic_axes", [(True, True, True), (True, False, True)])
def test_periodic_unwrapped(method, dtype, periodic_axes):
    """Gamma rays (seed 003 §3.3) in the fused mode too; positions given
    unwrapped are wrapped by the methods."""
    rng = np.random.default_rng(7)
    side = np.array([2.0, 1.5, 1.0])
    inside = rng.random((500, 3)) * side
    shift = rng.integers(-2, 3, size=inside.shape) * side * np.array(periodic_axes)
    cutoff = 0.25
    periodic = periodic_axes
    fused = FusedEnergy(method, cutoff=cutoff, sigma=0.5 * cutoff, box=side,
                        periodic=periodic)
    given = (inside + shift).astype(dtype)
    energy, count = jax.jit(fused)(jnp.asarray(given))
    # The oracle's minimum image of the positions given (exact in float64).
    sides = np.where(periodic_axes, side, np.inf)
    d = given.astype(np.float64)
    d = d[:, None] - d[None]
    d = np.where(periodic_axes, d - side * np.round(d / side), d)
    d2 = np.sum(d * d, axis=-1)
    np.fill_diagonal(d2, np.inf)
    pairs = set(zip(*(x.tolist() for x in np.nonzero(d2 < cutoff ** 2))))
    assert len(pairs) > 500
    e64, magnitude, over_r, k = oracle(given, pairs, 0.5 * cutoff, side=sides)
    np.testing.assert_array_equal(np.asarray(count), k)
    err = np.abs(np.asarray(energy) - e64)
    tol = tolerance(dtype, magnitude, k, over_r, np.max(side))
    assert np.all(err <= tol), np.max(err / tol)
    # The unwrapped positions gave the same as the wrapped ones.
    wrapped = jax.jit(fused)(jnp.asarray(np.where(periodic_axes, given % side, given)
                                         .astype(dtype)))
    np.testing.assert_array_equal(np.asarray(wrapped[1]), k)


def _pairs_at_cutoff(dtype):
    """Isolated pairs at exactly C = 5/16 (exact in binary; strict '<'
    drops them) and at C +- 1 ulp of one coordinate."""
    cutoff = 5 / 16
    offsets = [np.array(v) / 16 for v in ((5, 0, 0), (3, 4, 0), (0, -4, 3), (-3, 0, -4))]
    positions = []
    for k, offset in enumerate(offsets):
        for m, nudge in enumerate((0.0, np.inf, -np.inf)):
            base = np.array([4.0 * k, 4.0 * m, 0.5], dtype) + dtype(1.0)
            other = (base + offset.astype(dtype)).astype(dtype)
            axis = int(np.argmax(np.abs(offset)))
            if nudge:
                other[axis] = np.nextafter(other[axis], dtype(nudge))
            positions += [base, other]
    return np.array(positions, dtype), cutoff


def test_pairs_exactly_at_cutoff_and_one_ulp_either_side(method, dtype):
    positions, cutoff = _pairs_at_cutoff(dtype)
    pairs = check(method, positions, cutoff, sigma=0.5 * cutoff, box=20.0,
                  expect_pairs=brute_pairs(positions, cutoff))
    exact = {(6 * k, 6 * k + 1) for k in range(4)}
    assert not pairs & exact  # the pairs at exactly C carry no energy
    assert len(pairs) >= 4    # some nudged pairs are in, in both directions
    energy, count = jax.jit(FusedEnergy(method, cutoff=cutoff, sigma=0.5 * cutoff))(
        jnp.asarray(positions))
    assert np.all(np.asarray(energy)[::6] == 0) and np.all(np.asarray(count)[::6] == 0)


@pytest.mark.parametrize("method_name", ["aabb", "aabb-unsorted", "squares"])
def test_coincident_particles_are_clamped(method_name, dtype):
    """aabb and squares list coincident particles; their energy is U at
    r_min (sigma / 10), finite and equal to the list path's, never NaN."""
    positions, cutoff = scenes.uniform(beta=4, p=2, seed=9)
    positions = positions.astype(dtype)
    positions[17] = positions[3]
    sigma = 0.5 * cutoff
    pairs = check(method_name, positions, cutoff, sigma=sigma,
                  expect_pairs=brute_pairs(positions, cutoff))
    assert (3, 17) in pairs and (17, 3) in pairs
    energy, _ = jax.jit(FusedEnergy(method_name, cutoff=cutoff, sigma=sigma))(
        jnp.asarray(positions))
    clamped = 4.0 * (1e12 - 1e6)  # U(sigma / 10)
    assert np.asarray(energy)[3] > 0.99 * clamped


def test_coincident_particles_spheres_raise(dtype):
    """The sphere method cannot see pairs closer than its resolution (seed
    Appendix 7): its fused energy raises as its list does, from the jitted
    call, rather than returning an energy without the pair."""
    positions, cutoff = scenes.uniform(beta=4, p=2, seed=9)
    positions = positions.astype(dtype)
    positions[17] = positions[3]
    fused = jax.jit(FusedEnergy("spheres", cutoff=cutoff, sigma=0.5 * cutoff))
    with pytest.raises(Exception, match="ParticlesTooCloseError|closer than"):
        jax.block_until_ready(fused(jnp.asarray(positions)))
    from jaxrt.backends.rt import SpheresMethod
    import warp as wp
    from jaxrt.backends.rt.seed_energy import lj_params
    scalar = wp.float32 if dtype == np.float32 else wp.float64
    vector = wp.vec3 if dtype == np.float32 else wp.vec3d
    n = len(positions)
    with pytest.raises(ParticlesTooCloseError):
        SpheresMethod().energy(
            wp.array(positions, dtype=vector), cutoff=cutoff, side=None,
            periodic=(False,) * 3,
            params=wp.array(lj_params(sigma=0.5 * cutoff, dtype=dtype), dtype=scalar),
            out_energy=wp.zeros(n, dtype=scalar), out_count=wp.zeros(n, dtype=wp.int32))


def test_kept_tree_refit_and_vmap():
    """The custom AABB refits its kept tree between calls (as the "bvh"
    lists) and stays right; vmap keeps systems apart."""
    positions, cutoff = scenes.uniform(beta=6, p=2, seed=5)
    positions = positions.astype(np.float32)
    fused = FusedEnergy(Bvh(), cutoff=cutoff, sigma=0.5 * cutoff)
    step = jax.jit(fused)
    rng = np.random.default_rng(0)
    from jaxrt.backends.rt import ffi
    before = dict(ffi.update_counts)
    for _ in range(3):
        positions = (positions + rng.normal(0, 1e-3 * cutoff, positions.shape)
                     ).astype(np.float32)
        energy, count = step(jnp.asarray(positions))
        pairs = brute_pairs(positions, cutoff)
        e64, magnitude, _, k = oracle(positions, pairs, 0.5 * cutoff)
        np.testing.assert_array_equal(np.asarray(count), k)
        assert np.all(np.abs(np.asarray(energy) - e64)
                      <= tolerance(np.float32, magnitude, k))
    assert ffi.update_counts["refit"] - before.get("refit", 0) >= 2
    two = jnp.stack([jnp.asarray(positions), jnp.asarray(positions[::-1])])
    energies, counts = jax.jit(jax.vmap(fused))(two)
    np.testing.assert_array_equal(np.asarray(counts[1]), np.asarray(counts[0])[::-1])
    np.testing.assert_allclose(np.asarray(energies[1]), np.asarray(energies[0])[::-1],
                               rtol=1e-6)


def test_two_dimensional_positions(method):
    positions = np.random.default_rng(2).random((400, 2)).astype(np.float32)
    cutoff = 0.1
    energy, count = jax.jit(FusedEnergy(method, cutoff=cutoff, sigma=0.05))(
        jnp.asarray(positions))
    padded = np.pad(positions, ((0, 0), (0, 1)))
    e64, magnitude, _, k = oracle(padded, brute_pairs(positions, cutoff), 0.05)
    np.testing.assert_array_equal(np.asarray(count), k)
    assert np.all(np.abs(np.asarray(energy) - e64) <= tolerance(np.float32, magnitude, k))


def test_bad_arguments():
    with pytest.raises(ValueError, match="choose one of"):
        FusedEnergy("cell", cutoff=0.1, sigma=0.05)
    with pytest.raises(TypeError, match="Bvh, Spheres, Squares"):
        FusedEnergy(object(), cutoff=0.1, sigma=0.05)
    with pytest.raises(ValueError, match="cluster_size=1"):
        FusedEnergy(Bvh(cluster_size=4), cutoff=0.1, sigma=0.05)
    with pytest.raises(ValueError, match="sigma"):
        FusedEnergy("aabb", cutoff=0.1, sigma=-1.0)
    with pytest.raises(ValueError, match="r_min"):
        FusedEnergy("aabb", cutoff=0.1, sigma=0.05, r_min=0.0)
    R = jnp.zeros((4, 3), jnp.float32)
    with pytest.raises(ValueError, match="box="):
        FusedEnergy("squares", cutoff=0.1, sigma=0.05, periodic=True)(R)
    with pytest.raises(ValueError, match="below half the periodic box side"):
        FusedEnergy("spheres", cutoff=0.6, sigma=0.05, box=1.0, periodic=True)(R)
    with pytest.raises(ValueError, match=r"\(N, dim\)"):
        FusedEnergy("aabb", cutoff=0.1, sigma=0.05)(jnp.zeros((4, 5)))
