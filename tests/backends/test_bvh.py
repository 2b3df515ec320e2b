"""The ray-traced backend "bvh" (`jaxrt.rt`) against jax-md's own list, a
float64 brute force and the pure-JAX "cell" backend."""
from __future__ import annotations

import hypothesis
import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax_md import partition, space

import jaxrt
from oracle import assert_layout, brute_pairs, expected_pairs, list_pairs

pytest.importorskip("warp")
rt = pytest.importorskip("jaxrt.rt")
from jaxrt import backends  # noqa: E402
from jaxrt.backends import Capacity, Geometry, Query  # noqa: E402
from jaxrt.backends.rt import aabb  # noqa: E402
from jaxrt.backends.rt import ffi

Dense, Sparse, OrderedSparse = (partition.Dense, partition.Sparse,
                                partition.OrderedSparse)
FORMATS = [Dense, Sparse, OrderedSparse]


def displacement(periodic, side):
    return (space.periodic(side) if periodic else space.free())[0]


def check(R, side, cutoff, periodic, fmt, *, backend="bvh", mask_self=True,
          jax_md_too=True, cell_too=False, jax_md_brute=False):
    """Allocate with ``backend`` and compare with the float64 brute force,
    jax-md (its all-pairs path if ``jax_md_brute``) and, if asked, the "cell"
    backend (slow to compile, so only in a few tests). Returns the list."""
    disp = displacement(periodic, side)
    nbrs = jaxrt.neighbor_list(disp, side, cutoff, format=fmt, backend=backend,
                               mask_self=mask_self).allocate(R)
    assert not nbrs.did_buffer_overflow
    assert_layout(nbrs)
    got = list_pairs(nbrs)
    want = expected_pairs(fmt, brute_pairs(R, cutoff, side, periodic, mask_self))
    assert got == want
    if jax_md_too:
        ref = partition.neighbor_list(disp, side, cutoff, format=fmt,
                                      mask_self=mask_self,
                                      disable_cell_list=jax_md_brute).allocate(R)
        assert got == list_pairs(ref)
        assert nbrs.idx.shape == ref.idx.shape  # same capacity rule
    if cell_too:
        cell = jaxrt.neighbor_list(disp, side, cutoff, format=fmt, backend="cell",
                                   mask_self=mask_self).allocate(R)
        assert got == list_pairs(cell)
    return nbrs


def pairs_of(idx, fmt, n):
    """(i, j) set of a raw backend ``idx`` in layout ``fmt``."""
    idx = np.asarray(idx)
    if fmt is Dense:
        i, k = np.nonzero(idx < n)
        return set(zip(i.tolist(), idx[i, k].tolist()))
    keep = idx[0] < n
    return set(zip(idx[1][keep].tolist(), idx[0][keep].tolist()))


def lattice(n_per_side, spacing, dim=3):
    g = np.arange(n_per_side, dtype=np.float32) * spacing
    return np.stack(np.meshgrid(*[g] * dim, indexing="ij"), -1).reshape(-1, dim)


# --------------------------------------------------------------------------
# Identical lists


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("periodic", [True, False])
def test_random_scene_matches_jax_md_brute_force_and_cell(fmt, periodic):
    R = jax.random.uniform(jax.random.PRNGKey(1), (300, 3)) * 8.0
    check(R, 8.0, 1.7, periodic, fmt, cell_too=periodic == (fmt is Dense))


@pytest.mark.parametrize("periodic", [True, False])
def test_unsorted_variant_gives_the_same_lists(periodic):
    R = jax.random.uniform(jax.random.PRNGKey(2), (250, 3)) * 7.0
    for fmt in (Dense, OrderedSparse):
        check(R, 7.0, 1.4, periodic, fmt, backend="bvh-unsorted",
              jax_md_too=False)


@pytest.mark.parametrize("periodic", [True, False])
def test_lattice_pairs_exactly_at_cutoff_are_excluded(periodic):
    # spacing 0.5, cutoff 1.0: exactly representable; strict '<' drops the
    # second neighbours at exactly 1.0, also across periodic faces.
    R = lattice(8, 0.5)
    nbrs = check(R, 4.0, 1.0, periodic, Dense)
    if periodic:
        assert np.all(np.sum(np.asarray(nbrs.idx) < len(R), axis=1) == 26)
    check(R, 4.0, 1.0, periodic, Sparse)


@pytest.mark.parametrize("fmt", FORMATS)
def test_particles_on_faces_and_corners_periodic(fmt):
    side = 6.0
    below = np.nextafter(np.float32(side), np.float32(0))
    pts = [[0, 0, 0], [below, below, below], [0, below, 3], [below, 0, 0],
           [3, 3, 0], [3, 3, below], [0.0, 3, 3], [below, 3, 3], [1, 1, 1],
           [0.25, 0.25, 5.75], [5.75, 5.75, 0.25], [5.0, 0.0, 1.0]]
    R = np.asarray(pts, np.float32)
    check(R, side, 1.0, True, fmt)
    # corners crowded: every particle casts gamma rays, up to 7 extra.
    corner = np.random.default_rng(0).uniform(-0.6, 0.6, (200, 3))
    check(np.mod(corner, side).astype(np.float32), side, 1.0, True, fmt)


def test_coincident_particles_and_equal_coordinates():
    R = np.array([[1, 1, 1], [1, 1, 1], [1, 1, 2], [1, 2, 1], [2, 1, 1],
                  [1, 1, 1], [4.5, 1, 1], [0, 1, 1]], np.float32)
    for periodic in (True, False):
        for fmt in FORMATS:
            check(R, 5.0, 1.5, periodic, fmt, jax_md_too=fmt is Dense)
            check(R, 5.0, 1.5, periodic, fmt, mask_self=False, jax_md_too=False)


@pytest.mark.filterwarnings("ignore:scatter inputs have incompatible types")  # jax-md, x64
def test_float64_pairs_at_cutoff_with_coordinates_near_1e3():
    with jax.enable_x64(True):
        rng = np.random.default_rng(0)
        cutoff = 0.75
        direction = rng.normal(size=(50, 3))
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        # free space around 1e3; periodic box 1024 with pairs across the face
        for periodic, base in ((False, 1000.0 + rng.uniform(0, 1, (50, 3))),
                               (True, 1023.9 + rng.uniform(-0.1, 0.1, (50, 3)))):
            inside = base + direction * cutoff * (1 - 1e-12)
            outside = base + direction * cutoff * (1 + 1e-12)
            R = np.concatenate([base, inside, outside])
            if periodic:
                R = np.where(R >= 1024.0, R - 1024.0, R)  # exact (Sterbenz)
            side = 1024.0
            for fmt in FORMATS:
                nbrs = check(jnp.asarray(R), side, cutoff, periodic, fmt,
                             jax_md_brute=True)
                assert nbrs.reference_position.dtype == jnp.float64
            pairs = list_pairs(jaxrt.neighbor_list(
                displacement(periodic, side), side, cutoff,
                backend="bvh").allocate(jnp.asarray(R)))
            for k in range(50):
                assert (k, 50 + k) in pairs and (k, 100 + k) not in pairs


@pytest.mark.parametrize("periodic", [True, False])
def test_two_and_one_dimensions(periodic):
    R2 = jax.random.uniform(jax.random.PRNGKey(5), (300, 2)) * 10.0
    for fmt in FORMATS:
        check(R2, 10.0, 1.1, periodic, fmt)
    R1 = jax.random.uniform(jax.random.PRNGKey(6), (100, 1)) * 10.0
    check(R1, 10.0, 0.7, periodic, Sparse, jax_md_too=False)


def test_mask_self_false_keeps_one_self_pair():
    R = jax.random.uniform(jax.random.PRNGKey(7), (150, 3)) * 5.0
    for fmt in FORMATS:
        check(R, 5.0, 1.2, True, fmt, mask_self=False)


def test_positions_outside_the_box_and_fractional_coordinates():
    side = 7.0
    R = jax.random.uniform(jax.random.PRNGKey(8), (250, 3)) * side
    moved = R + side * jax.random.randint(jax.random.PRNGKey(9), R.shape, -2, 3)
    nbrs = jaxrt.neighbor_list(displacement(True, side), side, 1.5,
                               backend="bvh").allocate(moved)
    assert list_pairs(nbrs) == brute_pairs(R, 1.5, side, True)

    box = jnp.array([6.0, 8.0, 5.0])
    frac = jax.random.uniform(jax.random.PRNGKey(10), (200, 3))
    disp, _ = space.periodic_general(box, fractional_coordinates=True)
    fns = jaxrt.neighbor_list(disp, box, 1.4, fractional_coordinates=True,
                              format=Sparse, backend="bvh")
    nbrs = fns.allocate(frac)
    assert list_pairs(nbrs) == brute_pairs(frac * box, 1.4, box, True)
    bigger = box * 1.1  # NPT: the box changes under update
    nbrs = fns.update(frac, nbrs, box=bigger)
    assert not nbrs.did_buffer_overflow
    assert list_pairs(nbrs) == brute_pairs(frac * bigger, 1.4, bigger, True)
    # shrinking below twice the cutoff is reported (then allocate refuses)
    nbrs = fns.update(frac, nbrs, box=jnp.full(3, 2.7))
    assert nbrs.did_buffer_overflow
    with pytest.raises(ValueError, match=r"axis 0 \(L/2 = 1.35\)"):
        fns.allocate(frac, box=jnp.full(3, 2.7))


HYPOTHESIS_SCENES = dict(
    n=st.sampled_from([1, 2, 17, 120]),
    side=st.floats(3.2, 12.0),
    cutoff=st.floats(0.3, 1.55),
    periodic=st.booleans(),
    dim=st.sampled_from([2, 3]),
    seed=st.integers(0, 2**16),
    mask_self=st.booleans(),
)


@hypothesis.settings(max_examples=4, deadline=None)
@hypothesis.given(**HYPOTHESIS_SCENES)
def test_hypothesis_scenes(n, side, cutoff, periodic, dim, seed, mask_self):
    check_scene(n, side, cutoff, periodic, dim, seed, mask_self)


@pytest.mark.slow
@hypothesis.settings(max_examples=400, deadline=None)
@hypothesis.given(**HYPOTHESIS_SCENES)
def test_hypothesis_scenes_many(n, side, cutoff, periodic, dim, seed, mask_self):
    check_scene(n, side, cutoff, periodic, dim, seed, mask_self)


def check_scene(n, side, cutoff, periodic, dim, seed, mask_self):
    R = np.random.default_rng(seed).uniform(0, side, (n, dim)).astype(np.float32)
    disp = displacement(periodic, side)
    for fmt in FORMATS:
        nbrs = jaxrt.neighbor_list(disp, side, cutoff, format=fmt, backend="bvh",
                                   mask_self=mask_self).allocate(R)
        assert_layout(nbrs)
        assert list_pairs(nbrs) == expected_pairs(
            fmt, brute_pairs(R, cutoff, side, periodic, mask_self))


# --------------------------------------------------------------------------
# The backend directly: persistence, vmap, overflow


def setup_backend(R, side, cutoff, periodic, fmt, backend="bvh"):
    backend = backends.bind(backends.resolve(backend))
    dim = R.shape[1]
    query = Query(cutoff=cutoff, periodic=(periodic,) * dim, mask_self=True,
                  format=fmt)
    geometry = Geometry(side=jnp.full(dim, side, R.dtype),
                        scale=jnp.ones(dim, R.dtype))
    sizes = backend.measure(R, geometry, query, None)
    room = sizes["row"] if fmt is Dense else sizes["edges"]
    capacity = Capacity(int(room * 1.5) + 8, (("row", int(sizes["row"] * 1.5) + 8),))
    return backend, query, geometry, capacity


# One BVH box per run of 5 sorted particles (an odd size, so the last
# cluster is partial), with 3 boxes per leaf.
CLUSTERED = backends.Bvh(cluster_size=5, leaf_size=3)


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("periodic", [True, False])
def test_clustered_boxes_give_the_same_lists(fmt, periodic):
    R = jax.random.uniform(jax.random.PRNGKey(21), (303, 3)) * 8.0
    check(R, 8.0, 1.7, periodic, fmt, backend=CLUSTERED, jax_md_too=False)
    # Ties at the cutoff, and particles on faces and corners.
    check(lattice(8, 0.5), 4.0, 1.0, periodic, fmt, backend=CLUSTERED,
          jax_md_too=False)
    corners = np.array([[0, 0, 0], [3.999, 3.999, 3.999], [0, 3.999, 0],
                        [3.999, 0, 0.5], [2, 2, 2]], np.float32)
    check(corners, 4.0, 1.5, periodic, fmt, backend=CLUSTERED,
          jax_md_too=False)


@pytest.mark.parametrize("fmt,name", [(Dense, "bvh"), (OrderedSparse, "bvh"),
                                      (Dense, CLUSTERED)])
def test_scan_with_persistent_bvh_equals_fresh_build_every_step(fmt, name):
    n, side, cutoff = 250, 8.0, 1.7
    key = jax.random.PRNGKey(11)
    R0 = jax.random.uniform(key, (n, 3)) * side
    backend, query, geometry, capacity = setup_backend(R0, side, cutoff, True,
                                                       fmt, name)
    velocity = jax.random.normal(jax.random.PRNGKey(12), (n, 3)) * 0.03
    kicks = jnp.zeros(50).at[jnp.array([17, 35])].set(1.0)  # large moves: rebuilds

    def step(R, kick):
        R = jnp.mod(R + velocity + kick * 0.5 * jnp.sign(velocity), side)
        result = backend.search(R, geometry, query, capacity, None)
        return R, (R, result.idx, result.overflow)

    before = ffi.update_counts.copy()
    _, (Rs, idxs, overflows) = jax.jit(
        lambda R: jax.lax.scan(step, R, kicks))(R0)
    assert not np.any(overflows)
    done = ffi.update_counts - before
    assert done["refit"] >= 10 and done["rebuild"] >= 2, done
    for s in range(50):
        want = expected_pairs(fmt, brute_pairs(Rs[s], cutoff, side, True))
        assert pairs_of(idxs[s], fmt, n) == want, f"step {s}"


def test_front_update_inside_scan_and_fori_loop_match_cell():
    n, side = 300, 9.0
    disp, shift = space.periodic(side)
    R0 = jax.random.uniform(jax.random.PRNGKey(13), (n, 3)) * side
    velocity = jax.random.normal(jax.random.PRNGKey(14), (n, 3)) * 0.05
    lists = {b: jaxrt.neighbor_list(disp, side, 1.5, dr_threshold=0.3,
                                    format=OrderedSparse, backend=b)
             for b in ("bvh", "cell")}

    def run(fns):
        def step(carry, _):
            R, nbrs = carry
            R = shift(R, velocity)
            nbrs = fns.update(R, nbrs)
            return (R, nbrs), (nbrs.idx, nbrs.reference_position)
        return jax.jit(lambda R, nbrs: jax.lax.scan(step, (R, nbrs), None,
                                                    length=40))
    out = {b: run(f)(R0, f.allocate(R0)) for b, f in lists.items()}
    (_, last), (idx, refs) = out["bvh"]
    assert not last.did_buffer_overflow
    assert np.array_equal(refs, out["cell"][1][1])
    for s in range(40):
        assert pairs_of(idx[s], OrderedSparse, n) == pairs_of(
            out["cell"][1][0][s], OrderedSparse, n)

    fns = lists["bvh"]

    def body(_, carry):
        R, nbrs = carry
        R = shift(R, velocity)
        return R, fns.update(R, nbrs)
    R, nbrs = jax.jit(lambda R, nbrs: jax.lax.fori_loop(0, 10, body, (R, nbrs)))(
        R0, fns.allocate(R0))
    assert list_pairs(nbrs) == expected_pairs(
        OrderedSparse, brute_pairs(nbrs.reference_position, 1.8, side, True))


@pytest.mark.parametrize("fmt", [Dense, Sparse])
def test_vmap_over_four_systems_equals_four_calls(fmt):
    n, side, cutoff = 200, 7.0, 1.5
    Rs = jax.random.uniform(jax.random.PRNGKey(15), (4, n, 3)) * side
    backend, query, geometry, capacity = setup_backend(Rs[0], side, cutoff,
                                                       True, fmt)
    capacity = Capacity(capacity.neighbors * 2, capacity.internal)

    def search(R):
        return backend.search(R, geometry, query, capacity, None)

    batched = jax.jit(jax.vmap(search))(Rs)
    for b in range(4):
        alone = search(Rs[b])
        assert pairs_of(batched.idx[b], fmt, n) == pairs_of(alone.idx, fmt, n)
        assert pairs_of(alone.idx, fmt, n) == brute_pairs(Rs[b], cutoff, side, True)
        assert int(batched.occupancy[b]) == int(alone.occupancy)
    assert not np.any(batched.overflow)


@pytest.mark.parametrize("fmt", FORMATS)
def test_overflow_detected_with_exact_occupancy(fmt):
    n, side, cutoff = 200, 6.0, 1.5
    R = jax.random.uniform(jax.random.PRNGKey(16), (n, 3)) * side
    backend, query, geometry, _ = setup_backend(R, side, cutoff, True, fmt)
    want = expected_pairs(fmt, brute_pairs(R, cutoff, side, True))
    rows = np.bincount([i for i, _ in brute_pairs(R, cutoff, side, True)],
                       minlength=n)
    exact = int(rows.max()) if fmt is Dense else len(want)
    small = Capacity(exact - 3, (("row", int(rows.max())),))
    result = jax.jit(lambda R: backend.search(R, geometry, query, small, None))(R)
    assert bool(result.overflow) and int(result.occupancy) == exact
    stored = pairs_of(result.idx, fmt, n)
    assert stored <= want  # what fits is right
    fits = Capacity(exact, small.internal)
    result = backend.search(R, geometry, query, fits, None)
    assert not bool(result.overflow) and pairs_of(result.idx, fmt, n) == want

    # through the front: overflow flagged under update, allocate recovers
    fns = jaxrt.neighbor_list(displacement(True, side), side, cutoff, format=fmt,
                              backend="bvh", capacity_multiplier=1.0)
    nbrs = fns.update(R * 0.5, fns.allocate(R))  # denser than allocated for
    assert nbrs.did_buffer_overflow
    assert nbrs.did_buffer_overflow == fns.update(R, nbrs).did_buffer_overflow
    assert list_pairs(fns.allocate(R * 0.5)) == expected_pairs(
        fmt, brute_pairs(R * 0.5, cutoff, side, True))


def test_cutoff_too_large_for_the_periodic_box_is_refused():
    R = jax.random.uniform(jax.random.PRNGKey(17), (50, 3)) * 4.0
    fns = jaxrt.neighbor_list(displacement(True, 4.0), 4.0, 1.9,
                              dr_threshold=0.1, backend="bvh")
    with pytest.raises(ValueError, match=r"r_cutoff.*axis 0 \(L/2"):
        fns.allocate(R)
    with pytest.raises(ValueError, match="cutoff"):
        aabb.AabbMethod().find(
            aabb.wp.array(np.asarray(R), dtype=aabb.wp.vec3), cutoff=2.0,
            side=(4.0, 4.0, 4.0), periodic=(True, True, True), mask_self=True,
            out_idx=aabb.wp.empty((50, 4), dtype=aabb.wp.int32),
            out_count=aabb.wp.empty(50, dtype=aabb.wp.int32))


@pytest.mark.parametrize("fmt", FORMATS)
def test_generic_method_backend_wraps_any_rt_method(fmt):
    wrapped = ffi.method_backend(aabb.AabbMethod())
    R = jax.random.uniform(jax.random.PRNGKey(18), (200, 3)) * 6.0
    check(R, 6.0, 1.4, True, fmt, backend=wrapped, jax_md_too=False)
    backend, query, geometry, capacity = setup_backend(
        R, 6.0, 1.4, True, fmt, backend=wrapped)
    Rs = jnp.stack([R, R[::-1]])
    batched = jax.vmap(lambda R: backend.search(R, geometry, query, capacity,
                                                None))(Rs)
    for b in range(2):
        assert pairs_of(batched.idx[b], fmt, 200) == expected_pairs(
            fmt, brute_pairs(Rs[b], 1.4, 6.0, True))


@pytest.mark.filterwarnings("ignore:Explicitly requested dtype")  # jax-md's LJ
def test_gradients_flow_through_update_and_match_jax_md():
    from functools import partial

    from jax_md import energy
    side = 6.0
    R = jnp.asarray(lattice(5, 1.2) + np.random.default_rng(1).normal(
        scale=0.05, size=(125, 3)), jnp.float32)
    disp = displacement(True, side)
    grads = {}
    for name, fn in (("bvh", partial(jaxrt.neighbor_list, backend="bvh")),
                     ("jax-md", partition.neighbor_list)):
        nbr_fn, energy_fn = energy.lennard_jones_neighbor_list(
            disp, side, r_cutoff=2.0, dr_threshold=0.2, neighbor_list_fn=fn)
        nbrs = nbr_fn.allocate(R)
        grads[name] = jax.jit(jax.grad(
            lambda R: energy_fn(R, nbr_fn.update(R, nbrs))))(R)
    np.testing.assert_allclose(grads["bvh"], grads["jax-md"], rtol=1e-5,
                               atol=1e-5)


def test_non_finite_position_is_flagged_not_fatal():
    R = jax.random.uniform(jax.random.PRNGKey(19), (100, 3)) * 5.0
    for periodic in (True, False):
        fns = jaxrt.neighbor_list(displacement(periodic, 5.0), 5.0, 1.2,
                                  backend="bvh", format=Sparse)
        nbrs = fns.allocate(R)
        for bad in (jnp.nan, jnp.inf):
            broken = jax.jit(fns.update)(R.at[3, 1].set(bad), nbrs)
            assert broken.did_buffer_overflow
            assert all(3 not in pair for pair in list_pairs(broken))
        assert list_pairs(fns.update(R, nbrs)) == brute_pairs(R, 1.2, 5.0,
                                                              periodic)


def test_each_list_factory_keeps_its_own_trees_and_frees_them():
    """Ten live lists (more than the eight trees an LRU once kept) each
    refit their own BVH on every later call, and a factory's trees are
    freed with it (once JAX's caches, whose compiled programs may still
    call them, let go of it too)."""
    import gc
    n, side = 120, 6.0
    disp, _ = space.periodic(side)
    R = jax.random.uniform(jax.random.PRNGKey(30), (n, 3)) * side
    lists, cutoffs = [], [1.2 + 0.01 * k for k in range(10)]
    for cutoff in cutoffs:
        fns = jaxrt.neighbor_list(disp, side, cutoff, backend="bvh")
        lists.append((fns, fns.allocate(R)))
    step = [jax.jit(fns.update) for fns, _ in lists]
    for update, (_, nbrs) in zip(step, lists):  # compile; the calls finish
        jax.block_until_ready(update(R, nbrs))
    before = ffi.update_counts.copy()
    for _ in range(2):
        for update, (_, nbrs), cutoff in zip(step, lists, cutoffs):
            moved = jnp.mod(R + 0.001, side)
            got = update(moved, nbrs)
            assert list_pairs(got) == brute_pairs(moved, cutoff, side, True)
    done = ffi.update_counts - before
    assert done["refit"] == 20 and done["build"] == 0, done
    owned = [s for fns, _ in lists
             for s in fns.update.__self__.searcher.owner.slots]
    assert len(owned) == 10 and all(s in ffi._SLOTS for s in owned)
    del lists, step, update, nbrs, got, fns, _
    jax.clear_caches()
    gc.collect()
    assert not any(s in ffi._SLOTS for s in owned)
