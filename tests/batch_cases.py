"""ASE systems and the per-system oracle shared by tests/pairs/test_batch.py
and tests/pairs/test_dense.py (`jaxrt.pairs_batch` on flat batches in
jraph's layout)."""
from __future__ import annotations

import numpy as np
from ase import Atoms
from ase.neighborlist import neighbor_list as ase_neighbor_list

CUTOFF = 4.0


def skewed():
    """Five H atoms in a skewed triclinic cell, some given outside it:
    shifts of 2 and more at `CUTOFF`."""
    rng = np.random.default_rng(0)
    cell = np.array([[4.0, 0, 0], [3.1, 3.5, 0], [-2.7, 1.9, 3.2]])
    cell = cell + rng.uniform(-0.3, 0.3, (3, 3))
    frac = rng.uniform(-0.5, 1.7, (5, 3))
    return Atoms("H5", positions=frac @ cell, cell=cell, pbc=True)


def ase_set(atoms, cutoff=CUTOFF, **kw) -> set:
    """ASE's ``neighbor_list("ijS")`` as a set of (i, j, S0, S1, S2)."""
    i, j, s = ase_neighbor_list("ijS", atoms, cutoff, **kw)
    return {(int(a), int(b), *map(int, c)) for a, b, c in zip(i, j, s)}


def half_of(full: set) -> set:
    """The half list's representatives of a full (i, j, S) set: i < j, or
    the self images with S >= 0 lexicographically (S = 0 included)."""
    return {p for p in full if p[0] < p[1] or (
        p[0] == p[1] and tuple(p[2:]) >= (0, 0, 0))}


def per_system(result, n_node, n_systems: int) -> list[set]:
    """The stored edges split by system with n_edge, indices made local;
    asserts each edge lies in its system."""
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


def assert_padded_as_jraph(got, n_node, n_systems: int, capacity: int):
    """Padding edges point at the first padding node and are counted in the
    padding graph: sum(n_edge) is the capacity, as after
    jraph.pad_with_graphs."""
    n_real = int(np.sum(np.asarray(n_node)[:n_systems]))
    count = int(got.count)
    assert np.all(np.asarray(got.i)[count:] == n_real)
    assert np.all(np.asarray(got.j)[count:] == n_real)
    n_edge = np.asarray(got.n_edge)
    assert n_edge[n_systems] == capacity - count
    assert n_edge.sum() == capacity
