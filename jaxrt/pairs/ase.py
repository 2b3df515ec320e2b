"""ASE in and out of `jaxrt.pairs`.

* `pairs_from_ase(atoms, cutoff)`: the `jaxrt.Pairs` of an ``ase.Atoms``
  (its positions, its cell completed as ASE completes it, its ``pbc``).
* `pairs_to_ase(result, ...)`: a result as ASE's arrays, ``"ijS"`` (and
  ``"d"``, ``"D"``), sorted as ASE sorts them (by ``i``; here by ``(i, j,
  S)`` too, so the order is reproducible).
* `batch_from_ase(atoms_list)`: a flat batch of ``ase.Atoms`` for
  `jaxrt.pairs_batch`, padded as jraph's ``pad_with_graphs`` pads.
* `neighbor_list(quantities, atoms, cutoff)`: a drop-in for
  ``ase.neighborlist.neighbor_list`` (one cutoff, or ASE's dict by
  element; ``self_interaction``): switching is ``from jaxrt.pairs.ase
  import neighbor_list``.

ASE's positions are float64, and so is the search here (run under
``jax.enable_x64``), so the pairs are ASE's to the last bit of the decision
``|R[j] - R[i] + S @ cell| < cutoff``. ASE itself is imported only to
turn chemical symbols of a cutoff dict into atomic numbers: an ``Atoms``
is read through ``positions``, ``numbers``, ``pbc``, ``cell`` and
``get_cell(complete=True)``.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import numpy as np

from jaxrt.pairs.checks import bucket

# Names, not the module: the package binds jaxrt.pairs to the function.
from jaxrt.pairs.search import Pairs, pairs

_QUANTITIES = "ijdDS"


def _atoms_arrays(atoms):
    """float64 ``(N, 3)`` positions, ``(3, 3)`` complete cell or None (free
    space on every axis), the pbc tuple."""
    pbc = tuple(bool(p) for p in atoms.pbc)
    positions = np.asarray(atoms.positions, np.float64)
    cell = np.array(atoms.get_cell(complete=True).array, np.float64) \
        if any(pbc) else None
    return positions, cell, pbc


def _element_cutoffs(cutoff):
    """ASE's dict with symbols or atomic numbers -> numbers; others as
    they are."""
    if not isinstance(cutoff, dict):
        return cutoff
    from ase.data import atomic_numbers
    return {tuple(atomic_numbers.get(k, k) for k in key): value
            for key, value in cutoff.items()}


def pairs_from_ase(atoms, cutoff, *, capacity=None, backend: str = "auto",
                   half: bool = False, sort=None,
                   self_interaction: bool = False) -> Pairs:
    """`jaxrt.pairs` of an ``ase.Atoms`` in float64 (module docstring).

    Args:
      atoms: ``ase.Atoms``.
      cutoff: Python float > 0, or ASE's dict ``{(a, b): rc}`` by element
        (symbols or atomic numbers; pairs of elements not listed are never
        neighbours). ASE's per-atom radii are not supported.
      capacity, backend, half, sort, self_interaction: as `jaxrt.pairs`.
    Returns:
      `jaxrt.Pairs` (int32 arrays).
    """
    positions, cell, pbc = _atoms_arrays(atoms)
    cutoff = _element_cutoffs(cutoff)
    species = np.asarray(atoms.numbers) if isinstance(cutoff, dict) else None
    with jax.enable_x64(True):
        return pairs(positions, cutoff, cell=cell, pbc=pbc,
                     capacity=capacity, backend=backend, species=species,
                     half=half, sort=sort, self_interaction=self_interaction)


def pairs_to_ase(result, quantities: str = "ijS", *, positions=None,
                 cell=None):
    """A `jaxrt.Pairs` of one system as ASE's ``neighbor_list`` arrays.

    Args:
      result: `jaxrt.Pairs` (not a batch; raises if it overflowed).
      quantities: characters of ``"ijdDS"`` (ASE's meanings).
      positions, cell: needed for ``"d"`` and ``"D"``.
    Returns:
      numpy arrays in the order of ``quantities`` (one array alone when it
      is one character): ``i``, ``j`` int64 ``(P,)``, ``S`` int64 ``(P, 3)``,
      ``D`` float ``(P, 3)``, ``d`` float ``(P,)``, sorted by ``(i, j, S)``.
    """
    bad = [q for q in quantities if q not in _QUANTITIES]
    if bad or not quantities:
        raise ValueError(f"pairs_to_ase: quantities must be characters of "
                         f"{_QUANTITIES!r}, got {quantities!r}.")
    if np.ndim(result.count) != 0:
        raise ValueError("pairs_to_ase: one system's pairs, not a batch: "
                         "index the batch first.")
    result.check()
    count = int(result.count)
    i = np.asarray(result.i[:count], np.int64)
    j = np.asarray(result.j[:count], np.int64)
    s = np.asarray(result.shift[:count], np.int64)
    order = np.lexsort((s[:, 2], s[:, 1], s[:, 0], j, i))
    i, j, s = i[order], j[order], s[order]
    vectors = None
    if "d" in quantities or "D" in quantities:
        if positions is None:
            raise ValueError("pairs_to_ase: 'd' and 'D' need positions= (and "
                             "cell= for a periodic system).")
        r = np.asarray(positions, np.float64)
        vectors = r[j] - r[i]
        if cell is not None:
            h = np.asarray(cell, np.float64)
            vectors = vectors + s @ (np.diag(h) if h.ndim == 1 else h)
    out = {"i": i, "j": j, "S": s, "D": vectors,
           "d": None if vectors is None else np.sqrt(
               np.sum(vectors * vectors, axis=1))}
    values = tuple(out[q] for q in quantities)
    return values[0] if len(values) == 1 else values


def neighbor_list(quantities: str, atoms, cutoff, self_interaction=False,
                  max_nbins=None):
    """Drop-in for ``ase.neighborlist.neighbor_list``.

    Args:
      quantities: characters of ``"ijdDS"``.
      atoms: ``ase.Atoms``.
      cutoff: one number, or ASE's dict by element (symbols or atomic
        numbers); ASE's per-atom radii raise `NotImplementedError`.
      self_interaction: ASE's: also ``(i, i, 0)`` (with a dict, for the
        elements whose own cutoff is > 0, as ASE).
      max_nbins: ASE's bin limit; accepted and unused (jaxrt's grid sizes
        itself), so that calls written for ASE run unchanged.
    Returns:
      What ASE returns: the arrays of ``quantities`` (`pairs_to_ase`),
      sorted by ``i`` as ASE's are (then by ``j`` and ``S``).
    """
    del max_nbins  # documented: ASE's memory knob, nothing to do here
    if not isinstance(cutoff, dict) and np.ndim(cutoff) != 0:
        raise NotImplementedError(
            "jaxrt.pairs.ase.neighbor_list: ASE's per-atom radii (a list "
            "of cutoffs) are not supported: pass one cutoff or a dict by "
            "element.")
    result = pairs_from_ase(atoms, cutoff if isinstance(cutoff, dict)
                            else float(cutoff),
                            self_interaction=bool(self_interaction))
    positions, cell, _ = _atoms_arrays(atoms)
    return pairs_to_ase(result, quantities, positions=positions, cell=cell)


class FlatBatch(NamedTuple):
    """Systems concatenated for `jaxrt.pairs_batch` (numpy arrays).

    Attributes:
      positions: float64 ``(N, 3)``; numbers: int32 ``(N,)`` atomic numbers
        (0 for padding atoms).
      n_node: int32 ``(G,)``; cell: float64 ``(G, 3, 3)`` (as ASE holds
        it: zero rows stay, `jaxrt.pairs_batch` completes them); pbc: bool
        ``(G, 3)``; graph_mask: bool ``(G,)`` (False: padding).
    """

    positions: np.ndarray
    numbers: np.ndarray
    n_node: np.ndarray
    cell: np.ndarray
    pbc: np.ndarray
    graph_mask: np.ndarray

    @property
    def kwargs(self) -> dict:
        """``cell``, ``pbc`` and ``graph_mask`` for `jaxrt.pairs_batch`."""
        return {"cell": self.cell, "pbc": self.pbc,
                "graph_mask": self.graph_mask}


def batch_from_ase(atoms_list, *, n_node=None, n_graph=None,
                   pad: bool = True) -> FlatBatch:
    """A flat batch of ``ase.Atoms``, padded as jraph's ``pad_with_graphs``:
    after the systems, one padding system holding every padding atom (at
    least one) and empty padding systems up to ``n_graph``.

    Args:
      atoms_list: ``ase.Atoms`` (molecules, slabs and bulk may mix).
      n_node: total atoms after padding; None: the size bucket above the
        atoms plus one (1, 2, 3, 4, 6, 8, 12, 16, ...).
      n_graph: total systems after padding (more than the systems); None:
        the size bucket above them plus one.
      pad: False: no padding system (``n_node`` and ``n_graph`` unused).
    Returns:
      `FlatBatch`.
    """
    atoms_list = list(atoms_list)
    count = sum(len(a) for a in atoms_list)
    g = len(atoms_list)
    total = count if not pad else bucket(count + 1) if n_node is None \
        else int(n_node)
    graphs = g if not pad else bucket(g + 1) if n_graph is None \
        else int(n_graph)
    if pad and (total <= count or graphs <= g):
        raise ValueError(f"batch_from_ase: n_node={n_node} and "
                         f"n_graph={n_graph} must exceed the batch's {count} "
                         f"atoms and {g} systems (one padding system holds "
                         f"at least one padding atom).")
    positions = np.zeros((total, 3))
    numbers = np.zeros((total,), np.int32)
    sizes = np.zeros((graphs,), np.int32)
    cell = np.zeros((graphs, 3, 3))
    pbc = np.zeros((graphs, 3), bool)
    start = 0
    for k, atoms in enumerate(atoms_list):
        positions[start:start + len(atoms)] = atoms.positions
        numbers[start:start + len(atoms)] = atoms.numbers
        sizes[k] = len(atoms)
        cell[k] = atoms.cell.array
        pbc[k] = atoms.pbc
        start += len(atoms)
    if pad:
        sizes[g] = total - count
    return FlatBatch(positions, numbers, sizes, cell, pbc,
                     np.arange(graphs) < g)
