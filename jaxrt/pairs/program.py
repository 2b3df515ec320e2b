"""The search program of `jaxrt.pairs` and `jaxrt.pairs_batch`: the pairs
``(i, j, S)`` of one flat batch of systems, in one jitted program.

A batch is flat (jraph's layout): the atoms of every system concatenated,
``graph[a]`` naming each atom's system, one cell and one ``pbc`` per system
(traced: molecules, slabs and bulk share a program); one system is the
batch of one. Pairs never cross systems.

How it searches (the search of one system is the same with one graph):

1. **Cells.** Zero rows of a system's cell on its free axes are completed
   (ASE's molecules and ``vacuum=None`` slabs have them) by unit vectors
   orthogonal to the others; on a free axis the shift is always 0, so the
   pairs do not depend on the completion, only the binning does.
2. **Fractional coordinates.** ``f = R @ inv(cell)``, wrapped into
   ``[0, 1)`` on periodic axes (``w = floor(f)``); shifts found between
   wrapped atoms are turned back into shifts of the caller's positions,
   ``S = S' - w[j] + w[i]``.
3. **Grid.** Each system's axis ``k`` is cut into ``c_k`` cells at least
   ``cutoff / (r_k h_k)`` wide (fractional), ``h_k`` the cell's height
   across the axis and ``r_k`` the static stencil reach (on a periodic
   axis ``r_k >= ceil(cutoff / h_k)``, the largest lattice shift between
   wrapped atoms; a larger reach makes smaller cells). On a free axis the
   cells span the system's atoms. A system has at most ``4 n + 64`` cells
   (coarsened past that); cells of all systems are numbered in one table,
   atoms sorted by cell (stable: by index within a cell).
4. **Stencil.** Atom ``i`` in cell ``a`` reads the cells ``a + o`` of
   its own system, ``|o_k| <= r_k``; on a periodic axis ``a + o`` is the
   cell ``(a + o) mod c`` of the image ``floor((a + o) / c)``, so each
   candidate ``(j, S)`` is read once. Unsorted, only half the stencil is
   read (``o >= 0`` lexicographic; within ``o = 0`` only ``j`` sorted
   after ``i``); sorted by ``i``, all of it. On a GPU an unsorted list is
   searched as a sorted one (the full stencil): its order, ``i``-major, is
   one an unsorted list may have, and the half stencil's loop below has a
   trip count read back from the device on every trip there. On a GPU
   the cells' full stencil is walked by a Warp kernel, one thread per atom
   (`jaxrt.pairs.warp_search`): each atom's pairs counted, the counts
   scanned, the pairs written at their place; the same rows as steps 5-6
   below give, without their arrays of runs per atom and offset.
5. **Decide and store.** Sorted by ``i``, the candidates are the runs'
   slots laid end to end, atom by atom and offset by offset (``i``-major),
   read ``chunk`` at a time in a loop until every one is read (the work
   follows the candidates there are), or, where no run is longer than a
   word (32 atoms), every run at once, slot ``t`` of each in step ``t``,
   its keep bits packed in one uint32 per run; unsorted, the same words
   from the half stencil, the atoms in their cells' order (atoms of a
   cell read the same runs), the kept ones stored in one pass after the
   loop, or, past a word, every run read a slot at a time until the
   fullest cell is read. Each is decided as ASE
   decides, in the positions' dtype: ``|R[j] - R[i] + S @ cell| <
   cutoff`` (strict; the cutoff of the two atoms' species with a cutoff
   matrix), and kept candidates are written at the running count, so the
   count is exact past the capacity. From the half stencil a kept pair
   stands for ``(i, j, S)`` and ``(j, i, -S)`` (one decision: ``|-d| =
   |d|`` bit for bit):
   a full list writes both, a half list the representative, ``i < j``, or
   ``i == j`` and ``S`` lexicographically positive. From the full stencil
   each atom finds its own pairs (only representatives for a half list),
   in ``i``-major order.
6. **Assemble.** Unsorted (the half stencil): self pairs ``(i, i, 0)``
   first when asked for, then the pairs. Sorted: the pairs are already in place (the order they
   were found in); each atom's self pair, when asked for, is put before its
   pairs. Padding rows ``(pad, pad, 0)`` at the end.

**Own reach** (``own_reach``, sorted lists of several systems): steps 3-5
are replaced by `jaxrt.pairs.reach`: each system's grid and stencil are
those of its own reach (at most the static one), and the atoms' runs,
as many as each one's system needs, are read end to end, a chunk at a
time; a batch with a cell of more than a word of atoms is searched as
above.

**Dense blocks** (``max_nodes > 0``, sorted lists of flat batches of small
systems): steps 3-5 are replaced by `dense_rows`: each system is one
block of ``max_nodes`` slots, every atom against every atom of its system
in every image of the reach, decided as in step 5 (no cells, no runs),
the rows found by counting kept bits; past 32 atoms each atom reads only
the 32-atom tiles (Morton order) whose boxes may come within the cutoff.

``brute=True`` is the same program with one cell per system: every atom
of a system is a candidate of every atom of it, in every image.
`jaxrt.pairs.host` decides every candidate of one small system at once
in numpy, for eager calls, as this program decides them.
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxrt import platforms
from jaxrt.pairs.bits import ErrorBit
from jaxrt.pairs.blocks import dense_rows
from jaxrt.pairs.cells import DENSE_MOST, bin_atoms, candidates, offsets
from jaxrt.pairs.reach import ragged_full_stencil
from jaxrt.pairs.rows import (pair_rows, placed_rows, self_mask,
                              self_pair_rows)
from jaxrt.pairs.warp_search import warp_stencil

# On a GPU an unsorted list is searched as a sorted one (the full stencil,
# rows ``i``-major): the half stencil's slot loop has a traced trip count.
FULL_STENCIL_UNSORTED_ON_CUDA = True
# On a GPU the full stencil of the cells is walked by a Warp kernel
# (`jaxrt.pairs.warp_search`): the same rows, without the arrays of runs
# per atom and offset.
WARP_WALK_ON_CUDA = True
# Sorted lists of several systems: each system searched with its own reach
# (`jaxrt.pairs.reach`); False: the batch's static reach for every system.
# Read when `jaxrt.pairs_batch` is traced.
OWN_REACH = True


@functools.partial(jax.jit, static_argnames=(
    "periodic", "reach", "capacity", "brute", "chunk", "half", "sort",
    "self_interaction", "n_graph", "completed", "max_nodes", "own_reach"))
def search(positions, graph, mask, cells, pbc, cutoff, species, pad_index, *,
           periodic: tuple[bool, ...], reach: tuple[int, ...], capacity: int,
           brute: bool, chunk: int, half: bool, sort: bool,
           self_interaction: bool, n_graph: int, completed: bool = False,
           max_nodes: int = 0, own_reach: bool = False):
    """The pairs of a flat batch (module docstring).

    Args:
      positions: float ``(N, 3)``.
      graph: int32 ``(N,)``, each atom's system in ``[0, n_graph)``.
      mask: bool ``(N,)``, the real atoms (padding atoms have no pairs).
      cells: ``(G, 3, 3)`` rows, the positions' dtype.
      pbc: bool ``(G, 3)`` (traced); ANDed with the static ``periodic``.
      cutoff: float scalar, or float ``(S, S)`` by species (traced).
      species: int32 ``(N,)`` rows of the cutoff matrix, or None.
      pad_index: int32 scalar, ``i`` and ``j`` of the padding rows.
      reach: static ``r_k`` per axis (0 on the static free axes of the
        brute force).
      chunk: static candidates read per step of the loop.
      capacity: static rows; 0 counts only.
      completed: static; the cells have no zero rows to complete (checked
        on the host).
      max_nodes: static; positive (with ``sort``): every system has at
        most this many atoms and is searched as one dense block
        (`dense_rows`, with the stencil ``reach``) unless the blocks hold
        more than ``DENSE_MOST`` candidates; 0: cells.
      own_reach: static; with ``sort``, several systems and not ``brute``,
        each system is searched with its own reach, at most ``reach``
        (`jaxrt.pairs.reach`); False: with ``reach``.
    Returns:
      int32 ``(capacity, 5)`` rows ``(i, j, S)``, int32 count (exact), int32
      ``(G,)`` rows per system (exact), int32 error bits.
    """
    n, dtype = positions.shape[0], positions.dtype
    cut = jnp.asarray(cutoff, dtype)
    radius = cut if species is None else jnp.max(cut)
    pbc = jnp.asarray(pbc, bool) & np.array(periodic)
    if max_nodes > 0 and sort and n_graph * max_nodes * max_nodes * \
            offsets(reach, True).shape[0] <= DENSE_MOST:
        rows, total, per_system, error = dense_rows(
            positions, graph, mask, cells.astype(dtype), pbc, cut, species,
            radius, reach=reach, max_nodes=max_nodes, n_graph=n_graph,
            completed=completed, half=half,
            self_interaction=self_interaction, capacity=capacity)
        return _finish(rows, total, per_system, error, pad_index, n=n,
                       capacity=capacity)
    args = (positions, graph, mask, cells.astype(dtype), pbc, cut, species,
            radius)
    static = dict(reach=reach, chunk=chunk, capacity=capacity, brute=brute,
                  half=half, self_interaction=self_interaction,
                  n_graph=n_graph, completed=completed)
    if sort:
        def sorted_default():
            if own_reach and n_graph > 1 and not brute:
                return ragged_full_stencil(
                    *args, reach=reach, capacity=capacity, half=half,
                    self_interaction=self_interaction, n_graph=n_graph,
                    completed=completed,
                    fallback=lambda: _full_stencil(*args, **static))
            return _full_stencil(*args, **static)

        # The Warp walk reads each atom's own runs already.
        rows, total, per_system, error = platforms.cuda_or_default(
            cuda=lambda: _cuda_stencil(*args, **static),
            default=sorted_default)
    elif FULL_STENCIL_UNSORTED_ON_CUDA:
        # Any order is an unsorted list's; the full stencil's word-packed
        # runs have no loop of a traced trip count on a GPU, where each
        # trip of the half stencil's slot loop reads its predicate back.
        rows, total, per_system, error = platforms.cuda_or_default(
            cuda=lambda: _cuda_stencil(*args, **static),
            default=lambda: _half_stencil(*args, **static))
    else:
        rows, total, per_system, error = _half_stencil(*args, **static)
    return _finish(rows, total, per_system, error, pad_index, n=n,
                   capacity=capacity)


def _full_stencil(positions, graph, mask, cells, pbc, cut, species, radius, *,
                  reach, chunk, capacity, brute, half, self_interaction,
                  n_graph, completed):
    """Steps 3-6 from the full stencil: each atom finds its own pairs,
    placed by atom (``i``-major, no sort). Returns `search`'s rows, count,
    count per system and error bits (before the capacity's)."""
    binned = bin_atoms(positions, graph, mask, cells, pbc, radius,
                       reach=reach, brute=brute, n_graph=n_graph,
                       completed=completed, full=True)
    selfs = self_mask(binned.real, cut, species) if self_interaction \
        else None
    _, per_atom, out = candidates(
        positions, binned, cut, species, reach=reach, chunk=chunk,
        stored=capacity, brute=brute, full=True, half=half)
    rows, total, per_system = placed_rows(
        per_atom, out, binned, selfs, capacity=capacity, n_graph=n_graph)
    return rows, total, per_system, binned.error


def _cuda_stencil(*args, brute, chunk, **static):
    """The full stencil on a GPU: by the Warp walk (the cells), or by
    `_full_stencil` (the brute force, or with the walk switched off)."""
    if WARP_WALK_ON_CUDA and not brute:
        return warp_stencil(*args, **static)
    return _full_stencil(*args, brute=brute, chunk=chunk, **static)


def _half_stencil(positions, graph, mask, cells, pbc, cut, species, radius, *,
                  reach, chunk, capacity, brute, half, self_interaction,
                  n_graph, completed):
    """Steps 3-6 from the half stencil: each pair found once, written as
    both directions (or its representative), self pairs first. Returns as
    `_full_stencil`."""
    n = positions.shape[0]
    binned = bin_atoms(positions, graph, mask, cells, pbc, radius,
                       reach=reach, brute=brute, n_graph=n_graph,
                       completed=completed, full=False, by_slot=not brute)
    stored = capacity if half else (capacity + 1) // 2
    found, per_atom, out = candidates(
        positions, binned, cut, species, reach=reach, chunk=chunk,
        stored=stored, brute=brute, full=False, half=half)
    columns, total, per_system = pair_rows(
        found, per_atom, out, binned, half=half, n_graph=n_graph)
    if self_interaction:
        rows = jnp.stack(columns, axis=1)
        self_rows, n_self, self_system = self_pair_rows(
            self_mask(binned.real, cut, species), binned.graph, n_graph)
        both = jnp.concatenate([self_rows, jnp.broadcast_to(
            jnp.array([n, n, 0, 0, 0], jnp.int32),
            (capacity + rows.shape[0], 5))])
        rows = jax.lax.dynamic_update_slice(both, rows,
                                            (n_self, jnp.int32(0)))
        total, per_system = total + n_self, per_system + self_system
        return rows[:capacity], total, per_system, binned.error
    # Columns (`pair_rows`) padded to the capacity, cut there and stacked
    # last: XLA reads `_finish`'s columns of the stack straight from them.
    extra = max(capacity - columns[0].shape[0], 0)
    columns = [jnp.concatenate([x, jnp.full((extra,), v, jnp.int32)])[
        :capacity] for x, v in zip(columns, (n, n, 0, 0, 0))]
    return jnp.stack(columns, axis=1), total, per_system, binned.error


def _finish(rows, total, per_system, error, pad_index, *, n, capacity):
    """Padding rows set to ``pad_index`` (column by column: the outputs'
    ``i``, ``j`` and ``S`` are read from the columns), the capacity's
    bit."""
    columns = [rows[:, c] for c in range(5)]
    padding = columns[0] >= n
    fill = [jnp.asarray(pad_index, jnp.int32)] * 2 + [jnp.int32(0)] * 3
    rows = jnp.stack([jnp.where(padding, f, x) for f, x in zip(fill, columns)],
                     axis=1)
    error = error | jnp.where(total > capacity, int(ErrorBit.CAPACITY), 0)
    return rows, total, per_system, error.astype(jnp.int32)
