"""The Warp engine's grid: ``grid`` and ``cells`` of
`jaxrt.backends.rt.ffi.cell_lj_sums`, `jaxrt.backends.rt.ffi.cell_sort`,
`jaxrt.backends.rt.ffi.cell_candidate_rows` and the SPH calls, built in JAX
by one function (`build`) for both callers: the cell list's Warp walk
(`jaxrt.backends.cell.search`, ``Cell(kernel="warp")``) and the list-free
sums (`jaxrt.energy.listfree.warp_cell`). No Warp is imported here.

Each axis is one of three kinds, each cell at least its axis' minimum size
wide:

* periodic: the side (static, or traced) divided evenly, ``floor(side /
  min_size)`` cells;
* free: the particles' span from their minimum, ``floor(extent /
  min_size)`` cells of ``extent / cells`` (the kernels clamp the cell of the
  maximum into the last one);
* padding (past the caller's dimension): one cell.

Where the cells outnumber the table, the free axes are coarsened first
(callers with static sides size the table for the periodic axes' cells),
then the periodic ones: in each group evenly, then each axis capped in turn
by what the others leave, which makes the product fit even where an axis is
held at one cell (a flat cloud). Every grid whose cells are at least the
minimum size gives the same pairs; coarser cells only mean more candidates.
"""
from __future__ import annotations

import math

import jax
import jax.numpy as jnp

Array = jax.Array

# Cell counts are int32 and pass through floats (float32 rounds 2**31 - 1
# up, past int32): keep them well inside.
MAX_TABLE = 2 ** 30


def periodic_cells(side, min_size) -> tuple[int, ...]:
    """Static: ``floor(side / min_size)`` per axis (at least 1), counted in
    float64 so that each cell ``side / cells`` is at least ``min_size``.
    ``side``, ``min_size``: sequences of positive floats."""
    out = []
    for s, m in zip(side, min_size):
        s, m = float(s), float(m)
        cells = max(1, math.floor(s / m)) if math.isfinite(s / m) else 1
        if cells > 1 and s / cells < m:  # the quotient rounded up
            cells -= 1
        out.append(cells)
    return tuple(out)


def _check(periodic, padding, min_size, reach, table):
    for name, value in (("periodic", periodic), ("padding", padding),
                        ("min_size", min_size), ("reach", reach)):
        if len(value) != 3:
            raise ValueError(f"warp_grid.build({name}={value!r}): give one "
                             "entry per axis (3).")
    if any(p and q for p, q in zip(periodic, padding)):
        raise ValueError(f"warp_grid.build(periodic={periodic!r}, padding="
                         f"{padding!r}): an axis is one or the other.")
    if not all(math.isfinite(m) and m > 0 for m in map(float, min_size)):
        raise ValueError(f"warp_grid.build(min_size={min_size!r}): cell "
                         "sizes must be positive and finite.")
    if not all(int(r) >= 1 for r in reach):
        raise ValueError(f"warp_grid.build(reach={reach!r}): the stencil "
                         "reaches at least one cell per axis.")
    if not 1 <= int(table) <= MAX_TABLE:
        raise ValueError(f"warp_grid.build(table={table!r}): the table "
                         f"holds 1 to {MAX_TABLE} cells.")


def _room(table: int, others) -> Array:
    """int32 ``max(1, table // prod(others))``, divided one factor at a
    time: the product itself may overflow int32."""
    room = jnp.asarray(table, jnp.int32)
    for c in others:
        room = room // c
    return jnp.maximum(room, 1)


def _coarsen(counts: list, axes: list[int], table: int) -> list:
    """``counts`` (int32 scalars) with those of ``axes`` coarsened so that
    the product fits ``table``: evenly first (the root computed in
    float32; its margin covers the rounding), then each axis capped in
    turn by what the others leave, which alone makes the product fit (the
    capped axis at most ``table // others``, so the axes capped so far
    never exceed the table, and the last one brings the whole under it)."""
    if not axes:
        return counts
    counts = list(counts)
    room = _room(table, [counts[b] for b in range(3) if b not in axes])
    ideal = [counts[a].astype(jnp.float32) for a in axes]
    ratio = math.prod(ideal) / room.astype(jnp.float32)
    # Axes already at one cell (a flat cloud) shrink no further: the root
    # is over the others.
    k = jnp.maximum(sum((c > 1).astype(jnp.float32) for c in ideal), 1.0)
    shrink = jnp.where(ratio > 1, jnp.maximum(
        1.0, ratio ** (1.0 / k) * 1.001), 1.0)
    for a, c in zip(axes, ideal):
        counts[a] = jnp.maximum(1.0, jnp.floor(c / shrink)).astype(jnp.int32)
    for a in axes:
        counts[a] = jnp.minimum(counts[a], _room(
            table, [counts[b] for b in range(3) if b != a]))
    return counts


def build(points: Array, side, *, periodic, padding, min_size, reach,
          table: int) -> tuple[Array, Array]:
    """The Warp engine's grid for ``points``.

    Args:
      points: float ``(N, 3)`` finite positions (``N`` may be 0); free axes
        span them, periodic ones hold them wrapped or not (the kernels
        wrap), padding axes read none.
      side: ``(3,)`` the box side, read on periodic axes: static floats
        (cells counted in float64, as `periodic_cells`, so that they match
        a table sized from them) or a float array, traced or not.
      periodic, padding: static, 3 bools each, never both on one axis;
        the remaining axes are free.
      min_size: static, 3 positive floats: the least cell width per axis.
      reach: static, 3 ints: the stencil's reach in cells per axis.
      table: static int: the most cells in all (the cell-start table's
        size less one).

    Returns:
      ``(grid, cells)``: float ``(3, 3)`` in ``points``' dtype, per axis
      the origin (the minimum on free axes, else 0), cell width (at least
      ``min_size``; a periodic side under it is one cell) and side (1 off
      periodic axes); int32 ``(6,)`` the cells per axis (their product at
      most ``table``), then ``reach``.
    """
    periodic = tuple(bool(p) for p in periodic)
    padding = tuple(bool(p) for p in padding)
    _check(periodic, padding, min_size, reach, table)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"warp_grid.build(points of shape {points.shape}): "
                         "give float (N, 3) positions (pad the missing axes "
                         "with zeros).")
    dtype = points.dtype
    free = tuple(not p and not q for p, q in zip(periodic, padding))
    least = jnp.asarray([float(m) for m in min_size], dtype)
    if points.shape[0]:
        lo, hi = jnp.min(points, axis=0), jnp.max(points, axis=0)
    else:
        lo = hi = jnp.zeros((3,), dtype)
    extent = jnp.where(jnp.asarray(free), hi - lo, 0)
    if isinstance(side, jax.Array):
        side = jnp.where(jnp.asarray(periodic), side.astype(dtype), 1)
        q = side / least
        # NaN or sides below the minimum: one cell (q >= 1 is False).
        counts = jnp.where(q >= 1, jnp.floor(jnp.minimum(q, table)), 1)
        counts = jnp.where((counts > 1) & (side / counts < least),
                           counts - 1, counts)
        counts = [counts[a].astype(jnp.int32) if periodic[a] else
                  jnp.ones((), jnp.int32) for a in range(3)]
    else:
        static = [float(s) if p else 1.0 for s, p in zip(side, periodic)]
        fixed = periodic_cells(static, min_size)
        counts = [jnp.asarray(min(c, table) if p else 1, jnp.int32)
                  for c, p in zip(fixed, periodic)]
        side = jnp.asarray(static, dtype)
    # Free axes: at most what the periodic cells leave of the table.
    room = _room(table, [counts[a] for a in range(3) if periodic[a]])
    q = extent / least
    limit = room.astype(dtype)
    for a in range(3):
        if free[a]:
            counts[a] = jnp.where(q[a] >= 1, jnp.floor(jnp.minimum(
                q[a], limit)), 1).astype(jnp.int32)
    counts = _coarsen(counts, [a for a in range(3) if free[a]], table)
    counts = _coarsen(counts, [a for a in range(3) if periodic[a]], table)
    cells = jnp.stack(counts)
    n = cells.astype(dtype)
    width = jnp.where(jnp.asarray(periodic), side / n,
                      jnp.maximum(extent / n, least))
    origin = jnp.where(jnp.asarray(free), lo, 0).astype(dtype)
    grid = jnp.stack([origin, width.astype(dtype), side.astype(dtype)])
    return grid, jnp.concatenate([cells, jnp.asarray(
        [int(r) for r in reach], jnp.int32)])
