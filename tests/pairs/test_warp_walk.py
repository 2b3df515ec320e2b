"""The Warp walk of `jaxrt.pairs` (`jaxrt.pairs.warp_search`, the GPU's
full stencil), run here on Warp's CPU device by forcing the CUDA branch of
`jaxrt.platforms.cuda_or_default`, against the program's own full stencil
(``WARP_WALK_ON_CUDA`` off): row for row the same rows, count, counts per
system and error bits, padding and overflow included; and against ASE.
"""
from __future__ import annotations

import importlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("warp")
ase = pytest.importorskip("ase")
from ase import Atoms  # noqa: E402
from ase.build import bulk, fcc111, molecule  # noqa: E402

import jaxrt  # noqa: E402
from batch_cases import CUTOFF, ase_set, half_of, skewed  # noqa: E402
from jaxrt import platforms  # noqa: E402

program = importlib.import_module("jaxrt.pairs.program")
checks = importlib.import_module("jaxrt.pairs.checks")
ErrorBit = importlib.import_module("jaxrt.pairs.bits").ErrorBit


@pytest.fixture
def walk(monkeypatch):
    """``walk(warp)``: the program takes its CUDA branch, by the Warp walk
    or by its own full stencil; compiled programs dropped between."""
    monkeypatch.setattr(platforms, "cuda_or_default",
                        lambda cuda, default: cuda())

    def take(warp: bool):
        monkeypatch.setattr(program, "WARP_WALK_ON_CUDA", warp)
        jax.clear_caches()
    yield take
    jax.clear_caches()


def mixed():
    cu = bulk("Cu", "fcc", a=3.61, cubic=True)
    cu.rattle(0.05, seed=1)
    slab = fcc111("Al", size=(2, 2, 2), vacuum=None)
    lone = Atoms("Ar", positions=[[0.5, 0.5, 0.5]], cell=[4.5, 4.5, 4.5],
                 pbc=True)
    return [molecule("CH3CH2OH"), slab, cu, lone, skewed()]


def search(systems, cutoff, *, capacity, sort=True, half=False,
           self_interaction=False, species=None, dtype=np.float64,
           positions=None, reach=None):
    """`program.search` on a flat batch with its padding system.
    ``species``: a cutoff matrix, the atomic numbers of its rows, and rows
    to set by atom (a dict). Returns the rows, count, counts per system and
    error bits."""
    batch = jaxrt.batch_from_ase(systems)
    n, g = len(batch.positions), len(batch.n_node)
    graph = np.repeat(np.arange(g, dtype=np.int32), batch.n_node)
    mask = batch.graph_mask[graph]
    r = batch.positions if positions is None else positions
    if species is None:
        cut, spec, radius = cutoff, None, cutoff
    else:
        cut, numbers, odd = species
        spec = np.array([numbers.index(z) if z in numbers else 0
                         for z in batch.numbers], np.int32)
        for atom, row in odd.items():
            spec[atom] = row
        radius = float(np.max(cut))
    shift = np.max([checks.shift_for_cell(checks.concrete_cell(
        a.cell.array, tuple(a.pbc)), radius, tuple(a.pbc))
        if a.pbc.any() else (0, 0, 0) for a in systems], axis=0)
    # A free axis is searched with a reach of one (a traced pbc).
    brute, plan_reach, chunk = checks.plan(
        n, (True,) * 3, tuple(int(x) for x in np.maximum(shift, 1)), "cell")
    assert not brute
    out = program.search(
        jnp.asarray(r, dtype), jnp.asarray(graph), jnp.asarray(mask),
        jnp.asarray(batch.cell, dtype), jnp.asarray(batch.pbc),
        jnp.asarray(cut, dtype), None if spec is None else jnp.asarray(spec),
        jnp.int32(n), periodic=(True,) * 3,
        reach=plan_reach if reach is None else reach, capacity=capacity,
        brute=False, chunk=chunk, half=half, sort=sort,
        self_interaction=self_interaction, n_graph=g)
    return [np.asarray(x) for x in out]


def on_both(walk, *args, **kwargs):
    got = {}
    for warp in (True, False):
        walk(warp)
        got[warp] = search(*args, **kwargs)
    return got[True], got[False]


def assert_identical(warp, xla):
    for a, b in zip(warp, xla):
        np.testing.assert_array_equal(a, b)


def local_sets(rows, count, systems):
    starts = np.cumsum([0] + [len(a) for a in systems])
    out = [set() for _ in systems]
    for i, j, *s in rows[:count].tolist():
        k = int(np.searchsorted(starts, i, side="right")) - 1
        assert starts[k] <= j < starts[k + 1]
        out[k].add((i - starts[k], j - starts[k], *s))
    return out


@pytest.mark.parametrize("half,self_interaction", [(False, False),
                                                   (True, True)])
def test_mixed_batch_row_for_row_and_ase(x64, walk, half, self_interaction):
    """Molecule, slab, bulk, a one-atom cell, a skewed cell needing several
    images, and a padding system: the walk's rows are the program's."""
    systems = mixed()
    want = [ase_set(a, self_interaction=self_interaction) for a in systems]
    if half:
        want = [half_of(w) for w in want]
    capacity = sum(map(len, want)) + 9
    warp, xla = on_both(walk, systems, CUTOFF, capacity=capacity, half=half,
                        self_interaction=self_interaction)
    assert_identical(warp, xla)
    rows, count, per_system, error = warp
    assert int(error) == 0
    assert local_sets(rows, int(count), systems) == want
    np.testing.assert_array_equal(per_system[:len(systems)],
                                  [len(w) for w in want])
    assert not per_system[len(systems):].any()
    n = len(jaxrt.batch_from_ase(systems).positions)
    np.testing.assert_array_equal(rows[int(count):], [[n, n, 0, 0, 0]] * (
        capacity - int(count)))


def test_unsorted_and_float32_row_for_row(walk):
    """The unsorted request (the same full stencil on a GPU) and float32
    positions: decisions in the positions' dtype, as the program's."""
    systems = mixed()
    want = sum(len(ase_set(a)) for a in systems)
    warp, xla = on_both(walk, systems, CUTOFF, capacity=want + 4,
                        sort=False, dtype=np.float32)
    assert_identical(warp, xla)
    assert int(warp[1]) == want and int(warp[3]) == 0


def test_species_cutoffs_with_a_species_outside_the_matrix(x64, walk):
    """Per-species cutoffs (ASE's dict); an atom whose species row is past
    the matrix (or negative) has no pairs, as in the program."""
    systems = [bulk("NaCl", "rocksalt", a=5.64), molecule("CH3CH2OH")]
    cutoffs = {(11, 17): 3.2, (17, 17): 4.2, (11, 11): 3.0, (1, 6): 1.2,
               (6, 6): 1.6, (6, 8): 1.5, (1, 8): 1.0, (1, 1): 0.0}
    numbers = [1, 6, 8, 11, 17]
    matrix = np.zeros((5, 5))
    for (a, b), rc in cutoffs.items():
        matrix[numbers.index(a), numbers.index(b)] = rc
        matrix[numbers.index(b), numbers.index(a)] = rc
    want = [ase_set(a, cutoffs) for a in systems]
    capacity = sum(map(len, want)) + 5
    warp, xla = on_both(walk, systems, 0.0, capacity=capacity,
                        species=(matrix, numbers, {}))
    assert_identical(warp, xla)
    assert local_sets(warp[0], int(warp[1]), systems) == want
    # Two Na atoms with no row of the matrix.
    odd = {0: 7, 3: 9}
    warp, xla = on_both(walk, systems, 0.0, capacity=capacity,
                        species=(matrix, numbers, odd), self_interaction=True)
    assert_identical(warp, xla)
    assert not np.isin(warp[0][:int(warp[1]), :2], [0, 3]).any()


def test_overflow_nonfinite_and_short_reach_are_the_programs(x64, walk):
    """Past the capacity the same first rows are stored and the counts stay
    exact; a non-finite position and a reach too short for a cell set the
    same bits."""
    systems = mixed()[2:]
    full = sum(len(ase_set(a)) for a in systems)
    warp, xla = on_both(walk, systems, CUTOFF, capacity=11,
                        self_interaction=True)
    assert_identical(warp, xla)
    assert int(warp[1]) == full + sum(map(len, systems))
    assert int(warp[3]) == int(ErrorBit.CAPACITY)
    r = jaxrt.batch_from_ase(systems).positions.copy()
    r[2] = np.nan
    warp, xla = on_both(walk, systems, CUTOFF, capacity=full + 50,
                        positions=r)
    assert_identical(warp, xla)
    assert int(warp[3]) & int(ErrorBit.NONFINITE_POSITION)
    assert not np.isin(warp[0][:int(warp[1]), :2], [2]).any()
    warp, xla = on_both(walk, systems, CUTOFF, capacity=full + 50,
                        reach=(1, 1, 1))
    assert_identical(warp, xla)
    assert int(warp[3]) & int(ErrorBit.MAX_SHIFT)


def test_large_periodic_box_row_for_row(x64, walk):
    """A 3000-atom periodic box with cells of many atoms (runs longer than
    a word: the program's stream), sorted and half."""
    rng = np.random.default_rng(3)
    side = 18.0
    atoms = Atoms(f"Ar{3000}", positions=rng.uniform(0, side, (3000, 3)),
                  cell=[side, side * 1.1, side * 0.9], pbc=[True, True, False])
    want = half_of(ase_set(atoms, 3.0))
    warp, xla = on_both(walk, [atoms], 3.0, capacity=len(want) + 1,
                        half=True)
    assert_identical(warp, xla)
    assert local_sets(warp[0], int(warp[1]), [atoms]) == [want]


@pytest.mark.parametrize("width", [0, 1, 3, 64])
def test_atoms_past_their_scratch_row_are_walked_again(x64, walk,
                                                       monkeypatch, width):
    """Scratch rows narrower than most atoms' pairs (every atom written by
    the second walk), than some, and wider than all: the same rows."""
    warp_search = importlib.import_module("jaxrt.pairs.warp_search")
    monkeypatch.setattr(warp_search, "scratch_width",
                        lambda capacity, n: width)
    systems = mixed()
    want = sum(len(ase_set(a, self_interaction=True)) for a in systems)
    warp, xla = on_both(walk, systems, CUTOFF, capacity=want + 3,
                        self_interaction=True)
    assert_identical(warp, xla)
    assert int(warp[1]) == want
