"""The unsorted cell search (``sort=None``, under ``jit``) against ASE's
``neighbor_list``: runs of at most a word (`_half_words`: the atoms read
in sorted order, one keep bit per candidate) and a cell fuller than a word
(the slot loop it falls back to), with every option the compaction decodes
(full and half lists, self pairs, cutoffs by species, masked atoms); and
the cells' order in the sorted search of a flat batch. Sets of ``(i, j,
S)`` are compared exactly (float64)."""
from __future__ import annotations

import jax
import numpy as np
import pytest

ase = pytest.importorskip("ase")
from ase import Atoms  # noqa: E402
from ase.neighborlist import neighbor_list as ase_neighbor_list  # noqa: E402

import jaxrt  # noqa: E402
from jaxrt.pairs.checks import DENSE_WORD  # noqa: E402

CUTOFF = 3.0


def cloud(n: int, seed: int, crowd: int = 0) -> Atoms:
    """``n`` atoms uniform in a triclinic periodic cell (a few per cell of
    the cutoff's width), and ``crowd`` more within 0.3 Å of one point (one
    cell holds them all)."""
    rng = np.random.default_rng(seed)
    cell = np.array([[14.0, 0, 0], [2.5, 13.0, 0], [-1.5, 2.0, 15.0]])
    frac = rng.uniform(0, 1, (n, 3))
    pos = frac @ cell
    if crowd:
        # Around the middle of the first cell (3 to 5 cells an axis).
        centre = np.full(3, 1 / 8) @ cell
        pos = np.concatenate([pos, centre + rng.uniform(-0.3, 0.3,
                                                        (crowd, 3))])
    return Atoms(f"H{len(pos)}", positions=pos, cell=cell, pbc=True)


def ase_set(atoms, cutoff, self_interaction=False) -> set:
    i, j, s = ase_neighbor_list("ijS", atoms, cutoff,
                                self_interaction=self_interaction)
    return {(int(a), int(b), *map(int, c)) for a, b, c in zip(i, j, s)}


def stored(result, n: int) -> list:
    count = int(result.count)
    i, j, s = (np.asarray(x) for x in (result.i, result.j, result.shift))
    assert count <= len(i) and np.all(i[count:] == n) \
        and np.all(j[count:] == n) and not np.any(s[count:])
    return [(int(a), int(b), *map(int, c)) for a, b, c in zip(
        i[:count], j[:count], s[:count])]


def representative(p) -> bool:
    i, j, *s = p
    return i < j or (i == j and tuple(s) > (0, 0, 0))


def search(atoms, cutoff, capacity, **kw):
    f = jax.jit(lambda r, c: jaxrt.pairs(
        r, cutoff, cell=c, capacity=capacity, max_shift=1, **kw))
    return f(atoms.positions, np.asarray(atoms.cell.array))


@pytest.mark.parametrize("crowd", [0, DENSE_WORD + 8])
def test_unsorted_cell_search_full_and_half_lists_as_ase(crowd, x64):
    atoms = cloud(300, seed=5, crowd=crowd)
    n = len(atoms)
    want = ase_set(atoms, CUTOFF)
    full = stored(search(atoms, CUTOFF, len(want) + 5), n)
    assert len(full) == len(set(full)) and set(full) == want
    half = stored(search(atoms, CUTOFF, len(want) // 2 + 5, half=True), n)
    assert len(half) == len(set(half))
    assert set(half) == {p for p in want if representative(p)}
    # The same pairs as the sorted search (the full stencil's own words).
    by_i = stored(search(atoms, CUTOFF, len(want), sort="i"), n)
    assert set(by_i) == set(full)


def test_unsorted_cell_search_self_pairs_and_species_as_ase(x64):
    atoms = cloud(300, seed=6)
    numbers = np.where(np.arange(len(atoms)) % 3 == 0, 8, 1)
    atoms.set_atomic_numbers(numbers)
    cutoffs = {(1, 1): 2.2, (1, 8): 3.0, (8, 8): 2.6}
    i, j, s = ase_neighbor_list("ijS", atoms, cutoffs)
    want = {(int(a), int(b), *map(int, c)) for a, b, c in zip(i, j, s)}
    matrix = np.zeros((9, 9))
    for (a, b), rc in cutoffs.items():
        matrix[a, b] = matrix[b, a] = rc
    f = jax.jit(lambda r, c, m, z: jaxrt.pairs(
        r, m, cell=c, species=z, capacity=len(want) + 3, max_shift=1))
    got = f(atoms.positions, np.asarray(atoms.cell.array), matrix, numbers)
    assert set(stored(got, len(atoms))) == want and int(got.error) == 0
    with_self = stored(search(atoms, CUTOFF, len(ase_set(atoms, CUTOFF, True)),
                              self_interaction=True), len(atoms))
    assert set(with_self) == ase_set(atoms, CUTOFF, True)


def test_unsorted_cell_search_of_a_padded_batch_as_ase(x64):
    systems = [cloud(120, seed=7), cloud(90, seed=8, crowd=DENSE_WORD + 2),
               cloud(150, seed=9)]
    n_node = np.array([len(a) for a in systems] + [0], np.int32)
    pad = 11  # padding atoms past the last system
    positions = np.concatenate([a.positions for a in systems]
                               + [np.zeros((pad, 3))])
    n_node[-1] = pad
    cells = np.stack([a.cell.array for a in systems] + [np.eye(3)])
    mask = np.array([True] * len(systems) + [False])
    sizes = jaxrt.pairs_batch_sizes(positions, n_node, CUTOFF, cell=cells,
                                    graph_mask=mask)
    kwargs = {**sizes.kwargs, "max_nodes": 0}
    got = jax.jit(lambda r, c: jaxrt.pairs_batch(
        r, n_node, CUTOFF, cell=c, graph_mask=mask, **kwargs))(
            positions, cells)
    first = np.concatenate([[0], np.cumsum(n_node)])
    i, j, s = (np.asarray(x) for x in (got.i, got.j, got.shift))
    count = int(got.count)
    rows = {(int(a), int(b), *map(int, c)) for a, b, c in zip(
        i[:count], j[:count], s[:count])}
    want = set()
    for g, atoms in enumerate(systems):
        want |= {(a + first[g], b + first[g], *c)
                 for a, b, *c in ase_set(atoms, CUTOFF)}
    assert rows == want and int(got.error) == 0


def test_unsorted_cell_search_skips_masked_atoms(x64):
    atoms = cloud(300, seed=10, crowd=DENSE_WORD + 1)
    n = len(atoms)
    mask = np.ones(n, bool)
    mask[::7] = False
    want = {p for p in ase_set(atoms, CUTOFF) if mask[p[0]] and mask[p[1]]}
    f = jax.jit(lambda r, c, m: jaxrt.pairs(
        r, CUTOFF, cell=c, mask=m, capacity=len(want) + 4, max_shift=1))
    got = f(atoms.positions, np.asarray(atoms.cell.array), mask)
    pairs = stored(got, n)
    assert len(pairs) == len(set(pairs)) and set(pairs) == want
