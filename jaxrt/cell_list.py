"""Pure-JAX sorted cell list: the backend ``"cell"``, which runs wherever JAX runs.

Particles are hashed to cells of side >= the search radius, sorted by cell
key (x fastest), and each particle visits the neighbouring cells through
*ranges of the sorted order*: the three cells ``x-1, x, x+1`` of one row are
consecutive keys, so a 3D particle needs 9 contiguous ranges (2D: 3, 1D: 1),
plus up to as many single-cell ranges where a periodic x row wraps around.
Range ends are found by binary search on the sorted keys.

Memory is O(N·k): no buffer is sized by the number of cells (only keys are,
and they are computed, never allocated), and each particle's candidates are
visited in blocks of slots, ``(N, block)`` per step, never
``N × 27 × cell capacity``.
The cell grid is recomputed on every call from the box (periodic axes) or
from the particles' bounding box (free axes), so a changing box or a
wandering cloud never invalidates it; only the bound on one particle's
candidates is static, and exceeding it sets the overflow flag.
"""
from __future__ import annotations

import functools
import itertools

import jax
import jax.numpy as jnp
import numpy as np

from jaxrt import backends
from jaxrt.backends import Capacity, Geometry, MetricSq, Query

# Cells are made this much wider than the search radius so that a particle
# binned one cell off by rounding still has all its neighbours in the stencil.
_CELL_MARGIN = 2.0 ** -10
# Cells are at least cutoff / _REACH wide; the stencil spans _REACH cells
# each way. Finer cells waste fewer candidates (2: 15.6 rc³ of volume per
# particle instead of 27 rc³) at the price of more, shorter ranges.
_REACH = 1
# Candidate slots visited per step: memory (N, _BLOCK) per step.
_BLOCK = 32
# Keys are int32: keep the (virtual) grid below 2**30 cells.
_MAX_CELLS_PER_AXIS = {1: 2 ** 30, 2: 2 ** 15, 3: 2 ** 10}


def _grid(cart: jax.Array, geometry: Geometry, query: Query):
    """Cell coordinates of each particle.

    Args:
      cart: float ``(N, dim)`` Cartesian positions.
    Returns:
      int32 ``(N, dim)`` cell coordinates and int32 ``(dim,)`` cells per axis.
    """
    dim = query.dim
    max_cells = _MAX_CELLS_PER_AXIS[dim]
    min_size = query.cutoff * (1.0 + _CELL_MARGIN) / _REACH
    # NaN positions are reported by the front; keep them from poisoning keys.
    cart = jnp.where(jnp.isfinite(cart), cart, 0.0)
    coords, counts = [], []
    for a in range(dim):
        x = cart[:, a]
        if query.periodic[a]:
            side = geometry.side[a]
            x = jnp.mod(x, side)
            n = jnp.clip(jnp.floor(side / min_size), 1, max_cells)
            size = side / n
            origin = 0.0
        else:
            origin = jnp.min(x)
            extent = jnp.max(x) - origin
            size = jnp.maximum(min_size, extent / (max_cells - 1))
            n = jnp.floor(extent / size) + 1
        n = n.astype(jnp.int32)
        c = jnp.floor((x - origin) / size).astype(jnp.int32)
        coords.append(jnp.clip(c, 0, n - 1))
        counts.append(n)
    return jnp.stack(coords, axis=1), jnp.stack(counts)


def _key(coord, n):
    """Linear cell key, x fastest. coord: int32 ``(..., dim)``; n: ``(dim,)``."""
    key = coord[..., -1]
    for a in range(coord.shape[-1] - 2, -1, -1):
        key = key * n[a] + coord[..., a]
    return key


def _distinct_offset(d: int, n):
    """On a periodic axis of ``n`` cells, is offset ``d`` the first of
    ``-REACH..REACH`` to name its cell? (Small boxes alias offsets.)"""
    ok = jnp.ones((), bool)
    for earlier in range(-_REACH, d):
        ok &= jnp.mod(d - earlier, n) != 0
    return ok


def _ranges(sorted_key, cell, n, query: Query):
    """Ranges of the sorted order that hold each particle's candidate cells.

    Args:
      sorted_key: int32 ``(N,)`` ascending cell keys.
      cell: int32 ``(N, dim)`` cell coordinates of the sorted particles.
      n: int32 ``(dim,)`` cells per axis.
    Returns:
      ``(start, stop)``, each int32 ``(N, R)``: one range per row of cells
      of the stencil, and when x is periodic one more per row for the cells
      that wrap around (empty for most particles).
    """
    dim = query.dim
    starts, stops = [], []
    cx, nx = cell[:, 0], n[0]
    for offset in itertools.product(range(-_REACH, _REACH + 1), repeat=dim - 1):
        other = []
        valid = jnp.ones(cx.shape, bool)
        for a, d in enumerate(offset, start=1):
            c = cell[:, a] + d
            if query.periodic[a]:
                c = jnp.mod(c, n[a])
                valid &= _distinct_offset(d, n[a])
            else:
                valid &= (c >= 0) & (c < n[a])
            other.append(c)

        def cells(lo, hi, valid):
            first = _key(jnp.stack([lo] + other, axis=1), n)
            last = _key(jnp.stack([hi] + other, axis=1), n)
            start = jnp.searchsorted(sorted_key, first, side="left")
            stop = jnp.searchsorted(sorted_key, last, side="right")
            starts.append(jnp.where(valid, start, 0))
            stops.append(jnp.where(valid, stop, 0))

        lo, hi = cx - _REACH, cx + _REACH
        if query.periodic[0]:
            whole_row = nx <= 2 * _REACH + 1
            cells(jnp.where(whole_row, 0, jnp.maximum(lo, 0)),
                  jnp.where(whole_row, nx - 1, jnp.minimum(hi, nx - 1)), valid)
            # The stencil pokes out of one end of the row: its cells wrap to
            # a second contiguous run at the other end.
            below = lo < 0
            wraps = ~whole_row & (below | (hi >= nx))
            cells(jnp.where(below, nx + lo, 0),
                  jnp.where(below, nx - 1, hi - nx), valid & wraps)
        else:
            cells(jnp.maximum(lo, 0), jnp.minimum(hi, nx - 1), valid)
    start = jnp.stack(starts, axis=1).astype(jnp.int32)
    stop = jnp.stack(stops, axis=1).astype(jnp.int32)
    return start, stop


@functools.partial(jax.jit, static_argnames="query")
def _sorted_system(position, geometry: Geometry, query: Query):
    """Sort particles by cell. Returns int32 ``order`` ``(N,)`` (sorted
    position -> caller's index) and the ``(N, R)`` candidate ranges."""
    cart = position * geometry.scale
    cell, n = _grid(cart, geometry, query)
    key = _key(cell, n)
    order = jnp.argsort(key).astype(jnp.int32)
    start, stop = _ranges(key[order], cell[order], n, query)
    return order, start, stop


@functools.partial(jax.jit, static_argnames=("candidates", "row_width", "query"))
def _visit(position, order, start, stop, metric_sq: MetricSq, *, candidates,
           row_width, query: Query):
    """Walk every particle's candidates and collect its neighbours.

    The candidates of particle i are its ranges laid end to end; they are
    visited in blocks of slots, so only their total (not every range) is
    padded to a static width.

    Args:
      position: float ``(N, dim)`` positions in the caller's coordinates.
      order: int32 ``(N,)`` sorted position -> caller's index.
      start, stop: int32 ``(N, R)`` candidate ranges (sorted positions).
      candidates: static bound on a particle's total number of candidates.
      row_width: static width of the output rows.
    Returns:
      rows int32 ``(N, row_width)`` in the caller's order (indices in the
      caller's numbering, padded with N), exact counts int32 ``(N,)``,
      counts of ``j < i`` int32 ``(N,)``, and whether some particle had more
      candidates than ``candidates`` (bool scalar).
    """
    n = position.shape[0]
    sorted_position = position[order]
    cutoff_sq = jnp.asarray(query.cutoff ** 2, position.dtype)
    pair_metric = jax.vmap(jax.vmap(metric_sq, (None, 0)), (0, 0))
    self_index = jnp.arange(n, dtype=jnp.int32)[:, None]
    length = stop - start
    end = jnp.cumsum(length, axis=1, dtype=jnp.int32)
    total = end[:, -1]
    shift = start - (end - length)  # slot -> sorted index, per range
    block = min(_BLOCK, max(candidates, 1))
    n_blocks = -(-candidates // block)

    def visit_block(b, carry):
        rows, count, lower = carry
        slot = b * block + jnp.arange(block, dtype=jnp.int32)[None, :]
        r = jnp.sum(end[:, None, :] <= slot[:, :, None], axis=2,
                    dtype=jnp.int32)
        r = jnp.minimum(r, end.shape[1] - 1)
        j = slot + jnp.take_along_axis(shift, r, axis=1)
        inside = slot < total[:, None]
        j = jnp.clip(j, 0, n - 1)
        d2 = pair_metric(sorted_position, sorted_position[j])
        keep = inside & (d2 < cutoff_sq)
        if query.mask_self:
            keep &= j != self_index
        j_caller = order[j]
        at = count[:, None] + jnp.cumsum(keep, axis=1, dtype=jnp.int32) - 1
        # Flat indices scatter faster than (row, column) pairs on CPU.
        at = jnp.where(keep & (at < row_width), self_index * row_width + at,
                       n * row_width)
        rows = rows.at[at].set(j_caller, mode="drop")
        count = count + jnp.sum(keep, axis=1, dtype=jnp.int32)
        if row_width == 0:  # only measure() reads it (OrderedSparse sizing)
            lower = lower + jnp.sum(keep & (j_caller < order[:, None]),
                                    axis=1, dtype=jnp.int32)
        return rows, count, lower

    rows = jnp.full((n * row_width,), n, jnp.int32)
    zeros = jnp.zeros((n,), jnp.int32)
    rows, count, lower = jax.lax.fori_loop(0, n_blocks, visit_block,
                                           (rows, zeros, zeros))
    rows = rows.reshape(n, row_width)
    # Back to the caller's order.
    rows = jnp.zeros_like(rows).at[order].set(rows)
    count = zeros.at[order].set(count)
    lower = zeros.at[order].set(lower)
    return rows, count, lower, jnp.any(total > candidates)


class CellList:
    """The sorted cell list as a `jaxrt.backends.Backend`.

    Internal capacities: ``"candidates"`` (most candidates of one particle)
    and ``"row"`` (width of the rows built before conversion to a Sparse
    layout).
    """

    name = "cell"

    def measure(self, position, geometry, query, metric_sq):
        order, start, stop = _sorted_system(position, geometry, query)
        candidates = max(int(np.max(np.sum(stop - start, axis=1))), 1)
        _, count, lower, _ = _visit(position, order, start, stop, metric_sq,
                                    candidates=candidates, row_width=0,
                                    query=query)
        count, lower = np.asarray(count), np.asarray(lower)
        ordered = query.format.name == "OrderedSparse"
        return {"row": int(count.max(initial=0)),
                "edges": int(lower.sum() if ordered else count.sum()),
                "candidates": candidates}

    def search(self, position, geometry, query, capacity: Capacity, metric_sq):
        order, start, stop = _sorted_system(position, geometry, query)
        rows, count, _, too_many = _visit(
            position, order, start, stop, metric_sq,
            candidates=capacity["candidates"], row_width=capacity["row"],
            query=query)
        result = backends.format_dense_rows(rows, count, query, capacity)
        return result._replace(overflow=result.overflow | too_many)


backends.register("cell", CellList)
