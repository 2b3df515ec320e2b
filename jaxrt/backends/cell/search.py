"""Pure-JAX sorted cell list: the backend ``"cell"``, which runs wherever JAX runs.

Four passes, each a few large array programs, none of them a scatter over
candidates (XLA's CPU scatter costs ~14 ns per element, more than all else
a candidate needs):

1. **Sort.** Particles are hashed to cells ``cutoff / 4`` wide along x and
   ``cutoff`` wide across, and sorted by cell key, x fastest.
2. **Runs.** The cells ``x-4 .. x+4`` of one stencil row ``(dy, dz)`` are
   consecutive keys, so each row is one run of the sorted order (two where a
   periodic x row wraps around): 9 runs in 3D, 3 in 2D, 1 in 1D. Their ends
   come from a table of cell starts (cells are coarsened where there would
   be more than 4 per particle, so the table is O(N)).
   Finer x cells make a row ``2.25 cutoff`` long instead of ``3 cutoff``;
   finer cells across would add rows.
3. **Windows.** Each run is read as a window of ``W`` slots (``W`` static:
   the longest run). Every slot gets a cheap distance test in the cell
   list's own arithmetic (Cartesian, minimum image by rounding), which
   sorts it into *sure* (below ``cutoff - tol``), *shell* (within ``tol``
   of the cutoff) or out, as bits packed into uint32 words.
4. **Decide and pack.** The caller's metric decides the shell pairs (a few
   per hundred particles), which join the sure bits; then each particle's
   set bits are left-packed into its row with gathers (`_select`).

For OrderedSparse both passes keep only the candidates ``j < i`` (caller's
indices): its edges come out as half rows, left-packed, which become edges
with no rank along full rows (`_lower_only`).

On CUDA, passes 3 and 4 are one kernel instead (`jaxrt.backends.cell.kernel`,
Pallas lowered to Triton, chosen where the program is lowered): each thread
walks its particle's runs to their real ends with the same cheap test and
appends sure pairs to the row and shell pairs to a small buffer, whose
pairs the caller's metric then decides and appends. Same sets, and no
window: XLA's GPU code for the windows was at its floor (the window is the
longest run, so two thirds of the slots lie past a run's end).

So every pair is decided as ``metric_sq(Ri, Rj) < cutoff**2`` with the
caller's metric, bit for bit as jax-md decides, provided that metric is the
Euclidean minimum-image distance up to ``tol`` (``2**-18`` of the cutoff
plus 16 ulps of the largest coordinate, wrapped or not: the metric rounds
the unwrapped difference), which the cell grid assumes anyway.
The caller's metric is not used on every slot because jax-md's periodic
wrap (a float ``mod``) is a scalar libm call on CPU: many times the cheap test.
Where the metric is not that distance (a triclinic box, binned in its
fractional coordinates scaled by its heights; a metric that is not a
quadratic form), ``Query.decide_by_metric`` makes the metric the test on
every slot instead, on the portable path: slower, and exact as long as
the metric is never shorter than the grid's distance, which the front
checks (`jaxrt.lists.metric`).

Small boxes (a cutoff of half a periodic height or more) need nothing of
their own. Cells are at least ``cutoff / reach`` wide, so a partner whose
image under the caller's wrap (each axis's difference into half a period
either way) is within the cutoff lies within ``reach`` cells of the
particle, counted around the periodic axis; an axis with fewer cells than
the stencil spans has each cell once in it (`_runs` drops an offset that
names a cell an earlier one named, and a periodic x row of at most ``2
reach + 1`` cells is one whole run; the kernel's run reader does the same),
so every candidate is met once. A small axis has one cell across (and at
most 7 along x: one whole run), so there every particle is a candidate,
whatever image the caller's metric picks. The cheap test rounds each axis's
difference to its nearest image, which in an orthorhombic box has the
length of the caller's image (ties at half a side are the same length); in
a triclinic box the metric decides every candidate anyway. So the list is
every pair the caller's metric puts within the cutoff, once: jax-md's list
for such a box.

Memory is O(N·k): the sorted keys, a cell-start table of at most 4 N, and
``(N, 9 · W / 32)`` words; no buffer is sized by the volume, and there is no
``N × 27 × cell capacity`` candidate array. The grid is recomputed on every
call from the box (periodic axes) or the particles' bounding box (free
axes; and periodic ones across which a sparse cloud leaves an empty slab,
`_grid`), so a changing box or a wandering cloud never invalidates it; ``W``
and the two shell buffers are the only static sizes, and exceeding any
sets the overflow flag.
"""
from __future__ import annotations

import dataclasses
import functools
import itertools
import math
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from jaxrt import platforms
from jaxrt.backends import contract as _backend
from jaxrt.backends.cell import kernel as _cell_kernel
from jaxrt.backends.cell import radius_classes, warp_grid
from jaxrt.backends.contract import Capacity, Geometry, MetricSq, Query
from jaxrt.errors import ListTooLargeError

# Cells are made this much wider than their minimum so that a particle
# binned one cell off by rounding still has all its neighbours in the stencil.
_CELL_MARGIN = 2.0 ** -10
# Stencil reach in cells: (along x, across). Cells are cutoff / reach wide.
_REACH = (4, 1)
# The cheap test's margin over the cutoff: relative, plus ulps of the
# largest coordinate. The two metrics differ by a few ulps of the box side
# (each rounds a difference, a wrap and a square); this is 4x that.
_TOL_RELATIVE = 2.0 ** -18
_TOL_ULPS = 16
# The shell buffer (pairs within tol of the cutoff, which the caller's
# metric decides: ~0.04 per particle in a float32 liquid) is twice the
# largest shell seen at allocate, and at least this: its fullest particle
# is a rare event, which must not overflow the list during a run.
_MIN_SHELL = 4
# Prefix sums over at most this many words per particle are a matrix product.
_MATMUL_PREFIX = 64
# Particles whose shell pairs are decided: twice as many as had one at
# allocate (or would have in a liquid, `Cell.measure`), and at least
# this many (capped at N).
_MIN_SHELL_ROWS = 64


def _shell_rows(measured: int, n: int) -> int:
    return min(max(2 * measured, _MIN_SHELL_ROWS), n)


# Cells are coarsened where the grid would have more than this many cells
# per particle: the table of cell starts is O(N).
_CELLS_PER_PARTICLE = 4


def _grid(cart: jax.Array, geometry: Geometry, query: Query,
          reach: tuple[int, int] = _REACH, coarsen: bool = True):
    """Cell coordinates of each particle.

    Cells are as small as the stencil allows, unless that makes more than
    ``_CELLS_PER_PARTICLE · N`` cells (sparse clouds, huge boxes): then all
    are coarsened together until the cell-start table fits.

    A free axis is gridded over the particles' span, a periodic one over
    the box side, except where the grid would coarsen and the particles
    leave an empty slab across a periodic axis (`_gaps`): that axis is
    *compacted*, gridded as a free axis over the occupied stretch, which
    a small cloud in a huge box needs to keep its cells small.

    A compacted axis: positions are shifted so that the slab straddles the
    box's faces, ``x' = x - cut`` wrapped into ``[0, side)`` (``cut`` in
    the slab's middle); cells of the free-axis size span ``[min x', max
    x']``, followed by ``2 reach + 1`` empty cells (``reach`` of that
    axis). No pair within the cutoff crosses the slab, so every such pair's
    minimum image along the axis is its plain difference in ``x'``, which
    the cells and stencil find as on a free axis. `_runs` and every copy of
    it (`_run_images`, `jaxrt.backends.cell.kernel._run_reader`,
    `jaxrt.backends.cell.radius_classes._stencil`) still wrap the axis as periodic, but
    a stencil of reach ``r`` from an occupied cell wraps only into the last
    ``r`` cells, which are empty: its wrapped runs are empty, and every
    nonempty run has image 0 along the axis (the plain difference), which
    is what the positions ``x'`` need. With those ``2 reach + 1`` empty
    cells the axis has at least ``2 reach + 2`` cells, so no stencil cell
    repeats (`_runs` drops no offset) and a periodic x row is never one
    whole run: the static rules of `_image_axes` hold on it too. An axis
    is compacted only where that gives it no more cells than the box would
    at the box-wide grid's coarsening: then the compacted grid fits the
    table at that coarsening, is coarsened no more than the box-wide grid,
    and the other periodic axes keep at least the cells `_image_axes`
    counted. The search runs only where the box-wide grid would coarsen
    (one scalar test otherwise, and the grid is bitwise the same).

    Args:
      cart: float ``(N, dim)`` Cartesian positions.
      reach: stencil reach in cells (along x, across): cells are
        ``query.cutoff / reach`` wide, or wider.
      coarsen: static; False skips the coarsening loop (a device loop whose
        every test is a host round trip on a GPU) and the search for empty
        slabs, for callers that proved with `_static_cells` that it would
        not coarsen.
    Returns:
      float ``(N, dim)`` positions wrapped into ``[0, side)`` on periodic
      axes (shifted on compacted axes); int32 ``(N, dim)`` cell
      coordinates; int32 ``(dim,)`` cells per axis.
    """
    dim = query.dim
    budget = _table_size(cart.shape[0]) - 1
    # NaN positions are reported by the front; keep them from poisoning keys.
    cart = jnp.where(jnp.isfinite(cart), cart, 0.0)
    periodic = np.array(query.periodic)
    side = geometry.side

    def wrap():  # free axes stay as they are (no wrap arithmetic)
        return jnp.stack([jnp.mod(cart[:, a], side[a].astype(cart.dtype))
                          if query.periodic[a] else cart[:, a]
                          for a in range(dim)], axis=1)

    origin = jnp.where(periodic, 0.0, jnp.min(cart, axis=0))
    extent = jnp.where(periodic, side, jnp.max(cart, axis=0) - origin)
    min_size = query.cutoff * (1.0 + _CELL_MARGIN) / np.array(
        [reach[a > 0] for a in range(dim)])
    padding = np.array([2 * reach[a > 0] + 1 for a in range(dim)])
    kept = np.zeros(dim, bool)

    def cells(coarsen, compact, extent):  # float (dim,): cells per axis
        size = min_size * coarsen
        return jnp.where(periodic & ~compact,
                         jnp.maximum(jnp.floor(extent / size), 1),
                         jnp.floor(extent / size) + 1
                         + jnp.where(compact, padding, 0))

    def binned(wrapped, compact, origin, extent, coarsen):
        n = cells(coarsen, compact, extent)
        size = jnp.where(periodic & ~compact, extent / n, min_size * coarsen)
        occupied = (n - jnp.where(compact, padding, 0)).astype(jnp.int32)
        coord = jnp.floor((wrapped - origin) / size).astype(jnp.int32)
        return wrapped, jnp.clip(coord, 0, occupied - 1), n.astype(jnp.int32)

    if not coarsen:  # the caller proved that it would not (`_static_cells`)
        return binned(wrap(), kept, origin, extent,
                      jnp.ones((), extent.dtype))
    coarsen = jax.lax.while_loop(
        lambda c: jnp.prod(cells(c, kept, extent)) > budget,
        lambda c: c * 1.25, jnp.ones((), extent.dtype))
    if not any(query.periodic):
        return binned(wrap(), kept, origin, extent, coarsen)

    def compacted():
        wrapped = wrap()
        compact, cut, low, span, factor = _compacted(
            wrapped, side, origin, extent, coarsen, query, budget, cells)
        wrapped = jnp.where(compact, _shifted(wrapped, cut, side), wrapped)
        return binned(wrapped, compact, low, span, factor)

    # The common case (a box the particles fill) never coarsens: one scalar
    # test, then the grid as it was, bitwise.
    return jax.lax.cond(
        coarsen > 1, compacted,
        lambda: binned(wrap(), kept, origin, extent, coarsen))


# Bins per periodic axis of the occupancy histogram that finds empty slabs
# (`_gaps`): a slab must span the cutoff plus one bin to be taken.
_GAP_BINS = 4096
# A slab must be this much (relatively) wider than the cutoff: far more than
# the cheap distance's tolerance and the cells' margin.
_GAP_MARGIN = 2.0 ** -4


def _gaps(wrapped, side, query: Query):
    """The widest empty slab across each periodic axis, from a histogram of
    `_GAP_BINS` bins per axis, read circularly.

    Bins are half-open and a position may round into a neighbouring bin,
    so a run of ``L`` empty bins is only trusted to be ``L - 1`` bins wide:
    a slab is taken where that is at least ``cutoff (1 + _GAP_MARGIN)``.
    Then no two particles on either side of it are within the cutoff along
    the axis, the other way round the box included.

    Args:
      wrapped: float ``(N, dim)`` positions in ``[0, side]`` on periodic
        axes.
      side: float ``(dim,)`` box sides.
    Returns:
      bool ``(dim,)``: a periodic axis with an empty slab wide enough;
      float ``(dim,)`` (``wrapped``'s dtype) the middle of its widest run
      of empty bins, in ``[0, side)`` (0 on free axes).
    """
    dim = wrapped.shape[1]
    axes = np.flatnonzero(query.periodic)
    bins = _GAP_BINS
    dtype = wrapped.dtype
    width = side.astype(dtype)[axes] / bins
    b = jnp.clip(jnp.floor(wrapped[:, axes] / width).astype(jnp.int32), 0,
                 bins - 1)
    b = b + bins * jnp.arange(len(axes), dtype=jnp.int32)
    occupied = jnp.zeros((len(axes) * bins,), bool).at[b.reshape(-1)].set(
        True).reshape(len(axes), bins)
    # Twice round the box: a run through the box's faces is one run.
    twice = jnp.concatenate([occupied, occupied], axis=1)
    index = jnp.arange(2 * bins, dtype=jnp.int32)
    last = jax.lax.cummax(jnp.where(twice, index, -1), axis=1)
    empty = index - last  # empty bins ending at each index, inclusive
    end = jnp.argmax(empty, axis=1).astype(jnp.int32)
    length = jnp.minimum(jnp.max(empty, axis=1), bins).astype(dtype)
    found = (length - 1) * width >= query.cutoff * (1.0 + _GAP_MARGIN)
    middle = ((end + 1).astype(dtype) - length / 2) * width
    middle = jnp.mod(middle, side.astype(dtype)[axes])
    return (jnp.zeros((dim,), bool).at[axes].set(found),
            jnp.zeros((dim,), dtype).at[axes].set(middle))


def _shifted(wrapped, cut, side):
    """``wrapped - cut`` wrapped into ``[0, side)``, per axis: the empty
    slab around ``cut`` moved to the box's faces. (Float ``(N, dim)``;
    one select, no float ``mod``, which is a libm call per element on
    CPUs.)"""
    side = side.astype(wrapped.dtype)
    return wrapped - cut + jnp.where(wrapped < cut, side, 0)


def _compacted(wrapped, side, origin, extent, coarsen, query: Query,
               budget, cells):
    """`_grid`'s compacted axes, for a grid that the box-wide cells would
    coarsen by ``coarsen``.

    Args:
      cells: `_grid`'s ``cells(coarsen, compact, extent)``.
    Returns:
      ``(compact, cut, origin, extent, coarsen)``: bool ``(dim,)`` the
      compacted axes; float ``(dim,)`` (``wrapped``'s dtype) the middles of
      their empty slabs (`_shifted`), 0 elsewhere; and the grid's origin,
      extent and coarsening factor with them, as given where no axis is
      compacted.
    """
    found, cut = _gaps(wrapped, side, query)
    shifted = jnp.where(found, _shifted(wrapped, cut, side), wrapped)
    low = jnp.min(shifted, axis=0)
    span = jnp.where(found, jnp.max(shifted, axis=0) - low, extent)
    # An axis is compacted where, at the box-wide grid's factor, that gives
    # it no more cells than the box does (a slab of a few cutoffs gains
    # less than the empty cells cost). Then at that factor the compacted
    # grid fits the table too, so the loop below stops at or before it.
    compact = found & (cells(coarsen, found, span)
                       <= cells(coarsen, np.zeros(len(query.periodic), bool),
                                extent))
    span = jnp.where(compact, span, extent)
    # The box-wide loop's factors (powers of 1.25, compared exactly).
    factor = jax.lax.while_loop(
        lambda c: (jnp.any(compact) & (c < coarsen)
                   & (jnp.prod(cells(c, compact, span)) > budget)),
        lambda c: c * 1.25, jnp.ones((), coarsen.dtype))
    return (compact, jnp.where(compact, cut, 0).astype(cut.dtype),
            jnp.where(compact, low, origin), span,
            jnp.where(jnp.any(compact), factor, coarsen))


def _key(coord, n):
    """Linear cell key, x fastest. coord: int32 ``(..., dim)``; n: ``(dim,)``."""
    key = coord[..., -1]
    for a in range(coord.shape[-1] - 2, -1, -1):
        key = key * n[a] + coord[..., a]
    return key


def _stencil_rows(dim: int, across: int) -> np.ndarray:
    """int32 ``(R, dim - 1)``: the offsets across (axes 1..) of the stencil
    rows, in the order of `_runs`' columns. As arrays: one op per step, not
    per row (compile time)."""
    offsets = np.array(list(itertools.product(range(-across, across + 1),
                                              repeat=dim - 1)), np.int32)
    return offsets.reshape(len(offsets), dim - 1)


def _runs(sorted_key, cell, n, query: Query,
          reach: tuple[int, int] = _REACH, table: int | None = None,
          cell_starts=None):
    """Runs of the sorted order that hold each particle's candidate cells.

    Args:
      sorted_key: int32 ``(N,)`` ascending cell keys.
      cell: int32 ``(N, dim)`` cell coordinates of the particles.
      n: int32 ``(dim,)`` cells per axis.
      cell_starts: `_cell_starts` of ``sorted_key`` and ``table`` where the
        caller has it.
    Returns:
      ``(start1, len1, start2, len2)``, each int32 ``(N, R)``, one column per
      stencil row: the run of its cells and, when x is periodic, the run of
      the cells that wrap around (empty for most particles).
    """
    dim = query.dim
    rx, across = reach
    assert rx == _REACH[0], "_cell_starts pads for _REACH[0] cells along x"
    offsets = _stencil_rows(dim, across)
    valid = jnp.ones((cell.shape[0], len(offsets)), bool)
    other = []
    for a in range(1, dim):
        d = offsets[:, a - 1]
        c = cell[:, a:a + 1] + d
        if query.periodic[a]:
            # |d| <= across < n or aliased away: one wrap (an integer mod
            # per candidate cell costs far more).
            c = jnp.where(c < 0, c + n[a], jnp.where(c >= n[a], c - n[a], c))
            # Small boxes alias offsets: keep the first to name each cell.
            gap = np.arange(1, 2 * across + 1)  # d - e for earlier e
            aliased = jnp.mod(gap, n[a]) == 0
            first = jnp.stack([~jnp.any(aliased[:x + across])
                               for x in range(-across, across + 1)])
            valid &= first[d + across][None, :]
        else:
            valid &= (c >= 0) & (c < n[a])
        other.append(c)
    base = jnp.zeros_like(valid, dtype=jnp.int32)
    stride = n[0]
    for a, c in enumerate(other, start=1):
        base = base + c * stride
        stride = stride * n[a]
    cx, nx = cell[:, :1], n[0]
    lo, hi = cx - rx, cx + rx
    if query.periodic[0]:
        whole_row = nx <= 2 * rx + 1
        lo1 = jnp.where(whole_row, 0, jnp.maximum(lo, 0))
        hi1 = jnp.where(whole_row, nx - 1, jnp.minimum(hi, nx - 1))
        # The stencil pokes out of one end of the row: its cells wrap to a
        # second contiguous run at the other end.
        below = lo < 0
        wraps = ~whole_row & (below | (hi >= nx))
        lo2 = jnp.where(below, nx + lo, 0)
        hi2 = jnp.where(below, nx - 1, hi - nx)
    else:
        lo1, hi1 = jnp.maximum(lo, 0), jnp.minimum(hi, nx - 1)
        lo2 = hi2 = wraps = jnp.zeros_like(lo)
    start = (_cell_starts(sorted_key, table) if cell_starts is None
             else cell_starts)
    start1, end1 = _run_ends(start, base + lo1, hi1 - lo1)
    start2, end2 = _run_ends(start, base + lo2, hi2 - lo2)
    len1 = jnp.where(valid, end1 - start1, 0)
    len2 = jnp.where(valid & wraps, end2 - start2, 0)
    return start1, len1, start2, len2


def _run_images(cell, n, query: Query, reach: tuple[int, int] = _REACH):
    """The periodic image that each run of `_runs` names, per axis.

    A stencil row's cell across, ``cell[:, a] + d``, is wrapped into
    ``[0, n)`` by `_runs`: from below, its particles stand for their image
    at ``x_a - side_a`` (``s = -1``); from above, at ``x_a + side_a``
    (``s = +1``); else as they are (``s = 0``). Along x a row's first part
    (cells clipped to the row) is as it is, and its wrapped part at
    ``-side_x`` where the stencil poked out below the row, else at
    ``+side_x``. Free axes are ``s = 0``.

    They are the minimum images of all pairs within the cutoff, for the
    positions `_grid` binned (so a walk may add them once per run instead
    of rounding every candidate's difference), where every stencil cell
    is a distinct cell: a partner within the cutoff has its nearest image
    in the unwrapped cell at most ``across`` (``reach``) away, and the one
    stencil offset that names its cell names that image. Not on an axis
    that aliases (``n <= 2 across``, where `_runs` drops repeated offsets)
    nor along a periodic x with ``n <= 2 reach + 1`` (the whole row is
    one run): `_image_axes` says statically where they are exact. Beyond
    the cutoff a run's image is never closer than the nearest. On an axis
    `_grid` compacted, every nonempty run is ``s = 0`` (its wrapped cells
    are the empty ones past the span), the plain difference of the
    shifted positions, which is every pair's minimum image there.

    Args:
      cell: int32 ``(N, dim)`` cell coordinates (the order of `_runs`').
      n: int32 ``(dim,)`` cells per axis.
    Returns:
      ``(first, wrapped)``, int32 ``(N, R)``, `_runs`' columns: image codes
      of each row's first and wrapped parts, ``s_a + 1`` in bits
      ``2 a`` and up (`_cell_kernel.IMAGE_BITS` per axis; decode:
      ``(code >> 2 a & 3) - 1``).
    """
    dim = query.dim
    rx, across = reach
    offsets = _stencil_rows(dim, across)
    code = jnp.ones((cell.shape[0], len(offsets)), jnp.int32)  # x: s = 0
    for a in range(1, dim):
        s = jnp.zeros_like(code)
        if query.periodic[a]:
            c = cell[:, a:a + 1] + offsets[:, a - 1]
            s = (c >= n[a]).astype(jnp.int32) - (c < 0).astype(jnp.int32)
        code = code + ((s + 1) << (_cell_kernel.IMAGE_BITS * a))
    wrapped = code
    if query.periodic[0]:
        below = cell[:, :1] - rx < 0
        wrapped = code + jnp.where(below, -1, 1)  # s_x = -1 or +1
    return code, wrapped


def _box_cells(n_particles: int, side, query: Query, reach, flat, slack):
    """``(cells, coarsen)``: `_grid`'s static cells per axis where the box
    sets them, counted in float64 with a relative ``slack`` on every count
    (``+`` bounds the traced float32 counts from above, ``-`` from below),
    after replaying its coarsening loop (``coarsen``: its factor, 1.0 if it
    did not run); None where a free axis is not ``flat`` (its spread
    coarsens the grid without bound)."""
    dim = query.dim
    flat = tuple(flat) or (False,) * dim
    periodic = query.periodic
    if not all(p or f for p, f in zip(periodic, flat)):
        return None
    budget = _table_size(n_particles) - 1
    min_size = [query.cutoff * (1.0 + _CELL_MARGIN) / reach[a > 0]
                for a in range(dim)]

    def cells(coarsen, slack):
        return [max(math.floor(side[a] / (min_size[a] * coarsen)
                               * (1 + slack)), 1) if periodic[a] else 1
                for a in range(dim)]

    # The traced loop stops no later than this one: its counts are at most
    # these, and its product is compared with the budget to float rounding.
    coarsen = 1.0
    while (math.prod(cells(coarsen, _STATIC_SLACK))
           > budget * (1 - _STATIC_SLACK)):
        coarsen *= 1.25
    return cells(coarsen, slack), coarsen


# Relative slack on the static cell counts: covers the rounding of the
# traced float32 grid.
_STATIC_SLACK = 2.0 ** -12


def _image_axes(n_particles: int, side, query: Query,
                reach: tuple[int, int] = _REACH,
                flat: tuple[bool, ...] = ()) -> tuple[bool, ...]:
    """Static: the periodic axes on which `_run_images` is every pair's
    minimum image, whatever the positions.

    `_grid`'s cells per axis are static where every axis is periodic (the
    box sets them) or ``flat`` (all positions equal there: one cell)
    (`_box_cells`). An axis is accepted where its fewest possible cells
    exceed ``2 across`` (``2 reach + 1`` along x).

    Axes that `_grid` compacts (a cloud leaving an empty slab, where the
    box-wide grid would coarsen) have cells set by the cloud, not the box,
    but at least ``2 reach + 2`` of them, and every nonempty run's image is
    0 on them (`_grid`, `_run_images`): still exact. The other axes keep
    the box's cells, coarsened no more than the box-wide grid (`_grid`
    compacts only where that holds), so no fewer than counted here.

    Args:
      n_particles: N (the cell-start table's budget).
      side: ``dim`` Python floats, the box (periodic axes).
      flat: ``dim`` bools (or empty: none), free axes whose positions the
        caller keeps all equal (zero padding).
    Returns:
      ``dim`` bools.
    """
    counted = _box_cells(n_particles, side, query, reach, flat, -_STATIC_SLACK)
    if counted is None:
        return (False,) * query.dim
    fewest = counted[0]
    need = [2 * reach[0] + 2] + [2 * reach[1] + 1] * (query.dim - 1)
    return tuple(bool(query.periodic[a] and fewest[a] >= need[a])
                 for a in range(query.dim))


def _static_cells(n_particles: int, side, query: Query,
                  reach: tuple[int, int] = _REACH,
                  flat: tuple[bool, ...] = ()) -> int | None:
    """Static: a bound on `_grid`'s number of cells when it provably does
    not coarsen, else None.

    The most cells `_box_cells` allows: if the coarsening loop replayed
    there does not run, the traced one cannot either, the grid has at most
    that many cells, and every key is below the bound. (Such a grid never
    searches for empty slabs to compact: `_grid`'s ``coarsen=False``.)

    Returns:
      int, more than every cell key (the `_cell_starts` table), or None
      (a free axis, or a grid that may coarsen: keep the loop and the
      default table).
    """
    counted = _box_cells(n_particles, side, query, reach, flat, _STATIC_SLACK)
    if counted is None or counted[1] != 1.0:
        return None
    return math.prod(counted[0]) + 1


def _table_size(n: int) -> int:
    return _CELLS_PER_PARTICLE * n + 64


# A stencil row spans at most this many cells along x (and its wrapped
# part fewer), plus one for the end of the run.
_RUN_SPAN = 2 * _REACH[0] + 2


def _cell_starts(sorted_key, table: int | None = None):
    """int32 ``(table + 1 + _RUN_SPAN,)``: how many sorted keys are below
    each cell key (a scatter-add of N and a cumsum), padded at the end so
    that a run's slice never leaves the table. ``table``: static, more
    than the largest key (default `_table_size`, the coarsening budget's
    bound); a smaller proven bound (`_static_cells`) makes the cumsum
    shorter."""
    size = table or _table_size(sorted_key.shape[0])
    count = jnp.zeros((size,), jnp.int32).at[sorted_key].add(1, mode="drop")
    total = jnp.full((_RUN_SPAN,), sorted_key.shape[0], jnp.int32)
    return jnp.concatenate([jnp.zeros((1,), jnp.int32),
                            jnp.cumsum(count, dtype=jnp.int32), total])


def _run_ends(start, first, extra):
    """Sorted positions where the run of cells ``first .. first + extra``
    begins and ends (int32, any shape; ``extra < _RUN_SPAN``, negative for
    an empty run): two gathers from the table. (One slice of the table per
    run, its end picked by a mask, was slower on both the CPU and the GPU:
    benchmarks/grid_stages.py.)"""
    size = start.shape[0] - _RUN_SPAN
    first = jnp.clip(first, 0, size)
    return start[first], start[first + jnp.clip(extra + 1, 0, _RUN_SPAN - 1)]


@functools.partial(jax.jit, static_argnames=("query", "coarsen"))
def _sorted_system(position, geometry: Geometry, query: Query,
                   coarsen: bool = True):
    """Sort particles by cell.

    Args:
      position: float ``(N, dim)`` in the caller's coordinates.
      coarsen: static, `_grid`'s (False where `_fixed_grid` proved that
        the grid never coarsens).
    Returns:
      int32 ``order`` ``(N,)`` (sorted position -> caller's index); float
      ``(N, dim)`` Cartesian positions wrapped into the box, in the caller's
      order; and each particle's runs ``(start1, len1, start2, len2)``
      (`_runs`), int32 ``(N, R)`` in the caller's order.
    """
    order, cart, sorted_key, cell, n = _sorted_grid(position, geometry, query,
                                                    coarsen)
    return order, cart, _runs(sorted_key, cell, n, query)


def _fixed_grid(n: int, geometry: Geometry, query: Query) -> bool:
    """Eager: whether `_grid` provably never coarsens this list's grid
    (`_static_cells`: every axis periodic, the box fixed for the list's
    life, `Query.fixed_box`). Its programs then skip the coarsening loop
    and the search for empty slabs, most of the grid's compile time."""
    if not (query.fixed_box and all(query.periodic)):
        return False
    side = [float(x) for x in np.asarray(geometry.side)]
    return _static_cells(n, side, query) is not None


def _sorted_grid(position, geometry: Geometry, query: Query,
                 coarsen: bool = True):
    """`_grid`'s cells and the order that sorts them: int32 ``order``
    ``(N,)``, float ``(N, dim)`` wrapped Cartesian positions, int32 ``(N,)``
    sorted keys, int32 ``(N, dim)`` cell coordinates (the caller's order),
    int32 ``(dim,)`` cells per axis."""
    cart, cell, n = _grid(geometry.grid_coordinates(position), geometry,
                          query, coarsen=coarsen)
    key = _key(cell, n)
    # Ties in any order: rows are sets.
    sorted_key, order = jax.lax.sort(
        (key, jnp.arange(key.shape[0], dtype=jnp.int32)), num_keys=1,
        is_stable=False)
    return order, cart, sorted_key, cell, n


def _even_bits(x):
    """The 16 even bits of each uint32, compacted into its low half."""
    x = x & jnp.uint32(0x55555555)
    x = (x | (x >> 1)) & jnp.uint32(0x33333333)
    x = (x | (x >> 2)) & jnp.uint32(0x0F0F0F0F)
    x = (x | (x >> 4)) & jnp.uint32(0x00FF00FF)
    return (x | (x >> 8)) & jnp.uint32(0x0000FFFF)


def _words(halves):
    """uint32 ``(N, 2M)`` of 16-bit halves -> ``(N, M)`` 32-bit words."""
    return halves[:, 0::2] | (halves[:, 1::2] << 16)


# _BIT_IN_BYTE[8 b + r]: position of the r-th set bit of byte b.
_BIT_IN_BYTE = np.zeros((256, 8), np.int32)
for _byte in range(256):
    _bits = [b for b in range(8) if _byte >> b & 1]
    _BIT_IN_BYTE[_byte, :len(_bits)] = _bits
_BIT_IN_BYTE = _BIT_IN_BYTE.reshape(-1)


def _popcount(x):
    return jax.lax.population_count(x).astype(jnp.int32)


def _select(words, width: int, payload, group: int):
    """Left-pack set bits: where each particle's ``t``-th set bit is.

    Args:
      words: uint32 ``(N, M)``; bit ``b`` of word ``m`` is slot ``32 m + b``.
      width: static number of output columns.
      payload: int32 ``(N, M, P)``, per word, gathered along with it.
      group: static, divides ``M``: words are searched a group at a time.
    Returns:
      int32 ``(N, width)`` bit ``b`` and int32 ``(N, width, P)`` the payload
      of its word (both meaningless where invalid), bool ``(N, width)``
      valid (``t < count``), int32 ``(N,)`` counts.
    """
    n, m = words.shape
    popcount = _popcount(words)
    inclusive = _prefix(popcount)
    count = inclusive[:, -1]
    t = jnp.arange(width, dtype=jnp.int32)[None, :]
    # The word holding bit t is the number of inclusive prefixes <= t: found
    # by compare-and-count over the groups' last prefixes, then within the
    # group (fused compares beat a binary search of gathers).
    groups = m // group
    k = jnp.zeros((n, width), jnp.int32)
    for c in range(group - 1, m - 1, group):
        k = k + (inclusive[:, c:c + 1] <= t)
    block = inclusive.reshape(n * groups, group)[
        jnp.arange(n, dtype=jnp.int32)[:, None] * groups + k]
    k = group * k + sum((block[..., c] <= t).astype(jnp.int32)
                        for c in range(group - 1))
    # One gather per output: the word, the bits before it, the payload.
    table = jnp.concatenate([words.astype(jnp.int32)[..., None],
                             (inclusive - popcount)[..., None], payload],
                            axis=2).reshape(n * m, -1)
    got = table[jnp.arange(n, dtype=jnp.int32)[:, None] * m + k]
    word = got[..., 0].astype(jnp.uint32)
    rank = t - got[..., 1]
    # The rank-th set bit of the word: its byte, then a table.
    below = [_popcount(word & jnp.uint32(mask))
             for mask in (0xFF, 0xFFFF, 0xFFFFFF)]
    byte = sum((rank >= c).astype(jnp.int32) for c in below)
    rank = rank - jnp.where(byte == 0, 0, jnp.where(
        byte == 1, below[0], jnp.where(byte == 2, below[1], below[2])))
    value = (word >> (8 * byte).astype(jnp.uint32)) & jnp.uint32(0xFF)
    bit = 8 * byte + jnp.asarray(_BIT_IN_BYTE)[value.astype(jnp.int32) * 8
                                               + jnp.clip(rank, 0, 7)]
    return bit, got[..., 2:], t < count[:, None], count


def _prefix(x):
    """Inclusive prefix sums along axis 1 of int32 ``(N, M)``, M small.

    Up to `_MATMUL_PREFIX` columns: one matrix product, exact (float32
    sums of at most M * 32 < 2**24). An unrolled chain of adds compiled
    into one XLA fusion per column and took twice the compile time; XLA's
    cumsum ran slower. Wider (clustered scenes' long windows): a log-depth
    scan, as the product costs M**2 per row.
    """
    m = x.shape[1]
    if m > _MATMUL_PREFIX:
        return jax.lax.associative_scan(jnp.add, x, axis=1)
    upper = jnp.asarray(np.triu(np.ones((m, m), np.float32)))
    return jnp.dot(x.astype(jnp.float32), upper,
                   precision=jax.lax.Precision.HIGHEST).astype(jnp.int32)


def _slots(window: int) -> int:
    """Slots per stencil row: whole words (a partial word breaks fusion)."""
    return 32 * max(-(-window // 32), 1)


def _check_candidate_words(backend_name: str, n: int, stencil_rows: int,
                           window: int, limit: int):
    """Refuse a portable search whose candidate bits (`_candidate_words`:
    N x stencil rows x window slots, in 32-slot words) int32 cannot index.

    Its flat word index would overflow (seed 003's r = 160 lattice at
    n = 10^6 on the CPU: 2.6e9 words, an OverflowError deep in XLA), so the
    count pass refuses before it runs, as the rows' check does after it.
    """
    words = n * stencil_rows * (_slots(window) // 32)
    if words > limit:
        raise ListTooLargeError(
            f"the cell list's portable search (off CUDA GPUs, or "
            f"Cell(kernel='xla')) would test {words * 32:,} candidate slots "
            f"in {words:,} 32-slot words (N = {n:,} x {stencil_rows} stencil "
            f"rows x {_slots(window):,} slots: the longest row holds "
            f"{window:,} particles), more than backend={backend_name!r} "
            f"indexes ({limit:,} words). Use the GPU kernel (backend='cell' on a CUDA"
            " device), fewer particles or a smaller r_cutoff + dr_threshold. "
            "Energies need no list: "
            "jaxrt.energy.lennard_jones_fused(..., backend='cell').")


def _tolerance(cart, geometry: Geometry, query: Query, position):
    """Bound on |cheap distance - caller's distance| (float scalar).

    The ulps are those of the largest coordinate the caller's metric sees:
    it subtracts the caller's positions (``position``), which on a periodic
    axis may lie many boxes outside it, before it wraps, so its rounding is
    that of the unwrapped coordinates, not of the wrapped ``cart``.
    """
    raw = geometry.grid_coordinates(position)
    raw = jnp.max(jnp.abs(jnp.where(jnp.isfinite(raw), raw, 0.0)),
                  initial=0.0)
    scale = jnp.maximum(jnp.max(jnp.abs(cart), initial=0.0),
                        raw.astype(cart.dtype)) + query.cutoff
    if any(query.periodic):
        scale = scale + jnp.max(jnp.where(jnp.asarray(query.periodic),
                                          geometry.side, 0.0))
    eps = jnp.finfo(cart.dtype).eps
    return query.cutoff * _TOL_RELATIVE + _TOL_ULPS * eps * scale


def _thresholds(cart, geometry: Geometry, query: Query, position):
    """Squared distances (float scalars, ``cart``'s dtype) below which the
    cheap test calls a pair sure, and below which it is in the shell."""
    tol = _tolerance(cart, geometry, query, position)
    inner_sq = (jnp.maximum(query.cutoff - tol, 0.0) ** 2).astype(cart.dtype)
    outer_sq = ((query.cutoff + tol) ** 2).astype(cart.dtype)
    return inner_sq, outer_sq


def _lower_only(query: Query) -> bool:
    """Whether rows hold only the neighbours ``j < i`` (caller's indices):
    OrderedSparse's edges. Half the entries of full rows, left-packed, so
    that its edges are the rows' entries in order: full rows would need a
    rank along each row and twice the memory (benchmarks/list_forces.py's
    ``update`` rows)."""
    return query.format.name == "OrderedSparse"


def _candidate_words(cart, order, runs, geometry: Geometry, query: Query,
                     window: int, position, metric_sq: MetricSq):
    """The cheap distance test on every slot of every stencil row's window.

    With ``query.decide_by_metric`` the test on each slot is the caller's
    metric instead (slower, and the shell is empty): the grid's distance
    then only bounds the metric from below (a triclinic box, or a metric
    that is not the Euclidean minimum image).

    Args:
      cart: float ``(N, dim)`` wrapped Cartesian positions (caller's order).
      order, runs: `_sorted_system`.
      position, metric_sq: the caller's positions and metric.
    Returns:
      uint32 ``(N, R · slots / 32)`` twice: the slots surely within the
      cutoff, and the slots within ``tol`` of it (the shell); bit ``s`` of
      row ``r`` is the run's ``s``-th particle. Only slots ``j < i`` where
      `_lower_only`.
    """
    n, dim = cart.shape
    slots = _slots(window)
    dtype = cart.dtype
    inner_sq, outer_sq = _thresholds(cart, geometry, query, position)
    if query.decide_by_metric:  # the metric's own decision, nothing near it
        inner_sq = outer_sq = jnp.asarray(query.cutoff ** 2, dtype)
    side = geometry.side.astype(dtype)
    inverse_side = 1.0 / side
    pad = jnp.zeros((dim, slots), dtype)
    source = position if query.decide_by_metric else cart
    table = jnp.concatenate([pad, source[order].T, pad], axis=1)
    slot = jnp.arange(slots, dtype=jnp.int32)[None, :]
    me = jnp.zeros((n,), jnp.int32).at[order].set(
        jnp.arange(n, dtype=jnp.int32))[:, None]  # each particle's sorted index
    lower_only = _lower_only(query)
    if lower_only:  # slot -> caller's index, laid out as ``table``
        no_one = jnp.full((slots,), n, jnp.int32)
        caller_table = jnp.concatenate([no_one, order, no_one])
        caller = jnp.arange(n, dtype=jnp.int32)[:, None]

    def windows(first, values=None):  # (N, [dim,] slots): s -> sorted first + s
        if values is not None:
            return jax.vmap(lambda f: jax.lax.dynamic_slice(
                values, (f + slots,), (slots,)))(first)
        return jax.vmap(lambda f: jax.lax.dynamic_slice(
            table, (jnp.zeros_like(f), f + slots), (dim, slots)))(first)

    def row(run):
        first1, size1, first2, size2 = (x[:, None] for x in run)
        near = windows(run[0])
        if query.periodic[0]:
            near = jnp.where((slot < size1)[:, None, :], near,
                             windows(run[2] - run[1]))
        if query.decide_by_metric:
            d2 = jax.vmap(jax.vmap(metric_sq, (None, 1)), (0, 0))(position,
                                                                  near)
        else:
            d2 = jnp.zeros((n, slots), dtype)
            for a in range(dim):
                d = near[:, a, :] - cart[:, a:a + 1]
                if query.periodic[a]:
                    d = d - side[a] * jnp.round(d * inverse_side[a])
                d2 = d2 + d * d
        inside = slot < size1 + size2
        if lower_only:
            theirs = windows(run[0], caller_table)
            if query.periodic[0]:
                theirs = jnp.where(slot < size1, theirs,
                                   windows(run[2] - run[1], caller_table))
            inside &= theirs < caller
        if query.mask_self:
            # The particle's own slot, a scalar per row (a per-slot index
            # made XLA GPU write a slot < size1 mask to memory).
            own1, own2 = me - first1, me - first2
            own = jnp.where((own1 >= 0) & (own1 < size1), own1, jnp.where(
                (own2 >= 0) & (own2 < size2), size1 + own2, -1))
            inside &= slot != own
        sure = inside & (d2 < inner_sq)
        shell = inside & ~sure & (d2 < outer_sq)
        # One reduction for both flags (two over the same windows made XLA
        # recompute the windows): slot b of 16 sets bit 2b if sure, 2b + 1
        # if in the shell.
        code = sure.astype(jnp.uint32) | (shell.astype(jnp.uint32) << 1)
        code = code.reshape(n, slots // 16, 16)
        return jnp.sum(code << (2 * jnp.arange(16, dtype=jnp.uint32)),
                       axis=2, dtype=jnp.uint32)

    start1, len1, start2, len2 = runs
    # All stencil rows in one fused pass (a scan's in-place output update
    # runs on one core).
    pairs = jax.vmap(row)((start1.T, len1.T, start2.T, len2.T))
    pairs = jnp.transpose(pairs, (1, 0, 2)).reshape(n, -1)
    return _words(_even_bits(pairs)), _words(_even_bits(pairs >> 1))


def _first_true(mask, size: int):
    """int32 ``(size,)``: the indices of the first ``size`` True entries of
    bool ``(N,)`` ``mask``, ascending, padded with N (a cumsum and a
    scatter of N; `jnp.nonzero`'s integer remainder would put a ``rem`` in
    free-space programs, which must have no periodic-image work)."""
    n = mask.shape[0]
    rank = jnp.cumsum(mask, dtype=jnp.int32) - 1
    return jnp.full((size,), n, jnp.int32).at[jnp.where(mask, rank, size)].set(
        jnp.arange(n, dtype=jnp.int32), mode="drop")


def _word_runs(runs, window: int):
    """Per word, where its bits point: int32 ``(N, M, 3)`` = (sorted index
    of bit 0 in the first run, bits in the first run, sorted index of bit 0
    in the second run). Word m is part ``m % wpr`` of stencil row
    ``m // wpr`` (a static layout)."""
    start1, len1, start2, _ = runs
    n, rows = start1.shape
    wpr = _slots(window) // 32
    offset = 32 * jnp.arange(wpr, dtype=jnp.int32)[None, None, :]

    def per_word(x):  # (N, R) -> (N, R, wpr) by broadcasting, not gathers
        return jnp.broadcast_to(x[:, :, None], (n, rows, wpr))

    first1 = per_word(start1) + offset
    limit = per_word(len1) - offset
    first2 = per_word(start2 - len1) + offset
    return jnp.stack([first1, limit, first2], axis=3).reshape(n, rows * wpr, 3)


def _sorted_index(bit, word_run):
    """Sorted index of ``bit`` of a word with `_word_runs` ``word_run``
    (int32 ``(..., 3)``)."""
    first1, limit, first2 = (word_run[..., c] for c in range(3))
    return jnp.where(bit < limit, first1, first2) + bit


def _visit_fn(position, geometry: Geometry, metric_sq: MetricSq, *, window,
              shell, shell_rows, row_width, query: Query, coarsen=True):
    """Every particle's neighbours, as the caller's metric decides.

    Args:
      position: float ``(N, dim)`` in the caller's coordinates.
      window: static slots per stencil row (longest run), rounded up to
        whole 32-slot words.
      shell: static most shell pairs of one particle.
      shell_rows: static most particles with a shell pair.
      row_width: static width of the output rows (0: only count).
    Returns:
      rows int32 ``(N, row_width)``, left-packed with neighbour indices
      (only ``j < i`` where `_lower_only`), padded with ``N``; counts
      int32 ``(N,)``, exact unless a buffer
      overflowed; int32 ``(2,)`` the particles with a shell pair and the
      most shell pairs of one; and whether a run was longer than the window
      or a shell buffer too small (bool scalar).
    """
    n = position.shape[0]
    order, cart, runs = _sorted_system(position, geometry, query, coarsen)
    sure, maybe = _candidate_words(cart, order, runs, geometry, query, window,
                                   position, metric_sq)
    m = sure.shape[1]

    # The shell: the caller's metric decides the pairs of the few particles
    # that have any (a few in a hundred), gathered first so that the search
    # for their bits and the metric run on them only.
    has_shell = jnp.any(maybe != 0, axis=1)
    at = _first_true(has_shell, shell_rows)
    real = at < n
    at = jnp.minimum(at, n - 1)
    flat_word = at[:, None] * m + jnp.arange(m, dtype=jnp.int32)[None, :]
    # Their runs are gathered, not their words' (the per-word table is then
    # used once, and XLA builds it inside the row packing's table).
    payload = jnp.concatenate([_word_runs([r[at] for r in runs], window),
                               flat_word[..., None]], axis=2)
    bit, got, valid, per_particle = _select(
        jnp.where(real[:, None], maybe[at], jnp.uint32(0)), shell, payload,
        _slots(window) // 32)
    j = order[jnp.clip(_sorted_index(bit, got), 0, n - 1)]
    d2 = jax.vmap(jax.vmap(metric_sq, (None, 0)), (0, 0))(position[at],
                                                           position[j])
    accept = valid & (d2 < jnp.asarray(query.cutoff ** 2, position.dtype))
    words = sure.reshape(-1).at[jnp.where(accept, got[..., 3], sure.size)].add(
        jnp.uint32(1) << bit.astype(jnp.uint32), mode="drop").reshape(
            sure.shape)
    shell_sizes = jnp.stack([jnp.sum(has_shell, dtype=jnp.int32),
                             jnp.max(per_particle, initial=0)])
    # Runs may fill the window's whole words: its real size.
    overflow = (jnp.any(runs[1] + runs[3] > _slots(window))
                | (shell_sizes[0] > shell_rows) | (shell_sizes[1] > shell))
    if row_width == 0:
        count = jnp.sum(jax.lax.population_count(words), axis=1,
                        dtype=jnp.int32)
        return jnp.zeros((n, 0), jnp.int32), count, shell_sizes, overflow

    word_runs = _word_runs(runs, window)
    bit, got, valid, count = _select(words, row_width, word_runs,
                                     _slots(window) // 32)
    j = jnp.clip(_sorted_index(bit, got), 0, n - 1)
    rows = jnp.where(valid, order[j], n)
    return rows, count, shell_sizes, overflow


_VISIT_STATIC = ("window", "shell", "shell_rows", "row_width", "query",
                 "coarsen")
_visit = jax.jit(_visit_fn, static_argnames=_VISIT_STATIC)


def _run_sizes(position, geometry: Geometry, query: Query, coarsen=True):
    """What sizes the count: int32 ``(R,)`` the longest pair of runs of
    each stencil row, and `_tolerance` (float scalar)."""
    _, cart, (_, len1, _, len2) = _sorted_system(position, geometry, query,
                                                 coarsen)
    return (jnp.max(len1 + len2, axis=0, initial=0),
            _tolerance(cart, geometry, query, position))


# ``allocate`` measures once, then builds: the measuring programs run once
# or twice. Up to this many particles on a CPU they are compiled for
# compile speed (`QUICK_COMPILE_OPTIONS`: tens of ms slower to run here).
_QUICK_MAX_N = 1 << 15
_QUICK = _backend.QUICK_COMPILE_OPTIONS
_run_sizes_fast = jax.jit(_run_sizes, static_argnames=("query", "coarsen"))
_run_sizes_quick = jax.jit(_run_sizes, static_argnames=("query", "coarsen"),
                           compiler_options=_QUICK)
_visit_quick = jax.jit(_visit_fn, static_argnames=_VISIT_STATIC,
                       compiler_options=_QUICK)


# Up to this many particles on a CPU, ``allocate`` counts rows over all
# pairs (`_all_pairs_counts`): its program compiles in a fraction of the
# windows' count. Past it the N**2 distances slow down every ``allocate``
# on a new structure (at N = 1000 it took as long either way; at 2000 a
# third longer: a training set's allocates).
_ALL_PAIRS_COUNT_MAX_N = 1024


@functools.partial(jax.jit, static_argnames=("query",))
def _all_pairs_counts(position, metric_sq: MetricSq, tol, *, query: Query):
    """`_visit`'s counts (row_width 0) over all pairs, for ``allocate``.

    The rows are the list's: each pair the caller's metric puts within the
    cutoff (once, through the image it picks; the windows find the same
    set). The shell sizes bound the windows' from above: a pair in their
    shell is within ``tol`` of the cutoff by the cheap distance, which is
    within ``tol / 4`` of the caller's (`_TOL_ULPS`), so within ``2 tol``
    of it by the caller's metric, where all such pairs are counted here.

    Args:
      position: float ``(N, dim)``; ``tol``: `_tolerance` (float scalar).
    Returns:
      int32 ``(N,)`` row counts (only ``j < i`` where `_lower_only`) and
      int32 ``(2,)`` the particles with a pair near the cutoff and the
      most such pairs of one.
    """
    n = position.shape[0]
    dtype = position.dtype
    d2 = jax.vmap(jax.vmap(metric_sq, (None, 0)), (0, None))(position,
                                                             position)
    j = jnp.arange(n, dtype=jnp.int32)[None, :]
    i = jnp.arange(n, dtype=jnp.int32)[:, None]
    keep = d2 < jnp.asarray(query.cutoff ** 2, dtype)
    if query.mask_self:
        keep &= i != j
    if _lower_only(query):
        keep &= j < i
    count = jnp.sum(keep, axis=1, dtype=jnp.int32)
    if query.decide_by_metric:  # the metric decides every slot: no shell
        return count, jnp.zeros((2,), jnp.int32)
    tol = jnp.asarray(tol, dtype)
    low = jnp.maximum(query.cutoff - 2 * tol, 0) ** 2
    high = (query.cutoff + 2 * tol) ** 2
    near = jnp.sum((d2 >= low) & (d2 < high), axis=1, dtype=jnp.int32)
    return count, jnp.stack([jnp.sum(near > 0, dtype=jnp.int32),
                             jnp.max(near, initial=0)])


@functools.partial(jax.jit, static_argnames=("shell", "shell_rows",
                                             "row_width", "query",
                                             "interpret"))
def _walk(position, geometry: Geometry, metric_sq: MetricSq, *, shell,
          shell_rows, row_width, query: Query, interpret: bool = False):
    """`_visit` with the candidate pass as one GPU kernel (`_cell_kernel`):
    the same sets, in another order within rows. Needs no window: the
    kernel walks each run to its end.

    Returns:
      As `_visit`: rows int32 ``(N, max(row_width, 1))``, counts int32
      ``(N,)``, int32 ``(2,)`` shell sizes, bool scalar overflow.
    """
    n = position.shape[0]
    order, cart, sorted_key, cell, cells = _sorted_grid(position, geometry,
                                                        query)
    # The kernel finds each particle's runs in the cell-start table.
    grid = _cell_kernel.CellGrid(_cell_starts(sorted_key), cell[order],
                                 cells, _REACH)
    inner_sq, outer_sq = _thresholds(cart, geometry, query, position)
    rows, count, shells, shell_count = _cell_kernel.candidate_rows(
        cart[order], order, grid, inner_sq, outer_sq, geometry.side,
        periodic=query.periodic, mask_self=query.mask_self,
        lower_only=_lower_only(query), row_width=row_width, shell=shell,
        interpret=interpret)
    return _append_shell(position, metric_sq, rows, count, shells,
                         shell_count, shell_rows=shell_rows, query=query)


def _append_shell(position, metric_sq: MetricSq, rows, count, shells,
                  shell_count, *, shell_rows: int, query: Query):
    """The shell pairs of a kernel's candidate pass, decided by the
    caller's metric for the few particles that have any, appended to their
    rows.

    Args:
      position: float ``(N, dim)`` in the caller's coordinates.
      rows, count, shells, shell_count: a kernel's four outputs in the
        caller's order (`_cell_kernel.candidate_rows`'): int32 ``(N, W)``,
        ``(N,)``, ``(N, S)``, ``(N,)``.
      shell_rows: static, most particles whose shells are decided.
    Returns:
      As `_visit`: rows, counts, int32 ``(2,)`` shell sizes, bool overflow.
    """
    n = position.shape[0]
    shell = shells.shape[1]
    width = rows.shape[1]
    has_shell = shell_count > 0
    at = _first_true(has_shell, shell_rows)
    real = at < n
    at = jnp.minimum(at, n - 1)
    valid = real[:, None] & (jnp.arange(shells.shape[1], dtype=jnp.int32)
                             < shell_count[at][:, None])
    j = jnp.where(valid, shells[at], 0)
    d2 = jax.vmap(jax.vmap(metric_sq, (None, 0)), (0, 0))(position[at],
                                                           position[j])
    accept = valid & (d2 < jnp.asarray(query.cutoff ** 2, position.dtype))
    slot = count[at][:, None] + jnp.cumsum(accept, axis=1,
                                           dtype=jnp.int32) - 1
    rows = rows.at[at[:, None], jnp.where(accept, slot, width)].set(
        j, mode="drop")
    count = count.at[at].add(jnp.sum(accept, axis=1, dtype=jnp.int32))
    shell_sizes = jnp.stack([jnp.sum(has_shell, dtype=jnp.int32),
                             jnp.max(shell_count, initial=0)])
    overflow = (shell_sizes[0] > shell_rows) | (shell_sizes[1] > shell)
    return rows, count, shell_sizes, overflow


# The Warp walk's reach in cells (along x, across): cells ``cutoff / 4``
# wide along x and ``cutoff / 2`` across, as the list-free sums' Warp walk
# (`jaxrt.energy.listfree.lj.CellSums.reach`).
_WARP_REACH = (4, 2)


def _warp_grid(points, geometry: Geometry, query: Query, table: int,
               reach: tuple[int, int] = _WARP_REACH):
    """The Warp pipeline's grid (`jaxrt.backends.rt.ffi.cell_lj_sums`'
    ``grid`` and ``cells``) for a list: `jaxrt.backends.cell.warp_grid.build`
    with cells at least ``cutoff (1 + _CELL_MARGIN) / reach`` wide, the
    box's (traced) sides on periodic axes, one cell on axes past ``dim``.

    Args:
      points: float ``(N, 3)`` finite Cartesian positions (unwrapped), zeros
        past ``dim``.
      table: static, the most cells.
    Returns:
      float ``(3, 3)`` origin, cell width, side (1 off periodic axes) per
      axis; int32 ``(6,)`` cells per axis then the reach per axis.
    """
    dim = query.dim
    padding = tuple(a >= dim for a in range(3))
    reach3 = tuple(1 if pad else reach[a > 0]
                   for a, pad in enumerate(padding))
    side = jnp.pad(geometry.side.astype(points.dtype), (0, 3 - dim),
                   constant_values=1)
    return warp_grid.build(
        points, side, periodic=tuple(query.periodic) + (False,) * (3 - dim),
        padding=padding, reach=reach3, table=table,
        min_size=tuple(query.cutoff * (1.0 + _CELL_MARGIN) / r
                       for r in reach3))


@functools.partial(jax.jit, static_argnames=("shell", "shell_rows",
                                             "row_width", "query", "graph"))
def _warp_walk(position, geometry: Geometry, metric_sq: MetricSq, *, shell,
               shell_rows, row_width, query: Query, graph: str = "none"):
    """`_walk` on the Warp pipeline (`jaxrt.backends.cell.warp_rows`, one
    call of `jaxrt.backends.rt.ffi.cell_candidate_rows`): its own grid
    (`_warp_grid`), the same thresholds and shell decision, so the same
    sets; rows in the walk's order. ``graph``: `Cell.warp_graph`.

    Returns:
      As `_visit`: rows int32 ``(N, max(row_width, 1))``, counts int32
      ``(N,)``, int32 ``(2,)`` shell sizes, bool scalar overflow.
    """
    from jaxrt.backends.cell import warp_rows
    from jaxrt.backends.rt import ffi
    n, dim = position.shape
    row_width, shell = max(row_width, 1), max(shell, 1)
    if n == 0:
        empty = jnp.zeros((0,), jnp.int32)
        return (jnp.zeros((0, row_width), jnp.int32), empty,
                jnp.zeros((2,), jnp.int32), jnp.zeros((), bool))
    cart = geometry.grid_coordinates(position)
    # NaN positions are reported by the front; keep them from poisoning keys.
    cart = jnp.where(jnp.isfinite(cart), cart, 0.0)
    table = _table_size(n)
    points = jnp.pad(cart, [(0, 0), (0, 3 - dim)])
    grid, cells = _warp_grid(points, geometry, query, table)
    # The walk's coordinates reach a side on periodic axes (wrapped there):
    # its rounding is bounded as `_walk`'s, whose wrapped positions the
    # tolerance sees.
    periodic = jnp.asarray(query.periodic)
    reach = jnp.concatenate([cart, jnp.where(periodic, geometry.side, 0)[
        None].astype(cart.dtype)])
    inner_sq, outer_sq = _thresholds(reach, geometry, query, position)
    flags = warp_rows.MASK_SELF if query.mask_self else 0
    flags |= warp_rows.LOWER_ONLY if _lower_only(query) else 0
    for a, p in enumerate(query.periodic):
        flags |= (warp_rows.PERIODIC << a) if p else 0
    rows, count, shells, shell_count = ffi.cell_candidate_rows(
        points, grid, cells, jnp.stack([inner_sq, outer_sq]).astype(
            cart.dtype), flags=flags, table=table, row_width=row_width,
        shell=shell, graph=graph)
    return _append_shell(position, metric_sq, rows, count, shells,
                         shell_count, shell_rows=shell_rows, query=query)


def _warp_fits(n: int, row_width: int, shell: int) -> bool:
    """Whether the Warp walk's int32 outputs can be addressed (Warp's
    offsets are 32-bit byte offsets)."""
    from jaxrt.backends.rt import ffi
    return n * max(row_width, shell, 1) <= ffi.MAX_LIST_ENTRIES


_KERNELS = ("auto", "pallas", "xla", "interpret", "warp")
_WARP_GRAPHS = ("none", "warp", "jax")


@dataclasses.dataclass(frozen=True)
class Cell:
    """The sorted cell list as a `jaxrt.backends.Backend` (``"cell"``).

    Attributes:
      kernel: the candidate pass (passes 3 and 4 of the module docstring).
        ``"auto"``: the `jaxrt.backends.cell.kernel` kernel on CUDA (chosen where
        the program is lowered) and the windows of array programs
        elsewhere, or wherever the kernel cannot serve the list (a metric
        that decides every pair, buffers past its int32 offsets).
        ``"pallas"``: the kernel, or an error at ``allocate`` where it
        cannot run. ``"xla"``: the windows everywhere. ``"interpret"``:
        the kernel in Pallas' interpreter (tests on CPUs). All four find
        the same pairs. ``"warp"``: the Warp pipeline of
        `jaxrt.backends.cell.warp_rows` (CPU or CUDA; also the engine of the
        list-free energies `jaxrt.energy.lennard_jones_fused`,
        `jaxrt.energy.density_fused` and `jaxrt.energy.acceleration_fused`),
        the same pairs, for orthorhombic and free boxes with the Euclidean
        metric and no radii; an error at ``allocate`` elsewhere. Its rows
        hold each particle's neighbours in the order its walk meets them.
      radius_classes: with per-particle radii (``radii=``), how many radius
        classes get a grid each (`jaxrt.backends.cell.radius_classes`): None, as many as
        the radii at ``allocate`` need; 1, one grid of cells of the largest
        radius (the plain scheme, for comparison).

      warp_graph: with ``kernel="warp"``, who captures the Warp
        pipeline's launches in a CUDA graph
        (`jaxrt.backends.rt.ffi.cell_candidate_rows`): ``"none"`` (its
        launches enqueued from Python at every call), ``"warp"`` (Warp
        captures them once per set of buffer addresses and replays),
        ``"jax"`` (JAX captures them in its own graphs); on a CPU, none.

    Internal capacities: ``"window"`` (longest run of one stencil row),
    ``"shell"`` (most pairs of one particle that the caller's metric
    decides), ``"shell_rows"`` (most particles with such pairs) and
    ``"row"`` (width of the rows built before conversion to a Sparse
    layout; for OrderedSparse, rows of the neighbours ``j < i`` alone).
    """

    kernel: str = "auto"
    radius_classes: int | None = None
    warp_graph: str = "none"

    name: ClassVar[str] = "cell"
    decides_by_metric: ClassVar[bool] = True
    supports_radii: ClassVar[bool] = True
    small_boxes: ClassVar[bool] = True
    fixed_sizes: ClassVar[tuple[str, ...]] = ("classes", "fixed_grid")

    def __post_init__(self):
        if self.kernel not in _KERNELS:
            raise ValueError(f"Cell(kernel={self.kernel!r}): choose one of "
                             f"{_KERNELS}.")
        if self.warp_graph not in _WARP_GRAPHS:
            raise ValueError(f"Cell(warp_graph={self.warp_graph!r}): choose "
                             f"one of {_WARP_GRAPHS}.")
        k = self.radius_classes
        if k is not None and (isinstance(k, bool) or not isinstance(k, int)
                              or not 1 <= k <= radius_classes.MAX_CLASSES):
            raise ValueError(
                f"Cell(radius_classes={k!r}): must be None (as many as the "
                "radii need) or an int in 1.."
                f"{radius_classes.MAX_CLASSES} (1: cells of the largest "
                "radius).")

    def _check_radii_kernel(self):
        if self.kernel in ("pallas", "interpret", "warp"):
            raise ValueError(
                f"Cell(kernel={self.kernel!r}) has no per-particle radii: "
                "lists with radii= run on the radius classes of "
                "jaxrt.backends.cell.radius_classes; use Cell(kernel='auto') or 'xla'.")

    def _engine(self, n: int, row_width: int, shell: int, query: Query,
                platform: str | None) -> str:
        """``"kernel"``, ``"interpret"``, ``"portable"``, ``"warp"`` or
        ``"lowering"`` (the kernel on CUDA, else portable, decided where
        the program is lowered); ``platform``: where an eager call runs,
        None under jit.

        Raises:
          ValueError: ``kernel`` names the kernel where it cannot serve.
        """
        if self.kernel == "xla":
            return "portable"
        if self.kernel == "warp":
            why = None
            if query.decide_by_metric:
                why = ("the caller's metric decides every pair here (a "
                       "triclinic box, or a metric that is not the "
                       "Euclidean minimum image), and the Warp walk "
                       "computes its own distances")
            elif query.dim > 3:
                why = f"the Warp walk is for 1 to 3 dimensions, not {query.dim}"
            elif not _warp_fits(n, row_width, shell):
                why = (f"N x row width = {n} x {max(row_width, shell)} is "
                       "past Warp's int32 offsets")
            if why is not None:
                raise ValueError(
                    f"Cell(kernel='warp') cannot serve this list: {why}. "
                    "Use Cell(kernel='auto') or Cell(kernel='xla').")
            return "warp"
        why = None
        if query.decide_by_metric:
            why = ("the caller's metric decides every pair here (a triclinic "
                   "box, or a metric that is not the Euclidean minimum "
                   "image), and the kernel computes its own distances")
        elif not _cell_kernel.fits(n, row_width, shell):
            why = ("this JAX has no Pallas Triton backend" if
                   _cell_kernel.plgpu is None else
                   f"N x row width = {n} x {max(row_width, shell)} is past "
                   "the kernel's int32 offsets")
        if self.kernel == "auto":
            if why is not None or platform not in (None, "gpu", "cuda"):
                return "portable"
            return "lowering" if platform is None else "kernel"
        if why is None and self.kernel == "pallas" and platform not in (
                None, "gpu", "cuda"):
            why = f"positions live on {platform!r}, not on a CUDA GPU"
        if why is not None:
            raise ValueError(
                f"Cell(kernel={self.kernel!r}) cannot serve this list: {why}."
                " Use Cell(kernel='auto') (the kernel where it can run) or "
                "Cell(kernel='xla').")
        return self.kernel if self.kernel == "interpret" else "kernel"

    def _candidates(self, engine: str, position, geometry, metric_sq, *,
                    window: int, quick: bool = False, coarsen: bool = True,
                    **options):
        """`_visit` or `_walk` per ``engine`` (`_engine`); ``quick``: the
        portable path compiled for compile speed (`_QUICK`); ``coarsen``:
        the portable path's grid (`_fixed_grid`)."""
        def portable():
            return (_visit_quick if quick else _visit)(
                position, geometry, metric_sq, window=window, coarsen=coarsen,
                **options)

        def kernel():
            return _walk(position, geometry, metric_sq, **options)

        if engine == "portable":
            return portable()
        if engine == "warp":
            return _warp_walk(position, geometry, metric_sq,
                              graph=self.warp_graph, **options)
        if engine == "interpret":
            return _walk(position, geometry, metric_sq, interpret=True,
                         **options)
        if engine == "kernel":
            return kernel()
        return platforms.cuda_or_default(kernel, portable)

    def measure(self, position, geometry, query, metric_sq):
        if geometry.reach is not None:
            self._check_radii_kernel()
            return radius_classes.measure(position, geometry, query,
                                          metric_sq, self.radius_classes)
        n = position.shape[0]
        # Counting runs on the engine the search will use (the portable
        # path at N = 1e6 would compile and run XLA's largest program).
        platform = _platform_of(position)
        quick = (platform == "cpu" and n <= _QUICK_MAX_N
                 and not platforms.under_trace())
        fixed = _fixed_grid(n, geometry, query)
        longest, tol = (_run_sizes_quick if quick else _run_sizes_fast)(
            position, geometry, query, not fixed)
        longest, tol = np.asarray(longest), float(tol)
        window = max(int(np.max(longest, initial=0)), 1)
        # The counts run on whole words, as the search does: positions
        # whose longest runs differ a little reuse one compiled count (the
        # list's own window stays the run's length, sized from it).
        words = _slots(window)
        # A first guess that fits liquids (a few in a hundred have a shell).
        shell, shell_rows = _MIN_SHELL, _shell_rows(n // 8, n)
        limit = _backend.max_list_entries(self)
        # Small lists on a CPU: all pairs count the rows (on the portable
        # path, which the search then takes there).
        all_pairs = (platform == "cpu" and n <= _ALL_PAIRS_COUNT_MAX_N
                     and self.kernel in ("auto", "xla"))
        if all_pairs:
            _check_candidate_words(self.name, n, longest.shape[0], window,
                                   limit)
            count, near = _all_pairs_counts(position, metric_sq, tol,
                                            query=query)
            has, fullest = (int(x) for x in np.asarray(near))
        while not all_pairs:  # enough room to count every shell pair exactly
            engine = self._engine(n, 1, shell, query, platform)
            if engine == "portable":
                _check_candidate_words(self.name, n, longest.shape[0],
                                       window, limit)
            _, count, near, _ = self._candidates(
                engine, position, geometry, metric_sq, window=words,
                quick=quick, coarsen=not fixed,
                shell=shell, shell_rows=shell_rows, query=query,
                row_width=0 if engine == "portable" else 1)
            # On the host: unpacking a jax.Array compiles a program.
            has, fullest = (int(x) for x in np.asarray(near))
            if has <= shell_rows and fullest <= shell:
                break
            shell = max(shell, 2 * fullest)
            shell_rows = max(shell_rows, _shell_rows(has, n))
        count = np.asarray(count)
        # Every layout is built from rows N x row wide: refuse now what the
        # front would refuse after sizing (a cluster where each particle
        # sees all others needs N^2), before the rows pass below allocates
        # them (seed 003's cluster at n = 50 000 was killed for host memory
        # there, and ran past the benchmark's time limit on the GPU).
        entries = n * int(count.max(initial=0))
        if entries > limit:
            raise _backend.list_too_large(self.name, entries,
                                          "rows before conversion", n, limit)
        # A lattice at allocate may have no pair near the cutoff, and a
        # liquid a few per hundred particles: expect the liquid's share,
        # from the pairs found (they grow as r**dim, so a shell of width
        # 2 tol holds 2 dim tol / cutoff of them).
        per_particle = count.mean() * 2 * query.dim * tol / query.cutoff
        liquid = math.ceil(n * -math.expm1(-per_particle))
        sizes = {"row": int(count.max(initial=0)), "window": window,
                 "shell": max(2 * fullest, _MIN_SHELL),
                 "shell_rows": _shell_rows(max(has, liquid), n),
                 "fixed_grid": int(fixed)}
        # OrderedSparse's rows hold its edges alone (`_lower_only`).
        sizes["edges"] = int(count.sum())
        # An explicit kernel that cannot hold the sized buffers fails here,
        # at allocate, not at the first traced update.
        self._engine(n, max(sizes["row"], 1), sizes["shell"], query, None)
        return sizes

    def search(self, position, geometry, query, capacity: Capacity, metric_sq):
        if geometry.reach is not None:
            self._check_radii_kernel()
            return radius_classes.search(position, geometry, query, capacity,
                                         metric_sq)
        options = dict(shell=capacity["shell"],
                       shell_rows=capacity["shell_rows"],
                       row_width=max(capacity["row"], 1), query=query)
        engine = self._engine(position.shape[0], options["row_width"],
                              options["shell"], query, None)
        fixed = dict(capacity.internal).get("fixed_grid", 0)
        rows, count, _, overflow = self._candidates(
            engine, position, geometry, metric_sq, window=capacity["window"],
            coarsen=not fixed, **options)
        result = _backend.format_dense_rows(
            rows, count, query, capacity, lower_only=_lower_only(query))
        return result._replace(overflow=result.overflow | overflow)


def _platform_of(position) -> str:
    """The platform an eager computation on ``position`` runs on."""
    devices = getattr(position, "devices", None)
    if callable(devices):
        try:
            return next(iter(devices())).platform
        except Exception:  # noqa: BLE001 - a tracer or a deleted array
            pass
    return jax.default_backend()


# ---------------------------------------------------------------------------
# The grid, by public-internal names (`jaxrt.backends.cell.grid` holds them
# for the radius classes and the list-free energies).

REACH = _REACH
cell_starts = _cell_starts
grid = _grid
image_axes = _image_axes
key = _key
run_images = _run_images
runs = _runs
select = _select
static_cells = _static_cells
table_size = _table_size
