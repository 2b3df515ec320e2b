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

import jaxrt  # noqa: E402
from batch_cases import (CUTOFF, ase_set, assert_padded_as_jraph,  # noqa: E402
                         half_of, per_system, skewed)

ErrorBit = importlib.import_module("jaxrt.pairs.bits").ErrorBit
checks = importlib.import_module("jaxrt.pairs.checks")
bucket = checks.bucket


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


def mixed():
    cu = bulk("Cu", "fcc", a=3.61, cubic=True)
    cu.rattle(0.05, seed=1)
    return [molecule("CH3CH2OH"), fcc111("Al", size=(2, 2, 2), vacuum=None),
            cu, one_atom(), skewed(), rhombohedral()]


def jitted_padded(systems, extra: int = 0, max_nodes=None):
    """The jitted search on the systems padded as jraph pads them, with
    `jaxrt.pairs_batch_sizes`' reach, its capacity plus ``extra`` and
    ``max_nodes`` (the sizes' where None), checked against ASE. Returns
    the result, the batch, the sizes and the capacity."""
    batch = jaxrt.batch_from_ase(systems)
    sizes = jaxrt.pairs_batch_sizes(batch.positions, batch.n_node, CUTOFF,
                                    **batch.kwargs)
    capacity = sizes.capacity + extra
    m = sizes.max_nodes if max_nodes is None else max_nodes

    @jax.jit
    def edges(r, n_node, cell, pbc, mask):
        return jaxrt.pairs_batch(r, n_node, CUTOFF, cell=cell, pbc=pbc,
                                 graph_mask=mask, capacity=capacity,
                                 max_shift=sizes.max_shift, max_nodes=m)

    got = edges(*batch[:1], *batch[2:])
    assert int(got.error) == 0
    assert per_system(got, batch.n_node, len(systems)) == [
        ase_set(a) for a in systems]
    return got, batch, sizes, capacity


def check_half_self_species(systems, cutoffs, max_nodes: int, half: bool,
                            n_self: int):
    """Per-species cutoffs with self pairs, full or half: the blocks'
    edges are ASE's (halved), in the cells' order, and each of the
    ``n_self`` atoms with a same-species cutoff has its self pair first."""
    batch = jaxrt.batch_from_ase(systems, pad=False)
    kw = dict(species=batch.numbers, half=half, self_interaction=True,
              **batch.kwargs)
    got = jaxrt.pairs_batch(batch.positions, batch.n_node, cutoffs,
                            max_nodes=max_nodes, **kw)
    cells = jaxrt.pairs_batch(batch.positions, batch.n_node, cutoffs,
                              max_nodes=0, **kw)
    for a, edges in zip(systems, per_system(got, batch.n_node,
                                            len(systems))):
        want = ase_set(a, cutoffs, self_interaction=True)
        assert edges == (half_of(want) if half else want)
    np.testing.assert_array_equal(got.i, cells.i)
    np.testing.assert_array_equal(got.n_edge, cells.n_edge)
    i, j = np.asarray(got.i)[:int(got.count)], np.asarray(got.j)
    self_at = np.nonzero((i == j[:len(i)]) & ~np.asarray(
        got.shift)[:len(i)].any(axis=1))[0]
    assert len(self_at) == n_self
    np.testing.assert_array_equal(self_at, np.searchsorted(i, i[self_at]))


def blocks_match_ase_and_the_cells(systems):
    """The blocks' search (``max_nodes`` the largest system) of the
    systems, unpadded: ASE's edges system by system, and the cells' counts
    and order (both sorted by ``i``). Returns the result, the batch, ASE's
    sets and ``max_nodes``."""
    batch = jaxrt.batch_from_ase(systems, pad=False)
    m = int(np.max(batch.n_node))
    got = jaxrt.pairs_batch(batch.positions, batch.n_node, CUTOFF,
                            max_nodes=m, **batch.kwargs)
    cells = jaxrt.pairs_batch(batch.positions, batch.n_node, CUTOFF,
                              max_nodes=0, **batch.kwargs)
    assert int(got.error) == 0
    want = [ase_set(a) for a in systems]
    assert per_system(got, batch.n_node, len(systems)) == want
    np.testing.assert_array_equal(got.n_edge, cells.n_edge)
    np.testing.assert_array_equal(got.i, cells.i)
    return got, batch, want, m


def test_mixed_batch_dense_matches_ase_and_the_cells(x64):
    got, batch, want, _ = blocks_match_ase_and_the_cells(mixed())
    assert max(max(abs(p[2]), abs(p[3]), abs(p[4])) for p in want[-1]) >= 3
    d = np.asarray(got.distances(batch.positions, batch.cell))
    assert np.all(d < CUTOFF) and np.all(d > 0)


def test_jitted_padded_dense_batch_matches_ase_and_pads_as_jraph(x64):
    systems = mixed()
    got, batch, _, capacity = jitted_padded(
        systems, extra=5, max_nodes=max(len(a) for a in systems))
    assert_padded_as_jraph(got, batch.n_node, len(systems), capacity)


@pytest.mark.parametrize("half", [False, True])
def test_dense_half_lists_self_pairs_and_species(x64, half):
    # Cl and the two C have a self pair; no Na-Na, O-O or H-H cutoff.
    check_half_self_species(
        [bulk("NaCl", "rocksalt", a=5.64), molecule("CH3CH2OH")],
        {(11, 17): 3.2, (17, 17): 4.2, (1, 6): 1.2, (6, 6): 1.6,
         (6, 8): 1.5, (1, 8): 1.0}, max_nodes=9, half=half, n_self=3)


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
    ethanol, slab = mixed()[:2]
    small = jaxrt.batch_from_ase([ethanol, ethanol.copy(), slab, one_atom()],
                                 pad=False)
    sizes = jaxrt.pairs_batch_sizes(small.positions, small.n_node, CUTOFF,
                                    **small.kwargs)
    assert sizes.max_shift == (2, 2, 2)
    assert sizes.kwargs["max_nodes"] == 12  # 9 atoms (bucket 12) x 125
    # 27 atoms in 5 blocks of 12 slots: fewer than half filled, cells.
    thinly = jaxrt.batch_from_ase(mixed()[:-1], pad=False)
    assert jaxrt.pairs_batch_sizes(thinly.positions, thinly.n_node, CUTOFF,
                                   **thinly.kwargs).max_nodes == 0
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


def test_sizes_send_thinly_filled_blocks_to_the_cells(x64):
    """Systems of 16-96 atoms: blocks of 96 slots, mostly empty (padding
    systems included), go to the cells; the same systems, each as large
    as the block, stay dense. Both jitted searches equal ASE per system."""
    si = bulk("Si", "diamond", a=5.43, cubic=True)
    cu = bulk("Cu", "fcc", a=3.61, cubic=True)
    systems = [cu.repeat((1, 2, 2)), si.repeat((2, 2, 3)),
               cu.repeat((2, 2, 1)), si.repeat((1, 2, 2))]
    for k, a in enumerate(systems):
        a.rattle(0.05, seed=k)
    assert [len(a) for a in systems] == [16, 96, 16, 32]
    # 160 real atoms in 4 + 1 padding systems of 96 slots: a third filled.
    got, _, sizes, _ = jitted_padded(systems)
    assert bucket(96) == 96 and 5 * 96 >= 2 * 160
    assert sizes.max_nodes == 0
    full = [si.repeat((2, 2, 3)) for _ in range(4)]
    for k, a in enumerate(full):
        a.rattle(0.05, seed=k)
    _, _, sizes_full, _ = jitted_padded(full)
    assert sizes_full.max_nodes == 96  # 384 atoms in 5 x 96 slots
    # Calling the sizes' choice explicitly: the slots' rule, not the reach.
    assert checks.dense_nodes(96, (2, 2, 2)) == 96
    assert checks.dense_nodes(96, (2, 2, 2), 160, 5) == 0
    assert checks.dense_nodes(96, (2, 2, 2), 241, 5) == 96


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
    _, batch, want, m = blocks_match_ase_and_the_cells(systems)
    assert m > 64
    # The simple cubic lattice has pairs at exactly 4.0 that ASE drops:
    # twice as many at a cutoff a rounding above it.
    above = ase_set(systems[1], np.nextafter(CUTOFF, 5.0))
    assert len(above) > len(want[1])
    assert max(max(abs(p[2]), abs(p[3]), abs(p[4])) for p in want[-1]) >= 2
    # A cutoff a rounding above: the pairs at 4.0 come in, as in ASE.
    got_above = jaxrt.pairs_batch(batch.positions, batch.n_node,
                                  np.nextafter(CUTOFF, 5.0), max_nodes=m,
                                  **batch.kwargs)
    assert per_system(got_above, batch.n_node, len(systems))[1] == above


def test_jitted_padded_tiles_match_ase(x64):
    systems = tiled_systems()
    m = bucket(max(len(a) for a in systems))
    assert m >= 108
    # The sizes send these thinly filled blocks to the cells; the tiles
    # are asked for here, and must match ASE all the same.
    _, _, sizes, _ = jitted_padded(systems, max_nodes=m)
    assert sizes.max_nodes == 0


@pytest.mark.parametrize("half", [False, True])
def test_tiles_half_lists_self_pairs_and_species(x64, half):
    nacl = bulk("NaCl", "rocksalt", a=5.64, cubic=True).repeat((2, 2, 3))
    nacl.rattle(0.05, seed=4)  # 96 atoms
    # Cl and C have a self pair: no Na-Na cutoff.
    check_half_self_species(
        [nacl, molecule("C60")],
        {(11, 17): 3.2, (17, 17): 4.2, (6, 6): 1.6, (11, 11): 0.0},
        max_nodes=96, half=half, n_self=48 + 60)


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


@pytest.mark.parametrize("systems, max_nodes", [
    (lambda: mixed()[:-1], 9), (tiled_systems, 108)], ids=["dense", "tiles"])
def test_float32_blocks_equal_the_cells(systems, max_nodes):
    # float32 (x64 off): both searches decide with the same expression in
    # the same dtype, so the edge sets are equal, not only close.
    systems = systems()
    batch = jaxrt.batch_from_ase(systems, pad=False)
    r = np.asarray(batch.positions, np.float32)
    kw = dict(batch.kwargs, cell=np.asarray(batch.cell, np.float32))
    dense = jaxrt.pairs_batch(r, batch.n_node, CUTOFF, max_nodes=max_nodes,
                              **kw)
    cells = jaxrt.pairs_batch(r, batch.n_node, CUTOFF, max_nodes=0, **kw)
    assert per_system(dense, batch.n_node, len(systems)) == per_system(
        cells, batch.n_node, len(systems))
    np.testing.assert_array_equal(dense.n_edge, cells.n_edge)
