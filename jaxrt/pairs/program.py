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
   atoms sorted by cell.
4. **Stencil.** Atom ``i`` in cell ``a`` reads the cells ``a + o`` of
   its own system, ``|o_k| <= r_k``; on a periodic axis ``a + o`` is the
   cell ``(a + o) mod c`` of the image ``floor((a + o) / c)``, so each
   candidate ``(j, S)`` is read once. Unsorted, only half the stencil is
   read (``o >= 0`` lexicographic; within ``o = 0`` only ``j`` sorted
   after ``i``); sorted by ``i``, all of it.
5. **Decide and store.** Sorted by ``i``, the candidates are the runs'
   slots laid end to end, atom by atom and offset by offset (``i``-major),
   read ``chunk`` at a time in a loop until every one is read (the work
   follows the candidates there are); unsorted, every run is read a slot
   at a time until the fullest cell is read. Each is decided as ASE decides, in the
   positions' dtype: ``|R[j] - R[i] + S @ cell| < cutoff`` (strict; the
   cutoff of the two atoms' species with a cutoff matrix), and kept
   candidates are written at the running count, so the count is exact
   past the capacity. From the half stencil a kept pair stands for ``(i,
   j, S)`` and ``(j, i, -S)`` (one decision: ``|-d| = |d|`` bit for bit):
   a full list writes both, a half list the representative, ``i < j``, or
   ``i == j`` and ``S`` lexicographically positive. From the full stencil
   each atom finds its own pairs (only representatives for a half list),
   in ``i``-major order.
6. **Assemble.** Unsorted: self pairs ``(i, i, 0)`` first when asked for,
   then the pairs. Sorted: the pairs are already in place (the order they
   were found in); each atom's self pair, when asked for, is put before its
   pairs. Padding rows ``(pad, pad, 0)`` at the end.

**Dense blocks** (``max_nodes > 0``, sorted lists of flat batches of small
systems): steps 3-5 are replaced by `_dense_rows`: each system is one
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
import itertools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxrt.pairs.bits import ErrorBit
from jaxrt.pairs.host import lex_positive

# Cells are this much (relatively) wider than their minimum, so that an atom
# binned one cell off by rounding still has all its neighbours in reach.
CELL_MARGIN = 2.0 ** -10
# The brute force up to this many slots (N² K) is one step, without a loop.
BRUTE_ONE_STEP = 2 ** 16
# A system has at most this many cells per atom, plus CELLS_PER_SYSTEM.
CELLS_PER_ATOM = 4
CELLS_PER_SYSTEM = 64
# Dense blocks up to this many candidates in all (their flat index is an
# int32, their keep bits one array); past it the cells search the batch.
DENSE_MOST = 2 ** 28


def shift_vectors(s, h):
    """``s @ h`` written out (``s`` float ``(..., 3)``, ``h`` ``(..., 3, 3)``
    broadcasting): elementwise in the dtype, as ASE's sum of three products
    (a GPU matrix product may round float32 to TF32)."""
    return (s[..., 0:1] * h[..., 0, :] + s[..., 1:2] * h[..., 1, :]
            + s[..., 2:3] * h[..., 2, :])


def safe_norm(d):
    """``|d|`` over the last axis, with a zero (finite) gradient at 0."""
    d2 = jnp.sum(d * d, axis=-1)
    positive = d2 > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, d2, 1)), 0)


def inverse(h):
    """``inv(h)`` and ``det(h)`` of ``(..., 3, 3)`` matrices, written out by
    cofactors: no solver call for a 3x3, a fraction of its compile time."""
    a, b, c = h[..., 0, :], h[..., 1, :], h[..., 2, :]
    adj = jnp.stack([jnp.cross(b, c), jnp.cross(c, a), jnp.cross(a, b)],
                    axis=-1)  # columns: inv(h) = adj / det
    det = jnp.sum(a * adj[..., :, 0], axis=-1)  # elementwise: no TF32 dot
    return adj / det[..., None, None], det


def heights(hinv):
    """float ``(..., 3)``: a cell's height across each axis, ``1 / |b_k|``
    with ``b_k`` column ``k`` of ``inv(cell)``."""
    return 1 / jnp.sqrt(jnp.sum(hinv * hinv, axis=-2))


def _unit(v):
    n = jnp.sqrt(jnp.sum(v * v, axis=-1, keepdims=True))
    return v / jnp.where(n > 0, n, 1)


def complete_cells(h, pbc):
    """Cells ``(G, 3, 3)`` with their zero rows on free axes replaced (ASE's
    ``complete_cell``: unit vectors orthogonal to the rows given), and bool
    ``(G,)``: a zero row on a periodic axis (the cell is singular)."""
    zero = ~jnp.any(h != 0, axis=-1)  # (G, 3)
    missing = zero & ~pbc
    count = jnp.sum(missing, axis=-1)
    rows = [h[:, 0], h[:, 1], h[:, 2]]
    # One row missing: the unit normal of the two others.
    normal = [_unit(jnp.cross(rows[(k + 1) % 3], rows[(k + 2) % 3]))
              for k in range(3)]
    # Two missing: the present row u and two unit vectors orthogonal to it
    # and to each other (from the Cartesian axis least along u).
    present = jnp.sum(jnp.where(missing[..., None], 0, h), axis=1)
    u = _unit(present)
    axis = jax.nn.one_hot(jnp.argmin(jnp.abs(u), axis=-1), 3, dtype=h.dtype)
    v1 = _unit(jnp.cross(u, axis))
    v2 = jnp.cross(u, v1)
    first_missing = jnp.argmax(missing, axis=-1)
    eye = jnp.eye(3, dtype=h.dtype)
    out = []
    for k in range(3):
        pair = jnp.where((first_missing == k)[:, None], v1, v2)
        row = jnp.where((count == 1)[:, None], normal[k],
                        jnp.where((count == 2)[:, None], pair, eye[k]))
        out.append(jnp.where(missing[:, k, None], row, rows[k]))
    return jnp.stack(out, axis=1), jnp.any(zero & pbc, axis=-1)


def offsets(reach: tuple[int, ...], full: bool = False) -> np.ndarray:
    """int32 ``(K, 3)``: the stencil, every offset with ``|o_k| <= r_k``;
    the half stencil (not ``full``) keeps those that are zero or
    lexicographically positive."""
    every = np.array(list(itertools.product(
        *(range(-r, r + 1) for r in reach))), np.int32)
    if full:
        return every
    first = np.array([next((v for v in o if v != 0), 0) for o in every])
    return every[first >= 0]


def _exclusive_prefix(x):
    """int32 ``(n,)`` exclusive prefix sums of int32 ``(n,)`` ``x``."""
    return _prefix_sum(x, jnp.float64) - x


def _triangular_dot(x, strict: bool = False):
    """Inclusive (or, ``strict``, exclusive) prefix sums along the last
    axis of float ``x`` as one product with a triangular matrix: exact for
    whole sums below 2^24 (float32) or 2^53 (float64), and one small dot
    compiles and runs faster than a scan on a CPU."""
    m = x.shape[-1]
    upper = jnp.asarray(np.triu(np.ones((m, m), x.dtype), k=int(strict)))
    return jnp.dot(x, upper, precision=jax.lax.Precision.HIGHEST)


_PREFIX_BLOCK = 64


def _prefix_sum(x, dtype=jnp.float32):
    """int32 inclusive prefix sums of 1-d ``x`` (bool or int) by blocks of
    triangular products (`_triangular_dot`) in ``dtype`` (float64 where the
    sum may pass 2^24): a CPU runs them several times faster than
    ``cumsum``'s scan."""
    m = x.shape[0]
    if jax.dtypes.canonicalize_dtype(dtype) != dtype:  # x64 off: no float64
        return jnp.cumsum(x, dtype=jnp.int32)
    x = x.astype(dtype)
    if m <= _PREFIX_BLOCK:
        return _triangular_dot(x).astype(jnp.int32)
    rows = -(-m // _PREFIX_BLOCK)
    inner = _triangular_dot(jnp.pad(x, (0, rows * _PREFIX_BLOCK - m)).reshape(
        rows, _PREFIX_BLOCK))
    totals = inner[:, -1]
    before = _prefix_sum(totals, dtype).astype(dtype) - totals
    return (inner + before[:, None]).reshape(-1)[:m].astype(jnp.int32)


_RANK_BLOCK = 32


def _row_ranks(keep):
    """int32 ``(R, M)``: the inclusive count of True along each row of bool
    ``(R, M)`` ``keep``: in blocks of 32 by triangular products (M x 32,
    then the blocks' totals), so the work grows as ``M (32 + M / 32)``, not
    ``M²``."""
    rows, m = keep.shape
    x = keep.astype(jnp.float32)
    if m <= 2 * _RANK_BLOCK:
        return _triangular_dot(x).astype(jnp.int32)
    blocks = -(-m // _RANK_BLOCK)
    x = jnp.pad(x, ((0, 0), (0, blocks * _RANK_BLOCK - m))).reshape(
        rows, blocks, _RANK_BLOCK)
    inner = _triangular_dot(x)
    before = _triangular_dot(inner[..., -1], strict=True)
    ranks = (inner + before[..., None]).reshape(rows, -1)[:, :m]
    return ranks.astype(jnp.int32)


def table_size(n: int, n_graph: int, brute: bool) -> int:
    return n_graph if brute else CELLS_PER_ATOM * n + CELLS_PER_SYSTEM * n_graph


def _grid(fw, graph, real, pbc, h_height, cutoff, reach, n_graph: int,
          brute: bool, count):
    """Each system's grid (module docstring, 3.).

    Args:
      fw: float ``(N, 3)`` wrapped fractional positions; graph: int32
        ``(N,)``; real: bool ``(N,)``; pbc: bool ``(G, 3)``; h_height:
        float ``(G, 3)``; count: int32 ``(G,)`` real atoms per system.
    Returns:
      int32 ``(G, 3)`` cells per axis, float ``(G, 3)`` origin and width,
      int32 ``(G,)`` the first cell of each system in the table.
    """
    dtype = fw.dtype
    g = n_graph
    if brute:
        cells = jnp.ones((g, 3), jnp.int32)
        return (cells, jnp.zeros((g, 3), dtype), jnp.ones((g, 3), dtype),
                jnp.arange(g, dtype=jnp.int32))
    reach_arr = np.maximum(np.array(reach), 1)
    big = jnp.asarray(jnp.finfo(dtype).max, dtype)
    lo = jax.ops.segment_min(jnp.where(real[:, None], fw, big), graph, g)
    hi = jax.ops.segment_max(jnp.where(real[:, None], fw, -big), graph, g)
    has = (count > 0)[:, None]
    origin = jnp.where(pbc, 0, jnp.where(has, lo, 0))
    extent = jnp.where(pbc, 1, jnp.where(has, jnp.maximum(hi - origin, 0), 0))
    least = cutoff * (1 + CELL_MARGIN) / (reach_arr * h_height)
    budget = CELLS_PER_ATOM * count + CELLS_PER_SYSTEM

    def count_cells(coarsen):
        size = least * coarsen[:, None]
        per_axis = jnp.where(pbc, jnp.maximum(jnp.floor(1 / size), 1),
                             jnp.floor(extent / size) + 1)
        return jnp.where(has, per_axis, 1)

    def over(coarsen):
        return jnp.prod(count_cells(coarsen), axis=-1) > budget

    coarsen = jax.lax.while_loop(
        lambda c: jnp.any(over(c)),
        lambda c: jnp.where(over(c), c * 1.25, c), jnp.ones((g,), dtype))
    cells_f = count_cells(coarsen)
    width = jnp.where(pbc, 1 / cells_f, least * coarsen[:, None])
    cells = cells_f.astype(jnp.int32)
    return cells, origin, width, _exclusive_prefix(jnp.prod(cells, axis=-1))


class _Binned(NamedTuple):
    """The atoms binned: what the loop and the assembly read."""
    error: jax.Array      # int32 bits so far
    real: jax.Array       # bool (N,)
    graph: jax.Array      # int32 (N,)
    h_atom: jax.Array     # (N, 3, 3) each atom's completed cell
    start: jax.Array      # int32 (N, K) first sorted slot of each target run
    length: jax.Array     # int32 (N, K) its length
    image: jax.Array      # int32 (N, K, 3) S' + w[i] of each target
    order: jax.Array      # int32 (N,) sorted slot -> atom
    rank: jax.Array       # int32 (N,) atom -> sorted slot
    w: jax.Array          # float (N, 3) whole cells each atom was moved by


def _runs(coord, target, inside, cells_a, base_a, real, n_graph):
    """The atoms sorted by cell: each target cell's run (first sorted slot
    and length, int32 ``(N, K)``), ``order`` (slot -> atom) and ``rank``
    (atom -> slot)."""
    n = coord.shape[0]
    table = table_size(n, n_graph, False)

    def key_of(c, cells_c, base_c):
        return base_c + (c[..., 2] * cells_c[..., 1] + c[..., 1]) * \
            cells_c[..., 0] + c[..., 0]

    key = jnp.where(real, key_of(coord, cells_a, base_a), table)
    sorted_key, order = jax.lax.sort(
        (key, jnp.arange(n, dtype=jnp.int32)), num_keys=1, is_stable=False)
    # Each cell's run: its first sorted slot and its length, by two
    # scatters (an empty cell's start is never read).
    slots = jnp.arange(n, dtype=jnp.int32)
    first = jnp.full((table,), n, jnp.int32).at[sorted_key].min(
        slots, mode="drop")
    sizes = jnp.zeros((table,), jnp.int32).at[sorted_key].add(1, mode="drop")
    tkey = jnp.where(inside, key_of(target, cells_a[:, None, :],
                                    base_a[:, None]), 0)
    # One gather for both (the key's arithmetic is fused into the gather,
    # and would be done once per gathered array).
    run = jnp.stack([first, sizes], axis=1)[tkey]
    start = run[..., 0]
    length = jnp.where(inside, run[..., 1], 0)
    rank = jnp.zeros((n,), jnp.int32).at[order].set(
        jnp.arange(n, dtype=jnp.int32))
    return start, length, order, rank


class _Frame(NamedTuple):
    """Steps 1-2: the completed cells, the real atoms, the wraps."""
    error: jax.Array      # int32 bits so far
    real: jax.Array       # bool (N,)
    graph: jax.Array      # int32 (N,) clipped to [0, G)
    unclipped: jax.Array  # int32 (N,) as given
    h: jax.Array          # (G, 3, 3) completed cells
    bad_cell: jax.Array   # bool (G,)
    h_height: jax.Array   # (G, 3)
    count: jax.Array      # int32 (G,) real atoms per system
    pbc_a: jax.Array      # bool (N, 3)
    w: jax.Array          # float (N, 3) whole cells each atom was moved by
    fw: jax.Array         # float (N, 3) wrapped fractional positions


def _frame(positions, graph, mask, cells, pbc, *, n_graph, completed):
    """Steps 1-2 of the module docstring (step 1 unless ``completed``)."""
    n, dtype = positions.shape[0], positions.dtype
    r = jax.lax.stop_gradient(positions)
    h = jax.lax.stop_gradient(cells)
    if completed:
        zero_periodic = jnp.zeros((n_graph,), bool)
    else:
        h, zero_periodic = complete_cells(h, pbc)
    hinv, det = inverse(h)
    bad_cell = zero_periodic | ~(jnp.isfinite(det) & (jnp.abs(det) > 0)
                                 & jnp.all(jnp.isfinite(hinv), axis=(1, 2)))
    unclipped, graph = graph, jnp.clip(graph, 0, n_graph - 1)
    finite = jnp.all(jnp.isfinite(r), axis=1)
    count = jax.ops.segment_sum(mask.astype(jnp.int32), graph, n_graph)
    error = jnp.where(jnp.any(mask & ~finite),
                      int(ErrorBit.NONFINITE_POSITION), 0)
    error = error | jnp.where(jnp.any(bad_cell & (count > 0)),
                              int(ErrorBit.SINGULAR_CELL), 0)
    real = mask & finite
    count = jax.ops.segment_sum(real.astype(jnp.int32), graph, n_graph)
    hinv = jnp.where(bad_cell[:, None, None], jnp.eye(3, dtype=dtype), hinv)
    h_height = heights(hinv)
    pbc_a, hinv_a = pbc[graph], hinv[graph]
    f = jnp.sum(jnp.where(real[:, None], r, 0)[:, :, None] * hinv_a, axis=1)
    w = jnp.where(pbc_a, jnp.floor(f), 0)
    fw = f - w
    return _Frame(error, real, graph, unclipped, h, bad_cell, h_height,
                  count, pbc_a, w, fw)


def _bin(positions, graph, mask, cells, pbc, radius, *, reach, brute,
         n_graph, completed, full) -> _Binned:
    """Steps 1-4 of the module docstring (step 1 unless ``completed``)."""
    n = positions.shape[0]
    (error, real, graph, unclipped, h, bad_cell, h_height, count, pbc_a, w,
     fw) = _frame(positions, graph, mask, cells, pbc, n_graph=n_graph,
                  completed=completed)
    grid_cells, origin, width, base = _grid(
        fw, graph, real, pbc, h_height, radius, reach, n_graph, brute, count)
    # The reach covers the cutoff unless the cell is too short for it.
    short = jnp.any(pbc & (radius * grid_cells / h_height > np.array(reach)),
                    axis=-1) & (count > 0) & ~bad_cell
    error = error | jnp.where(jnp.any(short), int(ErrorBit.MAX_SHIFT), 0)

    cells_a, base_a = grid_cells[graph], base[graph]
    coord = jnp.clip(jnp.floor((fw - origin[graph]) / width[graph]).astype(
        jnp.int32), 0, cells_a - 1)
    # The half stencil's target cells and their images (docstring, 4.).
    target = coord[:, None, :] + jnp.asarray(offsets(reach, full))[None]
    cells_k = cells_a[:, None, :]
    # floor(target / cells) of small whole numbers, in float32 (exact:
    # |target| < 2^24, and the 1/2 keeps the quotient off the integers);
    # faster than an integer division.
    image = jnp.where(pbc_a[:, None, :], jnp.floor(
        (target.astype(jnp.float32) + 0.5) / cells_k.astype(jnp.float32)
    ).astype(jnp.int32), 0)
    target = target - image * cells_k
    inside = jnp.all((target >= 0) & (target < cells_k), axis=2) & \
        real[:, None]
    if brute:
        # One cell per system: a system's run is its atoms as given (they
        # are contiguous; padding atoms in it are skipped by the loop), so
        # nothing is sorted.
        order = rank = jnp.arange(n, dtype=jnp.int32)
        system = jnp.clip(unclipped, 0, n_graph)
        sizes = jax.ops.segment_sum(jnp.ones((n,), jnp.int32), system,
                                    n_graph + 1)
        first = _exclusive_prefix(sizes)
        start = jnp.broadcast_to(first[system][:, None], inside.shape)
        length = jnp.where(inside, sizes[system][:, None], 0)
    else:
        start, length, order, rank = _runs(coord, target, inside, cells_a,
                                           base_a, real, n_graph)
    # Shifts of the caller's positions: S = S' + w[i] - w[j].
    image = image + w.astype(jnp.int32)[:, None, :]
    return _Binned(error, real, graph, h[graph], start, length, image, order,
                   rank, w)


def _candidates(positions, binned: _Binned, cut, species, *, reach, chunk,
                stored, brute, full, half):
    """Step 5: the loop over candidates. Returns the pairs found (int32),
    per atom (int32 ``(N,)``) and the candidates stored, ``(i K + k, p)``
    (atom ``i``'s offset ``k``, the partner's sorted slot ``p``) padded
    with ``i = N``: from the half stencil each pair is found once; from the
    ``full`` stencil each atom finds all its own pairs (its representatives
    only, with ``half``).

    From the ``full`` stencil the candidates are the runs' slots laid end
    to end, atom by atom and offset by offset (``i``-major), and read
    ``chunk`` at a time: the work follows the candidates there are, not
    the fullest cell times every run, and the pairs kept come out in
    ``i``-major order, so a pair's place in the list is its rank among the
    kept (no sort, one scatter). A brute force of few candidates is one
    step."""
    n, dtype = positions.shape[0], positions.dtype
    b = binned
    own = jnp.asarray(~offsets(reach, full).any(axis=1))  # (K,): offset 0
    k_offsets = own.shape[0]
    columns = [positions[b.order], b.w[b.order]]
    if species is not None:
        columns.append(species[b.order][:, None].astype(dtype))
    # One gather per candidate: the sorted atoms' positions, wraps (small
    # whole numbers, exact in the dtype) and species side by side.
    table = jnp.concatenate(columns, axis=1)

    def decide(i, k, p, image):
        """Which candidates ``(i, offset k, sorted slot p)`` (any shape;
        ``image`` the run's ``S' + w[i]``, shape + (3,)) are kept."""
        row = table[p]
        s = image - row[..., 3:6].astype(jnp.int32)
        d = (row[..., :3] - positions[i]) + shift_vectors(
            s.astype(dtype), b.h_atom[i])
        dist = jnp.sqrt(d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1]
                        + d[..., 2] * d[..., 2])
        if species is None:
            limit = cut
        else:
            limit = cut.at[species[i], row[..., 6].astype(jnp.int32)].get(
                mode="fill", fill_value=0)
        rank_i = b.rank[i]
        if not full:  # within the own cell, from the atom sorted first
            once = ~own[k] | (p > rank_i)
        else:  # all but (i, i, 0)
            once = ~(own[k] & (p == rank_i))
            if half:
                j = b.order[p]
                once = once & ((i < j) | ((i == j) & lex_positive(s)))
        if brute:  # runs hold padding atoms (not sorted out)
            once = once & b.real[p]
        return (dist < limit) & once

    pad = jnp.array([n * k_offsets, 0], jnp.int32)
    out = jnp.broadcast_to(pad, (stored, 2))
    if brute and n * n * k_offsets <= max(chunk, BRUTE_ONE_STEP):
        # Few candidates (every slot of every run, N² K at most): one
        # step, no loop and no stream to lay out.
        slot = jnp.arange(n, dtype=jnp.int32)
        atoms = jnp.arange(n, dtype=jnp.int32)[:, None, None]
        k = jnp.arange(k_offsets, dtype=jnp.int32)[None, :, None]
        p = jnp.clip(b.start[:, :, None] + slot, 0, n - 1)
        keep = (slot < b.length[:, :, None]) & decide(
            atoms, k, p, b.image[:, :, None, :])
        ranks = _prefix_sum(keep.reshape(-1))
        if stored > 0:
            rows = jnp.stack([jnp.broadcast_to(atoms * k_offsets + k,
                                               p.shape), p], axis=-1)
            out = out.at[jnp.where(keep.reshape(-1), ranks - 1, stored)].set(
                rows.reshape(-1, 2), mode="drop")
        return ranks[-1], jnp.sum(keep, axis=(1, 2), dtype=jnp.int32), out

    if not full:
        # Unsorted, the order is free: every run read a slot at a time (as
        # many steps as the fullest cell holds), which on a CPU costs less
        # than laying out the stream for one system of ~100 atoms.
        atoms = jnp.arange(n, dtype=jnp.int32)[:, None, None]
        k = jnp.arange(k_offsets, dtype=jnp.int32)[None, :, None]

        def slot_step(t, carry):
            total, per_atom, out = carry
            p = jnp.clip(b.start[:, :, None] + t, 0, n - 1)
            keep = ((t < b.length[:, :, None]) & decide(
                atoms, k, p, b.image[:, :, None, :])).reshape(n, k_offsets)
            ranks = _row_ranks(keep)
            row_count = ranks[:, -1]
            if stored > 0:
                at = total + _exclusive_prefix(row_count)[:, None] + ranks - 1
                rows = jnp.stack([(atoms * k_offsets + k).reshape(n, -1),
                                  p.reshape(n, -1)], axis=-1)
                out = out.at[jnp.where(keep, at, stored).reshape(-1)].set(
                    rows.reshape(-1, 2), mode="drop")
            return (total + jnp.sum(row_count, dtype=jnp.int32),
                    per_atom + row_count, out)

        return jax.lax.fori_loop(
            0, jnp.max(b.length, initial=0), slot_step,
            (jnp.zeros((), jnp.int32), jnp.zeros((n,), jnp.int32), out))

    return _stream(decide, b, out, n=n, k_offsets=k_offsets, chunk=chunk,
                   stored=stored)


def _stream(decide, b: _Binned, out, *, n, k_offsets, chunk, stored):
    """`_candidates` from the full stencil: the candidates as one
    ``i``-major stream read ``chunk`` at a time (its docstring)."""
    length = b.length.reshape(-1)
    ends = _prefix_sum(length, jnp.float64)  # (N K,) inclusive
    total_candidates = ends[-1]
    runs = n * k_offsets
    # The runs that hold candidates, in order (compacted, padded with
    # runs that start past every candidate): a block of ``chunk``
    # candidates meets at most ``chunk`` of them, in one slice.
    nonempty = length > 0
    at = jnp.where(nonempty, _prefix_sum(nonempty) - 1,
                   runs + chunk)
    big = jnp.iinfo(jnp.int32).max
    run_first = jnp.full((runs + chunk,), big, jnp.int32).at[at].set(
        ends - length, mode="drop")
    run_ends = jnp.full((runs + chunk,), big, jnp.int32).at[at].set(
        ends, mode="drop")
    run_id = jnp.full((runs + chunk,), runs - 1, jnp.int32).at[at].set(
        jnp.arange(runs, dtype=jnp.int32), mode="drop")
    runs_start = b.start.reshape(-1)
    image = b.image.reshape(-1, 3)
    # Each atom's last candidate: the kept count there, read as the block
    # holding it passes, gives the pairs per atom (exact past the capacity).
    atom_end = ends[k_offsets - 1::k_offsets] - 1
    slots = jnp.arange(chunk, dtype=jnp.int32)

    def step(carry):
        c0, total, upto, out = carry
        c = c0 + slots
        valid = c < total_candidates
        # The compacted run of each candidate: the block's first (holding
        # c0), plus the later runs that start at or before it.
        r0 = jnp.searchsorted(run_ends, c0, side="right").astype(jnp.int32)
        first = jax.lax.dynamic_slice(run_first, (r0 + 1,), (chunk,))
        starts = jnp.zeros((chunk,), jnp.float32).at[first - c0].add(
            1, mode="drop")
        compact = r0 + _prefix_sum(starts)
        run = run_id[compact]
        c_first = run_first[compact]
        i = run // k_offsets
        k = run - i * k_offsets
        p = jnp.clip(runs_start[run] + c - c_first, 0, n - 1)
        keep = valid & decide(i, k, p, image[run])
        ranks = _prefix_sum(keep)
        if stored > 0:
            at = jnp.where(keep, total + ranks - 1, stored)
            rows = jnp.stack([run, p], axis=-1)
            out = out.at[at].set(rows, mode="drop")
        last = atom_end - c0
        here = (last >= 0) & (last < chunk)
        upto = jnp.where(here, total + ranks[jnp.clip(last, 0, chunk - 1)],
                         upto)
        return c0 + chunk, total + ranks[-1], upto, out

    zero = jnp.zeros((), jnp.int32)
    _, found, upto, out = jax.lax.while_loop(
        lambda carry: carry[0] < total_candidates, step,
        (zero, zero, jnp.zeros((n,), jnp.int32), out))
    per_atom = upto - jnp.concatenate([zero[None], upto[:-1]])
    return found, per_atom, out


def _stored_pairs(out, binned: _Binned):
    """The stored candidates as ``i``, ``j`` (``N`` where padded) and
    ``S`` (int32)."""
    n, k_offsets = binned.image.shape[:2]
    i = out[:, 0] // k_offsets
    kept = i < n
    at = jnp.where(kept, i, 0)
    j = jnp.where(kept, binned.order[jnp.where(kept, out[:, 1], 0)], n)
    s = binned.image[at, out[:, 0] % k_offsets] - binned.w[
        jnp.where(kept, j, 0)].astype(jnp.int32)
    return jnp.where(kept, i, n), j, jnp.where(kept[:, None], s, 0)


def _placed_rows(per_atom, out, binned, selfs, *, capacity, n_graph):
    """The full stencil's rows, found ``i``-major (so stored at their place
    when there are no self pairs), with atom ``i``'s self pair (``selfs``)
    placed before its pairs. Returns int32 ``(capacity, 5)`` rows padded
    with ``(N, N, 0)``, their count and the count per system."""
    n = binned.order.shape[0]
    i, j, s = _stored_pairs(out, binned)
    rows = jnp.concatenate([i[:, None], j[:, None], s], axis=1)
    if selfs is None:
        return rows, jnp.sum(per_atom, dtype=jnp.int32), \
            jax.ops.segment_sum(per_atom, binned.graph, n_graph)
    kept = i < n
    at_i = jnp.where(kept, i, 0)
    own = selfs.astype(jnp.int32)
    # Each pair moves down by the self pairs of the atoms up to its own.
    before = _prefix_sum(own, jnp.float64)
    at = jnp.where(kept, jnp.arange(capacity, dtype=jnp.int32)
                   + before[at_i], capacity)
    placed = jnp.broadcast_to(jnp.array([n, n, 0, 0, 0], jnp.int32),
                              (capacity, 5)).at[at].set(rows, mode="drop")
    degree = per_atom + own
    first = _exclusive_prefix(degree)
    atoms = jnp.arange(n, dtype=jnp.int32)
    placed = placed.at[jnp.where(selfs, first, capacity)].set(
        jnp.stack([atoms, atoms] + [jnp.zeros_like(atoms)] * 3, axis=1),
        mode="drop")
    return placed, jnp.sum(degree, dtype=jnp.int32), jax.ops.segment_sum(
        degree, binned.graph, n_graph)


def _pair_rows(found, per_atom, out, binned, *, half, n_graph):
    """The stored rows as pairs ``(i, j, S)``: both directions of each (a
    full list) or its representative (a half list). Returns the rows, their
    count and the count per system (exact past the capacity)."""
    i, j, s = _stored_pairs(out, binned)
    per_system = jax.ops.segment_sum(per_atom, binned.graph, n_graph)
    if half:
        # The representative: i < j, or i == j and S > 0.
        swap = (j < i) | ((j == i) & ~lex_positive(s))
        rows = jnp.concatenate([
            jnp.stack([jnp.where(swap, j, i), jnp.where(swap, i, j)], axis=1),
            jnp.where(swap[:, None], -s, s)], axis=1)
        return rows, found, per_system
    # Each pair next to its reverse (j, i, -S).
    forward = jnp.concatenate([i[:, None], j[:, None], s], axis=1)
    reverse = jnp.concatenate([j[:, None], i[:, None], -s], axis=1)
    rows = jnp.stack([forward, reverse], axis=1).reshape(-1, 5)
    return rows, 2 * found, 2 * per_system


def _self_mask(real, cut, species):
    """bool ``(N,)``: the atoms with a self pair ``(i, i, 0)``, the real
    ones whose own cutoff is positive (ASE keeps ``0 < rc``)."""
    if species is None:
        return real & (cut > 0)
    return real & (cut.at[species, species].get(mode="fill",
                                                 fill_value=0) > 0)


def _self_rows(selfs, graph, n_graph):
    """Step 6's self pairs ``(i, i, 0)`` of ``selfs``, packed first: int32
    ``(N, 5)``, their count and count per system."""
    n = selfs.shape[0]
    atoms = jnp.arange(n, dtype=jnp.int32)
    at = _exclusive_prefix(selfs.astype(jnp.int32))
    pad = jnp.array([n, n, 0, 0, 0], jnp.int32)
    rows = jnp.broadcast_to(pad, (n, 5)).at[jnp.where(selfs, at, n)].set(
        jnp.stack([atoms, atoms] + [jnp.zeros_like(atoms)] * 3, axis=1),
        mode="drop")
    return rows, jnp.sum(selfs, dtype=jnp.int32), jax.ops.segment_sum(
        selfs.astype(jnp.int32), graph, n_graph)


_WORD = 32


def _popcount(x):
    """int32 set bits of uint32 ``x`` (elementwise)."""
    return jax.lax.population_count(x).astype(jnp.int32)


def _select_bit(bits, rank):
    """int32 ``(R,)``: the position of the set bit of rank ``rank`` (int32
    ``(R,)``, from 0) in each uint32 ``bits`` ``(R,)``: the bits whose
    inclusive count is at most ``rank``, counted (one reduction: XLA
    writes it out once rather than computing it again in each reader)."""
    lanes = jnp.arange(_WORD, dtype=jnp.uint32)
    # (2 << 31) - 1 wraps to every bit, as wanted.
    upto = (jnp.uint32(2) << lanes) - jnp.uint32(1)
    inclusive = _popcount(bits[:, None] & upto)
    return jnp.sum(inclusive <= rank[:, None], axis=1, dtype=jnp.int32)


def _running_max(x):
    """int32 ``(n,)`` inclusive running maximum of int32 ``(n,)`` ``x``."""
    return jax.lax.associative_scan(jnp.maximum, x)


# Dense blocks of more than one word are read by 32-atom tiles (`_dense_rows`):
# the (atom, tile, image) words decided this many at a time in a loop, ...
TILE_CHUNK = 2 ** 13
# ... a tile dropped only where the cutoff, grown by this much (relatively)
# and by this many of the dtype's epsilons per unit of fractional
# coordinate, does not reach its box: only where the exact test would drop
# every atom of it (the wrapped fractional coordinates' rounding is far
# smaller).
TILE_MARGIN = 2.0 ** -10
TILE_EPS = 2.0 ** 8


def _dense_setup(positions, graph, mask, cells, pbc, cut, species, radius,
                 *, reach, max_nodes, n_graph, completed, self_interaction):
    """What every dense block reads: each system's atoms as ``(G, M)``
    slots (the frame's arrays gathered), the stencil, the error bits."""
    n = positions.shape[0]
    g, m = n_graph, max_nodes
    fr = _frame(positions, graph, mask, cells, pbc, n_graph=n_graph,
                completed=completed)
    stencil = offsets(reach, full=True)
    # Each system's atoms are contiguous (a flat batch): slot = a - first.
    sizes = jnp.zeros((g,), jnp.int32).at[fr.unclipped].add(1, mode="drop")
    first = _exclusive_prefix(sizes)
    slot = jnp.arange(n, dtype=jnp.int32) - first[fr.graph]
    error = fr.error | jnp.where(jnp.any(fr.real & (slot >= m)),
                                 int(ErrorBit.MAX_NODES), 0)
    short = jnp.any(pbc & (radius / fr.h_height > np.array(reach)),
                    axis=-1) & (fr.count > 0) & ~fr.bad_cell
    error = error | jnp.where(jnp.any(short), int(ErrorBit.MAX_SHIFT), 0)
    slots = jnp.arange(m, dtype=jnp.int32)
    idx = first[:, None] + slots
    present = slots < sizes[:, None]
    at = jnp.where(present, idx, 0)
    real = present & fr.real[at]                                  # (G, M)
    o = jnp.asarray(stencil)
    if self_interaction:
        selfs = _self_mask(fr.real, cut, species)[at] & real
    else:
        selfs = jnp.zeros((g, m), bool)
    return dict(
        n=n, fr=fr, error=error, first=first, idx=idx, real=real,
        p=positions[at], w=fr.w[at].astype(jnp.int32), fw=fr.fw[at],
        sp=None if species is None else species[at], o=o,
        own=int(np.argmin(np.abs(stencil).sum(axis=1))),
        # On a free axis only the zero offset (its wrap is 0).
        allowed=jnp.all(pbc[:, None, :] | (o == 0)[None], axis=-1),  # (G, K)
        selfs=selfs)


def _pack(keep):
    """uint32 ``(..., W)`` words of bool ``(..., 32 W)`` (bit ``b`` of word
    ``w``: entry ``32 w + b``)."""
    shape = keep.shape
    keep = keep.reshape(shape[:-1] + (shape[-1] // _WORD, _WORD))
    bit = jnp.arange(_WORD, dtype=jnp.uint32)
    return jnp.sum(jnp.where(keep, jnp.uint32(1) << bit, jnp.uint32(0)),
                   axis=-1, dtype=jnp.uint32)


def _dense_full(st, cut, species, *, m, half):
    """Every atom against every atom of its system in every image: uint32
    ``(G, M, K W)`` words, word ``k W + t`` holding slots ``32 t ..`` in
    image ``k``."""
    g = st["real"].shape[0]
    dtype = st["p"].dtype
    p, w, o, real = st["p"], st["w"], st["o"], st["real"]
    k_offsets = o.shape[0]
    slots = jnp.arange(m, dtype=jnp.int32)
    s = (o[None, None, :, None, :] + w[:, :, None, None, :]
         - w[:, None, None, :, :])                          # (G, M, K, M, 3)
    diff = p[:, None, :, :] - p[:, :, None, :]              # (G, Mi, Mj, 3)
    d = diff[:, :, None] + shift_vectors(
        s.astype(dtype), st["fr"].h[:, None, None, None])
    dist = jnp.sqrt(d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1]
                    + d[..., 2] * d[..., 2])
    if species is None:
        limit = cut
    else:
        sp = st["sp"]
        limit = cut.at[sp[:, :, None], sp[:, None, :]].get(
            mode="fill", fill_value=0)[:, :, None, :]
    same = (slots[:, None] == slots[None, :])[None, :, None, :]
    not_self = ~(same & (jnp.arange(k_offsets) == st["own"])[
        None, None, :, None])
    keep = ((dist < limit) & real[:, :, None, None] & real[:, None, None, :]
            & st["allowed"][:, None, :, None] & not_self)
    if half:
        before = (slots[:, None] < slots[None, :])[None, :, None, :]
        keep = keep & (before | (same & lex_positive(s)))
    words = -(-m // _WORD)
    keep = jnp.pad(keep, ((0, 0), (0, 0), (0, 0), (0, words * _WORD - m)))
    return _pack(keep).reshape(g, m, k_offsets * words)


def _morton(u, bits: int = 3):
    """int32 Morton codes of ``u`` in ``[0, 1]`` ``(..., 3)``, ``bits``
    per axis."""
    q = jnp.clip(jnp.floor(u * (1 << bits)), 0, (1 << bits) - 1).astype(
        jnp.int32)
    code = jnp.zeros(u.shape[:-1], jnp.int32)
    for b in range(bits - 1, -1, -1):
        for a in range(3):
            code = code * 2 + ((q[..., a] >> b) & 1)
    return code


def _dense_tiles(st, radius, *, m, budget, self_interaction):
    """The words each atom reads (`_dense_rows`), listed flat, atom by
    atom: int32 ``(budget,)`` entries ``a C' + c`` (slot ``a = g M + i``;
    ``c = 0`` its self pair where ``self_interaction``, then ``lead + k T +
    t``: tile ``t`` in image ``k``; ``G M C'`` past the last), int32 the
    entries needed (the list is whole only if at most ``budget``), and the
    sort, int32 ``(G, 32 T)`` sorted slot -> slot (``M`` past the atoms).

    An atom reads tile ``t`` in image ``o`` unless, on some axis ``k``, the
    tile's box of wrapped fractional coordinates is farther from it than
    the cutoff: ``|d| >= |f_j - f_i + o|_k h_k`` (``h_k`` the height), so
    no atom of the tile is within the cutoff in that image
    (`TILE_MARGIN`)."""
    g = st["real"].shape[0]
    dtype = st["p"].dtype
    real, fw, o = st["real"], st["fw"], st["o"]
    tiles = -(-m // _WORD)
    big = jnp.asarray(jnp.finfo(dtype).max, dtype)
    lo = jnp.min(jnp.where(real[..., None], fw, big), axis=1)     # (G, 3)
    hi = jnp.max(jnp.where(real[..., None], fw, -big), axis=1)
    span = jnp.maximum(hi - lo, 0)
    u = (fw - lo[:, None]) / jnp.where(span > 0, span, 1)[:, None]
    key = jnp.where(real, _morton(u), 1 << 30)
    order = jnp.argsort(key, axis=1, stable=True).astype(jnp.int32)
    pad = tiles * _WORD - m
    # The last tile's missing slots are slot m: past every atom (padded
    # below wherever a tile reads it, so never real).
    order = jnp.pad(order, ((0, 0), (0, pad)), constant_values=m)
    real_s = jnp.pad(jnp.take_along_axis(real, order[:, :m], axis=1),
                     ((0, 0), (0, pad)))
    fw_s = jnp.take_along_axis(fw, jnp.minimum(order, m - 1)[..., None],
                               axis=1)
    real_t = real_s.reshape(g, tiles, _WORD)
    fw_t = fw_s.reshape(g, tiles, _WORD, 3)
    t_lo = jnp.min(jnp.where(real_t[..., None], fw_t, big), axis=2)
    t_hi = jnp.max(jnp.where(real_t[..., None], fw_t, -big), axis=2)
    filled = jnp.any(real_t, axis=2)                               # (G, T)
    # |d| >= |f_j - f_i + o|_k h_k on each axis k: the gap between the
    # atom and the tile's box, in heights.
    of = o.astype(dtype)
    gap = jnp.maximum(jnp.maximum(
        t_lo[:, None, None, :, :] + of[None, None, :, None, :]
        - fw[:, :, None, None, :],
        fw[:, :, None, None, :] - of[None, None, :, None, :]
        - t_hi[:, None, None, :, :]), 0)                    # (G, M, K, T, 3)
    scale = 1 + jnp.max(jnp.abs(fw), axis=(1, 2))                  # (G,)
    reach = (radius / st["fr"].h_height) * (1 + TILE_MARGIN) + (
        TILE_EPS * jnp.finfo(dtype).eps * scale)[:, None]          # (G, 3)
    near = jnp.all(gap < reach[:, None, None, None, :], axis=-1)
    near = (near & filled[:, None, None, :] & real[:, :, None, None]
            & st["allowed"][:, None, :, None]).reshape(g, m, -1)
    if self_interaction:
        near = jnp.concatenate([st["selfs"][..., None], near], axis=-1)
    # Each entry's place: the words listed before its atom's, then its
    # rank among the atom's (float32 block products: a few thousand words
    # per atom at most).
    near = near.reshape(g * m, -1)
    ranks = _row_ranks(near)
    count = ranks[:, -1]
    at = _exclusive_prefix(count)[:, None] + ranks - 1
    needed = jnp.sum(count, dtype=jnp.int32)
    entries = jnp.full((budget,), near.size, jnp.int32).at[
        jnp.where(near, at, budget).reshape(-1)].set(
            jnp.arange(near.size, dtype=jnp.int32), mode="drop")
    return entries, needed, order


def _dense_tile_rows(st, cut, species, entries, needed, order, *, m, half,
                     self_interaction, capacity):
    """The rows of the entries of `_dense_tiles` (all of them: ``needed``
    at most their number): the words decided exactly (as `_dense_full`),
    ``TILE_CHUNK`` entries at a time in a loop (the work follows the words
    there are), then placed and read as `_dense_decode` reads its words.
    Returns int32 ``(capacity, 5)`` rows, the count and the count per
    system."""
    g = st["real"].shape[0]
    n, dtype = st["n"], st["p"].dtype
    p, w, o, real = st["p"], st["w"], st["o"], st["real"]
    k_offsets = o.shape[0]
    tiles = order.shape[1] // _WORD
    lead = int(self_interaction)
    width = lead + k_offsets * tiles
    pad = tiles * _WORD - m
    p_flat, w_flat = p.reshape(-1, 3), w.reshape(-1, 3)
    sp_flat = None if species is None else st["sp"].reshape(-1)

    def tiled(x):
        """``(G T, ..., 32)`` of ``(G, M, ...)``: the tiles' slots last
        (each coordinate one ``(E, 32)`` array below: no ``(E, 32, 3)``
        array is ever made)."""
        x = jnp.pad(x, ((0, 0), (0, pad)) + ((0, 0),) * (x.ndim - 2))
        x = jnp.take_along_axis(x, order.reshape(
            (g, -1) + (1,) * (x.ndim - 2)), axis=1)
        x = x.reshape((g * tiles, _WORD) + x.shape[2:])
        return jnp.moveaxis(x, 1, -1)

    slot_tab = order.reshape(g * tiles, _WORD)
    real_tab, p_tab, w_tab = tiled(real), tiled(p), tiled(w)
    sp_tab = None if species is None else tiled(st["sp"])

    def split(e):
        valid = e < g * m * width
        atom = jnp.where(valid, e // width, 0)                    # g M + i
        combo = e - atom * width - lead
        is_self = valid & (combo < 0)
        word = valid & (combo >= 0)
        combo = jnp.maximum(combo, 0)
        k = jnp.where(word, combo // tiles, 0)
        t = jnp.where(word, combo - k * tiles, 0)
        gi = atom // m
        return valid, atom, is_self, word, k, t, gi

    def decide(e):
        _, atom, is_self, word, k, t, gi = split(e)
        si = atom - gi * m
        tile = gi * tiles + t
        slot_t = slot_tab[tile]                                  # (E, 32)
        real_t = real_tab[tile] & word[:, None]
        pj = p_tab[tile]                                         # (E, 3, 32)
        wj = w_tab[tile]
        si_w = o[k] + w_flat[atom]                               # (E, 3)
        s = [si_w[:, c, None] - wj[:, c] for c in range(3)]
        sf = [x.astype(dtype) for x in s]
        h = st["fr"].h[gi]                                       # (E, 3, 3)
        pi = p_flat[atom]
        dist2 = None
        for c in range(3):
            # As `shift_vectors` and `_dense_full`: the same operations in
            # the same order, so the same decisions.
            dc = (pj[:, c] - pi[:, c, None]) + (
                sf[0] * h[:, 0, c, None] + sf[1] * h[:, 1, c, None]
                + sf[2] * h[:, 2, c, None])
            dist2 = dc * dc if dist2 is None else dist2 + dc * dc
        dist = jnp.sqrt(dist2)
        if species is None:
            limit = cut
        else:
            limit = cut.at[sp_flat[atom][:, None], sp_tab[tile]].get(
                mode="fill", fill_value=0)
        same = slot_t == si[:, None]
        not_self = ~(same & (k == st["own"])[:, None])
        keep = (dist < limit) & real_t & not_self
        if half:
            positive = (s[0] > 0) | ((s[0] == 0) & (
                (s[1] > 0) | ((s[1] == 0) & (s[2] > 0))))
            keep = keep & ((si[:, None] < slot_t) | (same & positive))
        bits = _pack(keep)[:, 0]
        count = jnp.where(is_self, 1, _popcount(bits))
        # Where the rows of the word find their partner: its tile's first
        # sorted slot (flat over the systems), or -1 for the self pair.
        base = jnp.where(is_self, -1, tile * _WORD)
        kk = jnp.where(is_self, st["own"], k)
        return jnp.stack([jax.lax.bitcast_convert_type(bits, jnp.int32),
                          count, atom, gi, base, kk], axis=1)

    budget = entries.shape[0]
    chunk = min(TILE_CHUNK, budget)
    steps = -(-budget // chunk)
    entries = jnp.pad(entries, (0, steps * chunk - budget),
                      constant_values=g * m * width)

    # Each word's bits, count and where its rows go, written by the loop
    # (written out once: the rows below read them many times over).
    def step(c, words):
        at = c * chunk
        return jax.lax.dynamic_update_slice(words, decide(
            jax.lax.dynamic_slice(entries, (at,), (chunk,))), (at, at * 0))

    words = jax.lax.fori_loop(
        0, (jnp.minimum(needed, budget) + chunk - 1) // chunk, step,
        jnp.zeros((steps * chunk, 6), jnp.int32))
    counts = words[:, 1]
    ends = _prefix_sum(counts, jnp.float64)
    r = jnp.arange(capacity, dtype=jnp.int32)
    total = ends[-1]
    stored = r < total
    word_start = ends - counts
    marks = jnp.zeros((capacity,), jnp.int32).at[jnp.where(
        counts > 0, word_start, capacity)].set(
            jnp.arange(counts.shape[0], dtype=jnp.int32), mode="drop")
    wid = _running_max(marks)
    rank = r - word_start[wid]
    row = words[wid]                                           # (R, 6)
    bits = jax.lax.bitcast_convert_type(row[:, 0], jnp.uint32)
    row_atom, row_g, base, kk = row[:, 2], row[:, 3], row[:, 4], row[:, 5]
    b = _select_bit(bits, rank)
    sj = jnp.where(base < 0, row_atom - row_g * m, order.reshape(-1)[
        jnp.maximum(base, 0) + b])
    shift = o[kk] + w_flat[row_atom] - w_flat[row_g * m + sj]
    i = st["idx"].reshape(-1)[row_atom]
    j = st["first"][row_g] + sj
    rows = jnp.concatenate([jnp.stack([i, j], axis=1), shift], axis=1)
    rows = jnp.where(stored[:, None], rows,
                     jnp.array([n, n, 0, 0, 0], jnp.int32))
    per_system = jax.ops.segment_sum(counts, words[:, 3], g)
    return rows, total, per_system


def _dense_decode(st, packed, *, m, capacity):
    """The rows of `_dense_full`'s words ``packed`` (uint32 ``(G, M, K
    W)``), each atom's self pair (where ``st["selfs"]``) first: int32
    ``(capacity, 5)``, the count and the count per system."""
    g = st["real"].shape[0]
    n, o, w, first, idx = st["n"], st["o"], st["w"], st["first"], st["idx"]
    tiles = -(-m // _WORD)
    width_words = packed.shape[-1]
    per_word = _popcount(packed).reshape(g * m, width_words)
    # Each atom's row of counts: its self pair, then its words; row r of
    # the list is in the word whose running count first passes r.
    counts = jnp.concatenate([st["selfs"].reshape(-1, 1).astype(jnp.int32),
                              per_word], axis=1)
    width = counts.shape[1]
    ends = _prefix_sum(counts.reshape(-1), jnp.float64)
    degree = jnp.sum(counts, axis=1, dtype=jnp.int32)
    r = jnp.arange(capacity, dtype=jnp.int32)
    stored = r < ends[-1]
    # Each nonempty word marks its first row; a row's word is the last mark
    # at or before it (a running maximum: no search per row).
    flat_counts = counts.reshape(-1)
    word_start = ends - flat_counts
    marks = jnp.zeros((capacity,), jnp.int32).at[jnp.where(
        flat_counts > 0, word_start, capacity)].set(
            jnp.arange(ends.shape[0], dtype=jnp.int32), mode="drop")
    wid = _running_max(marks)
    rank = r - word_start[wid]
    row_atom = wid // width                               # g M + i slot
    col = wid - row_atom * width
    is_self = col == 0
    word = jnp.maximum(col - 1, 0)
    bits = packed.reshape(-1)[row_atom * width_words + word]
    k = word // tiles
    b = _select_bit(bits, rank)
    gi = row_atom // m
    si = row_atom - gi * m
    sj = jnp.where(is_self, si, (word - k * tiles) * _WORD + b)
    k = jnp.where(is_self, st["own"], k)
    w_flat = w.reshape(-1, 3)
    shift = o[k] + w_flat[row_atom] - w_flat[gi * m + jnp.minimum(sj, m - 1)]
    i = idx.reshape(-1)[row_atom]
    j = first[gi] + sj
    rows = jnp.concatenate([jnp.stack([i, j], axis=1), shift], axis=1)
    rows = jnp.where(stored[:, None], rows,
                     jnp.array([n, n, 0, 0, 0], jnp.int32))
    total = jnp.sum(degree, dtype=jnp.int32)
    per_system = jnp.sum(degree.reshape(g, m), axis=1, dtype=jnp.int32)
    return rows, total, per_system


def _dense_rows(positions, graph, mask, cells, pbc, cut, species, radius, *,
                reach, max_nodes, n_graph, completed, half,
                self_interaction, capacity):
    """The sorted rows of a batch of small systems, each system one dense
    block: atom ``i`` against every atom ``j`` of its system in every
    image ``o`` of the stencil, ``S = o + w[i] - w[j]`` (the wraps as in
    step 2), decided as in step 5 (no cells, no runs, no per-candidate
    gathers); each atom's self pair first, then its rows in the order of
    its words (``o``, then the word's slots).

    One word per system (``max_nodes <= 32``): every ``(G, M, K, M)``
    candidate is decided. More: each system's atoms are sorted along a
    Morton curve of their wrapped fractional coordinates and cut into
    tiles of 32 (one word each), and each atom decides only the ``(tile,
    image)`` words whose box may come within the cutoff (`_dense_tiles`,
    conservative), listed flat for the batch, in a loop that reads only
    the words listed: the work grows with the words near the atoms, not
    with ``M² K``. The list has room for ``K`` words per atom slot on
    average (a tile a little smaller than the cutoff's sphere has about
    half of that); a batch needing more (tiles as wide as the cell, short
    cells) is decided whole, as with one word.

    The decisions are packed into 32-bit words; the running count over
    each atom's self pair and words places the words, and each of the
    ``capacity`` rows finds its word (the last word starting at or before
    it: marks and a running maximum) and its bit (the word's set bit of
    its rank, by population counts): nothing runs over the candidates but
    the decision, nothing is scattered per candidate.

    Returns int32 ``(capacity, 5)`` rows padded with ``(N, N, 0)``, the
    count, the count per system and the error bits (a system with more
    than ``max_nodes`` atoms sets ``MAX_NODES``).
    """
    m = max_nodes
    st = _dense_setup(positions, graph, mask, cells, pbc, cut, species,
                      radius, reach=reach, max_nodes=m, n_graph=n_graph,
                      completed=completed, self_interaction=self_interaction)
    k_offsets = st["o"].shape[0]
    words = -(-m // _WORD)

    def full():
        packed = _dense_full(st, cut, species, m=m, half=half)
        return _dense_decode(st, packed, m=m, capacity=capacity)

    if words < 2:
        rows, total, per_system = full()
        return rows, total, per_system, st["error"]
    # Room for one word per image per atom, in all (every word where
    # fewer would do): past that, every candidate.
    budget = st["real"].size * (k_offsets + int(self_interaction))
    entries, needed, order = _dense_tiles(
        st, radius, m=m, budget=budget, self_interaction=self_interaction)

    def pruned():
        return _dense_tile_rows(
            st, cut, species, entries, needed, order, m=m, half=half,
            self_interaction=self_interaction, capacity=capacity)

    rows, total, per_system = jax.lax.cond(needed > budget, full, pruned)
    return rows, total, per_system, st["error"]


@functools.partial(jax.jit, static_argnames=(
    "periodic", "reach", "capacity", "brute", "chunk", "half", "sort",
    "self_interaction", "n_graph", "completed", "max_nodes"))
def search(positions, graph, mask, cells, pbc, cutoff, species, pad_index, *,
           periodic: tuple[bool, ...], reach: tuple[int, ...], capacity: int,
           brute: bool, chunk: int, half: bool, sort: bool,
           self_interaction: bool, n_graph: int, completed: bool = False,
           max_nodes: int = 0):
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
        (`_dense_rows`, with the stencil ``reach``) unless the blocks hold
        more than ``DENSE_MOST`` candidates; 0: cells.
    Returns:
      int32 ``(capacity, 5)`` rows ``(i, j, S)``, int32 count (exact), int32
      ``(G,)`` rows per system (exact), int32 error bits.
    """
    n, dtype = positions.shape[0], positions.dtype
    cut = jnp.asarray(cutoff, dtype)
    radius = cut if species is None else jnp.max(cut)
    pbc = jnp.asarray(pbc, bool) & np.array(periodic)
    pad = jnp.array([n, n, 0, 0, 0], jnp.int32)
    if max_nodes > 0 and sort and n_graph * max_nodes * max_nodes * \
            offsets(reach, True).shape[0] <= DENSE_MOST:
        rows, total, per_system, error = _dense_rows(
            positions, graph, mask, cells.astype(dtype), pbc, cut, species,
            radius, reach=reach, max_nodes=max_nodes, n_graph=n_graph,
            completed=completed, half=half,
            self_interaction=self_interaction, capacity=capacity)
        return _finish(rows, total, per_system, error, pad_index, n=n,
                       capacity=capacity)
    binned = _bin(positions, graph, mask, cells.astype(dtype), pbc, radius,
                  reach=reach, brute=brute, n_graph=n_graph,
                  completed=completed, full=sort)
    selfs = _self_mask(binned.real, cut, species) if self_interaction \
        else None
    pad = jnp.array([n, n, 0, 0, 0], jnp.int32)
    if sort:
        # Each atom finds its own pairs, placed by atom: sorted, no sort.
        _, per_atom, out = _candidates(
            positions, binned, cut, species, reach=reach, chunk=chunk,
            stored=capacity, brute=brute, full=True, half=half)
        rows, total, per_system = _placed_rows(
            per_atom, out, binned, selfs, capacity=capacity,
            n_graph=n_graph)
    else:
        stored = capacity if half else (capacity + 1) // 2
        found, per_atom, out = _candidates(
            positions, binned, cut, species, reach=reach, chunk=chunk,
            stored=stored, brute=brute, full=False, half=half)
        rows, total, per_system = _pair_rows(
            found, per_atom, out, binned, half=half, n_graph=n_graph)
        if self_interaction:
            self_rows, n_self, self_system = _self_rows(
                selfs, binned.graph, n_graph)
            both = jnp.concatenate([self_rows, jnp.broadcast_to(
                pad, (capacity + rows.shape[0], 5))])
            rows = jax.lax.dynamic_update_slice(both, rows,
                                                (n_self, jnp.int32(0)))
            total, per_system = total + n_self, per_system + self_system
        else:
            rows = jnp.concatenate([rows, jnp.broadcast_to(
                pad, (max(capacity - rows.shape[0], 0), 5))])
        rows = rows[:capacity]
    return _finish(rows, total, per_system, binned.error, pad_index, n=n,
                   capacity=capacity)


def _finish(rows, total, per_system, error, pad_index, *, n, capacity):
    """Padding rows set to ``pad_index``, the capacity's bit."""
    padding = rows[:, 0] >= n
    fill = jnp.concatenate([jnp.broadcast_to(pad_index, (2,)).astype(
        jnp.int32), jnp.zeros((3,), jnp.int32)])
    rows = jnp.where(padding[:, None], fill, rows)
    error = error | jnp.where(total > capacity, int(ErrorBit.CAPACITY), 0)
    return rows, total, per_system, error.astype(jnp.int32)
