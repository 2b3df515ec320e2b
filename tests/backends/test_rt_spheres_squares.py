"""Seed 001's sphere (§4.2) and double-square (§4.3) methods against a
float64 brute force, on random scenes and on the cases their filters are
for: aligned particles, equal y / z / both, equal x, distances at the
cutoff to the ulp, lattices, sphere surfaces, periodic images, particles
closer than ε, overflowing rows."""
from __future__ import annotations

import math

import numpy as np
import pytest
import warp as wp
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from jaxrt.sim import distributions as scenes
from jaxrt.backends.rt.epsilon import (
    EPSILON_RELATIVE,
    ParticlesTooCloseError,
    closest_pair_below,
    pair_below,
    seed_epsilon,
    sphere_resolution,
)
from jaxrt.backends.rt.periodic import CUTOFF_MARGIN
from jaxrt.backends.rt.spheres import SpheresMethod
from jaxrt.backends.rt.squares import SquaresMethod
from oracle import brute_pairs

wp.config.quiet = True

METHODS = {"spheres": SpheresMethod, "squares": SquaresMethod}
DTYPES = {"float32": (np.float32, wp.vec3), "float64": (np.float64, wp.vec3d)}
FREE = (False, False, False)


def find_rows(method, positions, cutoff, *, width=None, periodic=FREE, side=None,
              mask_self=True):
    """Run ``method.find`` on ``positions`` (numpy ``(N, 3)``, float32 or
    float64). Returns the rows as a set of (i, j) pairs and the counts; checks
    the row layout (valid entries first and distinct, then N)."""
    positions = np.asarray(positions)
    n = positions.shape[0]
    vector = wp.vec3 if positions.dtype == np.float32 else wp.vec3d
    if width is None:
        expected = brute_pairs(positions, cutoff, side=side, periodic=periodic,
                               mask_self=mask_self)
        width = 1 + max(np.bincount([i for i, _ in expected], minlength=n), default=0)
    points = wp.array(positions, dtype=vector)
    out_idx = wp.full((n, width), -7, dtype=wp.int32)  # garbage: find must overwrite
    out_count = wp.full(n, -7, dtype=wp.int32)
    method.find(points, cutoff=cutoff, side=side, periodic=periodic,
                mask_self=mask_self, out_idx=out_idx, out_count=out_count)
    rows, counts = out_idx.numpy(), out_count.numpy()
    pairs = set()
    for i in range(n):
        stored = min(counts[i], width)
        valid, rest = rows[i, :stored], rows[i, stored:]
        assert np.all((valid >= 0) & (valid < n)), f"row {i}: {rows[i]}"
        assert len(set(valid.tolist())) == stored, f"row {i} repeats a neighbour: {valid}"
        assert np.all(rest == n), f"row {i} not padded with N: {rows[i]}"
        pairs |= {(i, int(j)) for j in valid}
    return pairs, counts


def assert_exact(method, positions, cutoff, *, periodic=FREE, side=None, mask_self=True):
    """Rows and counts equal the float64 brute force's."""
    positions = np.asarray(positions)
    expected = brute_pairs(positions, cutoff, side=side, periodic=periodic,
                           mask_self=mask_self)
    pairs, counts = find_rows(method, positions, cutoff, periodic=periodic, side=side,
                              mask_self=mask_self)
    missing, extra = expected - pairs, pairs - expected
    assert not missing and not extra, (
        f"{method.name}: {len(missing)} missing, e.g. {sorted(missing)[:4]}; "
        f"{len(extra)} extra, e.g. {sorted(extra)[:4]}")
    n = positions.shape[0]
    np.testing.assert_array_equal(
        counts, np.bincount([i for i, _ in expected], minlength=n).astype(np.int32))
    return pairs


@pytest.fixture(params=sorted(METHODS))
def method(request):
    return METHODS[request.param]()


@pytest.fixture(params=sorted(DTYPES))
def dtype(request):
    return DTYPES[request.param][0]


# ---------------------------------------------------------------------------
# The seed's scenes.


@pytest.mark.parametrize("mask_self", [True, False])
def test_uniform_scene(method, dtype, mask_self):
    positions, cutoff = scenes.uniform(beta=6, p=4, seed=1)  # N = 864
    assert_exact(method, positions.astype(dtype), cutoff, mask_self=mask_self)


def test_sphere_surface_scene(method, dtype):
    positions, cutoff = scenes.sphere_surface(alpha=8, p=2, seed=2)  # N = 1024
    assert_exact(method, positions.astype(dtype), cutoff)


def test_methods_agree_with_each_other(dtype):
    positions, cutoff = scenes.uniform(beta=4, p=8, seed=3)
    positions = positions.astype(dtype)
    spheres, _ = find_rows(SpheresMethod(), positions, cutoff)
    squares, _ = find_rows(SquaresMethod(), positions, cutoff)
    assert spheres == squares


@pytest.mark.parametrize("scene", ["lattice", "disordered", "cluster"])
def test_seed_003_scenes_periodic(method, scene):
    if scene == "lattice":
        positions = scenes.lattice(729, side=9.0)  # spacing 1, at k + 0.5
    elif scene == "disordered":
        positions = scenes.disordered(700, seed=4, side=9.0)
    else:
        positions = scenes.cluster(700, seed=5, side=90.0, sigma=2.0)
    side = 9.0 if scene != "cluster" else 90.0
    assert_exact(method, positions, 1.5, periodic=(True,) * 3, side=(side,) * 3)


# ---------------------------------------------------------------------------
# The filters' hard cases.


@pytest.mark.parametrize("cutoff", [1.0, np.nextafter(1.0, 2.0), math.sqrt(2.0), 1.5, 2.0,
                                    np.nextafter(2.0, 3.0), math.sqrt(3.0)])
def test_lattice_ties_everywhere(method, dtype, cutoff):
    """A cubic lattice: every pair is aligned on an axis or shares y or z,
    and many lie exactly at the cutoff."""
    grid = np.stack(np.meshgrid(*[np.arange(6.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    assert_exact(method, (grid + 0.5).astype(dtype), cutoff)


def test_scaled_lattice_inexact_spacing(method, dtype):
    grid = np.stack(np.meshgrid(*[np.arange(7.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    positions = (0.1 * grid + 0.05).astype(dtype)
    for cutoff in (0.1, 0.1 * math.sqrt(2.0), 0.2, 0.1 * math.sqrt(3.0)):
        assert_exact(method, positions, cutoff)


def _offsets_at_distance_cutoff():
    """Separations of exactly 5/16, 7/16, 3/8, 1/4 (exact in binary), in
    every direction and axis order, with the cutoff equal to their length."""
    cases = []
    for vector, length in (((5, 0, 0), 5), ((3, 4, 0), 5), ((2, 3, 6), 7), ((1, 2, 2), 3),
                           ((0, 0, 4), 4)):
        for permutation in ((0, 1, 2), (1, 2, 0), (2, 0, 1), (1, 0, 2)):
            for signs in ((1, 1, 1), (-1, 1, -1), (1, -1, 1), (-1, -1, -1)):
                offset = np.array([signs[a] * vector[permutation[a]] for a in range(3)]) / 16
                cases.append((offset, length / 16))
    return cases


def test_distance_exactly_cutoff_and_one_ulp_either_side(method, dtype):
    """Pairs at exactly C (not neighbours) and C ± 1 ulp of one coordinate,
    in every direction: one scene per cutoff, each pair far from the others."""
    by_cutoff = {}
    for offset, cutoff in _offsets_at_distance_cutoff():
        by_cutoff.setdefault(cutoff, []).append(offset)
    for cutoff, offsets in by_cutoff.items():
        positions = []
        for k, offset in enumerate(offsets):
            base = np.array([4.0 * (k % 8), 4.0 * (k // 8), 0.5], dtype) + dtype(1.0)
            moved_axis = int(np.argmax(np.abs(offset)))
            for nudge in (0.0, np.inf, -np.inf):
                other = (base + offset.astype(dtype)).astype(dtype)
                if nudge:
                    other[moved_axis] = np.nextafter(other[moved_axis], dtype(nudge))
                positions += [base + dtype(0.0), other]
                base = base + np.array([0.0, 0.0, 2.0], dtype)
        positions = np.array(positions, dtype)
        pairs = assert_exact(method, positions, cutoff)
        # Sanity of the construction: the exact ones are out, some nudged are in.
        assert (0, 1) not in pairs and any((2 * k, 2 * k + 1) in pairs
                                           for k in range(len(positions) // 2))


def test_aligned_and_equal_coordinates(method, dtype):
    """Around each target: sources on its axes (equal y and z), in its
    xy / xz planes (equal z / equal y), with equal x (overlapping squares),
    and x nudged by one ulp so that a ray's two planes are both near."""
    h = 0.25
    offsets = []
    for a in (-3, -2, -1, 1, 2, 3):
        offsets += [(a, 0, 0), (0, a, 0), (0, 0, a)]                   # aligned
        for b in (-2, -1, 1, 2):
            offsets += [(a, b, 0), (a, 0, b), (0, a, b)]               # one equal
    targets = np.array([[1.0, 1.0, 1.0], [5.0, 1.0, 1.0], [1.0, 5.0, 1.0]])
    positions = [targets]
    for t in targets:
        positions.append(t + h * np.array(offsets))
    positions = np.concatenate(positions).astype(dtype)
    nudged = positions.copy()
    nudged[3:, 0] = np.nextafter(nudged[3:, 0], dtype(np.inf))
    for cutoff in (0.3, 0.5, 0.55, 0.75, 0.8):
        assert_exact(method, positions, cutoff)
        assert_exact(method, nudged, cutoff)


def test_equal_x_within_epsilon(method):
    """Sources whose x differs from the target's by 0, ε/2, ε and 2ε: the
    seed's rays would pierce both of their squares (float64: ε ≈ 1e-12)."""
    target = np.array([0.5, 0.5, 0.5])
    cutoff = 0.2
    epsilon = seed_epsilon(max(cutoff, 0.5 + 0.1))
    positions = [target]
    for k, dx in enumerate((0.0, epsilon / 2, epsilon, 2 * epsilon, -epsilon / 2, -epsilon)):
        spread = 1.0 + 0.1 * k  # keeps the sources apart from each other
        for dy, dz in ((0.05, 0.07), (0.0, 0.05), (0.05, 0.0), (-0.1, 0.03), (0.1, -0.1)):
            positions.append(target + np.array([dx, spread * dy, spread * dz]))
    assert_exact(method, np.array(positions), cutoff)


def test_two_dimensional_padded_with_zero(method, dtype):
    rng = np.random.default_rng(6)
    flat = np.concatenate([rng.random((400, 2)), np.zeros((400, 1))], axis=1)
    assert_exact(method, flat.astype(dtype), 0.08)
    grid = np.stack(np.meshgrid(np.arange(12.0), np.arange(12.0), [0.0], indexing="ij"),
                    -1).reshape(-1, 3)
    assert_exact(method, grid.astype(dtype), 1.0)
    assert_exact(method, grid.astype(dtype), 1.5)


COARSE_GRIDS = dict(
    cells=st.lists(st.tuples(*[st.integers(0, 4)] * 3), min_size=2, max_size=40),
    cutoff=st.sampled_from([0.5, 1.0, 1.5, 2.0, math.sqrt(2.0), np.nextafter(1.0, 2.0)]),
    dtype_name=st.sampled_from(sorted(DTYPES)), mask_self=st.booleans())


@settings(max_examples=40, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(**COARSE_GRIDS)
def test_coarse_grid_property(method, cells, cutoff, dtype_name, mask_self):
    check_coarse_grid(method, cells, cutoff, dtype_name, mask_self)


@pytest.mark.slow
@settings(max_examples=1000, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(**COARSE_GRIDS)
def test_coarse_grid_property_many(method, cells, cutoff, dtype_name, mask_self):
    check_coarse_grid(method, cells, cutoff, dtype_name, mask_self)


def check_coarse_grid(method, cells, cutoff, dtype_name, mask_self):
    """Random points on a coarse grid (ties on every axis, duplicates
    allowed): squares are exact; spheres are exact or report the
    duplicates as the ε contract says."""
    positions = (0.5 * np.array(cells, float) + 0.25).astype(DTYPES[dtype_name][0])
    has_duplicates = len(set(cells)) < len(cells)
    if method.name == "spheres" and has_duplicates:
        with pytest.raises(ParticlesTooCloseError):
            find_rows(method, positions, cutoff, mask_self=mask_self)
        return
    assert_exact(method, positions, cutoff, mask_self=mask_self)


# ---------------------------------------------------------------------------
# Periodic boxes (seed 003 §3.3 gamma rays).


@pytest.mark.parametrize("periodic", [(True, True, True), (True, False, True),
                                      (False, True, False)])
def test_periodic_random(method, dtype, periodic):
    rng = np.random.default_rng(7)
    side = (2.0, 1.5, 1.0)
    positions = rng.random((600, 3)) * side
    assert_exact(method, positions.astype(dtype), 0.25, periodic=periodic, side=side)


def test_periodic_faces_and_corners(method, dtype):
    """Particles on the faces, edges and corners of the box: at 0 and one
    ulp below the side, which are one ulp apart through the boundary."""
    side = (4.0, 4.0, 4.0)
    coordinates = [0.0, 0.25, 1.0, 2.0, 3.0, 3.75, np.nextafter(dtype(4.0), dtype(0.0))]
    grid = np.stack(np.meshgrid(*[coordinates] * 3, indexing="ij"), -1).reshape(-1, 3)
    grid = grid.astype(dtype)
    # Half the side itself is refused (the rule of every ray-traced method,
    # `jaxrt.backends.rt.periodic.cutoff_fits`); the largest cutoff it admits is not.
    with pytest.raises(ValueError, match="below half the periodic box side 4 on axis 0"):
        find_rows(method, grid, 2.0, periodic=(True,) * 3, side=side)
    largest = np.nextafter(0.5 * 4.0 * (1.0 - CUTOFF_MARGIN), 0.0)
    for cutoff in (0.25, 0.5, 1.0, largest):
        if method.name == "spheres" and dtype == np.float64:  # 1 ulp < 2ε
            with pytest.raises(ParticlesTooCloseError):
                find_rows(method, grid, cutoff, periodic=(True,) * 3, side=side)
            assert_exact(method, grid[grid.max(axis=1) < 4.0 - 1e-3], cutoff,
                         periodic=(True,) * 3, side=side)
        else:
            assert_exact(method, grid, cutoff, periodic=(True,) * 3, side=side)


def test_periodic_unwrapped_positions(method, dtype):
    """The protocol passes positions unwrapped; the methods wrap them."""
    rng = np.random.default_rng(8)
    side = (1.0, 1.0, 1.0)
    inside = rng.random((400, 3))
    unwrapped = inside + rng.integers(-2, 3, size=(400, 3))
    expected = brute_pairs(inside.astype(dtype), 0.2, side=side, periodic=True)
    pairs, _ = find_rows(method, unwrapped.astype(dtype), 0.2, periodic=(True,) * 3,
                         side=side)
    assert pairs == expected


# ---------------------------------------------------------------------------
# The ε contract.


def test_epsilon_rule():
    assert seed_epsilon(1.0) == EPSILON_RELATIVE == 2.0 ** -40
    assert sphere_resolution(seed_epsilon(3.0)) == 2 * 3.0 * 2.0 ** -40
    method = SpheresMethod()
    positions = np.array([[0.0, 0.0, 0.0], [7.0, -9.0, 1.0]])
    find_rows(method, positions, 2.0)
    assert method.last_survey.scale == 9.0
    assert method.last_survey.epsilon == 9.0 * 2.0 ** -40


def test_coincident_particles(dtype):
    """Spheres report the pair (seed Appendix 7); squares find it."""
    positions, cutoff = scenes.uniform(beta=4, p=2, seed=9)
    positions = positions.astype(dtype)
    positions[17] = positions[3]
    with pytest.raises(ParticlesTooCloseError) as error:
        find_rows(SpheresMethod(), positions, cutoff)
    assert sorted(error.value.pair) == [3, 17]
    assert "squares" in str(error.value) or "double-square" in str(error.value)
    unchecked = SpheresMethod(check_separation=False)
    find_rows(unchecked, positions, cutoff)
    flag = unchecked.separation_flag.numpy()
    assert flag[0] == 1 and sorted(flag[1:].tolist()) == [3, 17]
    assert (3, 17) in assert_exact(SquaresMethod(), positions, cutoff)


def test_separation_around_resolution():
    """float64 pairs 0.5ε … 3ε apart, on an axis and on the cube diagonal
    (the sphere's blind spot reaches √3·ε there): below 2ε the spheres
    flag, from 2ε on they find the pair, squares always do."""
    cutoff = 0.3
    base = np.array([0.5, 0.5, 0.5])
    bystander = base + [0.1, 0.05, 0.0]
    epsilon = seed_epsilon(bystander[0])  # the largest coordinate sets the scale
    for direction in (np.array([1.0, 0.0, 0.0]), np.ones(3) / math.sqrt(3.0)):
        for multiple, flagged in ((0.5, True), (1.0, True), (1.8, True), (2.2, False),
                                  (3.0, False)):
            positions = np.array([base, base + multiple * epsilon * direction, bystander])
            assert closest_pair_below(wp.array(positions, dtype=wp.vec3d),
                                      sphere_resolution(epsilon)) == flagged
            if flagged:
                with pytest.raises(ParticlesTooCloseError):
                    find_rows(SpheresMethod(), positions, cutoff)
            else:
                assert (0, 1) in assert_exact(SpheresMethod(), positions, cutoff)
            assert (0, 1) in assert_exact(SquaresMethod(), positions, cutoff)


def test_closest_pair_below(dtype):
    positions, _ = scenes.uniform(beta=3, p=10, seed=10)
    positions = positions.astype(dtype)
    vector = DTYPES[np.dtype(dtype).name][1]
    d = np.sqrt(((positions[:, None].astype(float) - positions[None]) ** 2).sum(-1))
    np.fill_diagonal(d, np.inf)
    closest = d.min()
    points = wp.array(positions, dtype=vector)
    assert not closest_pair_below(points, closest)
    assert closest_pair_below(points, np.nextafter(closest, 1.0))
    i, j = pair_below(points, np.nextafter(closest, 1.0))
    assert d[i, j] == closest
    assert not closest_pair_below(wp.array(positions[:1], dtype=vector), 1.0)


# ---------------------------------------------------------------------------
# Rows that overflow, odd positions, bad arguments.


@pytest.mark.parametrize("width", [0, 1, 5])
def test_overflow_counts_stay_exact(method, width):
    positions, cutoff = scenes.uniform(beta=3, p=8, seed=11)
    expected = brute_pairs(positions, cutoff)
    pairs, counts = find_rows(method, positions, cutoff, width=width)
    n = positions.shape[0]
    np.testing.assert_array_equal(counts, np.bincount([i for i, _ in expected], minlength=n))
    assert counts.max() > width
    assert pairs <= expected
    assert len(pairs) == np.minimum(counts, width).sum()


def test_nonfinite_particle_has_no_neighbours(method):
    positions, cutoff = scenes.uniform(beta=4, p=2, seed=12)
    positions[5] = [np.nan, 0.5, 0.5]
    positions[9] = [0.5, np.inf, 0.5]
    expected = {(i, j) for i, j in brute_pairs(np.nan_to_num(positions, posinf=9.0), cutoff)
                if {i, j}.isdisjoint({5, 9})}
    pairs, counts = find_rows(method, positions, cutoff, width=64)
    assert pairs == expected and counts[5] == counts[9] == 0


def test_bad_arguments(method):
    n = 4
    points = wp.array(np.random.default_rng(0).random((n, 3)), dtype=wp.vec3)
    out_idx = wp.zeros((n, 8), dtype=wp.int32)
    out_count = wp.zeros(n, dtype=wp.int32)
    good = dict(cutoff=0.5, side=None, periodic=FREE, mask_self=True,
                out_idx=out_idx, out_count=out_count)

    def expect(error, match, points=points, **changes):
        with pytest.raises(error, match=match):
            method.find(points, **{**good, **changes})

    expect(TypeError, "points must be", points=wp.zeros(n, dtype=wp.float32))
    expect(TypeError, "out_idx must be", out_idx=wp.zeros((n + 1, 8), dtype=wp.int32))
    expect(TypeError, "out_idx must be", out_idx=wp.zeros((n, 8), dtype=wp.int64))
    expect(TypeError, "out_count must be", out_count=wp.zeros(n - 1, dtype=wp.int32))
    expect(ValueError, "cutoff must be", cutoff=0.0)
    expect(ValueError, "cutoff must be", cutoff=float("nan"))
    expect(TypeError, "mask_self must be", mask_self=1)
    expect(ValueError, "periodic must be three bools", periodic=(True, False))
    expect(ValueError, "needs side", periodic=(True, False, False))
    expect(ValueError, r"side\[1\] must be", periodic=(False, True, False),
           side=(1.0, -1.0, 1.0))
    expect(ValueError, "= 0.5 must be below half the periodic box side 0.9 on axis 2",
           periodic=FREE[:2] + (True,), side=(1.0, 1.0, 0.9))
    with pytest.raises(TypeError, match="unexpected keyword"):
        method.find(points, **good, skin=0.1)


def test_empty_and_single_particle(method):
    for n in (0, 1):
        positions = np.full((n, 3), 0.5)
        pairs, counts = find_rows(method, positions, 0.3, width=2, mask_self=False)
        assert pairs == {(i, i) for i in range(n)}


# ---------------------------------------------------------------------------
# The scenes themselves.


def test_scene_shapes_and_reproducibility():
    positions, cutoff = scenes.uniform(beta=4, p=3, seed=0)
    assert positions.shape == (192, 3) and positions.dtype == np.float64
    assert cutoff == 0.25 and positions.min() >= 0 and positions.max() < 1
    np.testing.assert_array_equal(positions, scenes.uniform(beta=4, p=3, seed=0)[0])

    sphere, cutoff = scenes.sphere_surface(alpha=8, p=4, seed=0)
    assert sphere.shape == (2048, 3)
    np.testing.assert_allclose(np.linalg.norm(sphere, axis=1), 1.0)
    counts = np.bincount([i for i, _ in brute_pairs(sphere, cutoff)], minlength=2048)
    assert 0.9 * 36 < counts.mean() < 1.1 * 36  # ≈ 9·p neighbours

    grid = scenes.lattice(30, side=10.0)
    assert grid.shape == (30, 3) and len({tuple(p) for p in grid}) == 30
    assert grid.min() > 0 and grid.max() < 10.0
    for scene in (scenes.disordered(500, seed=1), scenes.cluster(500, seed=1)):
        assert scene.shape == (500, 3)
        assert scene.min() >= 0 and scene.max() < scenes.BOX_SIDE
    assert scenes.cluster(500, seed=1).std(axis=0).max() < 2 * scenes.CLUSTER_SIGMA


def test_radii():
    assert np.all(scenes.radii("r=1", 10, seed=0) == 1.0)
    assert np.all(scenes.radii("r=160", 10, seed=0) == 160.0)
    uniform = scenes.radii("U[1,160]", 1000, seed=0)
    assert 1.0 <= uniform.min() and uniform.max() <= 160.0
    lognormal = scenes.radii("LN[1,330]", 10000, seed=0)
    assert lognormal.min() == 1.0 and lognormal.max() <= 330.0
    assert np.median(lognormal) == pytest.approx(math.e, rel=0.15)
    with pytest.raises(ValueError, match="kind must be one of"):
        scenes.radii("LN", 10, seed=0)
    with pytest.raises(ValueError, match="beta must be"):
        scenes.uniform(beta=0, p=1, seed=0)


def test_all_three_methods_refuse_the_same_cutoffs_alike():
    """The custom AABB, spheres and squares share one rule for the cutoff
    against half a periodic side (`jaxrt.backends.rt.periodic.cutoff_fits`): the
    largest cutoff that fits works in all three, the next float and L/2
    are refused by all three with the same message."""
    from jaxrt.backends.rt import aabb
    from jaxrt.backends.rt import periodic as gamma
    side = 0.9
    largest = 0.5 * side * (1.0 - gamma.CUTOFF_MARGIN)
    while not gamma.cutoff_fits(largest, side):
        largest = np.nextafter(largest, 0.0)
    positions = np.random.default_rng(3).random((30, 3)) * side
    methods = [aabb.AabbMethod(), SpheresMethod(), SquaresMethod()]
    for method in methods:
        find_rows(method, positions, float(largest), width=30,
                  periodic=(True,) * 3, side=(side,) * 3)
    for cutoff in (float(np.nextafter(largest, 1.0)), side / 2):
        messages = set()
        for method in methods:
            with pytest.raises(ValueError) as refused:
                find_rows(method, positions, cutoff, width=30,
                          periodic=(True,) * 3, side=(side,) * 3)
            messages.add(str(refused.value))
        assert len(messages) == 1, messages
