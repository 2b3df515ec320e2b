"""The cell search of `jaxrt.pairs.program` (steps 1-5 of its docstring)
and the pieces the dense blocks (`jaxrt.pairs.blocks`) share with it: the
cells' geometry, fractional frames, prefix sums and row ranks."""
from __future__ import annotations

import functools
import itertools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxrt import platforms
from jaxrt.pairs.bits import ErrorBit
from jaxrt.pairs.host import lex_positive
from jaxrt.pairs.placement import cell_coords, short_reach_bit
from jaxrt.pairs.prefix import exclusive_prefix, prefix_sum, row_ranks
from jaxrt.pairs.words import WORD, popcount, row_words, select_bit

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
# Slots of every run decided per step of `_half_words`' loop.
HALF_UNROLL = 4
# On a GPU the short runs' loop is written out, every slot of a word in one
# program: a loop's traced trip count is read back to the host every trip.
UNROLL_SLOTS_ON_CUDA = True
# A system's cells are coarsened by factors 1.25^m, the first that fits the
# budget taken from a table: of COARSEN_STEPS factors (then a loop for the
# rest), or on a GPU, where the factors of every system fit this many
# elements, of every factor up to inf (no loop).
COARSEN_STEPS = 32
COARSEN_TABLE_MOST = 2 ** 14


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


def table_size(n: int, n_graph: int, brute: bool) -> int:
    return n_graph if brute else CELLS_PER_ATOM * n + CELLS_PER_SYSTEM * n_graph


def grid(fw, graph, real, pbc, h_height, cutoff, reach, n_graph: int,
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
        size = least * coarsen[..., None]
        per_axis = jnp.where(pbc, jnp.maximum(jnp.floor(1 / size), 1),
                             jnp.floor(extent / size) + 1)
        return jnp.where(has, per_axis, 1)

    def over(coarsen):
        return jnp.prod(count_cells(coarsen), axis=-1) > budget

    whole = powers(dtype).shape[0] * g <= COARSEN_TABLE_MOST
    coarsen = platforms.cuda_or_default(
        cuda=lambda: coarsening(over, g, dtype, None if whole
                                else COARSEN_STEPS),
        default=lambda: coarsening(over, g, dtype, COARSEN_STEPS))
    cells_f = count_cells(coarsen)
    width = jnp.where(pbc, 1 / cells_f, least * coarsen[:, None])
    cells = cells_f.astype(jnp.int32)
    return cells, origin, width, exclusive_prefix(jnp.prod(cells, axis=-1))


@functools.cache
def powers(dtype, steps=None) -> np.ndarray:
    """``(M,)`` of ``dtype``: ``1.25^m`` for ``m < steps``, each the one
    before times 1.25 rounded in ``dtype`` (as a loop multiplying by 1.25
    rounds); ``steps`` None: up to and including the first ``inf``."""
    dtype = np.dtype(dtype)
    out = [np.ones((), dtype)]
    with np.errstate(over="ignore"):
        while (len(out) < steps) if steps else np.isfinite(out[-1]):
            out.append(out[-1] * dtype.type(1.25))
    return np.array(out, dtype)


def coarsening(over, g: int, dtype, steps):
    """float ``(G,)``: each system's first factor ``c`` of ``1, 1.25,
    1.25², ...`` (`powers`) with ``over(c)`` False, ``over`` taking float
    ``(..., G)`` to bool ``(..., G)``: the factors ``m < steps`` tried at
    once, the first that fits taken. A system that fits none of them (a
    free extent many times the cells the cutoff allows: rare) goes on in
    a loop, 1.25 at a time. ``steps`` None: the table runs to ``inf``,
    where ``over`` is False whatever the system (no finite count of cells
    past the budget is left), so there is no loop (on a GPU a loop reads
    its predicate back to the host on every trip)."""
    table = powers(dtype, steps)
    fits = ~over(jnp.broadcast_to(jnp.asarray(table)[:, None],
                                  (table.shape[0], g)))
    coarsen = jnp.where(jnp.any(fits, axis=0), jnp.asarray(table)[
        jnp.argmax(fits, axis=0)], table[-1])
    if steps is None:
        return coarsen
    return jax.lax.while_loop(
        lambda c: jnp.any(over(c)),
        lambda c: jnp.where(over(c), c * 1.25, c), coarsen)


class _Binned(NamedTuple):
    """The atoms binned: what the loop and the assembly read."""
    error: jax.Array      # int32 bits so far
    real: jax.Array       # bool (N,)
    graph: jax.Array      # int32 (N,)
    h_atom: jax.Array     # (N, 3, 3) each atom's (by slot) completed cell
    start: jax.Array      # int32 (N, K) first sorted slot of each target run
    length: jax.Array     # int32 (N, K) its length
    image: jax.Array      # int32 (N, K, 3) S' + w[i] of each target
    # (by slot: (K, N), (K, N) and (3, K, N), `bin_atoms`)
    order: jax.Array      # int32 (N,) sorted slot -> atom
    rank: jax.Array       # int32 (N,) atom -> sorted slot
    w: jax.Array          # float (N, 3) whole cells each atom was moved by


def sort_cells(coord, cells_a, base_a, real, n_graph):
    """The atoms sorted by cell: ``order`` (slot -> atom), ``rank`` (atom
    -> slot) and each cell's run (first slot, length: int32 ``(T, 2)``)."""
    n = coord.shape[0]
    table = table_size(n, n_graph, False)
    key = jnp.where(real, base_a + (coord[:, 2] * cells_a[:, 1] + coord[:, 1])
                    * cells_a[:, 0] + coord[:, 0], table)
    slots = jnp.arange(n, dtype=jnp.int32)
    if jax.dtypes.canonicalize_dtype(jnp.int64) == jnp.int64:
        # Stable: key and atom as one int64, and one array sorts several
        # times faster than a key with its payload.
        packed = jax.lax.sort((key.astype(jnp.int64) << 32) | slots)
        sorted_key = (packed >> 32).astype(jnp.int32)
        order = (packed & 0xFFFFFFFF).astype(jnp.int32)
    else:  # no int64 (x64 off): the same order
        sorted_key, order = jax.lax.sort((key, slots), num_keys=1,
                                         is_stable=True)
    # Each cell's run: its first sorted slot and its length, by two
    # scatters (an empty cell's start is never read).
    first = jnp.full((table,), n, jnp.int32).at[sorted_key].min(
        slots, mode="drop")
    sizes = jnp.zeros((table,), jnp.int32).at[sorted_key].add(1, mode="drop")
    rank = jnp.zeros((n,), jnp.int32).at[order].set(slots)
    return order, rank, jnp.stack([first, sizes], axis=1)


def _runs_of(target, inside, cells_k, base_k, runs):
    """Each target cell's run: first sorted slot and length, int32 (the
    shape of ``inside``; ``target`` and ``cells_k`` a list per axis). One
    gather for both (the key's arithmetic is fused into the gather, and
    would be done once per gathered array)."""
    tkey = jnp.where(inside, base_k + (target[2] * cells_k[1] + target[1])
                     * cells_k[0] + target[0], 0)
    run = runs[tkey]
    return run[..., 0], jnp.where(inside, run[..., 1], 0)


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


def frame(positions, graph, mask, cells, pbc, *, n_graph, completed):
    """Steps 1-2 of the module docstring (step 1 unless ``completed``)."""
    dtype = positions.dtype
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


def bin_atoms(positions, graph, mask, cells, pbc, radius, *, reach, brute,
              n_graph, completed, full, by_slot=False) -> _Binned:
    """Steps 1-4 of the module docstring (step 1 unless ``completed``).
    ``by_slot`` (not with ``brute``): ``start`` and ``length`` are laid out
    ``(K, N)`` and ``image`` ``(3, K, N)``, their atoms (and ``h_atom``'s)
    sorted slots."""
    n = positions.shape[0]
    (error, real, graph, unclipped, h, bad_cell, h_height, count, pbc_a, w,
     fw) = frame(positions, graph, mask, cells, pbc, n_graph=n_graph,
                  completed=completed)
    frame_real = real
    grid_cells, origin, width, base = grid(
        fw, graph, real, pbc, h_height, radius, reach, n_graph, brute, count)
    error = error | short_reach_bit(pbc, grid_cells, h_height, radius,
                                    np.array(reach), count, bad_cell)
    cells_a, base_a = grid_cells[graph], base[graph]
    coord = cell_coords(fw, graph, origin, width, cells_a)
    atom_w = w
    if brute:
        # One cell per system: a system's run is its atoms as given (they
        # are contiguous; padding atoms in it are skipped by the loop), so
        # nothing is sorted.
        order = rank = jnp.arange(n, dtype=jnp.int32)
    else:
        order, rank, runs = sort_cells(coord, cells_a, base_a, real,
                                        n_graph)
        if by_slot:
            # The atom side in sorted order (atoms of a cell side by side
            # read the same runs), written out once (each reader would
            # gather them again).
            coord, cells_a, base_a, pbc_a, real, w = \
                jax.lax.optimization_barrier(tuple(
                    x[order] for x in (coord, cells_a, base_a, pbc_a, real,
                                       w)))
    # The stencil's target cells and their images (docstring, 4.), an
    # array per axis; by slot (K, N) (offset-major: the loop's layout).
    o = offsets(reach, full)
    if by_slot:
        target = [coord[None, :, c] + jnp.asarray(o[:, c, None])
                  for c in range(3)]
        cells_k = [cells_a[None, :, c] for c in range(3)]
        pbc_k = [pbc_a[None, :, c] for c in range(3)]
        real_k, base_k = real[None], base_a[None]
    else:
        target = [coord[:, None, c] + jnp.asarray(o[None, :, c])
                  for c in range(3)]
        cells_k = [cells_a[:, None, c] for c in range(3)]
        pbc_k = [pbc_a[:, None, c] for c in range(3)]
        real_k, base_k = real[:, None], base_a[:, None]
    # floor(target / cells) of small whole numbers, in float32 (exact:
    # |target| < 2^24, and the 1/2 keeps the quotient off the integers);
    # faster than an integer division.
    image = [jnp.where(p, jnp.floor((t.astype(jnp.float32) + 0.5)
                                    / c.astype(jnp.float32)).astype(
                                        jnp.int32), 0)
             for t, c, p in zip(target, cells_k, pbc_k)]
    target = [t - m * c for t, m, c in zip(target, image, cells_k)]
    inside = real_k
    for t, c in zip(target, cells_k):
        inside = inside & (t >= 0) & (t < c)
    if brute:
        system = jnp.clip(unclipped, 0, n_graph)
        sizes = jax.ops.segment_sum(jnp.ones((n,), jnp.int32), system,
                                    n_graph + 1)
        first = exclusive_prefix(sizes)
        start = jnp.broadcast_to(first[system][:, None], inside.shape)
        length = jnp.where(inside, sizes[system][:, None], 0)
    else:
        start, length = _runs_of(target, inside, cells_k, base_k, runs)
    # Shifts of the caller's positions: S = S' + w[i] - w[j].
    wi = w.astype(jnp.int32)
    if by_slot:  # (3, K, N): an array per axis
        image = jnp.stack([m + wi[None, :, c] for c, m in enumerate(image)])
    else:
        image = jnp.stack(image, axis=-1) + wi[:, None, :]
    if n_graph == 1:  # a broadcast (a gather would be written out)
        h_atom = jnp.broadcast_to(h[0], (n, 3, 3))
    else:
        h_atom = h[graph[order] if by_slot else graph]
    if by_slot:  # written out once, for the loop and the rows both
        start, length, image = jax.lax.optimization_barrier((start, length,
                                                             image))
    return _Binned(error, frame_real, graph, h_atom, start, length, image,
                   order, rank, atom_w)


def candidates(positions, binned: _Binned, cut, species, *, reach, chunk,
                stored, brute, full, half):
    """Step 5: the loop over candidates. Returns the pairs found (int32),
    per atom (int32 ``(N,)``) and the pairs stored: from the half stencil
    int32 ``i``, ``j`` ``(stored,)`` and ``S`` ``(stored, 3)`` (``i = j =
    N``, ``S = 0`` where padded), each pair found once; from the ``full``
    stencil int32 ``(stored, 5)`` rows ``(i, j, S)`` padded with ``(N, N,
    0)``, each atom finding all its own pairs (its representatives only,
    with ``half``). With ``b`` by slot (`bin_atoms`), runs of at most a word
    are read by `_half_words`.

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
    by_slot = not (full or brute)  # as `bin_atoms` was told
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
            s.astype(dtype), b.h_atom[b.rank[i] if by_slot else i])
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
        ranks = prefix_sum(keep.reshape(-1))
        if stored > 0:
            rows = jnp.stack([jnp.broadcast_to(atoms * k_offsets + k,
                                               p.shape), p], axis=-1)
            out = out.at[jnp.where(keep.reshape(-1), ranks - 1, stored)].set(
                rows.reshape(-1, 2), mode="drop")
        found = ranks[-1], jnp.sum(keep, axis=(1, 2), dtype=jnp.int32), out
        return _decoded(*found, b) if full else (
            *found[:2], _stored_pairs(out, b))

    if not full:
        def slots():
            by_atom = b if brute else _by_atom(b)
            found, per_atom, kept = _slot_loop(
                decide, by_atom, n=n, k_offsets=k_offsets, stored=stored,
                out=jnp.broadcast_to(pad, (stored, 2)))
            return found, per_atom, _stored_pairs(kept, by_atom)

        if brute:
            return slots()

        def words():
            return _half_words(table, b, cut, species, own, stored=stored)

        return jax.lax.cond(jnp.max(b.length, initial=0) <= WORD, words,
                            slots)

    # Each branch decodes its rows itself: outside, XLA fuses the binning
    # behind the decoding into it and computes it again for every row.
    def stream():
        return _decoded(*_stream(decide, b, out, n=n, k_offsets=k_offsets,
                                 chunk=chunk, stored=stored), b)

    if brute:
        return stream()

    def short():
        return _short_runs(positions, table, b, cut, species, own,
                           half=half, stored=stored)

    # Runs of at most a word (cells of a few atoms each, the common case)
    # are read a word at a time; a fuller cell anywhere falls back to the
    # stream.
    return jax.lax.cond(jnp.max(b.length, initial=0) <= WORD, short, stream)


def _by_atom(b: _Binned) -> _Binned:
    """``b``'s runs by atom (``by_slot`` undone; not ``h_atom``)."""
    return b._replace(start=b.start.T[b.rank], length=b.length.T[b.rank],
                      image=jnp.moveaxis(b.image, 0, -1).transpose(
                          1, 0, 2)[b.rank])


def _slot_loop(decide, b: _Binned, *, n, k_offsets, stored, out):
    """`candidates` from the half stencil, runs of any length: every run
    read a slot at a time (as many steps as the fullest cell holds), the
    kept candidates stored at the running count."""
    atoms = jnp.arange(n, dtype=jnp.int32)[:, None, None]
    k = jnp.arange(k_offsets, dtype=jnp.int32)[None, :, None]

    def slot_step(t, carry):
        total, per_atom, out = carry
        p = jnp.clip(b.start[:, :, None] + t, 0, n - 1)
        keep = ((t < b.length[:, :, None]) & decide(
            atoms, k, p, b.image[:, :, None, :])).reshape(n, k_offsets)
        ranks = row_ranks(keep)
        row_count = ranks[:, -1]
        if stored > 0:
            at = total + exclusive_prefix(row_count)[:, None] + ranks - 1
            rows = jnp.stack([(atoms * k_offsets + k).reshape(n, -1),
                              p.reshape(n, -1)], axis=-1)
            out = out.at[jnp.where(keep, at, stored).reshape(-1)].set(
                rows.reshape(-1, 2), mode="drop")
        return (total + jnp.sum(row_count, dtype=jnp.int32),
                per_atom + row_count, out)

    return jax.lax.fori_loop(
        0, jnp.max(b.length, initial=0), slot_step,
        (jnp.zeros((), jnp.int32), jnp.zeros((n,), jnp.int32), out))


def _slot_decision(t, start, image, columns, r_i, h_i, limit, *, n,
                   dtype):
    """Slot ``t`` of every run (laid out (K, N)): the candidate's sorted
    slot ``p``, lattice shift (three int32), squared length and squared
    cutoff (``limit``: a scalar, or the atom side's ``(N, S)`` limits by
    species, read at the partner's species ``columns[6]``)."""
    p = jnp.minimum(start + t, n - 1)
    s = [image[c] - columns[3 + c][p].astype(jnp.int32) for c in range(3)]
    sf = [x.astype(dtype) for x in s]
    d = [(columns[c][p] - r_i[c]) + (sf[0] * h_i[0][c] + sf[1] * h_i[1][c]
                                     + sf[2] * h_i[2][c])
         for c in range(3)]
    d2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
    if limit.ndim == 2:
        limit = jnp.take_along_axis(
            limit, columns[6][p].astype(jnp.int32).T, axis=1, mode="fill",
            fill_value=-jnp.inf).T
    return p, s, d2, limit


def _half_words(table, b: _Binned, cut, species, own, *, stored):
    """`candidates` from the half stencil when no run is longer than a
    word (``b`` by slot): slot ``t`` of every run in step ``t`` of a loop,
    kept as bit ``t`` of the run's uint32 word, then the kept candidates
    stored in one pass (offset-major): a row's word found by a running
    maximum, its slot by the rank of its bit. Each candidate is decided as
    `candidates`' ``decide`` does, with the squared cutoff
    (`square_limit`)."""
    k_offsets, n = b.length.shape
    dtype = table.dtype
    # Laid out (K, N), the atoms along the fast axis, every column its
    # own array (as in `_short_runs`).
    start, length, image = b.start, b.length, b.image
    columns = [table[:, c] for c in range(table.shape[1])]
    r_i = [x[None, :] for x in columns[:3]]
    h_i = [[b.h_atom[None, :, a, c] for c in range(3)] for a in range(3)]
    slot_i = jnp.arange(n, dtype=jnp.int32)[None, :]
    own_k = own[:, None]
    limit = square_limit(cut)
    if species is not None:
        limit_i = limit[columns[6].astype(jnp.int32)]     # (N, S)

    def slot_bits(t, bits):
        p, _, d2, lim = _slot_decision(
            t, start, image, columns, r_i, h_i,
            limit if species is None else limit_i, n=n, dtype=dtype)
        # Within the own cell, from the atom sorted first.
        keep = (t < length) & (d2 <= lim) & (~own_k | (p > slot_i))
        return bits | jnp.where(keep, jnp.uint32(1) << t.astype(jnp.uint32),
                                jnp.uint32(0))

    def block_bits(u, bits):
        # UNROLL slots a step: one fused pass over the runs reads each
        # run's start and image once for them all.
        for t in range(HALF_UNROLL):
            bits = slot_bits(u * HALF_UNROLL + t, bits)
        return bits

    blocks = -(-jnp.max(b.length, initial=0) // HALF_UNROLL)
    bits = jax.lax.fori_loop(0, blocks, block_bits,
                             jnp.zeros((k_offsets, n), jnp.uint32))
    per_slot = jnp.sum(popcount(bits), axis=0, dtype=jnp.int32)
    bits = bits.reshape(-1)                                      # (K N,)
    counts = popcount(bits)
    ends = prefix_sum(counts, jnp.float64, small=True)
    i = j = jnp.full((stored,), n, jnp.int32)
    s = jnp.zeros((stored, 3), jnp.int32)
    if stored > 0:
        wid, rank, kept = row_words(counts, ends, stored)
        slot = jnp.minimum(b.start.reshape(-1)[wid]
                           + select_bit(bits[wid], rank), n - 1)
        # Written out once: each of the rows' columns below would compute
        # them again.
        wid, slot, kept = jax.lax.optimization_barrier((wid, slot, kept))
        i = jnp.where(kept, b.order[jax.lax.rem(wid, jnp.int32(n))], n)
        j = jnp.where(kept, b.order[slot], n)
        s = jnp.where(kept[:, None], b.image.reshape(3, -1)[:, wid].T - b.w[
            jnp.minimum(j, n - 1)].astype(jnp.int32), 0)
    return ends[-1], per_slot[b.rank], (i, j, s)


def square_limit(cut):
    """The largest ``x`` (``cut``'s dtype and shape) with ``sqrt(x) < cut``,
    ``-inf`` where there is none: for ``x >= 0`` (a squared length),
    ``x <= square_limit(c)`` decides as ``sqrt(x) < c`` does, bit for bit, without a square root per candidate.
    ``sqrt(x) < c`` holds on a down-set of ``x``, whose edge lies within two
    spacings of the rounded ``c * c`` (for every ``c``, subnormal and
    overflowing squares included), so it is among the nine floats around
    it."""
    dtype = cut.dtype
    down = up = cut * cut
    near = [down]
    for _ in range(4):
        down = jnp.nextafter(down, jnp.asarray(-jnp.inf, dtype))
        up = jnp.nextafter(up, jnp.asarray(jnp.inf, dtype))
        near += [down, up]
    near = jnp.stack(near)
    return jnp.max(jnp.where(jnp.sqrt(near) < cut, near, -jnp.inf), axis=0)


def _short_runs(positions, table, b: _Binned, cut, species, own, *, half,
                stored):
    """`candidates` from the full stencil when no run is longer than a
    word: the slots of every run at once, slot ``t`` of each run in step
    ``t`` of a loop (as many steps as the longest run), kept as bit ``t``
    of the run's uint32 word; the rows come out ``i``-major, as the
    stream's, decoded (int32 ``(stored, 5)``). Each candidate is decided as
    `candidates`' ``decide`` does, with the squared cutoff
    (`square_limit`)."""
    n, k_offsets = b.length.shape
    dtype = positions.dtype
    # Laid out (K, N), the atoms along the fast axis, and every column its
    # own array: what the atom's side of a candidate reads is read once
    # per atom, and each step is a run of contiguous lanes.
    start, length = b.start.T, b.length.T
    image = [b.image[:, :, c].T for c in range(3)]
    atoms = jnp.arange(n, dtype=jnp.int32)[None, :]
    r_i = [positions[None, :, c] for c in range(3)]
    h_i = [[b.h_atom[None, :, a, c] for c in range(3)] for a in range(3)]
    rank_i = b.rank[None, :]
    own_k = own[:, None]
    columns = [table[:, c] for c in range(table.shape[1])]
    limit = square_limit(cut)
    if species is not None:
        # (N, S); a species past the matrix has no pairs, as `candidates`'.
        limit_i = limit.at[species].get(mode="fill", fill_value=-jnp.inf)

    def slot_bits(t, bits):
        p, s, d2, lim = _slot_decision(
            t, start, image, columns, r_i, h_i,
            limit if species is None else limit_i, n=n, dtype=dtype)
        once = ~(own_k & (p == rank_i))
        if half:
            j = b.order[p]
            once = once & ((atoms < j) | ((atoms == j) & lex_positive(
                jnp.stack(s, axis=-1))))
        keep = (t < length) & (d2 <= lim) & once
        return bits | jnp.where(keep, jnp.uint32(1) << t.astype(jnp.uint32),
                                jnp.uint32(0))

    no_bits = jnp.zeros((k_offsets, n), jnp.uint32)

    def looped():
        return jax.lax.fori_loop(0, jnp.max(b.length, initial=0), slot_bits,
                                 no_bits)

    def unrolled():
        # Slots past a run's length keep nothing (``t < length``).
        bits = no_bits
        for t in range(WORD):
            bits = slot_bits(jnp.int32(t), bits)
        return bits

    bits = (platforms.cuda_or_default(unrolled, looped)
            if UNROLL_SLOTS_ON_CUDA else looped()).T
    bits = bits.reshape(-1)                                      # (N K,)
    counts = popcount(bits)
    ends = prefix_sum(counts, jnp.float64, small=True)
    per_atom = jnp.sum(counts.reshape(n, k_offsets), axis=1,
                       dtype=jnp.int32)
    rows = jnp.broadcast_to(jnp.array([n, n, 0, 0, 0], jnp.int32),
                            (stored, 5))
    if stored > 0:
        wid, rank, kept = row_words(counts, ends, stored)
        slot = jnp.minimum(b.start.reshape(-1)[wid]
                           + select_bit(bits[wid], rank), n - 1)
        # The rows decoded here, from the arrays the loop read.
        i = jax.lax.div(wid, jnp.int32(k_offsets))
        j = b.order[slot]
        shift = b.image.reshape(-1, 3)[wid] - b.w.astype(jnp.int32)[j]
        rows = jnp.where(kept[:, None], jnp.concatenate(
            [i[:, None], j[:, None], shift], axis=1), rows)
    return ends[-1], per_atom, rows


def _stream(decide, b: _Binned, out, *, n, k_offsets, chunk, stored):
    """`candidates` from the full stencil: the candidates as one
    ``i``-major stream read ``chunk`` at a time (its docstring)."""
    length = b.length.reshape(-1)
    ends = prefix_sum(length, jnp.float64)  # (N K,) inclusive
    total_candidates = ends[-1]
    runs = n * k_offsets
    # The runs that hold candidates, in order (compacted, padded with
    # runs that start past every candidate): a block of ``chunk``
    # candidates meets at most ``chunk`` of them, in one slice.
    nonempty = length > 0
    at = jnp.where(nonempty, prefix_sum(nonempty) - 1,
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
        compact = r0 + prefix_sum(starts)
        run = run_id[compact]
        c_first = run_first[compact]
        i = run // k_offsets
        k = run - i * k_offsets
        p = jnp.clip(runs_start[run] + c - c_first, 0, n - 1)
        keep = valid & decide(i, k, p, image[run])
        ranks = prefix_sum(keep)
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


def _decoded(found, per_atom, out, binned: _Binned):
    """`candidates`' stored candidates ``out`` as int32 ``(stored, 5)``
    rows ``(i, j, S)`` padded with ``(N, N, 0)``."""
    i, j, s = _stored_pairs(out, binned)
    return found, per_atom, jnp.concatenate([i[:, None], j[:, None], s],
                                            axis=1)
