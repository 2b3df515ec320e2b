"""`jaxrt.neighbor_list` against jax-md's own list and a float64 brute force."""
from __future__ import annotations

import functools
import logging
import warnings

import hypothesis
import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax_md import energy, partition, simulate, space

import jaxrt
from oracle import assert_layout, brute_pairs, expected_pairs, list_pairs
from scenes import kicked_updates, lattice

FORMATS = [partition.Dense, partition.Sparse, partition.OrderedSparse]
PURE_JAX = ["cell", "brute"]


def make(periodic, side, dim=3):
    return space.periodic(side) if periodic else space.free()


def check_against_oracles(R, side, cutoff, periodic, fmt, backend,
                          mask_self=True, jax_md_too=True):
    disp, _ = make(periodic, side)
    nbrs = jaxrt.neighbor_list(disp, side, cutoff, format=fmt, backend=backend,
                               mask_self=mask_self).allocate(R)
    assert not nbrs.did_buffer_overflow
    assert_layout(nbrs)
    got = list_pairs(nbrs)
    want = expected_pairs(fmt, brute_pairs(R, cutoff, side, periodic, mask_self))
    assert got == want
    if jax_md_too:
        ref = partition.neighbor_list(disp, side, cutoff, format=fmt,
                                      mask_self=mask_self).allocate(R)
        assert got == list_pairs(ref)
        assert nbrs.idx.shape == ref.idx.shape  # same capacity rule
    return nbrs


@pytest.mark.parametrize("backend", PURE_JAX)
@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("periodic", [True, False])
def test_random_scene_matches_jax_md_and_brute_force(backend, fmt, periodic):
    side = 8.0
    R = jax.random.uniform(jax.random.PRNGKey(1), (300, 3)) * side
    check_against_oracles(R, side, 1.7, periodic, fmt, backend)


HYPOTHESIS_SCENES = dict(
    n=st.sampled_from([1, 2, 17, 150]),
    side=st.floats(3.2, 12.0),
    cutoff=st.floats(0.3, 3.0),
    periodic=st.booleans(),
    dim=st.sampled_from([2, 3]),
    seed=st.integers(0, 2**16),
    mask_self=st.booleans(),
)


# A backend of one's own, passed as backend= (the contract of
# jaxrt.backends.Backend; nothing to register): all pairs by the caller's
# metric, the Dense rows converted by the contract's layout helper.
import dataclasses as _dc  # noqa: E402


@_dc.dataclass(frozen=True)
class TwentyLineBrute:
    name = "twenty-line-brute"

    def _rows(self, position, query, metric_sq, width):
        n = position.shape[0]
        d2 = jax.vmap(jax.vmap(metric_sq, (None, 0)), (0, None))(position,
                                                                 position)
        keep = d2 < query.cutoff ** 2
        if query.mask_self:
            keep &= ~jnp.eye(n, dtype=bool)
        j = jnp.broadcast_to(jnp.arange(n, dtype=jnp.int32), (n, n))
        return jaxrt.backends.pack_rows(j, keep, width), keep

    def measure(self, position, geometry, query, metric_sq):
        _, keep = self._rows(position, query, metric_sq, 0)
        lower = np.tril(np.asarray(keep), -1)
        ordered = query.format is partition.OrderedSparse
        return {"row": int(np.asarray(keep).sum(1).max(initial=0)),
                "edges": int((lower if ordered else np.asarray(keep)).sum())}

    def search(self, position, geometry, query, capacity, metric_sq):
        (rows, count), _ = self._rows(position, query, metric_sq,
                                      capacity["row"])
        return jaxrt.backends.format_dense_rows(rows, count, query, capacity)


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("periodic", [True, False])
def test_a_backend_of_ones_own_plugs_in_as_a_value(fmt, periodic):
    R = jax.random.uniform(jax.random.PRNGKey(5), (150, 3)) * 6.0
    nbrs = check_against_oracles(R, 6.0, 1.3, periodic, fmt, TwentyLineBrute())
    disp, _ = make(periodic, 6.0)
    crowded = R.at[:40].multiply(0.05)  # rows outgrow the capacity
    assert nbrs.update(crowded).did_buffer_overflow
    with pytest.raises(TypeError, match="lacks \\['name', 'measure', 'search'\\]"):
        jaxrt.neighbor_list(disp, 6.0, 1.3, backend=object())


# Each example allocates three lists of a new size (~10 s of compiling on
# CI's cores): two here, 400 in the slow run below.
@hypothesis.settings(max_examples=2, deadline=None)
@hypothesis.given(**HYPOTHESIS_SCENES)
def test_hypothesis_scenes(n, side, cutoff, periodic, dim, seed, mask_self):
    check_scene(n, side, cutoff, periodic, dim, seed, mask_self)


@pytest.mark.slow
@hypothesis.settings(max_examples=400, deadline=None)
@hypothesis.given(**HYPOTHESIS_SCENES)
def test_hypothesis_scenes_many(n, side, cutoff, periodic, dim, seed, mask_self):
    check_scene(n, side, cutoff, periodic, dim, seed, mask_self)


def check_scene(n, side, cutoff, periodic, dim, seed, mask_self):
    hypothesis.assume(not periodic or cutoff < side / 2)
    R = np.random.default_rng(seed).uniform(0, side, (n, dim)).astype(np.float32)
    disp, _ = make(periodic, side)
    for fmt in FORMATS:
        nbrs = jaxrt.neighbor_list(disp, side, cutoff, format=fmt,
                                   mask_self=mask_self).allocate(R)
        assert_layout(nbrs)
        assert list_pairs(nbrs) == expected_pairs(
            fmt, brute_pairs(R, cutoff, side, periodic, mask_self))


# --------------------------------------------------------------------------
# Adversarial scenes


@pytest.mark.parametrize("backend", PURE_JAX)
@pytest.mark.parametrize("periodic", [True, False])
def test_lattice_pairs_exactly_at_cutoff_are_excluded(backend, periodic):
    # spacing 0.5, cutoff 1.0: second neighbours sit exactly at the cutoff,
    # exactly representable, so strict '<' must drop them.
    R = lattice(8, 0.5)
    nbrs = check_against_oracles(R, 4.0, 1.0, periodic, partition.Dense, backend)
    counts = np.sum(np.asarray(nbrs.idx) < len(R), axis=1)
    if periodic:  # 6 at 0.5, 12 at 0.707, 8 at 0.866; the 6 at 1.0 excluded
        assert np.all(counts == 26)


@pytest.mark.parametrize("fmt", FORMATS)
def test_particles_on_faces_and_corners_periodic(fmt):
    side = 6.0
    below = np.nextafter(np.float32(side), np.float32(0))
    pts = [[0, 0, 0], [below, below, below], [0, below, 3], [below, 0, 0],
           [3, 3, 0], [3, 3, below], [0.0, 3, 3], [below, 3, 3], [1, 1, 1]]
    R = np.asarray(pts, np.float32)
    check_against_oracles(R, side, 1.0, True, fmt, "cell")


def test_coincident_particles_and_equal_coordinates():
    R = np.array([[1, 1, 1], [1, 1, 1], [1, 1, 2], [1, 2, 1], [2, 1, 1],
                  [1, 1, 1]], np.float32)
    for periodic, fmt in [(True, partition.Dense), (False, partition.Sparse),
                          (True, partition.OrderedSparse)]:
        check_against_oracles(R, 5.0, 1.5, periodic, fmt, "cell")


def test_fewer_particles_than_cells_and_a_huge_free_box():
    R = np.array([[0.0, 0, 0], [0.5, 0, 0], [1000.0, 1000, 1000],
                  [1000.2, 1000, 1000]], np.float32)
    check_against_oracles(R, 1.0, 0.6, False, partition.Dense, "cell",
                          jax_md_too=False)


# 2.01 and 3.0 (two and three cells across, each at its aliasing edge) in
# the default run; 3.01 and 4.5 only add cells, and are slow (CI's budget).
@pytest.mark.parametrize("side_over_cutoff", [
    2.01, 3.0, pytest.param(3.01, marks=pytest.mark.slow),
    pytest.param(4.5, marks=pytest.mark.slow)])
def test_small_periodic_boxes(side_over_cutoff):
    cutoff = 1.0
    side = side_over_cutoff * cutoff
    R = jax.random.uniform(jax.random.PRNGKey(3), (120, 3)) * side
    for fmt in FORMATS:
        check_against_oracles(R, side, cutoff, True, fmt, "cell",
                              jax_md_too=side_over_cutoff > 3.0)


def test_per_axis_box_and_mixed_boundaries():
    side = np.array([6.0, 9.0, 4.0], np.float32)
    R = jax.random.uniform(jax.random.PRNGKey(4), (200, 3)) * side
    check_against_oracles(R, side, 1.3, True, partition.Sparse, "cell")

    # periodic in x and y only: a displacement we write ourselves.
    def slab(ra, rb):
        d = ra - rb
        wrapped = jnp.mod(d + side / 2, side) - side / 2
        return jnp.where(jnp.array([True, True, False]), wrapped, d)

    nbrs = jaxrt.neighbor_list(slab, side, 1.3).allocate(R)
    assert list_pairs(nbrs) == brute_pairs(R, 1.3, side, [True, True, False])


def test_two_dimensions():
    R = jax.random.uniform(jax.random.PRNGKey(5), (400, 2)) * 10.0
    for periodic, fmt in [(True, partition.Dense), (False, partition.Sparse),
                          (False, partition.OrderedSparse)]:
        check_against_oracles(R, 10.0, 1.1, periodic, fmt, "cell")


def test_float64_pairs_near_cutoff_with_large_coordinates():
    with jax.enable_x64(True):
        rng = np.random.default_rng(0)
        base = 1000.0 + rng.uniform(0, 1, (50, 3))
        cutoff = 0.75
        direction = rng.normal(size=(50, 3))
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        inside = base + direction * cutoff * (1 - 1e-12)
        outside = base + direction * cutoff * (1 + 1e-12)
        R = np.concatenate([base, inside, outside])
        disp, _ = space.free()
        nbrs = jaxrt.neighbor_list(disp, None, cutoff).allocate(jnp.asarray(R))
        assert nbrs.idx.dtype == jnp.int32
        pairs = list_pairs(nbrs)
        assert pairs == brute_pairs(R, cutoff)
        for k in range(50):
            assert (k, 50 + k) in pairs and (k, 100 + k) not in pairs


def test_periodic_positions_outside_the_box_are_wrapped_not_wrong():
    side = 7.0
    R = jax.random.uniform(jax.random.PRNGKey(6), (250, 3)) * side
    shifted = R + side * jax.random.randint(jax.random.PRNGKey(7), R.shape, -2, 3)
    disp, _ = space.periodic(side)
    nbrs = jaxrt.neighbor_list(disp, side, 1.5).allocate(shifted)
    assert list_pairs(nbrs) == brute_pairs(R, 1.5, side, True)


def test_fractional_coordinates_orthorhombic():
    box = jnp.array([6.0, 8.0, 5.0])
    frac = jax.random.uniform(jax.random.PRNGKey(8), (200, 3))
    disp, _ = space.periodic_general(box, fractional_coordinates=True)
    for fmt in FORMATS:
        nbrs = jaxrt.neighbor_list(disp, box, 1.4, fractional_coordinates=True,
                                   format=fmt).allocate(frac)
        want = brute_pairs(frac * box, 1.4, box, True)
        assert list_pairs(nbrs) == expected_pairs(fmt, want)
        ref = partition.neighbor_list(disp, box, 1.4, fractional_coordinates=True,
                                      format=fmt).allocate(frac)
        assert list_pairs(nbrs) == list_pairs(ref)
    # a box that grows under update (NPT): same result as a fresh list.
    fns = jaxrt.neighbor_list(disp, box, 1.4, fractional_coordinates=True)
    nbrs = fns.allocate(frac)
    bigger = box * 1.1
    nbrs = fns.update(frac, nbrs, box=bigger)
    assert not nbrs.did_buffer_overflow
    assert list_pairs(nbrs) == brute_pairs(frac * bigger, 1.4, bigger, True)


def test_mask_self_false_keeps_self_pairs_and_custom_mask():
    R = jax.random.uniform(jax.random.PRNGKey(10), (100, 3)) * 5.0
    disp, _ = space.periodic(5.0)
    nbrs = jaxrt.neighbor_list(disp, 5.0, 1.2, mask_self=False).allocate(R)
    assert all((i, i) in list_pairs(nbrs) for i in range(100))

    def drop_even_neighbours(idx):
        return jnp.where(idx % 2 == 0, idx.shape[0], idx)

    for fmt in FORMATS:
        kwargs = dict(format=fmt, custom_mask_function=drop_even_neighbours)
        got = jaxrt.neighbor_list(disp, 5.0, 1.2, **kwargs).allocate(R)
        ref = partition.neighbor_list(disp, 5.0, 1.2, **kwargs).allocate(R)
        assert_layout(got)
        assert list_pairs(got) == list_pairs(ref)
        assert got.idx.shape == ref.idx.shape


# --------------------------------------------------------------------------
# Skin, jit, scan, vmap, overflow


def test_skin_rebuild_rule_matches_jax_md():
    side, cutoff, skin = 6.0, 1.2, 0.4
    R = jax.random.uniform(jax.random.PRNGKey(11), (150, 3)) * side
    disp, shift = space.periodic(side)
    ours = jaxrt.neighbor_list(disp, side, cutoff, dr_threshold=skin)
    theirs = partition.neighbor_list(disp, side, cutoff, dr_threshold=skin)
    a, b = ours.allocate(R), theirs.allocate(R)
    # a move of 0.19 < skin/2 keeps the old list, 0.21 rebuilds.
    for step in (0.19, 0.21):
        moved = shift(R, jnp.zeros_like(R).at[0, 0].set(step))
        a2, b2 = ours.update(moved, a), theirs.update(moved, b)
        assert bool(jnp.all(a2.reference_position == b2.reference_position))
        assert list_pairs(a2) == list_pairs(b2)


def test_update_in_scan_lists_every_pair_within_the_skin_every_step():
    side, cutoff = 5.0, 1.0
    disp, shift = space.periodic(side)
    R = jax.random.uniform(jax.random.PRNGKey(12), (120, 3)) * side
    fns = jaxrt.neighbor_list(disp, side, cutoff, dr_threshold=0.3,
                              capacity_multiplier=2.0)
    last, Rs, idxs, _ = kicked_updates(fns.allocate(R), shift, R, 40)
    assert not last.did_buffer_overflow
    for t in range(0, 40, 7):
        snap = last.__class__(idxs[t], Rs[t], last.error, *[
            getattr(last, f) for f in ("cell_list_capacity", "max_occupancy",
                                       "format", "cell_size", "cell_list_fn",
                                       "update_fn")])
        within = brute_pairs(Rs[t], cutoff, side, True)
        listed = list_pairs(snap)
        # the skin guarantees every pair within the cutoff is listed
        assert within <= listed
        assert listed <= brute_pairs(Rs[t], cutoff + 0.3 + 0.3, side, True)


def test_vmap_over_systems_equals_separate_calls():
    side = 5.0
    disp, _ = space.periodic(side)
    fns = jaxrt.neighbor_list(disp, side, 1.1)
    Rs = jax.random.uniform(jax.random.PRNGKey(14), (4, 100, 3)) * side
    want = [brute_pairs(Rs[b], 1.1, side, True) for b in range(4)]
    # Room for the fullest row of any of the four systems.
    fullest = max(np.bincount([i for i, _ in w], minlength=100).max()
                  for w in want)
    nbrs = fns.allocate(Rs[0], extra_capacity=int(fullest))
    batch = jax.vmap(fns.update, in_axes=(0, None))(Rs, nbrs)
    assert not np.any(np.asarray(batch.did_buffer_overflow))
    for b in range(4):
        one = fns.update(Rs[b], nbrs)
        assert not one.did_buffer_overflow
        assert np.array_equal(np.asarray(batch.idx[b]), np.asarray(one.idx))
        assert list_pairs(one) == want[b]


@pytest.mark.parametrize("fmt", FORMATS)
def test_overflow_is_flagged_sticky_and_fixed_by_reallocation(fmt):
    side = 6.0
    disp, _ = space.periodic(side)
    fns = jaxrt.neighbor_list(disp, side, 1.2, format=fmt)
    R = jax.random.uniform(jax.random.PRNGKey(15), (200, 3)) * side
    nbrs = fns.allocate(R)
    update = jax.jit(fns.update)
    crowded = R.at[:40].set(R[0] + 0.01 * jnp.arange(40)[:, None])
    nbrs = update(crowded, nbrs)
    assert nbrs.did_buffer_overflow
    nbrs = update(R, nbrs)  # fits again, but the error bit stays
    assert nbrs.did_buffer_overflow
    with pytest.raises(jaxrt.NeighborListError, match="reallocate"):
        jaxrt.check(nbrs)
    nbrs = fns.allocate(crowded)
    assert not nbrs.did_buffer_overflow
    jaxrt.check(nbrs)
    assert list_pairs(nbrs) == expected_pairs(
        fmt, brute_pairs(crowded, 1.2, side, True))


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("multiplier", [1.25, 0.5])
def test_allocate_trims_its_wider_build_to_exactly_the_sized_list(
        fmt, multiplier):
    # allocate builds with sizes rounded up (so that it can reuse compiled
    # programs), then cuts the list to its capacity: the list, its shape and
    # its overflow flag must be those of a build at exactly that capacity,
    # which update (compiled for the list's own capacity) is. With
    # capacity_multiplier 0.5 the rows do not fit: flagged, and (the
    # truncated rows of a Sparse list depending on the rows' width) built
    # at exactly that capacity.
    side = 6.0
    disp, _ = space.periodic(side)
    fns = jaxrt.neighbor_list(disp, side, 1.2, format=fmt, backend="cell",
                              capacity_multiplier=multiplier)
    R = jax.random.uniform(jax.random.PRNGKey(21), (300, 3)) * side
    nbrs = fns.allocate(R)
    pairs = brute_pairs(R, 1.2, side, True)
    occupancy = {partition.Dense: max(np.bincount([i for i, _ in pairs])),
                 partition.Sparse: len(pairs),
                 partition.OrderedSparse: len(pairs) // 2}[fmt]
    # jax-md's rule (at 0.5 jax-md's own list is no reference: its cell
    # list overflows too and counts fewer).
    assert nbrs.idx.shape[-1] == int(occupancy * multiplier)
    rebuilt = jax.jit(fns.update)(R + 0.0, nbrs.set(  # force a rebuild
        reference_position=R + side / 4))
    np.testing.assert_array_equal(np.asarray(nbrs.idx),
                                  np.asarray(rebuilt.idx))
    assert bool(nbrs.did_buffer_overflow) == (multiplier < 1)
    assert bool(rebuilt.did_buffer_overflow) == (multiplier < 1)
    if multiplier >= 1:
        assert list_pairs(nbrs) == expected_pairs(fmt, pairs)


def test_allocate_on_new_positions_reuses_the_compiled_build():
    # A training set of structures with one N: each allocate measures its
    # own exact sizes, which differ a little; the build they compile must
    # not (a compile of the cell search is most of an allocate on a CPU).
    side, n = 9.0, 700
    disp, _ = space.periodic(side)
    fns = jaxrt.neighbor_list(disp, side, 1.5, backend="cell")
    lists = fns.allocate.__self__
    # The build is shared by factories of equal arguments: count this
    # one's compiles (its displacement is new, so are its programs).
    before = lists.build._cache_size()
    widths = []
    for seed in range(6):
        R = jax.random.uniform(jax.random.PRNGKey(seed), (n, 3)) * side
        nbrs = fns.allocate(R)
        widths.append(nbrs.idx.shape[1])
        assert list_pairs(nbrs) == expected_pairs(
            partition.Dense, brute_pairs(R, 1.5, side, True))
        # Every compile is one remembered capacity, none is made besides.
        (remembered,) = lists.compiled.values()
        assert lists.build._cache_size() - before == len(remembered)
    assert len(set(widths)) > 1  # the case this is about
    assert lists.build._cache_size() - before < len(set(widths))


def test_large_lists_are_built_at_their_exact_sizes(monkeypatch, caplog):
    # Past the cap the wide list and its trimmed copy would need twice the
    # memory: allocate must build exactly, one program per list size (the
    # update's own, which allocate builds through: `_Lists.plan_build`). The
    # device is made to report no free memory, as CPUs do; a GPU's report
    # would raise the cap (the next test).
    from jaxrt.lists import neighbors
    monkeypatch.setattr(neighbors, "_ROUNDED_LIST_ENTRIES", 1000)
    monkeypatch.setattr(neighbors, "_memory_stats", lambda position: None)
    side = 9.0
    disp, _ = space.periodic(side)
    fns = jaxrt.neighbor_list(disp, side, 1.5, backend="cell")
    lists = fns.allocate.__self__
    builds = lists.build._cache_size()
    capacities = set()
    # Compiles are counted from JAX's log, not from the jitted functions'
    # dispatch caches: on a GPU one compiled program can hold two dispatch
    # entries (arguments committed to the device or not).
    with jax.log_compiles(True), caplog.at_level(logging.WARNING, "jax"):
        for seed in range(3):
            R = jax.random.uniform(jax.random.PRNGKey(seed), (700, 3)) * side
            capacities.add(fns.allocate(R).cell_list_capacity)
    updates = sum("Compiling jit(_update_arrays)" in r.getMessage()
                  for r in caplog.records)
    assert lists.compiled == {}
    assert len(capacities) > 1  # the case this is about
    assert (updates, lists.build._cache_size()) == (len(capacities), builds)


@pytest.mark.parametrize("free_bytes", [None, 10_000, 10 ** 9])
def test_large_lists_round_where_the_device_has_room(monkeypatch, free_bytes):
    """Past the cap, a device that reports its free memory (GPUs) still
    rounds and reuses builds while the wide list fits an eighth of it; one
    that reports none (CPUs) or too little builds exactly. The trimmed
    list is the exact build's either way."""
    from jaxrt.lists import neighbors
    monkeypatch.setattr(neighbors, "_ROUNDED_LIST_ENTRIES", 1000)
    stats = None if free_bytes is None else {"bytes_limit": free_bytes + 5,
                                             "bytes_in_use": 5}
    monkeypatch.setattr(neighbors, "_memory_stats", lambda position: stats)
    side = 9.0
    disp, _ = space.periodic(side)
    fns = jaxrt.neighbor_list(disp, side, 1.5, backend="cell")
    exact = jaxrt.neighbor_list(disp, side, 1.5, backend="cell")
    has_room = free_bytes is not None and free_bytes // 8 // 4 > 1000
    R = jax.random.uniform(jax.random.PRNGKey(4), (700, 3)) * side
    nbrs = fns.allocate(R)
    lists = fns.allocate.__self__
    assert bool(lists.compiled) == has_room
    monkeypatch.setattr(neighbors, "_memory_stats", lambda position: None)
    reference = exact.allocate(R)
    assert nbrs.idx.shape == reference.idx.shape
    np.testing.assert_array_equal(np.asarray(nbrs.idx), np.asarray(reference.idx))


def test_a_compiled_capacity_is_reused_only_where_it_holds_the_list():
    from jaxrt.backends import Capacity
    from jaxrt.lists.neighbors import _reused_capacity

    def cap(row, shell_rows, classes=3, **options):
        return Capacity(row, (("classes", classes), ("row", row),
                              ("shell_rows", shell_rows)), **options)

    built = [cap(64, 512), cap(96, 512)]
    # Just past a rounding step (65 > 64): the larger one, not a new one.
    assert _reused_capacity(built, cap(65, 385), ["classes"]) == built[1]
    assert _reused_capacity(built, cap(60, 300), ["classes"]) == built[1]
    # Too small somewhere, or more than twice what the list needs.
    assert _reused_capacity(built, cap(97, 385), ["classes"]) is None
    assert _reused_capacity(built, cap(40, 200), ["classes"]) is None
    # Other options, or another count of a fixed size: never.
    assert _reused_capacity(built, cap(64, 512, radii=True),
                            ["classes"]) is None
    assert _reused_capacity(built, cap(64, 512, classes=2),
                            ["classes"]) is None


def test_compile_sizes_cover_and_stay_within_half_again():
    from jaxrt.backends import contract as _backend
    for size in range(0, 200):
        up = _backend.compile_size(size)
        assert size <= up <= max(size, 1.5 * size), size
        assert _backend.compile_size(up) == up, size  # a fixed point


@pytest.mark.parametrize("words", [1, 27, 64, 65, 300])
def test_cell_list_prefix_sums_are_exact(words):
    # Both ways (matrix product up to 64 words, scan beyond) against numpy,
    # at the largest counts a word can hold.
    from jaxrt.backends.cell import search as cell_list
    rng = np.random.default_rng(words)
    counts = rng.integers(0, 33, size=(7, words)).astype(np.int32)
    counts[0] = 32
    got = np.asarray(cell_list._prefix(jnp.asarray(counts)))
    assert got.dtype == np.int32
    np.testing.assert_array_equal(got, np.cumsum(counts, axis=1))


def test_cell_list_allocated_on_a_lattice_survives_melting():
    # No lattice distance lies near the cutoff, so no particle has a pair
    # in the shell at allocate; once the lattice is shaken a few percent
    # do, and the shell buffers sized at allocate must hold them.
    # Large enough that a hundred or so particles then have one.
    n_side, spacing, cutoff = 22, 1.0, 2.5 * (1 + 2 ** -6)
    side = n_side * spacing
    disp, _ = space.periodic(side)
    fns = jaxrt.neighbor_list(disp, side, cutoff, backend="cell")
    R = jnp.asarray(lattice(n_side, spacing), jnp.float32)
    nbrs = fns.allocate(R)
    shaken = jnp.mod(R + 0.2 * jax.random.normal(jax.random.PRNGKey(3), R.shape),
                     side)
    nbrs = jax.jit(fns.update)(shaken, nbrs)
    assert not nbrs.did_buffer_overflow
    reference = partition.neighbor_list(disp, side, cutoff).allocate(shaken)
    assert list_pairs(nbrs) == list_pairs(reference)


@pytest.mark.parametrize("kernel", ["xla", "interpret"])
def test_cell_list_internal_buffer_overflow_is_flagged(kernel):
    """The cell list's internal buffers (the longest stencil-row run, the
    shell of pairs at the cutoff that the caller's metric decides, and the
    particles that have such pairs) overflowing is reported even when the
    neighbour rows have room. The GPU kernel (run here in the interpreter)
    walks runs to their ends: it has no window to overflow."""
    from jaxrt import backends
    from jaxrt.backends import Capacity, Geometry, MetricSq, Query
    from jaxrt.lists.neighbors import metric_sq_fn

    side = 6.0
    disp, _ = space.periodic(side)
    cell = backends.Cell(kernel=kernel)
    query = Query(1.0, (True,) * 3, True, partition.Dense)
    geometry = Geometry(jnp.full(3, side), jnp.ones(3))
    metric = MetricSq(metric_sq_fn(disp, 3))
    # A unit lattice at cutoff 1: six pairs of every particle lie exactly
    # at the cutoff (the shell), none inside.
    # A crowd of 40 near one point: a stencil-row run longer than one
    # 32-slot window word.
    uniform = jax.random.uniform(jax.random.PRNGKey(16), (200, 3)) * side
    crowded = uniform.at[:40].set(uniform[0] + 1e-3 * jnp.arange(40)[:, None])
    for R, shell_pairs in [(crowded, None),
                           (jnp.asarray(lattice(6, 1.0)), 6)]:
        sizes = cell.measure(R, geometry, query, metric)
        if shell_pairs is not None:
            assert sizes["shell"] >= shell_pairs
        fits = dict(row=len(R) - 1, window=sizes["window"],
                    shell=sizes["shell"], shell_rows=sizes["shell_rows"])

        def search(**change):
            internal = tuple(sorted({**fits, **change}.items()))
            return cell.search(R, geometry, query,
                               Capacity(len(R) - 1, internal), metric)

        ok = search()
        assert not ok.overflow and int(ok.occupancy) == sizes["row"]
        if shell_pairs is None:
            assert sizes["window"] > 32
            short = search(window=32)
            assert bool(short.overflow) == (kernel == "xla")
            if kernel != "xla":
                assert np.array_equal(np.asarray(short.idx),
                                      np.asarray(ok.idx))
        if shell_pairs is not None:
            assert search(shell=shell_pairs - 1).overflow
            assert not search(shell=shell_pairs).overflow
            # every lattice particle has shell pairs
            assert sizes["shell_rows"] == len(R)
            assert search(shell_rows=len(R) - 1).overflow


# --------------------------------------------------------------------------
# jax-md consumers work unchanged


def test_lennard_jones_energy_and_forces_equal_jax_md():
    side = 7.0
    disp, _ = space.periodic(side)
    R = lattice(6, side / 6) + 0.05 * np.asarray(
        jax.random.normal(jax.random.PRNGKey(18), (216, 3)))
    R = jnp.mod(jnp.asarray(R), side)
    # every format and backend is covered in tests/energy/test_energy_lj.py
    for fmt in (partition.OrderedSparse,):
        kw = dict(r_cutoff=2.5, format=fmt)
        nf_ref, e_ref = energy.lennard_jones_neighbor_list(disp, side, **kw)
        nf, e = energy.lennard_jones_neighbor_list(
            disp, side, neighbor_list_fn=functools.partial(
                jaxrt.neighbor_list, backend="cell"), **kw)
        n_ref, n = nf_ref.allocate(R), nf.allocate(R)
        np.testing.assert_allclose(e(R, n), e_ref(R, n_ref), rtol=2e-6)
        f, f_ref = jax.grad(e)(R, n), jax.grad(e_ref)(R, n_ref)
        np.testing.assert_allclose(f, f_ref, rtol=1e-4, atol=1e-4)


def test_grad_finite_with_coincident_particles():
    side = 5.0
    disp, _ = space.periodic(side)
    nf, e = energy.soft_sphere_neighbor_list(
        disp, side, neighbor_list_fn=jaxrt.neighbor_list)
    R = jnp.array([[1.0, 1, 1], [1.0, 1, 1], [2.0, 2, 2]])
    nbrs = nf.allocate(R)
    g = jax.grad(e)(R, nbrs)
    assert bool(jnp.all(jnp.isfinite(g)))


def test_nve_in_fori_loop_with_jaxrt_list():
    side = 6.0
    disp, shift = space.periodic(side)
    R = jnp.asarray(lattice(5, side / 5))
    nf, e = energy.soft_sphere_neighbor_list(
        disp, side, sigma=1.1, dr_threshold=0.3,
        neighbor_list_fn=jaxrt.neighbor_list)
    init, apply = simulate.nve(e, shift, 1e-3)
    nbrs = nf.allocate(R)
    state = init(jax.random.PRNGKey(0), R, kT=0.5, neighbor=nbrs)

    def body(_, carry):
        state, nbrs = carry
        nbrs = nbrs.update(state.position)
        return apply(state, neighbor=nbrs), nbrs

    state, nbrs = jax.lax.fori_loop(0, 200, body, (state, nbrs))
    assert not nbrs.did_buffer_overflow
    assert bool(jnp.all(jnp.isfinite(state.position)))
    fresh = nf.allocate(state.position)
    np.testing.assert_allclose(e(state.position, nbrs),
                               e(state.position, fresh), rtol=1e-5)


# --------------------------------------------------------------------------
# Bad input


def test_bad_arguments_raise_clear_errors():
    disp, _ = space.periodic(5.0)
    with pytest.warns(UserWarning, match="cell_size"):  # jax-md ignores it
        jaxrt.neighbor_list(disp, 5.0, 1.0, cell_size=2.0)
    with pytest.raises(ValueError, match="r_cutoff"):
        jaxrt.neighbor_list(disp, 5.0, 0.0)
    with pytest.raises(ValueError, match="r_cutoff"):
        jaxrt.neighbor_list(disp, 5.0, float("nan"))
    with pytest.raises(ValueError, match="dr_threshold"):
        jaxrt.neighbor_list(disp, 5.0, 1.0, dr_threshold=-0.1)
    with pytest.raises(ValueError, match="backend"):
        jaxrt.neighbor_list(disp, 5.0, 1.0, backend="nope")
    with pytest.raises(ValueError, match="format"):
        jaxrt.neighbor_list(disp, 5.0, 1.0, format="Dense")
    fns = jaxrt.neighbor_list(disp, 5.0, 1.0)
    R = jax.random.uniform(jax.random.PRNGKey(0), (10, 3)) * 5.0
    with pytest.raises(ValueError, match="shape"):
        fns.allocate(R[:, :, None])
    with pytest.raises(TypeError, match="floating"):
        fns.allocate(jnp.ones((10, 3), jnp.int32))
    with pytest.raises(ValueError, match="non-finite.*particle 3"):
        fns.allocate(R.at[3, 1].set(jnp.nan))
    with pytest.raises(ValueError, match="non-finite"):
        fns.allocate(R.at[2, 0].set(jnp.inf))
    with pytest.raises(TypeError, match="unexpected keyword"):
        fns.allocate(R, neighbour_idx=3)
    nbrs = fns.allocate(R)
    with pytest.raises(ValueError, match="allocated for"):
        fns.update(R[:5], nbrs)
    with pytest.raises(TypeError, match="unexpected keyword"):
        fns.update(R, nbrs, species=1)


def test_box_that_does_not_match_the_displacement_is_refused():
    disp, _ = space.periodic(20.0)
    R = jax.random.uniform(jax.random.PRNGKey(0), (10, 3)) * 5.0
    with pytest.raises(ValueError, match="periodic=True/False"):
        jaxrt.neighbor_list(disp, 5.0, 1.0).allocate(R)
    free, _ = space.free()
    # explicit periodic without a box
    with pytest.raises(ValueError, match="box"):
        jaxrt.neighbor_list(free, None, 1.0, periodic=True).allocate(R)


def test_nan_under_jit_sets_error_bits_and_check_raises():
    disp, _ = space.periodic(5.0)
    fns = jaxrt.neighbor_list(disp, 5.0, 1.0)
    R = jax.random.uniform(jax.random.PRNGKey(0), (30, 3)) * 5.0
    nbrs = fns.allocate(R)
    bad = jax.jit(fns.update)(R.at[4, 2].set(jnp.nan), nbrs)
    assert bad.did_buffer_overflow  # so the usual reallocation loop notices
    assert int(bad.error.code) & jaxrt.ErrorCode.NONFINITE_POSITION
    with pytest.raises(jaxrt.NeighborListError, match="NaN"):
        jaxrt.check(bad)


def test_free_space_needs_no_box():
    free, _ = space.free()
    R = jax.random.normal(jax.random.PRNGKey(0), (200, 3)) * 3.0
    for box in (None, 0.0, 1.0):
        nbrs = jaxrt.neighbor_list(free, box, 1.0).allocate(R)
        assert list_pairs(nbrs) == brute_pairs(R, 1.0)


def test_lists_beyond_what_the_backend_can_index_are_refused():
    # A Warp kernel computes byte offsets in 32-bit ints, so its outputs
    # must stay below 2**29 int32 entries: a larger list must be refused at
    # allocate with the fix, never written through a wrapped offset.
    R = jnp.asarray(np.random.default_rng(0).uniform(0, 6, (200, 3)),
                    jnp.float32)
    disp, _ = space.periodic(6.0)
    small = jaxrt.neighbor_list(disp, 6.0, 1.5, backend="cell").allocate(R)
    entries = int(np.prod(small.idx.shape))

    def limited(limit):
        return jaxrt.neighbor_list(disp, 6.0, 1.5,
                                   backend=_cell_limited_to(limit))

    with pytest.raises(jaxrt.ListTooLargeError,
                       match="more than backend='cell' can "
                       "address.*fewer particles"):
        limited(entries - 1).allocate(R)
    assert limited(entries).allocate(R).idx.shape == small.idx.shape


def _cell_limited_to(limit, **options):
    """A `Cell` backend that indexes at most ``limit`` int32 entries."""
    import dataclasses
    from typing import ClassVar

    from jaxrt import backends

    @dataclasses.dataclass(frozen=True)
    class Limited(backends.Cell):
        max_list_entries: ClassVar[int] = limit
    return Limited(**options)


def _cluster_within_the_cutoff(n=300):
    """float32 ``(n, 3)`` points in a cube 0.6 wide: all pairs within 1.5."""
    return jnp.asarray(np.random.default_rng(1).uniform(-0.3, 0.3, (n, 3)),
                       jnp.float32)


@pytest.mark.parametrize("windows", [False, True])
@pytest.mark.parametrize("fmt", [partition.Dense, partition.OrderedSparse])
def test_cell_rows_past_the_limit_are_refused_before_they_are_built(
        monkeypatch, fmt, windows):
    # Seed 003's cluster: every particle within the cutoff of every other,
    # so every layout's rows are N wide. The cell list must refuse after its
    # count pass, before the pass that writes N x row entries (at n = 50 000
    # that pass was killed for host memory, or ran past 100 s on the GPU).
    from jaxrt import backends
    n = 300
    R = _cluster_within_the_cutoff(n)
    disp, _ = space.free()
    limited = _cell_limited_to

    widths = []
    candidates = backends.Cell._candidates

    def spy(self, *args, **options):
        widths.append(options.get("row_width"))
        return candidates(self, *args, **options)

    monkeypatch.setattr(backends.Cell, "_candidates", spy)
    if windows:  # the windows' count even where all pairs would count
        from jaxrt.backends.cell import search
        monkeypatch.setattr(search, "_ALL_PAIRS_COUNT_MAX_N", 0)
    with pytest.raises(jaxrt.ListTooLargeError, match=r"needs 89,700 int32 entries \(rows "
                       r"before conversion.*lennard_jones_fused"):
        jaxrt.neighbor_list(disp, None, 1.5, backend=limited(n * (n - 1) - 1),
                            format=fmt).allocate(R)
    # Only a count ran (small lists on a CPU count over all pairs, with
    # no candidate pass at all): no rows pass.
    assert max(widths, default=0) <= 1
    assert bool(widths) == (windows or jax.default_backend() != "cpu")
    # Room for N x N (the rows' capacity is capped at N) and the same list
    # is built, every pair in it.
    nbrs = jaxrt.neighbor_list(disp, None, 1.5, backend=limited(n * n),
                               format=fmt).allocate(R)
    idx = np.asarray(nbrs.idx)
    if fmt is partition.Dense:
        assert int(np.sum(idx < n)) == n * (n - 1)
    else:
        assert int(np.sum(idx[0] < n)) == n * (n - 1) // 2


def test_portable_candidates_past_int32_are_refused_before_counting():
    # Seed 003's r = 160 lattice at n = 10^6 on the CPU: the portable
    # search's candidate bits (N x 9 stencil rows x the longest row's slots)
    # passed 2^31 words and XLA raised an OverflowError on a flat index.
    # Here 300 particles share one cell: each of the 9 rows' window is the
    # cell's 300 particles, 320 slots or 10 words, so 27 000 words in all.
    n = 300
    R = _cluster_within_the_cutoff(n)
    disp, _ = space.free()

    def limited(limit):
        return _cell_limited_to(limit, kernel="xla")

    with pytest.raises(jaxrt.ListTooLargeError, match=r"portable search .* 27,000 32-slot "
                       r"words \(N = 300 x 9 stencil rows x 320 slots.*"
                       r"GPU kernel.*lennard_jones_fused"):
        jaxrt.neighbor_list(disp, None, 1.5,
                            backend=limited(26_999)).allocate(R)
    # At exactly the limit the candidates pass; the rows (300 x 299
    # entries) are the next refusal, and room for them builds the list.
    with pytest.raises(jaxrt.ListTooLargeError, match=r"needs 89,700 int32 entries"):
        jaxrt.neighbor_list(disp, None, 1.5,
                            backend=limited(27_000)).allocate(R)
    nbrs = jaxrt.neighbor_list(disp, None, 1.5,
                               backend=limited(n * n)).allocate(R)
    assert int(np.sum(np.asarray(nbrs.idx) < n)) == n * (n - 1)


# --------------------------------------------------------------------------
# Fractional positions the caller does not announce. jax-md's
# Stillinger-Weber and EAM wrappers take fractional_coordinates but do not
# pass it on to neighbor_list_fn: on a space.periodic_general(box) space
# (fractional positions by default) the list is asked for with a box and no
# word of fractional coordinates. jaxrt must read the displacement as one of
# fractional coordinates (it is periodic with period 1) and give jax-md's
# list, with a warning naming fractional_coordinates=True.


def _fcc_fractional(basis, n: int):
    """Fractional positions (float32 ``(n**3 len(basis), 3)``) of a basis
    (fractional, in the primitive cell) repeated ``n`` times per axis."""
    cells = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"),
                     -1).reshape(-1, 3)
    basis = np.asarray(basis, np.float64)
    return ((cells[:, None, :] + basis[None]) / n).reshape(-1, 3).astype(
        np.float32)


def _fcc_box(a: float, n: int) -> np.ndarray:
    """The fcc primitive lattice vectors (columns) times ``n``."""
    return (np.array([[0, 1, 1], [1, 0, 1], [1, 1, 0]]) * a / 2 * n).astype(
        np.float32)


def _silicon(n: int = 3):
    """Diamond silicon (a = 5.428 Å): two atoms per fcc primitive cell."""
    return _fcc_fractional([[0, 0, 0], [0.25, 0.25, 0.25]], n), \
        _fcc_box(5.428, n)


def _our_eam(cutoff: float):
    """A small EAM of our own (smooth to zero at ``cutoff``)."""
    def charge(r):
        return jnp.where(r < cutoff, (cutoff - r) ** 2, 0.0)

    def embedding(rho):
        return -jnp.sqrt(rho + 1e-12)

    def pairwise(r):
        return jnp.where(r < cutoff, 0.2 * (cutoff - r) ** 3, 0.0)
    return charge, embedding, pairwise


def _unannounced_scene(name):
    """``(displacement, box_size, positions, wrapper)``: ``wrapper(disp,
    box_size, neighbor_list_fn)`` -> jax-md's (neighbor_fn, energy_fn)."""
    if name == "stillinger-weber":
        R, box = _silicon(3)

        def wrapper(disp, box_size, neighbor_list_fn):
            return energy.stillinger_weber_neighbor_list(
                disp, box_size, neighbor_list_fn=neighbor_list_fn)
    else:
        # fcc aluminium-like, 4 cells per axis: fractional differences of
        # exactly 1/2, where jax-md's wrap picks -1/2 (a triclinic box makes
        # the two images differ in length).
        R, box = _fcc_fractional([[0, 0, 0]], 4), _fcc_box(4.05, 4)

        def wrapper(disp, box_size, neighbor_list_fn):
            return energy.eam_neighbor_list(
                disp, box_size, *_our_eam(4.0), cutoff=4.0,
                format=partition.Dense, neighbor_list_fn=neighbor_list_fn)
    disp, _ = space.periodic_general(jnp.asarray(box))
    # As jax-md's own tests pass it: a side length, not the box.
    box_size = float(np.linalg.det(box.astype(np.float64)) ** (1 / 3))
    return disp, box_size, jnp.asarray(R), wrapper


@pytest.mark.parametrize("name", ["stillinger-weber", "eam"])
def test_fractional_positions_the_wrapper_does_not_announce(name):
    disp, box_size, R, wrapper = _unannounced_scene(name)
    ref_fn, energy_fn = wrapper(disp, box_size, partition.neighbor_list)
    ref = ref_fn.allocate(R)
    with pytest.warns(UserWarning, match="fractional_coordinates=True"):
        neighbor_fn, _ = wrapper(disp, box_size, jaxrt.neighbor_list)
        nbrs = neighbor_fn.allocate(R)
    assert not nbrs.did_buffer_overflow
    assert list_pairs(nbrs) == list_pairs(ref)
    # The same terms summed in another order (float32, a few hundred
    # terms per atom: 1e-5 of the energy is ~100 ulps of each sum).
    np.testing.assert_allclose(energy_fn(R, nbrs), energy_fn(R, ref),
                               rtol=1e-5)
    if name == "stillinger-weber":
        # The perfect crystal's energy per atom, from jax-md's all-pairs
        # Stillinger-Weber (no list).
        want = energy.stillinger_weber(disp)(R) / len(R)
        np.testing.assert_allclose(energy_fn(R, nbrs) / len(R), want,
                                   rtol=1e-5)
    # periodic=True, the fix an earlier error message suggested, reads the
    # positions the same way; fractional_coordinates=True says it outright.
    with pytest.warns(UserWarning, match="fractional_coordinates=True"):
        periodic = wrapper(disp, box_size, functools.partial(
            jaxrt.neighbor_list, periodic=True))[0].allocate(R)
    assert list_pairs(periodic) == list_pairs(ref)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        said = wrapper(disp, box_size, functools.partial(
            jaxrt.neighbor_list, fractional_coordinates=True))[0].allocate(R)
    assert not [w for w in caught if "fractional" in str(w.message)]
    assert list_pairs(said) == list_pairs(ref)


def test_a_displacement_periodic_with_neither_box_nor_one_is_refused():
    """Neither the box's period nor fractional coordinates' period 1: the
    error names periodic=, the box and fractional_coordinates=True."""
    disp, _ = space.periodic(3.0)
    R = jax.random.uniform(jax.random.PRNGKey(0), (10, 3)) * 3.0
    with pytest.raises(ValueError, match="periodic=True/False.*"
                       "fractional_coordinates=True"):
        jaxrt.neighbor_list(disp, 7.0, 1.0).allocate(R)
