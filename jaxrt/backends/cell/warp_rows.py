"""Warp kernels of the cell list's candidate pass (``Cell(kernel="warp")``):
Warp and NumPy only (no JAX; `jaxrt.backends.rt.ffi.cell_candidate_rows`
puts `candidate_rows` behind a JAX call).

The particles are binned, sorted and gathered by the list-free sums'
pipeline (`jaxrt.backends.cell.warp_kernels.sort_cells`); then a
thread per sorted particle walks the same stencil as their walk
(`jaxrt.backends.cell.warp_kernels.stencil_functions`) and, instead of
summing, makes the three-way split of the other candidate passes
(`jaxrt.backends.cell.kernel.candidate_rows`), with the thresholds it is
given: a pair surely within the cutoff (``d2 < inner_sq``) is appended to
the particle's row, a pair within the tolerance of it (``d2 < outer_sq``)
to its shell buffer, which the caller's metric decides afterwards, and
the rest are dropped. Rows and shells hold caller's indices and are
written at the particle's caller's index; within a row the neighbours are
in the order the walk meets them (stencil rows z, then y, then x cells
ascending; within a cell, the sort's order), not sorted.

Counts are exact past the buffers' widths: a row or shell that does not
fit keeps its first ``width`` entries, and its count tells the caller.
"""

import warp as wp

from jaxrt.backends.cell import warp_kernels

# `candidate_rows`' ``flags`` bits, besides warp_kernels.PERIODIC << axis:
# skip the particle itself; keep only partners of lower caller's index
# (OrderedSparse's half rows).
MASK_SELF = 64
LOWER_ONLY = 128
PERIODIC = warp_kernels.PERIODIC
# ``thresholds``' entries.
INNER_SQ, OUTER_SQ = 0, 1
# Threads per block of the walk (as the sums' walk).
WALK_BLOCK = warp_kernels.WALK_BLOCK


# The rows are stored 16 bytes at a time: one 4-byte store per pair (a
# store instruction per sector per thread) made the walk two and a half
# times the walk that only counts (benchmarks/warp_rows_variants.py).
@wp.func_native("""
#if defined(__CUDA_ARCH__)
reinterpret_cast<int4*>(rows.data)[quad] = make_int4(a, b, c, d);
#else
int* q = reinterpret_cast<int*>(rows.data) + 4 * (size_t)quad;
q[0] = a; q[1] = b; q[2] = c; q[3] = d;
#endif
""")
def _store_quad(rows: wp.array(dtype=wp.int32), quad: int, a: int, b: int,
                c: int, d: int):
    ...


@wp.func
def _pick(slot: int, b0: int, b1: int, b2: int, b3: int):
    return wp.where(slot == 0, b0,
                    wp.where(slot == 1, b1, wp.where(slot == 2, b2, b3)))


@wp.func
def _pad(rows: wp.array(dtype=wp.int32), first: int, stop: int, value: int):
    """``rows[first:stop] = value``: the aligned quads whole, the ends one
    entry at a time."""
    # A fresh variable (``at = first`` would make them one in Warp's code).
    at = wp.max(first, first)
    while at < stop and (at & 3) != 0:
        rows[at] = value
        at = at + 1
    for quad in range(at >> 2, stop >> 2):
        _store_quad(rows, quad, value, value, value, value)
    for k in range(wp.max(at, (stop >> 2) << 2), stop):
        rows[k] = value


@wp.func
def _append(rows: wp.array(dtype=wp.int32), at: int, row_base: int,
            value: int, b0: int, b1: int, b2: int, b3: int):
    """Entry ``at`` of a row starting at ``row_base``: kept in its quad's
    registers (by the address' last two bits), the quad stored when full
    (entry by entry where the row starts inside it)."""
    slot = at & 3
    c0 = wp.where(slot == 0, value, b0)
    c1 = wp.where(slot == 1, value, b1)
    c2 = wp.where(slot == 2, value, b2)
    c3 = wp.where(slot == 3, value, b3)
    if slot == 3:
        if at - 3 >= row_base:
            _store_quad(rows, at >> 2, c0, c1, c2, c3)
        else:
            for k in range(row_base, at + 1):
                rows[k] = _pick(k & 3, c0, c1, c2, c3)
    return c0, c1, c2, c3


def _rows_kernel(scalar, trim):
    """The walk that writes rows, for positions of ``scalar``; ``trim``:
    each stencil row cut to the sphere the stencil covers
    (`jaxrt.backends.cell.warp_kernels.trim_functions`)."""
    vector = wp.types.vector(3, scalar)
    _, difference = warp_kernels.stencil_functions(scalar)
    frame, row_range = warp_kernels.trim_functions(scalar)
    stencil = warp_kernels.stencil
    row = warp_kernels.row
    x_ranges_between = warp_kernels.x_ranges_between
    grid_side = warp_kernels.SIDE

    @wp.kernel(module="unique", module_options=warp_kernels.MODULE_OPTIONS)
    def rows_walk(position: wp.array(dtype=vector),
                  keys: wp.array(dtype=wp.int32),
                  values: wp.array(dtype=wp.int32),
                  start: wp.array(dtype=wp.int32),
                  grid: wp.array(dtype=vector),
                  cells: wp.array(dtype=wp.int32),
                  thresholds: wp.array(dtype=scalar), flags: int,
                  row_width: int, shell: int,
                  rows: wp.array(dtype=wp.int32),
                  count: wp.array(dtype=wp.int32),
                  shells: wp.array(dtype=wp.int32),
                  shell_count: wp.array(dtype=wp.int32)):
        i = wp.tid()
        n = position.shape[0]
        mask_self = flags & MASK_SELF
        lower_only = flags & LOWER_ONLY
        side = grid[grid_side]
        inner_sq = thresholds[INNER_SQ]
        outer_sq = thresholds[OUTER_SQ]
        s = stencil(flags, cells, keys[i])
        p = position[i]
        me = values[i]
        row_base = me * row_width
        shell_base = me * shell
        hits = int(0)
        near = int(0)
        # The row's entries of the current aligned quad of ``rows``, by
        # their address' last two bits.
        b0 = int(0)
        b1 = int(0)
        b2 = int(0)
        b3 = int(0)
        if wp.static(trim):
            t = frame(s, p, grid, cells)
        for dz in range(-s.az, s.az + 1):
            z, oz, okz = row(s.cz, dz, s.nz, s.pz, s.az)
            for dy in range(-s.ay, s.ay + 1):
                y, oy, oky = row(s.cy, dy, s.ny, s.py, s.ay)
                near_row = True
                lo = -s.ax
                hi = s.ax
                if wp.static(trim):
                    near_row, lo, hi = row_range(s, t, dy, dz)
                if okz and oky and near_row:
                    base = s.nx * (y + s.ny * z)
                    lo0, hi0, ox0, hi1, ox1 = x_ranges_between(
                        s.cx, lo, hi, s.nx, s.px, s.rx)
                    for part in range(2):
                        a = wp.where(part == 0, lo0, 0)
                        b = wp.where(part == 0, hi0, hi1)
                        ox = wp.where(part == 0, ox0, ox1)
                        if b >= a:
                            q = p - vector(scalar(ox) * side[0],
                                           scalar(oy) * side[1],
                                           scalar(oz) * side[2])
                            for j in range(start[base + a],
                                           start[base + b + 1]):
                                d, d2 = difference(q, position[j], side, s)
                                # The caller's index is loaded only for the
                                # few candidates that are kept.
                                if d2 < outer_sq and (mask_self == 0
                                                      or j != i):
                                    theirs = values[j]
                                    if lower_only == 0 or theirs < me:
                                        if d2 < inner_sq:
                                            if hits < row_width:
                                                b0, b1, b2, b3 = _append(
                                                    rows, row_base + hits,
                                                    row_base, theirs, b0, b1,
                                                    b2, b3)
                                            hits = hits + 1
                                        else:
                                            if near < shell:
                                                shells[shell_base + near] = \
                                                    theirs
                                            near = near + 1
        # The entries of an unfinished last quad, then the padding (N, as
        # every list pads).
        stop = row_base + wp.min(hits, row_width)
        for k in range(wp.max(row_base, (stop >> 2) << 2), stop):
            rows[k] = _pick(k & 3, b0, b1, b2, b3)
        _pad(rows, stop, row_base + row_width, n)
        count[me] = hits
        shell_count[me] = near

    return rows_walk


_WALKS: dict = {}


# Each stencil row cut to the sphere it must cover: about a third fewer
# candidates with the list's reach (4, 2, 2), yet the trimmed walk measured
# slower than the full rows on the H100 (a warp still walks its longest
# lane's range; benchmarks/warp_rows_variants.py, "untrimmed"): off.
TRIM = False


def rows_kernel(scalar, trim: bool | None = None):
    """The row-writing walk for positions of ``scalar`` (``trim``: as
    `_rows_kernel`'s, `TRIM` by default), built on first use (a module of
    its own: load it before a graph capture)."""
    key = (scalar, TRIM if trim is None else bool(trim))
    if key not in _WALKS:
        _WALKS[key] = _rows_kernel(*key)
    return _WALKS[key]


def candidate_rows(points, grid, cells, thresholds, flags: int, *,
                   row_width: int, shell: int, rows, count, shells,
                   shell_count, keys, values, wrapped, start, position,
                   radius, block_dim: int = WALK_BLOCK) -> None:
    """Sort the particles by cell and write every particle's candidate rows
    (the module docstring), on ``points``' device.

    Args:
      points: vec3 ``(N,)`` Cartesian positions (padding axes all equal).
      grid, cells: as `jaxrt.backends.cell.warp_kernels.lj_sums`' (cells
        at least the shell's outer radius over the axis' reach wide).
      thresholds: scalar ``(2,)``: `INNER_SQ`, `OUTER_SQ`.
      flags: `MASK_SELF`, `LOWER_ONLY`, ``PERIODIC << axis``.
      row_width, shell: the widths (>= 1) of the rows and shell buffers.
      rows: int32 ``(N * row_width,)`` out: row ``i`` (caller's index) at
        ``i * row_width``, caller's indices of the sure pairs, then ``N``;
        count: int32 ``(N,)`` out, their exact numbers; shells: int32
        ``(N * shell,)`` out, the shell pairs (valid up to the count);
        shell_count: int32 ``(N,)`` out, their exact numbers.
      keys, values, wrapped, start, position, radius: scratch, as
        `jaxrt.backends.cell.warp_kernels.lj_sums`' (``radius``: ``(1,)``).
      block_dim: the walk's threads per block.
    """
    n = points.shape[0]
    if n == 0:
        return
    # The sort reads only the periodic bits (no radii here).
    warp_kernels.sort_cells(
        points, radius, grid, cells, flags & (7 * PERIODIC), keys=keys,
        values=values, wrapped=wrapped, start=start, position=position,
        radius=radius)
    walk = rows_kernel(warp_kernels.scalar_of(points.dtype))
    wp.launch(walk, dim=n, device=points.device, block_dim=block_dim,
              inputs=[position, keys, values, start, grid, cells, thresholds,
                      flags, row_width, shell, rows, count, shells,
                      shell_count])
