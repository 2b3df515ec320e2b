"""The cell list's GPU kernel (`jaxrt.backends.cell.kernel`) against the float64 brute
force and the portable path, run in Pallas' interpreter so that CPUs test
the same kernel body that CUDA compiles (on a GPU, every cell-list test in
`test_neighbors.py` runs the compiled kernel as well)."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax_md import partition, space

import jaxrt
from jaxrt import backends
from oracle import assert_layout, brute_pairs, expected_pairs, list_pairs
from scenes import lattice


INTERPRETED = backends.Cell(kernel="interpret")
PORTABLE = backends.Cell(kernel="xla")


@pytest.fixture
def kernel():
    """The cell list with its kernel run in Pallas' interpreter."""
    from jaxrt.backends.cell import kernel as _cell_kernel
    if not _cell_kernel.fits(1, 1, 1):
        pytest.skip("SKIPPED KERNEL TEST: this JAX has no Pallas Triton "
                    "backend, so the cell list's kernel is untested here")
    return INTERPRETED


def kernel_list(R, side, cutoff, periodic, fmt=partition.Dense,
                mask_self=True, metric=None, backend=INTERPRETED):
    disp = metric or (space.periodic(side)[0] if periodic
                      else space.free()[0])
    nbrs = jaxrt.neighbor_list(disp, side if periodic else None, cutoff,
                               format=fmt, mask_self=mask_self,
                               backend=backend).allocate(jnp.asarray(R))
    assert not nbrs.did_buffer_overflow
    assert_layout(nbrs)
    return nbrs


def check(R, side, cutoff, periodic, fmt=partition.Dense, mask_self=True):
    nbrs = kernel_list(R, side, cutoff, periodic, fmt, mask_self)
    want = brute_pairs(R, cutoff, side, periodic, mask_self)
    assert list_pairs(nbrs) == expected_pairs(fmt, want)
    return nbrs


RNG = np.random.default_rng(20)
SIDE = np.float32(6.0)
BELOW = np.nextafter(SIDE, np.float32(0))
SCENES = {
    # name: (positions, side, cutoff, periodic)
    "random": (RNG.uniform(0, 7, (260, 3)).astype(np.float32), 7.0, 1.6,
               True),
    "random free": (RNG.uniform(0, 7, (260, 3)).astype(np.float32), 7.0, 1.6,
                    False),
    # second neighbours exactly at the cutoff: the shell decides them.
    "lattice at cutoff": (lattice(6, 0.5), 3.0, 1.0, True),
    "lattice at cutoff, free": (lattice(6, 0.5), 3.0, 1.0, False),
    # faces and corners: runs that wrap around x.
    "faces": (np.asarray([[0, 0, 0], [BELOW] * 3, [0, BELOW, 3], [BELOW, 0, 0],
                          [3, 3, 0], [3, 3, BELOW], [0, 3, 3], [BELOW, 3, 3],
                          [1, 1, 1]], np.float32), SIDE, 1.0, True),
    "coincident": (np.asarray([[1, 1, 1], [1, 1, 1], [1, 1, 2], [1, 2, 1],
                               [2, 1, 1], [1, 1, 1]], np.float32), 5.0, 1.5,
                   True),
    # the whole x row is the stencil: one run of every cell.
    "box of 2.01 cutoffs": (RNG.uniform(0, 2.01, (90, 3)).astype(np.float32),
                            2.01, 1.0, True),
    "box of 3.01 cutoffs": (RNG.uniform(0, 3.01, (90, 3)).astype(np.float32),
                            3.01, 1.0, True),
    "2d": (RNG.uniform(0, 9, (300, 2)).astype(np.float32), 9.0, 1.1, True),
    "2d free": (RNG.uniform(0, 9, (300, 2)).astype(np.float32), 9.0, 1.1,
                False),
}


@pytest.mark.parametrize("name", SCENES)
def test_kernel_matches_brute_force_and_the_portable_path(kernel, name):
    R, side, cutoff, periodic = SCENES[name]
    got = check(R, side, cutoff, periodic)
    portable = kernel_list(R, side, cutoff, periodic, backend=PORTABLE)
    # the same sets; the kernel appends shell pairs after the sure ones
    assert np.array_equal(np.sort(np.asarray(got.idx), axis=1),
                          np.sort(np.asarray(portable.idx), axis=1))


@pytest.mark.parametrize("fmt, mask_self", [(partition.Sparse, False),
                                             (partition.OrderedSparse, True)])
def test_kernel_sparse_layouts_and_self_pairs(kernel, fmt, mask_self):
    R, side, cutoff, periodic = SCENES["random"]
    check(R[:120], side, cutoff, periodic, fmt, mask_self)


def test_kernel_mixed_boundaries_and_per_axis_box(kernel):
    side = np.array([6.0, 9.0, 4.0], np.float32)
    R = RNG.uniform(0, 1, (200, 3)).astype(np.float32) * side

    def slab(ra, rb):  # periodic in x and y only
        d = ra - rb
        wrapped = jnp.mod(d + side / 2, side) - side / 2
        return jnp.where(jnp.array([True, True, False]), wrapped, d)

    nbrs = kernel_list(R, side, 1.3, True, metric=slab)
    assert list_pairs(nbrs) == brute_pairs(R, 1.3, side, [True, True, False])


def test_kernel_float64_pairs_a_hair_inside_and_outside(kernel):
    with jax.enable_x64(True):
        rng = np.random.default_rng(0)
        base = 1000.0 + rng.uniform(0, 1, (40, 3))
        direction = rng.normal(size=(40, 3))
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        R = np.concatenate([base, base + direction * 0.75 * (1 - 1e-12),
                            base + direction * 0.75 * (1 + 1e-12)])
        pairs = list_pairs(kernel_list(R, None, 0.75, False))
        assert pairs == brute_pairs(R, 0.75)
        for k in range(40):
            assert (k, 40 + k) in pairs and (k, 80 + k) not in pairs


def test_kernel_overflow_is_flagged_and_fixed_by_reallocation(kernel):
    side = 6.0
    disp, _ = space.periodic(side)
    fns = jaxrt.neighbor_list(disp, side, 1.2, backend=kernel)
    R = jax.random.uniform(jax.random.PRNGKey(15), (150, 3)) * side
    nbrs = fns.allocate(R)
    # squeeze a third of the particles into a corner: rows outgrow capacity
    crowded = R.at[:50].multiply(0.1)
    nbrs = jax.jit(fns.update)(crowded, nbrs)
    assert nbrs.did_buffer_overflow
    nbrs = fns.allocate(crowded)
    assert not nbrs.did_buffer_overflow
    assert list_pairs(nbrs) == brute_pairs(crowded, 1.2, side, True)


def test_kernel_under_vmap_and_scan(kernel):
    side = 5.0
    disp, shift = space.periodic(side)
    fns = jaxrt.neighbor_list(disp, side, 1.1, capacity_multiplier=1.5,
                              backend=kernel)
    Rs = jax.random.uniform(jax.random.PRNGKey(14), (3, 80, 3)) * side
    nbrs = fns.allocate(Rs[0])
    batch = jax.vmap(fns.update, in_axes=(0, None))(Rs, nbrs)
    assert not np.any(np.asarray(batch.did_buffer_overflow))
    for b in range(3):
        one = batch.idx[b]
        listed = {(i, int(j)) for i, row in enumerate(np.asarray(one))
                  for j in row if j < 80}
        assert listed == brute_pairs(Rs[b], 1.1, side, True)

    def step(nbrs, R):
        nbrs = nbrs.update(R)
        return nbrs, nbrs.idx

    last, idxs = jax.lax.scan(step, nbrs, Rs)
    assert np.array_equal(np.asarray(idxs), np.asarray(batch.idx))
    assert not last.did_buffer_overflow


def test_kernel_list_update_inside_grad(kernel):
    """Differentiating through ``nbrs.update`` (forces inside a training
    loss) must not differentiate the kernel: the same gradient as the
    portable path."""
    side = 5.0
    disp, _ = space.periodic(side)
    R = jax.random.uniform(jax.random.PRNGKey(21), (60, 3)) * side

    def gradient(backend):
        fns = jaxrt.neighbor_list(disp, side, 1.5, backend=backend)
        nbrs = fns.allocate(R)

        def loss(sigma_scale, R):
            nbrs2 = nbrs.update(R * sigma_scale)
            d = jax.vmap(lambda i, row: jax.vmap(
                lambda j: disp(R[i], R[j]))(row))(jnp.arange(60), nbrs2.idx)
            r = jnp.sqrt(jnp.sum(d ** 2, axis=-1) + 1.0)
            return jnp.sum(jnp.where(nbrs2.idx < 60, r, 0.0)) * sigma_scale

        return jax.grad(loss, argnums=(0, 1))(1.0, R)

    got = gradient(kernel)
    want = gradient(PORTABLE)
    # Rows list the same neighbours in another order, so each entry is the
    # same float32 sum in another order: over at most ~64 terms of size up
    # to max|w| (|dr/dR| <= 1), reordering moves it by up to 64 eps max|w|,
    # absolute. An entry that cancels to near zero has no relative bound
    # (1 of 180 differed by 6e-8, 1.5e-5 relative, on the H200).
    eps = np.finfo(np.float32).eps
    for g, w in zip(got, want):
        g, w = np.asarray(g), np.asarray(w)
        assert np.all(np.isfinite(g))
        np.testing.assert_allclose(g, w, rtol=1e-6,
                                   atol=64 * eps * np.max(np.abs(w)))


# --------------------------------------------------------------------------
# OrderedSparse as half rows: both candidate passes keep only j < i, so the
# rows hold its edges alone (no rank along full rows, no second measuring
# pass at allocate).


@pytest.mark.parametrize("backend", [INTERPRETED, PORTABLE],
                         ids=["interpret", "xla"])
@pytest.mark.parametrize("name", ["random", "lattice at cutoff", "faces",
                                  "coincident", "box of 2.01 cutoffs",
                                  "2d free"])
def test_ordered_sparse_rows_hold_only_lower_neighbours(backend, name):
    from jaxrt.backends import Geometry, MetricSq, Query
    from jaxrt.lists.neighbors import metric_sq_fn

    if backend is INTERPRETED:
        from jaxrt.backends.cell import kernel as _cell_kernel
        if not _cell_kernel.fits(1, 1, 1):
            pytest.skip("SKIPPED KERNEL TEST: no Pallas Triton backend")
    R, side, cutoff, periodic = SCENES[name]
    nbrs = kernel_list(R, side, cutoff, periodic, partition.OrderedSparse,
                       backend=backend)
    want = brute_pairs(R, cutoff, side, periodic, True)
    assert list_pairs(nbrs) == expected_pairs(partition.OrderedSparse, want)
    # The rows' width is the most lower neighbours of one particle, exactly
    # (full rows would need the most neighbours: larger wherever the
    # particle with the most neighbours has one of higher index).
    dim = R.shape[1]
    disp = space.periodic(side)[0] if periodic else space.free()[0]
    query = Query(cutoff, (periodic,) * dim, True, partition.OrderedSparse)
    geometry = Geometry(jnp.full(dim, side, jnp.float32), jnp.ones(dim))
    sizes = backend.measure(jnp.asarray(R), geometry, query,
                            MetricSq(metric_sq_fn(disp, dim)))
    lower = np.zeros(len(R), int)
    for i, j in want:
        lower[i] += j < i
    assert sizes["row"] == lower.max(initial=0)
    assert sizes["edges"] == lower.sum()


# --------------------------------------------------------------------------
# Rows to edges (`jaxrt.layouts.edge_kernel`), run in Pallas' interpreter, against
# XLA's scatters: the same array, slot for slot.


def _rows(counts, width, seed=0):
    counts = np.asarray(counts)
    n = len(counts)
    rng = np.random.default_rng(seed)
    dense = np.full((n, width), n, np.int32)
    for i, c in enumerate(counts):
        dense[i, :c] = rng.integers(0, n, c)
    return jnp.asarray(dense), jnp.asarray(counts, jnp.int32)


EDGE_ROWS = {
    # name: (counts, width); N and widths off the kernel's 32 x 32 tiles
    "random": (np.random.default_rng(1).integers(0, 41, 75), 40),
    "all empty": (np.zeros(33, int), 5),
    "all full": (np.full(65, 70), 70),
    "one row": ([3], 3),
    "one full row among empty ones": ([0] * 40 + [64] + [0] * 30, 64),
    "width one": (np.random.default_rng(2).integers(0, 2, 100), 1),
}


@pytest.mark.parametrize("name", EDGE_ROWS)
@pytest.mark.parametrize("room", [0, 9, -7], ids=["exact", "more", "fewer"])
def test_rows_to_edges_kernel_writes_what_the_scatters_write(name, room):
    from jaxrt.backends import contract as _backend
    from jaxrt.layouts import edge_kernel as _edge_kernel

    counts, width = EDGE_ROWS[name]
    dense, counts = _rows(counts, width)
    total = int(counts.sum())
    capacity = max(total + room, 1)
    if not _edge_kernel.fits(len(counts), width, capacity):
        pytest.skip("SKIPPED KERNEL TEST: no Pallas Triton backend")
    want, want_total = _backend.dense_to_sparse(dense, capacity, False,
                                                engine="xla")
    # On a GPU "auto" is the compiled kernel: it is tested there too.
    engines = ["interpret"] + (["auto"] if jax.default_backend() == "gpu"
                               else [])
    for engine in engines:
        got, got_total = _backend.dense_to_sparse(dense, capacity, False,
                                                  counts=counts,
                                                  engine=engine)
        assert int(got_total) == int(want_total) == total
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    # The scatters themselves, against the definition.
    dense_np, counts_np = np.asarray(dense), np.asarray(counts)
    edges = [(int(dense_np[i, c]), i) for i in range(len(counts_np))
             for c in range(counts_np[i])][:capacity]
    listed = np.asarray(want)[:, :len(edges)].T
    assert [tuple(e) for e in listed.tolist()] == edges
    assert np.all(np.asarray(want)[:, len(edges):] == len(counts_np))


def test_rows_to_edges_kernel_under_vmap():
    """A batch of lists (`vmap` over `update`) converts through the kernel
    batched by Pallas: each list's edges as converted alone."""
    from jaxrt.backends import contract as _backend
    from jaxrt.layouts import edge_kernel as _edge_kernel

    rng = np.random.default_rng(4)
    batch = [_rows(rng.integers(0, 13, 50), 12, seed=b) for b in range(3)]
    dense = jnp.stack([d for d, _ in batch])
    counts = jnp.stack([c for _, c in batch])
    capacity = int(counts.sum(1).max()) + 5
    if not _edge_kernel.fits(50, 12, capacity):
        pytest.skip("SKIPPED KERNEL TEST: no Pallas Triton backend")
    want = jax.vmap(lambda d: _backend.dense_to_sparse(
        d, capacity, False, engine="xla"))(dense)
    engines = ["interpret"] + (["auto"] if jax.default_backend() == "gpu"
                               else [])
    for engine in engines:
        got = jax.vmap(lambda d, c, e=engine: _backend.dense_to_sparse(
            d, capacity, False, counts=c, engine=e))(dense, counts)
        np.testing.assert_array_equal(np.asarray(got[0]), np.asarray(want[0]))
        np.testing.assert_array_equal(np.asarray(got[1]), np.asarray(want[1]))


def test_rows_to_edges_refuses_unknown_engine():
    from jaxrt.backends import contract as _backend

    dense, _ = _rows([1, 0], 1)
    with pytest.raises(ValueError, match="engine='gpu'.*choose one of"):
        _backend.dense_to_sparse(dense, 2, False, engine="gpu")


def test_rows_to_edges_refuses_counts_of_ordered_rows():
    from jaxrt.backends import contract as _backend

    dense, counts = _rows([1, 0], 1)
    with pytest.raises(ValueError, match="counts=.*ordered=True"):
        _backend.dense_to_sparse(dense, 2, True, counts=counts)
