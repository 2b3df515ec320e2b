"""Warp kernels of the list-free Lennard-Jones sums on a cell grid: Warp
and NumPy only (no JAX; `jaxrt.backends.rt.ffi.cell_lj_sums` puts
`lj_sums` behind a JAX call).

The pipeline, one launch each (`lj_sums`; steps 1 to 4 are `sort_cells`,
which the SPH walks (`jaxrt.backends.cell.warp_sph`), the cluster walk
(`jaxrt.backends.cell.warp_cluster`) and the neighbour lists' walk
(`jaxrt.backends.cell.warp_rows`) share with the stencil's functions,
`stencil` and `stencil_functions`):

1. ``bin_particles``: each particle wrapped into the box on periodic axes,
   its cell's row-major key (x fastest) and its index.
2. ``wp.utils.radix_sort_pairs`` on (key, index), only the key's bits.
3. ``cell_table``: ``start[c]``, the first sorted particle of a cell ``>=
   c``, for every ``c`` in ``[0, T]``: cells ``a..b`` of one row hold the
   sorted range ``[start[a], start[b + 1])``.
4. ``gather``: wrapped positions (and radii) in sorted order, so that the
   threads of a warp read neighbouring particles.
5. ``pair_sums`` (`walk_kernel`): a thread per sorted particle walks its
   stencil: rows (y, z), each one contiguous range of x-adjacent cells (two
   where a periodic x row wraps), every pair met from both of its
   particles (no atomics), and writes its force to the caller's order.
   The flags that choose what is summed are compiled in.

The grid (per axis: origin, cell width, box side, cell count) is an input,
so that free axes can follow the particles' extent while the table keeps a
static size. Cells are at least the cutoff over the axis' reach ``a``
wide, and the stencil spans ``2 a + 1`` cells. On a periodic axis with
``2 a + 1`` cells or more each stencil cell is a distinct cell with a known
image (the neighbour row's shift by a box side); with fewer, the stencil
keeps each distinct cell once and the difference is rounded to its minimum
image (exact, as the cutoff is below half the side).
"""

import warp as wp

# No adjoints (the sums are their own derivatives), and the stencil's loops
# kept as loops: the unrolled walk took minutes to compile for the CPU.
# Fast math on CUDA: float32 reciprocals and divisions approximate to 2 ulp
# (as Triton's), well inside the float32 tolerances of the tests.
_OPTIONS = {"enable_backward": False, "max_unroll": 1, "fast_math": True}
wp.set_module_options(_OPTIONS)
# The same options, for walks built in other modules.
MODULE_OPTIONS = _OPTIONS

# Grid rows (`lj_sums`' ``grid``): origin, cell width, box side per axis.
ORIGIN, WIDTH, SIDE = 0, 1, 2
# `lj_sums`' ``params``.
SIGMA, EPSILON, R_ONSET, R_CUTOFF = 0, 1, 2, 3
N_PARAMS = 4
# `lj_sums`' ``flags`` bits; bits ``PERIODIC << a`` for axis ``a``.
HAS_RADII, DERIVATIVES, COUNT = 1, 2, 4
PERIODIC = 8


def _scalar_kernels(scalar):
    """Binning and gather (`lj_sums` steps 1 and 4) for positions of
    ``scalar`` (wp.float32 / wp.float64)."""
    vector = wp.types.vector(3, scalar)

    @wp.func
    def wrap(x: scalar, side: scalar, periodic: int):
        if periodic == 0:
            return x
        w = x - side * wp.floor(x / side)
        if w < scalar(0.0):
            w = w + side
        if w >= side:
            w = scalar(0.0)
        return w

    @wp.func
    def cell_of(x: scalar, origin: scalar, width: scalar, n: int):
        c = int(wp.floor((x - origin) / width))
        return wp.clamp(c, 0, n - 1)

    @wp.kernel
    def bin_particles(points: wp.array(dtype=vector),
                      grid: wp.array(dtype=vector),
                      cells: wp.array(dtype=wp.int32), flags: int,
                      wrapped: wp.array(dtype=vector),
                      keys: wp.array(dtype=wp.int32),
                      values: wp.array(dtype=wp.int32)):
        i = wp.tid()
        p = points[i]
        o, w, s = grid[ORIGIN], grid[WIDTH], grid[SIDE]
        x = wrap(p[0], s[0], (flags >> 3) & 1)
        y = wrap(p[1], s[1], (flags >> 4) & 1)
        z = wrap(p[2], s[2], (flags >> 5) & 1)
        wrapped[i] = vector(x, y, z)
        nx, ny, nz = cells[0], cells[1], cells[2]
        keys[i] = cell_of(x, o[0], w[0], nx) + nx * (
            cell_of(y, o[1], w[1], ny) + ny * cell_of(z, o[2], w[2], nz))
        values[i] = i

    @wp.kernel
    def gather(values: wp.array(dtype=wp.int32),
               wrapped: wp.array(dtype=vector),
               radii: wp.array(dtype=scalar), has_radii: int,
               position: wp.array(dtype=vector),
               radius: wp.array(dtype=scalar)):
        i = wp.tid()
        j = values[i]
        position[i] = wrapped[j]
        if has_radii != 0:
            radius[i] = radii[j]

    return dict(bin_particles=bin_particles, gather=gather)


@wp.func
def x_ranges_between(c: int, lo: int, hi: int, n: int, periodic: int,
                     rounded: int):
    """The x cells ``c + lo .. c + hi`` (``lo <= 0 <= hi``, ``hi - lo <
    n`` on a periodic axis that is not rounded) as up to two ranges with
    images: (lo0, hi0, image0, hi1, image1), the second range ``[0, hi1]``,
    empty (hi1 < 0) for one range."""
    lo0 = wp.max(c + lo, 0)
    hi0 = wp.min(c + hi, n - 1)
    ox0 = 0
    hi1 = -1
    ox1 = 0
    if periodic != 0:
        if rounded != 0:
            lo0 = 0
            hi0 = n - 1
        elif c + lo < 0:
            lo0 = c + lo + n
            hi0 = n - 1
            ox0 = -1
            hi1 = c + hi
        elif c + hi >= n:
            lo0 = c + lo
            hi0 = n - 1
            hi1 = c + hi - n
            ox1 = 1
    return lo0, hi0, ox0, hi1, ox1


@wp.func
def x_ranges(c: int, reach: int, n: int, periodic: int, rounded: int):
    """The stencil's x cells as up to two ranges with images: (lo0, hi0,
    image0, hi1, image1), the second range ``[0, hi1]``, empty (hi1 < 0)
    for one range."""
    return x_ranges_between(c, -reach, reach, n, periodic, rounded)


@wp.func
def row(c: int, d: int, n: int, periodic: int, reach: int):
    """(cell, image, valid) of the stencil row ``c + d`` on one axis."""
    t = c + d
    if periodic == 0:
        return t, 0, t >= 0 and t < n
    if n < 2 * reach + 1:  # each distinct cell once, differences rounded
        return (t + reach * n) % n, 0, d + reach < n
    if t < 0:
        return t + n, -1, True
    if t >= n:
        return t - n, 1, True
    return t, 0, True


@wp.struct
class Stencil:
    """A cell's stencil (`stencil`): the grid's cells ``nx, ny, nz``, the
    reach ``ay, az`` and periodic bits ``py, pz`` of the rows, the cell's
    ``cy, cz``, the rounded axes ``rx, ry, rz`` (periodic with too few
    cells for images), the x ranges of `x_ranges` and ``pieces``, the (y
    row, x range) pairs of a z row; the cell's ``cx``, the reach ``ax``
    and periodic bit ``px`` of x."""
    nx: wp.int32
    ny: wp.int32
    nz: wp.int32
    ay: wp.int32
    az: wp.int32
    py: wp.int32
    pz: wp.int32
    cy: wp.int32
    cz: wp.int32
    rx: wp.int32
    ry: wp.int32
    rz: wp.int32
    lo0: wp.int32
    hi0: wp.int32
    ox0: wp.int32
    hi1: wp.int32
    ox1: wp.int32
    pieces: wp.int32
    cx: wp.int32
    ax: wp.int32
    px: wp.int32


@wp.func
def stencil(flags: int, cells: wp.array(dtype=wp.int32), key: int):
    """The `Stencil` of cell ``key`` (row-major, x fastest) on the grid
    of ``cells`` (`lj_sums`' ``cells``, ``flags``' periodic bits)."""
    s = Stencil()
    nx, ny, nz = cells[0], cells[1], cells[2]
    ax, ay, az = cells[3], cells[4], cells[5]
    px, py, pz = (flags >> 3) & 1, (flags >> 4) & 1, (flags >> 5) & 1
    s.nx = nx
    s.ny = ny
    s.nz = nz
    s.ay = ay
    s.az = az
    s.py = py
    s.pz = pz
    s.cy = (key / nx) % ny
    s.cz = key / (nx * ny)
    s.rx = wp.where(px != 0 and nx < 2 * ax + 1, 1, 0)
    s.ry = wp.where(py != 0 and ny < 2 * ay + 1, 1, 0)
    s.rz = wp.where(pz != 0 and nz < 2 * az + 1, 1, 0)
    lo0, hi0, ox0, hi1, ox1 = x_ranges(key % nx, ax, nx, px, s.rx)
    s.lo0 = lo0
    s.hi0 = hi0
    s.ox0 = ox0
    s.hi1 = hi1
    s.ox1 = ox1
    # Two per y row (a constant divisor), the second empty for one range.
    s.pieces = (2 * ay + 1) * 2
    s.cx = key % nx
    s.ax = ax
    s.px = px
    return s


def stencil_functions(scalar):
    """The stencil walk's functions for ``scalar``, shared by every walk
    over the grid: ``span(s, start, side, dz, piece)``, the sorted range
    ``[first, end)`` of `Stencil` ``s``' z row ``dz`` and its ``piece``
    (y rows ascending, each x range in turn; empty off a free axis' end
    or past the x ranges) and the shift by which the particle meets it;
    ``difference(q, x, side, s)``, ``q - x`` rounded to its minimum image
    on ``s``' rounded axes, and its square. A walk::

        s = stencil(flags, cells, keys[i])
        for dz in range(-s.az, s.az + 1):
            for piece in range(s.pieces):
                first, end, shift = span(s, start, side, dz, piece)
                for j in range(first, end):
                    d, d2 = difference(p - shift, position[j], side, s)
    """
    vector = wp.types.vector(3, scalar)

    @wp.func
    def span(s: Stencil, start: wp.array(dtype=wp.int32), side: vector,
             dz: int, piece: int):
        part = piece % 2
        z, oz, okz = row(s.cz, dz, s.nz, s.pz, s.az)
        y, oy, oky = row(s.cy, piece / 2 - s.ay, s.ny, s.py, s.ay)
        lo = wp.where(part == 0, s.lo0, 0)
        hi = wp.where(part == 0, s.hi0, s.hi1)
        first = int(0)
        end = int(0)
        if okz and oky and hi >= lo:
            base = s.nx * (y + s.ny * z)
            first = start[base + lo]
            end = start[base + hi + 1]
        ox = wp.where(part == 0, s.ox0, s.ox1)
        return first, end, vector(scalar(ox) * side[0], scalar(oy) * side[1],
                                  scalar(oz) * side[2])

    @wp.func
    def rounded(d: scalar, side: scalar, on: int):
        if on != 0:
            return d - side * wp.round(d / side)
        return d

    @wp.func
    def difference(q: vector, x: vector, side: vector, s: Stencil):
        d = q - x
        d = vector(rounded(d[0], side[0], s.rx), rounded(d[1], side[1], s.ry),
                   rounded(d[2], side[2], s.rz))
        return d, wp.dot(d, d)

    return span, difference


def trim_functions(scalar):
    """The stencil's rows trimmed to the sphere the stencil covers, for
    ``scalar``: ``frame(s, p, grid, cells)``, a particle's `Trim`; and
    ``row_range(s, t, dy, dz)``, whether its stencil row ``(dy, dz)``
    comes within the sphere and the x cells ``lo..hi`` (relative to its
    own, ``-ax <= lo <= 0 <= hi <= ax``) that reach it (`x_ranges_between`
    makes them ranges). The sphere's radius is the least ``width * reach``
    of the trimmed axes (at least the cutoff, as every cell is at least
    cutoff / reach wide), widened by a margin for rounding: a row or cell
    is dropped only where no point of it is within that radius of the
    particle. Only periodic axes with images are trimmed (a free axis'
    edge cells also hold the particles clamped into them; a rounded
    axis' cells are each met once at the minimum image)."""
    vector = wp.types.vector(3, scalar)
    Trim = _TRIMS[scalar]

    @wp.func
    def frame(s: Stencil, p: vector, grid: wp.array(dtype=vector),
              cells: wp.array(dtype=wp.int32)):
        o, w, side = grid[ORIGIN], grid[WIDTH], grid[SIDE]
        f = p - vector(o[0] + scalar(s.cx) * w[0], o[1] + scalar(s.cy) * w[1],
                       o[2] + scalar(s.cz) * w[2])
        tx = wp.where(s.px != 0 and s.rx == 0, 1, 0)
        ty = wp.where(s.py != 0 and s.ry == 0, 1, 0)
        tz = wp.where(s.pz != 0 and s.rz == 0, 1, 0)
        big = scalar(3.0e38)
        radius = wp.min(
            wp.where(tx != 0, w[0] * scalar(cells[3]), big),
            wp.min(wp.where(ty != 0, w[1] * scalar(cells[4]), big),
                   wp.where(tz != 0, w[2] * scalar(cells[5]), big)))
        largest = wp.max(side[0], wp.max(side[1], side[2]))
        # Positions within a cell are good to a few ulp of the side.
        margin = wp.where(radius < big, radius * scalar(0.0009765625)
                          + largest * scalar(9.5367431640625e-07), scalar(0.0))
        reach = wp.where(radius < big, radius + margin, big)
        t = Trim()
        t.f = f
        t.w = w
        t.reach_sq = reach * reach
        t.margin = margin
        t.tx = tx
        t.ty = ty
        t.tz = tz
        return t

    @wp.func
    def gap(d: int, f: scalar, w: scalar, margin: scalar):
        # From the particle to the nearest point of the cells d away.
        g = scalar(0.0)
        if d > 0:
            g = scalar(d) * w - f
        if d < 0:
            g = f - scalar(d + 1) * w
        return wp.max(g - margin, scalar(0.0))

    @wp.func
    def row_range(s: Stencil, t: Trim, dy: int, dz: int):
        gy = wp.where(t.ty != 0, gap(dy, t.f[1], t.w[1], t.margin),
                      scalar(0.0))
        gz = wp.where(t.tz != 0, gap(dz, t.f[2], t.w[2], t.margin),
                      scalar(0.0))
        h2 = gy * gy + gz * gz
        lo = -s.ax
        hi = s.ax
        if t.tx != 0 and h2 < t.reach_sq:
            chord = wp.sqrt(t.reach_sq - h2) + t.margin
            lo = wp.min(wp.max(int(wp.floor((t.f[0] - chord) / t.w[0])),
                               -s.ax), 0)
            hi = wp.max(wp.min(int(wp.floor((t.f[0] + chord) / t.w[0])),
                               s.ax), 0)
        return h2 < t.reach_sq, lo, hi

    return frame, row_range


def _trim_struct(scalar):
    vector = wp.types.vector(3, scalar)

    class Trim:
        """A particle's frame for `trim_functions`: its offset ``f`` in
        its cell, the cell widths ``w``, the sphere's squared radius, the
        rounding margin and which axes ``tx, ty, tz`` are trimmed."""
        f: vector
        w: vector
        reach_sq: scalar
        margin: scalar
        tx: wp.int32
        ty: wp.int32
        tz: wp.int32

    Trim.__name__ = Trim.__qualname__ = f"Trim_{scalar.__name__}"
    return wp.struct(Trim)


_TRIMS = {t: _trim_struct(t) for t in (wp.float32, wp.float64)}


def pair_functions(scalar, static_bits, hoist):
    """The Lennard-Jones walks' pair terms for ``scalar`` (``static_bits``,
    ``hoist`` as `walk_kernel`'s): ``terms(d2, cut, cut2, sigma, epsilon,
    r_onset, r_cutoff, inverse_cube)``, a pair's energy, force factor,
    d/dsigma and d/depsilon at its cut (``cut2 = cut^2``; ``inverse_cube``
    the switch band's, ``(r_cutoff^2 - r_onset^2)^-3``). Every Lennard-Jones
    walk (`jaxrt.backends.cell.warp_cluster`'s too) adds these terms."""
    fast = (bool(hoist) and static_bits is not None
            and not int(static_bits) & HAS_RADII)

    @wp.func
    def lj(d2: scalar, sigma: scalar, epsilon: scalar, r_onset: scalar,
           r_cutoff: scalar, sigma_base: scalar):
        # The terms of `jaxrt.energy.listfree.lj.lj_terms` for one pair
        # inside the cut (d2 > 0): energy, force factor, d/dsigma_base,
        # d/depsilon.
        inverse = scalar(1.0) / d2
        idr = sigma * sigma * inverse
        idr6 = idr * idr * idr
        idr12 = idr6 * idr6
        lj_unit = scalar(4.0) * (idr12 - idr6)
        repulsion = scalar(24.0) * (scalar(2.0) * idr12 - idr6)
        rc2 = r_cutoff * r_cutoff
        ro2 = r_onset * r_onset
        switch = scalar(1.0)
        dswitch = scalar(0.0)
        if d2 >= ro2:
            width = rc2 - ro2
            inverse_cube = scalar(1.0) / (width * width * width)
            gap = rc2 - d2
            switch = gap * gap * (rc2 + scalar(2.0) * d2 - scalar(3.0) * ro2
                                  ) * inverse_cube
            dswitch = scalar(-6.0) * gap * (d2 - ro2) * inverse_cube
        e = switch * epsilon * lj_unit
        g = (switch * epsilon * repulsion * inverse
             - scalar(2.0) * dswitch * epsilon * lj_unit)
        return e, g, switch * epsilon * repulsion / sigma_base, switch * lj_unit

    @wp.func
    def lj_forces(d2: scalar, sigma2: scalar, epsilon: scalar, ro2: scalar,
                  rc2: scalar, inverse_cube: scalar):
        # `lj`'s energy and force factor at one cut (no radii), its
        # constants computed once per particle and the switch selected
        # rather than branched on (lanes of a warp straddle the onset).
        inverse = scalar(1.0) / d2
        idr = sigma2 * inverse
        idr6 = idr * idr * idr
        idr12 = idr6 * idr6
        lj_unit = scalar(4.0) * (idr12 - idr6)
        repulsion = scalar(24.0) * (scalar(2.0) * idr12 - idr6)
        gap = rc2 - d2
        inside = d2 >= ro2
        switch = wp.where(inside, gap * gap * (
            rc2 + scalar(2.0) * d2 - scalar(3.0) * ro2) * inverse_cube,
            scalar(1.0))
        dswitch = wp.where(inside, scalar(-6.0) * gap * (d2 - ro2)
                           * inverse_cube, scalar(0.0))
        return (switch * epsilon * lj_unit,
                switch * epsilon * repulsion * inverse
                - scalar(2.0) * dswitch * epsilon * lj_unit,
                switch * epsilon * repulsion, switch * lj_unit)

    @wp.func
    def terms(d2: scalar, cut: scalar, cut2: scalar, sigma: scalar,
              epsilon: scalar, r_onset: scalar, r_cutoff: scalar,
              inverse_cube: scalar):
        if wp.static(fast):
            e, g, ds, de = lj_forces(d2, sigma * sigma, epsilon,
                                     r_onset * r_onset, cut2, inverse_cube)
            return e, g, ds / sigma, de
        scale = cut / r_cutoff
        return lj(d2, sigma * scale, epsilon, r_onset * scale, cut, sigma)

    return terms


# The flag bits a walk may fix at compile time.
STATIC_BITS = HAS_RADII | DERIVATIVES | COUNT


def _walk_kernel(scalar, static_bits, hoist, trim):
    """The thread walk (`lj_sums` step 5) for positions of ``scalar``.

    ``trim``: each stencil row cut to the sphere it covers
    (`trim_functions`).
    ``static_bits``: the `STATIC_BITS` of ``flags`` fixed at compile time
    (the branches they guard compiled away), or None to read them from
    ``flags``. ``hoist`` (with ``static_bits`` and no radii): the pair
    terms by `lj_forces` (`pair_functions`).
    """
    vector = wp.types.vector(3, scalar)
    _, difference = stencil_functions(scalar)
    terms = pair_functions(scalar, static_bits, hoist)
    frame, row_range = trim_functions(scalar)
    generic = static_bits is None
    fixed = 0 if generic else int(static_bits)

    @wp.kernel(module="unique", module_options=_OPTIONS)
    def pair_sums(position: wp.array(dtype=vector),
                  keys: wp.array(dtype=wp.int32),
                  values: wp.array(dtype=wp.int32),
                  radius: wp.array(dtype=scalar),
                  start: wp.array(dtype=wp.int32),
                  grid: wp.array(dtype=vector),
                  cells: wp.array(dtype=wp.int32),
                  params: wp.array(dtype=scalar), flags: int,
                  forces: wp.array(dtype=vector),
                  energy: wp.array(dtype=scalar),
                  d_sigma: wp.array(dtype=scalar),
                  d_epsilon: wp.array(dtype=scalar),
                  count: wp.array(dtype=wp.int32)):
        i = wp.tid()
        low = flags & STATIC_BITS
        if wp.static(not generic):
            low = wp.static(fixed)
        has_radii = low & HAS_RADII
        derivatives = low & DERIVATIVES
        counting = low & COUNT
        side = grid[SIDE]
        sigma, epsilon = params[SIGMA], params[EPSILON]
        r_onset, r_cutoff = params[R_ONSET], params[R_CUTOFF]
        s = stencil(flags, cells, keys[i])
        p = position[i]
        ri = scalar(0.0)
        if has_radii != 0:
            ri = radius[i]
        cut2 = r_cutoff * r_cutoff
        band = cut2 - r_onset * r_onset
        inverse_cube = scalar(1.0) / (band * band * band)
        f = vector()
        e_sum = scalar(0.0)
        ds_sum = scalar(0.0)
        de_sum = scalar(0.0)
        hits = int(0)
        # `span`'s loops written out (each x range of a row in turn): its
        # pieces cost this walk 8 registers on sm_90 (64 to 72).
        if wp.static(trim):
            t = frame(s, p, grid, cells)
        for dz in range(-s.az, s.az + 1):
            z, oz, okz = row(s.cz, dz, s.nz, s.pz, s.az)
            if okz:
                for dy in range(-s.ay, s.ay + 1):
                    y, oy, oky = row(s.cy, dy, s.ny, s.py, s.ay)
                    # Fresh values (a field is a reference in Warp).
                    lo0 = s.lo0 + 0
                    hi0 = s.hi0 + 0
                    ox0 = s.ox0 + 0
                    hi1 = s.hi1 + 0
                    ox1 = s.ox1 + 0
                    if wp.static(trim):
                        near_row, dlo, dhi = row_range(s, t, dy, dz)
                        oky = oky and near_row
                        lo0, hi0, ox0, hi1, ox1 = x_ranges_between(
                            s.cx, dlo, dhi, s.nx, s.px, s.rx)
                    if oky:
                        base = s.nx * (y + s.ny * z)
                        for part in range(2):
                            lo = wp.where(part == 0, lo0, 0)
                            hi = wp.where(part == 0, hi0, hi1)
                            ox = wp.where(part == 0, ox0, ox1)
                            if hi >= lo:
                                q = p - vector(scalar(ox) * side[0],
                                               scalar(oy) * side[1],
                                               scalar(oz) * side[2])
                                for j in range(start[base + lo],
                                               start[base + hi + 1]):
                                    d, d2 = difference(q, position[j], side, s)
                                    cut = r_cutoff
                                    if has_radii != 0:
                                        cut = wp.max(ri, radius[j])
                                        cut2 = cut * cut
                                    # Coincident pairs count, with no terms.
                                    if counting != 0 and d2 < cut2 and j != i:
                                        hits = hits + 1
                                    if d2 < cut2 and d2 > scalar(0.0):
                                        e, g, ds, de = terms(
                                            d2, cut, cut2, sigma, epsilon,
                                            r_onset, r_cutoff, inverse_cube)
                                        f = f + g * d
                                        e_sum = e_sum + e
                                        if derivatives != 0:
                                            ds_sum = ds_sum + ds
                                            de_sum = de_sum + de
        forces[values[i]] = f
        energy[i] = e_sum
        d_sigma[i] = ds_sum
        d_epsilon[i] = de_sum
        count[i] = hits

    return pair_sums


_WALKS: dict = {}
# Stencil rows cut to the sphere they must cover (`trim_functions`): about
# a third fewer candidates with reach (4, 2, 2), but a warp still walks its
# longest lane's range (benchmarks/warp_stages.py measures both).
TRIM = False
# The walk's threads per block: small blocks let an SM mix more of them
# while the longest lanes of one finish (benchmarks/warp_stages.py).
WALK_BLOCK = 64


def walk_kernel(scalar, flags: int, *, specialize: bool = True,
                hoist: bool = True, trim: bool | None = None):
    """The walk for positions of ``scalar`` and ``flags``, built (and
    compiled) on first use: ``specialize`` fixes ``flags``' `STATIC_BITS`
    at compile time, ``hoist`` takes `lj_forces` where it can, ``trim``
    cuts each stencil row to the sphere it covers (`trim_functions`;
    `TRIM` by default) (`_walk_kernel`)."""
    bits = (int(flags) & STATIC_BITS) if specialize else None
    key = (scalar, bits, bool(hoist), TRIM if trim is None else bool(trim))
    if key not in _WALKS:
        _WALKS[key] = _walk_kernel(*key)
    return _WALKS[key]


@wp.kernel
def cell_table(keys: wp.array(dtype=wp.int32), n: int, table: int,
               start: wp.array(dtype=wp.int32)):
    """``start[c]``: thread ``t < n`` writes the cells between sorted
    particles ``t - 1``'s and ``t``'s keys; thread ``t <= table`` past the
    last key writes ``n`` there (launch ``table_threads(n, table)``)."""
    t = wp.tid()
    if t < n:
        previous = int(-1)
        if t > 0:
            previous = keys[t - 1]
        for c in range(previous + 1, keys[t] + 1):
            start[c] = t
    # The tail past the last key is most of the table where the grid has
    # fewer cells than the table holds: a thread per entry, not one thread
    # looping over all of them (serial on a GPU).
    if t <= table and t > keys[n - 1]:
        start[t] = n


def table_threads(n: int, table: int) -> int:
    """`cell_table`'s launch size for ``n >= 1`` sorted keys and a table
    of ``table + 1`` entries."""
    return max(n, table + 1)


KERNELS = {t: _scalar_kernels(t) for t in (wp.float32, wp.float64)}


def scalar_of(vector) -> type:
    """wp.float32 or wp.float64, the scalar of a vec3 type."""
    return vector._wp_scalar_type_


def sort_cells(points, radii, grid, cells, flags: int, *, keys, values,
               wrapped, start, position, radius) -> None:
    """Steps 1 to 4 of the module docstring (bin, sort, cell table,
    gather) on ``points``' device: what every walk over the grid reads.

    Args: as `lj_sums`' (``flags``: `HAS_RADII` and ``PERIODIC << axis``
    are read). Fills ``keys[:N]`` (sorted cell keys), ``values[:N]`` (the
    caller's index of each sorted particle), ``start``, ``position``
    (wrapped, sorted) and, with radii, ``radius`` (sorted).
    """
    n = points.shape[0]
    if n == 0:
        return
    device = points.device
    k = KERNELS[scalar_of(points.dtype)]
    table = start.shape[0] - 1
    wp.launch(k["bin_particles"], dim=n, device=device,
              inputs=[points, grid, cells, flags, wrapped, keys, values])
    wp.utils.radix_sort_pairs(keys, values, n,
                              end_bit=max(1, int(table).bit_length()))
    wp.launch(cell_table, dim=table_threads(n, table), device=device,
              inputs=[keys, n, table, start])
    wp.launch(k["gather"], dim=n, device=device,
              inputs=[values, wrapped, radii, flags & HAS_RADII, position,
                      radius])


def lj_sums(points, radii, grid, cells, params, flags: int, *, forces,
            energy, d_sigma, d_epsilon, count, keys, values, wrapped, start,
            position, radius, specialize: bool = True,
            hoist: bool = True, block_dim: int = WALK_BLOCK) -> None:
    """Launch the pipeline of the module docstring on ``points``' device.

    Args:
      points: vec3 ``(N,)`` Cartesian positions (padding axes all equal).
      radii: scalar ``(N,)`` per-particle cutoffs (``flags & HAS_RADII``),
        else anything of that type.
      grid: vec3 ``(3,)`` rows `ORIGIN`, `WIDTH` (>= the largest cut
        over the axis' reach), `SIDE` (1 on free axes); cells: int32
        ``(6,)``, cells per axis (x, y, z), their product ``T`` at most
        ``start``'s size - 1, then the stencil's reach in cells per axis.
      params: scalar ``(N_PARAMS,)``; flags: `HAS_RADII`, `DERIVATIVES`,
        `COUNT`, ``PERIODIC << axis``.
      forces: vec3 ``(N,)`` out, caller's order; energy, d_sigma, d_epsilon:
        scalar ``(N,)`` out, count int32 ``(N,)`` out: per sorted particle,
        the sums over all its pairs (each pair in two particles' sums).
      keys, values: int32 ``(2N,)`` scratch (the sort's); wrapped,
        position: vec3 ``(N,)`` scratch; start: int32 ``(T + 1,)`` at
        least; radius: scalar ``(N,)`` scratch (or ``(1,)`` without radii).
      specialize, hoist: `walk_kernel`'s (the same sums to rounding);
      block_dim: the walk's threads per block.
    """
    n = points.shape[0]
    if n == 0:
        return
    device = points.device
    sort_cells(points, radii, grid, cells, flags, keys=keys, values=values,
               wrapped=wrapped, start=start, position=position, radius=radius)
    walk = walk_kernel(scalar_of(points.dtype), flags, specialize=specialize,
                       hoist=hoist)
    wp.launch(walk, dim=n, device=device, block_dim=block_dim,
              inputs=[position, keys, values, radius, start, grid, cells,
                      params, flags, forces, energy, d_sigma, d_epsilon,
                      count])
