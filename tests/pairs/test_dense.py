"""`jaxrt.pairs_batch(max_nodes=...)`: each system searched as one dense
block (every atom against every atom of its system, in every image of the
reach), checked against ASE's ``neighbor_list("ijS")`` system by system and
against the cell search on the same batch (same edges, same ``n_edge``,
sorted by ``i``, each atom's self pair first).

The batches hold what the dense block must get right: a molecule (all-zero
cell), a ``vacuum=None`` slab, rattled bulk, one-atom cells and skewed or
rhombohedral cells with the cutoff several heights across (shifts of 3 and
more), atoms given outside their cell (wrapped, then shifted back).
"""
from __future__ import annotations

import importlib

import jax
import numpy as np
import pytest

ase = pytest.importorskip("ase")
from ase import Atoms  # noqa: E402
from ase.build import bulk, fcc111, molecule  # noqa: E402
from ase.neighborlist import neighbor_list as ase_neighbor_list  # noqa: E402

import jaxrt  # noqa: E402

ErrorBit = importlib.import_module("jaxrt.pairs.bits").ErrorBit

CUTOFF = 4.0


@pytest.fixture
def x64():
    with jax.enable_x64(True):
        yield


def one_atom():
    return Atoms("Cu", positions=[[0.3, -0.2, 0.1]],
                 cell=[[0, 1.8, 1.8], [1.8, 0, 1.8], [1.8, 1.8, 0]],
                 pbc=True)


def rhombohedral():
    # A thin cell (heights near 1.2 Å): cutoff / height > 3 on every axis.
    a, alpha = 2.0, np.radians(35.0)
    c = np.cos(alpha)
    cell = a * np.array([[1, 0, 0], [c, np.sin(alpha), 0],
                         [c, (c - c * c) / np.sin(alpha),
                          np.sqrt(1 - c * c - ((c - c * c) / np.sin(alpha))
                                  ** 2)]])
    frac = np.array([[0.1, 0.2, 0.3], [0.6, -0.4, 1.7]])
    return Atoms("H2", positions=frac @ cell, cell=cell, pbc=True)


def skewed():
    rng = np.random.default_rng(0)
    cell = np.array([[4.0, 0, 0], [3.1, 3.5, 0], [-2.7, 1.9, 3.2]])
    cell = cell + rng.uniform(-0.3, 0.3, (3, 3))
    frac = rng.uniform(-0.5, 1.7, (5, 3))
    return Atoms("H5", positions=frac @ cell, cell=cell, pbc=True)


def mixed():
    cu = bulk("Cu", "fcc", a=3.61, cubic=True)
    cu.rattle(0.05, seed=1)
    return [molecule("CH3CH2OH"), fcc111("Al", size=(2, 2, 2), vacuum=None),
            cu, one_atom(), skewed(), rhombohedral()]


def ase_set(atoms, cutoff=CUTOFF, **kw) -> set:
    i, j, s = ase_neighbor_list("ijS", atoms, cutoff, **kw)
    return {(int(a), int(b), *map(int, c)) for a, b, c in zip(i, j, s)}


def per_system(result, n_node, n_systems: int) -> list[set]:
    i, j, s = (np.asarray(x) for x in (result.i, result.j, result.shift))
    n_edge = np.asarray(result.n_edge)
    starts = np.concatenate([[0], np.cumsum(n_node)])
    edges = np.concatenate([[0], np.cumsum(n_edge)])
    out = []
    for g in range(n_systems):
        a, b = edges[g], edges[g + 1]
        lo, hi = starts[g], starts[g + 1]
        assert np.all((i[a:b] >= lo) & (i[a:b] < hi)), g
        assert np.all((j[a:b] >= lo) & (j[a:b] < hi)), g
        out.append({(int(p) - lo, int(q) - lo, *map(int, t))
                    for p, q, t in zip(i[a:b], j[a:b], s[a:b])})
    return out


def test_mixed_batch_dense_matches_ase_and_the_cells(x64):
    systems = mixed()
    batch = jaxrt.batch_from_ase(systems, pad=False)
    m = int(np.max(batch.n_node))
    got = jaxrt.pairs_batch(batch.positions, batch.n_node, CUTOFF,
                            max_nodes=m, **batch.kwargs)
    cells = jaxrt.pairs_batch(batch.positions, batch.n_node, CUTOFF,
                              max_nodes=0, **batch.kwargs)
    assert int(got.error) == 0
    want = [ase_set(a) for a in systems]
    assert max(max(abs(p[2]), abs(p[3]), abs(p[4])) for p in want[-1]) >= 3
    assert per_system(got, batch.n_node, len(systems)) == want
    np.testing.assert_array_equal(got.n_edge, cells.n_edge)
    np.testing.assert_array_equal(got.i, cells.i)  # both sorted by i
    d = np.asarray(got.distances(batch.positions, batch.cell))
    assert np.all(d < CUTOFF) and np.all(d > 0)


def test_jitted_padded_dense_batch_matches_ase_and_pads_as_jraph(x64):
    systems = mixed()
    batch = jaxrt.batch_from_ase(systems)
    n_real = int(np.sum(batch.n_node[:len(systems)]))
    sizes = jaxrt.pairs_batch_sizes(batch.positions, batch.n_node, CUTOFF,
                                    **batch.kwargs)
    capacity = sizes.capacity + 5
    m = int(np.max(batch.n_node[:len(systems)]))

    @jax.jit
    def edges(r, n_node, cell, pbc, mask):
        return jaxrt.pairs_batch(r, n_node, CUTOFF, cell=cell, pbc=pbc,
                                 graph_mask=mask, capacity=capacity,
                                 max_shift=sizes.max_shift, max_nodes=m)

    got = edges(*batch[:1], *batch[2:])
    assert int(got.error) == 0
    assert per_system(got, batch.n_node, len(systems)) == [
        ase_set(a) for a in systems]
    count = int(got.count)
    assert np.all(np.asarray(got.i)[count:] == n_real)
    assert np.all(np.asarray(got.j)[count:] == n_real)
    n_edge = np.asarray(got.n_edge)
    assert n_edge[len(systems)] == capacity - count
    assert n_edge.sum() == capacity


@pytest.mark.parametrize("half", [False, True])
def test_dense_half_lists_self_pairs_and_species(x64, half):
    systems = [bulk("NaCl", "rocksalt", a=5.64), molecule("CH3CH2OH")]
    cutoffs = {(11, 17): 3.2, (17, 17): 4.2, (1, 6): 1.2, (6, 6): 1.6,
               (6, 8): 1.5, (1, 8): 1.0}
    batch = jaxrt.batch_from_ase(systems, pad=False)
    kw = dict(species=batch.numbers, half=half, self_interaction=True,
              **batch.kwargs)
    got = jaxrt.pairs_batch(batch.positions, batch.n_node, cutoffs,
                            max_nodes=9, **kw)
    cells = jaxrt.pairs_batch(batch.positions, batch.n_node, cutoffs,
                              max_nodes=0, **kw)
    for a, edges in zip(systems, per_system(got, batch.n_node, 2)):
        want = ase_set(a, cutoffs, self_interaction=True)
        if half:
            want = {p for p in want if p[0] < p[1] or (
                p[0] == p[1] and tuple(p[2:]) >= (0, 0, 0))}
        assert edges == want
    np.testing.assert_array_equal(got.i, cells.i)
    # Each atom's self pair opens its edges (Cl and the two C have one; no
    # Na-Na, O-O or H-H cutoff).
    i, j = np.asarray(got.i)[:int(got.count)], np.asarray(got.j)
    self_at = np.nonzero((i == j[:len(i)]) & ~np.asarray(
        got.shift)[:len(i)].any(axis=1))[0]
    assert len(self_at) == 3
    np.testing.assert_array_equal(self_at, np.searchsorted(i, i[self_at]))


def test_dense_flags_a_system_larger_than_max_nodes(x64):
    systems = [bulk("Cu", "fcc", a=3.61, cubic=True), one_atom()]
    batch = jaxrt.batch_from_ase(systems, pad=False)
    got = jax.jit(lambda r: jaxrt.pairs_batch(
        r, batch.n_node, CUTOFF, capacity=512, max_shift=3, max_nodes=3,
        **batch.kwargs))(batch.positions)
    assert int(got.error) == int(ErrorBit.MAX_NODES)
    with pytest.raises(jaxrt.PairsError, match="max_nodes"):
        got.check()
    with pytest.raises(ValueError, match="max_nodes"):
        jaxrt.pairs_batch(batch.positions, batch.n_node, CUTOFF,
                          max_nodes=-1, **batch.kwargs)


def test_sizes_choose_dense_blocks_for_small_systems_only(x64):
    small = jaxrt.batch_from_ase(mixed()[:-1], pad=False)
    sizes = jaxrt.pairs_batch_sizes(small.positions, small.n_node, CUTOFF,
                                    **small.kwargs)
    assert sizes.max_shift == (2, 2, 2)
    assert sizes.kwargs["max_nodes"] == 12  # 9 atoms (bucket 12) x 125
    thin = jaxrt.batch_from_ase(mixed(), pad=False)
    sizes_thin = jaxrt.pairs_batch_sizes(thin.positions, thin.n_node,
                                         CUTOFF, **thin.kwargs)
    assert sizes_thin.max_shift == (4, 4, 4)
    assert sizes_thin.max_nodes == 0  # 12 x 729 images: cells
    mid = jaxrt.batch_from_ase([bulk("Cu", "fcc", a=3.61, cubic=True)
                                .repeat((4, 4, 4))], pad=False)
    sizes_mid = jaxrt.pairs_batch_sizes(mid.positions, mid.n_node, CUTOFF,
                                        **mid.kwargs)
    assert sizes_mid.max_nodes == 256  # 256 atoms x 27 images: tiles
    assert sizes.merge(sizes_mid).max_nodes == 256  # x 125 images
    big = jaxrt.batch_from_ase([bulk("Cu", "fcc", a=3.61, cubic=True)
                                .repeat((7, 7, 7))], pad=False)
    sizes_big = jaxrt.pairs_batch_sizes(big.positions, big.n_node, CUTOFF,
                                        **big.kwargs)
    assert sizes_big.max_nodes == 0  # 1372 atoms (bucket 1536): cells
    assert sizes.merge(sizes_big).max_nodes == 0
    assert sizes_mid.merge(sizes_thin).max_nodes == 0  # 256 x 729 images
    assert jaxrt.pairs_sizes(big.positions, CUTOFF,
                             cell=big.cell[0]).max_nodes is None


def test_dense_capacity_overflow_keeps_exact_counts(x64):
    systems = mixed()[2:4]
    batch = jaxrt.batch_from_ase(systems)
    exact = jaxrt.pairs_batch(batch.positions, batch.n_node, CUTOFF,
                              **batch.kwargs)
    small = jax.jit(lambda r: jaxrt.pairs_batch(
        r, batch.n_node, CUTOFF, capacity=10, max_shift=3, max_nodes=4,
        **batch.kwargs))(batch.positions)
    assert int(small.error) == int(ErrorBit.CAPACITY)
    np.testing.assert_array_equal(np.asarray(small.n_edge)[:2],
                                  np.asarray(exact.n_edge)[:2])
    assert int(small.count) == int(exact.count)
    # The stored prefix is the exact list's prefix.
    np.testing.assert_array_equal(np.asarray(small.i), exact.i[:10])
    np.testing.assert_array_equal(np.asarray(small.shift),
                                  exact.shift[:10])


def test_dense_too_short_reach_is_flagged(x64):
    batch = jaxrt.batch_from_ase([rhombohedral()], pad=False)
    got = jax.jit(lambda r: jaxrt.pairs_batch(
        r, batch.n_node, CUTOFF, capacity=512, max_shift=1, max_nodes=2,
        **batch.kwargs))(batch.positions)
    assert int(got.error) & int(ErrorBit.MAX_SHIFT)


def test_float32_dense_equals_the_cells():
    # float32 (x64 off): both searches decide with the same expression in
    # the same dtype, so the edge sets are equal, not only close.
    systems = mixed()[:-1]
    batch = jaxrt.batch_from_ase(systems, pad=False)
    r = np.asarray(batch.positions, np.float32)
    kw = dict(batch.kwargs, cell=np.asarray(batch.cell, np.float32))
    dense = jaxrt.pairs_batch(r, batch.n_node, CUTOFF, max_nodes=9, **kw)
    cells = jaxrt.pairs_batch(r, batch.n_node, CUTOFF, max_nodes=0, **kw)
    assert per_system(dense, batch.n_node, len(systems)) == per_system(
        cells, batch.n_node, len(systems))
    np.testing.assert_array_equal(dense.n_edge, cells.n_edge)


# Tiles: systems of more than one word (32 atoms), each atom deciding only
# the 32-atom tiles whose box may come within the cutoff.


def simple_cubic(n: int = 4, spacing: float = 2.0):
    # Every distance a whole multiple of 2.0 apart along the axes: pairs at
    # exactly the cutoff (4.0) through the images, which ASE leaves out.
    grid = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"),
                    -1).reshape(-1, 3) * spacing
    return Atoms(f"Cu{len(grid)}", positions=grid,
                 cell=np.eye(3) * n * spacing, pbc=True)


def crowded_skewed(n: int = 70, seed: int = 3):
    # Many atoms in a thin skewed cell (shifts of 2 and more): most tiles
    # near most atoms.
    rng = np.random.default_rng(seed)
    cell = np.array([[3.1, 0, 0], [1.7, 2.9, 0], [-0.8, 1.1, 9.0]])
    frac = rng.uniform(-0.3, 1.4, (n, 3))
    return Atoms(f"H{n}", positions=frac @ cell, cell=cell, pbc=True)


def tiled_systems():
    cu = bulk("Cu", "fcc", a=3.61, cubic=True).repeat((3, 3, 3))
    cu.rattle(0.05, seed=2)  # 108 atoms: the last tile part empty
    slab = fcc111("Al", size=(3, 3, 4), vacuum=None)  # 36 atoms
    big = molecule("C60")  # free axes
    return [cu, simple_cubic(), slab, big, one_atom(), crowded_skewed()]


def test_tiles_match_ase_at_the_cutoff_and_with_many_images(x64):
    systems = tiled_systems()
    batch = jaxrt.batch_from_ase(systems, pad=False)
    m = int(np.max(batch.n_node))
    assert m > 64
    got = jaxrt.pairs_batch(batch.positions, batch.n_node, CUTOFF,
                            max_nodes=m, **batch.kwargs)
    cells = jaxrt.pairs_batch(batch.positions, batch.n_node, CUTOFF,
                              max_nodes=0, **batch.kwargs)
    assert int(got.error) == 0
    want = [ase_set(a) for a in systems]
    # The simple cubic lattice has pairs at exactly 4.0 that ASE drops:
    # twice as many at a cutoff a rounding above it.
    above = ase_set(systems[1], np.nextafter(CUTOFF, 5.0))
    assert len(above) > len(want[1])
    assert max(max(abs(p[2]), abs(p[3]), abs(p[4])) for p in want[-1]) >= 2
    assert per_system(got, batch.n_node, len(systems)) == want
    np.testing.assert_array_equal(got.n_edge, cells.n_edge)
    np.testing.assert_array_equal(got.i, cells.i)
    # A cutoff a rounding above: the pairs at 4.0 come in, as in ASE.
    got_above = jaxrt.pairs_batch(batch.positions, batch.n_node,
                                  np.nextafter(CUTOFF, 5.0), max_nodes=m,
                                  **batch.kwargs)
    assert per_system(got_above, batch.n_node, len(systems))[1] == above


def test_jitted_padded_tiles_match_ase(x64):
    systems = tiled_systems()
    batch = jaxrt.batch_from_ase(systems)
    sizes = jaxrt.pairs_batch_sizes(batch.positions, batch.n_node, CUTOFF,
                                    **batch.kwargs)
    assert sizes.max_nodes >= 108
    capacity = sizes.capacity

    @jax.jit
    def edges(r, n_node, cell, pbc, mask):
        return jaxrt.pairs_batch(r, n_node, CUTOFF, cell=cell, pbc=pbc,
                                 graph_mask=mask, capacity=capacity,
                                 max_shift=sizes.max_shift,
                                 max_nodes=sizes.max_nodes)

    got = edges(*batch[:1], *batch[2:])
    assert int(got.error) == 0
    assert per_system(got, batch.n_node, len(systems)) == [
        ase_set(a) for a in systems]


@pytest.mark.parametrize("half", [False, True])
def test_tiles_half_lists_self_pairs_and_species(x64, half):
    nacl = bulk("NaCl", "rocksalt", a=5.64, cubic=True).repeat((2, 2, 3))
    nacl.rattle(0.05, seed=4)  # 96 atoms
    systems = [nacl, molecule("C60")]
    cutoffs = {(11, 17): 3.2, (17, 17): 4.2, (6, 6): 1.6, (11, 11): 0.0}
    batch = jaxrt.batch_from_ase(systems, pad=False)
    kw = dict(species=batch.numbers, half=half, self_interaction=True,
              **batch.kwargs)
    got = jaxrt.pairs_batch(batch.positions, batch.n_node, cutoffs,
                            max_nodes=96, **kw)
    cells = jaxrt.pairs_batch(batch.positions, batch.n_node, cutoffs,
                              max_nodes=0, **kw)
    for a, edges in zip(systems, per_system(got, batch.n_node, 2)):
        want = ase_set(a, cutoffs, self_interaction=True)
        if half:
            want = {p for p in want if p[0] < p[1] or (
                p[0] == p[1] and tuple(p[2:]) >= (0, 0, 0))}
        assert edges == want
    np.testing.assert_array_equal(got.i, cells.i)
    np.testing.assert_array_equal(got.n_edge, cells.n_edge)
    # Each atom's self pair opens its edges (Cl and C: no Na-Na cutoff).
    i, j = np.asarray(got.i)[:int(got.count)], np.asarray(got.j)
    self_at = np.nonzero((i == j[:len(i)]) & ~np.asarray(
        got.shift)[:len(i)].any(axis=1))[0]
    assert len(self_at) == 48 + 60
    np.testing.assert_array_equal(self_at, np.searchsorted(i, i[self_at]))


def test_tiles_near_everything_fall_back_to_every_candidate(x64):
    # 64 atoms in a cell a little wider than the cutoff: every tile is near
    # every atom in nearly every image, past the tiles' room (one word per
    # image per atom), so every candidate is decided.
    rng = np.random.default_rng(5)
    systems = []
    for skew in (0.2, 0.0):
        cell = np.eye(3) * 4.2 + rng.uniform(-skew, skew, (3, 3))
        systems.append(Atoms("H64", positions=rng.uniform(
            0, 1, (64, 3)) @ cell, cell=cell, pbc=True))
    batch = jaxrt.batch_from_ase(systems, pad=False)
    got = jaxrt.pairs_batch(batch.positions, batch.n_node, CUTOFF,
                            max_nodes=64, **batch.kwargs)
    assert int(got.error) == 0
    assert per_system(got, batch.n_node, 2) == [ase_set(a) for a in systems]


def test_tiles_capacity_overflow_keeps_exact_counts(x64):
    systems = tiled_systems()[:3]
    batch = jaxrt.batch_from_ase(systems, pad=False)
    exact = jaxrt.pairs_batch(batch.positions, batch.n_node, CUTOFF,
                              max_nodes=108, **batch.kwargs)
    small = jax.jit(lambda r: jaxrt.pairs_batch(
        r, batch.n_node, CUTOFF, capacity=100, max_shift=2, max_nodes=108,
        **batch.kwargs))(batch.positions)
    assert int(small.error) == int(ErrorBit.CAPACITY)
    np.testing.assert_array_equal(np.asarray(small.n_edge),
                                  np.asarray(exact.n_edge))
    np.testing.assert_array_equal(np.asarray(small.i), exact.i[:100])


def test_float32_tiles_equal_the_cells():
    systems = tiled_systems()
    batch = jaxrt.batch_from_ase(systems, pad=False)
    r = np.asarray(batch.positions, np.float32)
    kw = dict(batch.kwargs, cell=np.asarray(batch.cell, np.float32))
    dense = jaxrt.pairs_batch(r, batch.n_node, CUTOFF, max_nodes=108, **kw)
    cells = jaxrt.pairs_batch(r, batch.n_node, CUTOFF, max_nodes=0, **kw)
    assert per_system(dense, batch.n_node, len(systems)) == per_system(
        cells, batch.n_node, len(systems))
    np.testing.assert_array_equal(dense.n_edge, cells.n_edge)
