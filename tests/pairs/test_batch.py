"""`jaxrt.pairs_batch`: flat batches in jraph's layout, checked against
ASE's ``neighbor_list("ijS")`` system by system; and the few programs that
eager calls compile over a data set of many sizes.

Sets of ``(i, j, S)`` are compared exactly (float64, per system, indices
made local by the system's offset). A mixed batch holds a molecule (all-zero
cell), a ``vacuum=None`` slab (a zero row), rattled bulk, a one-atom cell
and a skewed triclinic cell needing shifts of 2 and more.
"""
from __future__ import annotations

import importlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

ase = pytest.importorskip("ase")
from ase import Atoms  # noqa: E402
from ase.build import bulk, fcc111, molecule  # noqa: E402
from ase.neighborlist import neighbor_list as ase_neighbor_list  # noqa: E402

import jaxrt  # noqa: E402
from batch_cases import (CUTOFF, ase_set, assert_padded_as_jraph,  # noqa: E402
                         half_of, per_system, skewed)

program = importlib.import_module("jaxrt.pairs.program")
ErrorBit = importlib.import_module("jaxrt.pairs.bits").ErrorBit


def mixed():
    cu = bulk("Cu", "fcc", a=3.61, cubic=True)
    cu.rattle(0.05, seed=1)
    return [molecule("CH3CH2OH"), fcc111("Al", size=(2, 2, 2), vacuum=None),
            cu, bulk("Cu", "fcc", a=3.61), skewed()]


def test_mixed_batch_eager_matches_ase_per_system(x64):
    systems = mixed()
    batch = jaxrt.batch_from_ase(systems, pad=False)
    got = jaxrt.pairs_batch(batch.positions, batch.n_node, CUTOFF,
                            **batch.kwargs)
    assert int(got.count) == got.capacity == int(np.sum(got.n_edge))
    assert per_system(got, batch.n_node, len(systems)) == [
        ase_set(a) for a in systems]
    assert np.all(np.diff(np.asarray(got.i)) >= 0)  # sorted by i
    # Vectors and distances as ASE's, with each system's cell.
    d = np.asarray(got.distances(batch.positions, batch.cell))
    want = np.concatenate([ase_neighbor_list("d", a, CUTOFF)
                           for a in systems])
    np.testing.assert_allclose(np.sort(d), np.sort(want), rtol=0,
                               atol=1e-12)


def test_jitted_padded_batch_matches_ase_and_pads_as_jraph(x64):
    systems = mixed()
    batch = jaxrt.batch_from_ase(systems)  # a padding graph, jraph's way
    sizes = jaxrt.pairs_batch_sizes(batch.positions, batch.n_node, CUTOFF,
                                    **batch.kwargs)
    assert sizes.max_shift == (2, 2, 2)  # the 1-atom and triclinic cells'
    capacity = sizes.capacity + 5

    @jax.jit
    def edges(r, n_node, cell, pbc, mask):
        return jaxrt.pairs_batch(r, n_node, CUTOFF, cell=cell, pbc=pbc,
                                 graph_mask=mask, capacity=capacity,
                                 max_shift=sizes.max_shift)

    got = edges(*batch[:1], *batch[2:])
    assert int(got.error) == 0
    assert per_system(got, batch.n_node, len(systems)) == [
        ase_set(a) for a in systems]
    assert_padded_as_jraph(got, batch.n_node, len(systems), capacity)
    assert np.all(np.asarray(got.distances(batch.positions,
                                           batch.cell))[int(got.count):] == 0)


def test_graphs_tuple_for_jraph(x64):
    jraph = pytest.importorskip("jraph")
    systems = [molecule("H2O"), bulk("Cu", "fcc", a=3.61)]
    batch = jaxrt.batch_from_ase(systems, n_node=8, n_graph=4)
    got = jaxrt.pairs_batch(batch.positions, batch.n_node, 3.0,
                            capacity=64, **batch.kwargs)
    graph = got.graphs_tuple(nodes={"positions": batch.positions})
    np.testing.assert_array_equal(jraph.get_graph_padding_mask(graph),
                                  [True, True, False, False])
    np.testing.assert_array_equal(
        jraph.get_edge_padding_mask(graph), np.arange(64) < int(got.count))
    assert int(jraph.get_number_of_padding_with_graphs_nodes(graph)) == 8 - 4


def test_half_lists_self_pairs_and_species_in_a_batch(x64):
    systems = [bulk("NaCl", "rocksalt", a=5.64), molecule("CH3CH2OH")]
    cutoffs = {(11, 17): 3.2, (17, 17): 4.2, (1, 6): 1.2, (6, 6): 1.6,
               (6, 8): 1.5, (1, 8): 1.0}
    batch = jaxrt.batch_from_ase(systems, pad=False)
    got = jaxrt.pairs_batch(batch.positions, batch.n_node, cutoffs,
                            species=batch.numbers, half=True,
                            self_interaction=True, **batch.kwargs)
    for a, edges in zip(systems, per_system(got, batch.n_node, 2)):
        assert edges == half_of(ase_set(a, cutoffs, self_interaction=True))


def test_overflow_is_flagged_with_exact_counts_per_system(x64):
    systems = mixed()[2:4]
    batch = jaxrt.batch_from_ase(systems)
    exact = jaxrt.pairs_batch(batch.positions, batch.n_node, CUTOFF,
                              **batch.kwargs)
    small = jax.jit(lambda r: jaxrt.pairs_batch(
        r, batch.n_node, CUTOFF, capacity=10, max_shift=2, **batch.kwargs))(
            batch.positions)
    assert bool(small.overflow)
    assert int(small.error) == int(ErrorBit.CAPACITY)
    np.testing.assert_array_equal(np.asarray(small.n_edge)[:2],
                                  np.asarray(exact.n_edge)[:2])
    assert int(small.count) == int(exact.count)
    with pytest.raises(jaxrt.PairsError, match="capacity"):
        small.check()


def test_forces_through_batch_vectors_match_finite_differences(x64):
    systems = [bulk("Cu", "fcc", a=3.61), skewed()]
    for a in systems:
        a.rattle(0.05, seed=4)
    batch = jaxrt.batch_from_ase(systems, pad=False)
    sizes = jaxrt.pairs_batch_sizes(batch.positions, batch.n_node, CUTOFF,
                                    **batch.kwargs)

    def energy(r, cell):
        edges = jaxrt.pairs_batch(jax.lax.stop_gradient(r), batch.n_node,
                                  CUTOFF, cell=cell, pbc=batch.pbc,
                                  **sizes.kwargs)
        d = edges.distances(r, cell)
        x = jnp.where(edges.valid, d / CUTOFF, 1.0)
        return jnp.sum((1 - x) ** 3 * jnp.exp(-d))

    r, h = jnp.asarray(batch.positions), jnp.asarray(batch.cell)
    both = jax.jit(jax.value_and_grad(energy, argnums=(0, 1)))
    g_r, g_h = both(r, h)[1]
    eps = 1e-6
    for a, b in [(0, 0), (3, 2)]:
        dr = np.zeros(r.shape)
        dr[a, b] = eps
        fd = (both(r + dr, h)[0] - both(r - dr, h)[0]) / (2 * eps)
        assert abs(fd - g_r[a, b]) < 1e-7 * max(1, abs(fd))
    dh = np.zeros(h.shape)
    dh[1, 2, 0] = eps
    fd = (both(r, h + dh)[0] - both(r, h - dh)[0]) / (2 * eps)
    assert abs(fd - g_h[1, 2, 0]) < 1e-7 * max(1, abs(fd))


def gas(n: int, seed: int):
    """n random atoms at a solid's density (0.085 Å⁻³) in a cubic cell."""
    side = (n / 0.085) ** (1 / 3)
    rng = np.random.default_rng(seed)
    return Atoms(f"H{n}", positions=rng.uniform(0, side, (n, 3)),
                 cell=[side] * 3, pbc=True)


def programs_for_sizes(sizes) -> int:
    before = program.search._cache_size()
    for n in sizes:
        atoms = gas(n, n)
        got = jaxrt.pairs(atoms.positions, 3.0, cell=atoms.cell.array)
        if n % 7 == 0:
            assert {(int(a), int(b), *map(int, c)) for a, b, c in zip(
                got.i, got.j, got.shift)} == ase_set(atoms, 3.0)
    return program.search._cache_size() - before


def test_sixteen_sizes_compile_two_programs(x64):
    # Eager calls round the atoms (17..32 -> 24 or 32) and the capacity
    # (at the padded size's expected count) up to shared buckets.
    assert programs_for_sizes(range(17, 33)) <= 2


@pytest.mark.slow
def test_fifty_sizes_compile_a_few_programs(x64):
    assert programs_for_sizes(range(20, 70)) <= 6


def _scene(clustered: bool, seed: int):
    """A triclinic periodic box of random atoms, some outside the cell (so
    their wraps count); ``clustered``: 160 of them packed into a ball of
    radius 1.2 Å, whose cells hold far more than a word of atoms."""
    rng = np.random.default_rng(seed)
    cell = np.array([[16.0, 0, 0], [2.0, 15.0, 0], [1.0, -1.5, 17.0]])
    frac = rng.uniform(-0.1, 1.1, (420, 3))
    r = frac @ cell
    if clustered:
        ball = rng.normal(0, 1, (160, 3))
        ball *= 1.2 * rng.uniform(0, 1, (160, 1)) ** (1 / 3) / np.linalg.norm(
            ball, axis=1, keepdims=True)
        r = np.concatenate([r, ball + np.array([5.0, 6.0, 7.0])])
    return r, cell


@pytest.mark.parametrize("unrolled", [False, True])
@pytest.mark.parametrize("clustered", [False, True])
def test_cell_runs_short_and_long_match_ase_exactly(x64, clustered, unrolled,
                                                    monkeypatch):
    """The cell search (max_nodes=0), whose runs of at most a word are read
    as words and longer ones by the stream: every (i, j, S) and each
    distance's decision exactly as ASE's in float64. ``unrolled``: the
    short runs' loop as a GPU runs it (every slot of a word written out),
    taken here on the CPU."""
    from ase.neighborlist import primitive_neighbor_list
    cells = importlib.import_module("jaxrt.pairs.cells")
    words = importlib.import_module("jaxrt.pairs.words")
    if unrolled:
        monkeypatch.setattr(cells.platforms, "cuda_or_default",
                            lambda cuda, default: cuda())
        # The program traced before (the CPU's loop) would be reused.
        jax.clear_caches()
    cutoff = 3.0
    r, cell = _scene(clustered, seed=3)
    n = len(r)
    binned = cells.bin_atoms(
        jnp.asarray(r), jnp.zeros(n, jnp.int32), jnp.ones(n, bool),
        jnp.asarray(cell)[None], jnp.ones((1, 3), bool), jnp.asarray(cutoff),
        reach=(1, 1, 1), brute=False, n_graph=1, completed=False, full=True)
    longest = int(jnp.max(binned.length))
    assert (longest > words.WORD) == clustered, longest
    sizes = jaxrt.pairs_batch_sizes(r, np.array([n]), cutoff, cell=cell[None])
    kwargs = dict(sizes.kwargs, max_nodes=0)
    got = jax.jit(lambda x: jaxrt.pairs_batch(
        x, jnp.array([n]), cutoff, cell=jnp.asarray(cell)[None],
        **kwargs))(jnp.asarray(r))
    got.check()
    i, j, s = primitive_neighbor_list("ijS", [True] * 3, cell, r, cutoff)
    want = {(int(a), int(b), *map(int, c)) for a, b, c in zip(i, j, s)}
    count = int(got.count)
    have = {(int(a), int(b), *map(int, c)) for a, b, c in zip(
        np.asarray(got.i)[:count], np.asarray(got.j)[:count],
        np.asarray(got.shift)[:count])}
    assert count == len(want) and have == want
    # Sorted by i, as the stream lays them out.
    assert np.all(np.diff(np.asarray(got.i)[:count]) >= 0)


def test_square_limit_decides_as_the_square_root(x64):
    """x <= square_limit(c) exactly where sqrt(x) < c, for floats x >= 0
    around c² in both dtypes and for the edge cutoffs."""
    cells = importlib.import_module("jaxrt.pairs.cells")
    rng = np.random.default_rng(0)
    for dtype in (np.float64, np.float32):
        cuts = np.concatenate([rng.uniform(0.5, 12, 200), [0.0, -1.0, 5.0,
                               np.inf, 1e-30, 1e30]]).astype(dtype)
        limit = np.asarray(cells.square_limit(jnp.asarray(cuts)))
        for c, t in zip(cuts, limit):
            x = np.array([c * c], dtype)
            near = [x[0]]
            for _ in range(6):
                near += [np.nextafter(near[-1], dtype(np.inf))]
            down = [x[0]]
            for _ in range(6):
                down += [np.nextafter(down[-1], dtype(-np.inf))]
            for v in near + down:
                v = dtype(v)
                if v < 0:  # a squared length is never negative
                    continue
                assert (v <= t) == (np.sqrt(v) < c), (dtype, c, v, t)
