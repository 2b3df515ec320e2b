"""The cluster walk of the list-free Lennard-Jones sums: Warp and NumPy only
(no JAX; `jaxrt.backends.rt.ffi.cell_lj_sums` with ``walk="cluster"`` puts
`lj_sums` behind a JAX call).

`jaxrt.backends.cell.warp_kernels.lj_sums` walks the stencil once per
sorted particle. Particles of one cell share their stencil, so here a
thread walks it once for a *cluster*: up to ``size`` consecutive sorted
particles of one cell (a cell of 13 particles and ``size`` 8 holds
clusters of 8 and 5). The thread keeps the cluster's positions in
registers, loads each candidate once and tests it against every particle
of the cluster; candidates farther than the cut from the cluster's
bounding box are skipped before that (``prune``). Each particle adds the
same terms in the same order as in the thread walk, so the sums are the
thread walk's (bit for bit where the compiler contracts both alike).

The pipeline after `jaxrt.backends.cell.warp_kernels.prepare` (bin, sort,
cell table, gather):

1. ``cluster_counts``: clusters per cell, ``ceil(n_c / size)``.
2. ``wp.utils.array_scan`` (exclusive): each cell's first cluster, and at
   the table's end the number of clusters.
3. ``cluster_table``: each cluster's first sorted particle (``clusters``;
   a cluster ends where the next one starts, the last at ``N``).
4. ``cluster_sums``: a thread per cluster, launched for a bound on their
   number (``N / size`` plus the non-empty cells) and idle past it.

Pruning is exact: a candidate's distance to the box, computed with the
operations of the pairs' differences, rounds no larger than its distance
to any particle of the box (rounding is monotonic), so a skipped
candidate is outside every particle's cut. Axes whose differences are
rounded to their minimum image (small periodic boxes) are not pruned.
"""

import warp as wp

from jaxrt.backends.cell import warp_kernels as wk

# As warp_kernels' walk; the cluster's loop unrolled on CUDA only (its
# registers then stay registers), kept a loop on the CPU (compile time).
_OPTIONS = {"enable_backward": False, "max_unroll": 1, "fast_math": True}
wp.set_module_options(_OPTIONS)
# Particles per cluster: the sizes a walk may be built for.
SIZES = (1, 2, 4, 8, 16)
CLUSTER_SIZE = 8
# Threads per block of the cluster walk (a thread carries ``size``
# particles' sums, so fewer threads than the thread walk's fill an SM).
CLUSTER_BLOCK = 64


@wp.kernel
def cluster_counts(start: wp.array(dtype=wp.int32), table: int, size: int,
                   counts: wp.array(dtype=wp.int32)):
    """``counts[c]``: cell ``c``'s clusters, zero at ``c = table`` (a
    thread per ``c`` in ``[0, table]``)."""
    c = wp.tid()
    m = int(0)
    if c < table:
        m = (start[c + 1] - start[c] + size - 1) / size
    counts[c] = m


@wp.kernel
def cluster_table(start: wp.array(dtype=wp.int32),
                  offsets: wp.array(dtype=wp.int32), table: int, size: int,
                  n: int, clusters: wp.array(dtype=wp.int32)):
    """``clusters[offsets[c] + m] = start[c] + m size`` for cell ``c``'s
    clusters, and ``clusters[total] = n`` (a thread per ``c`` in ``[0,
    table]``; ``offsets``: the exclusive scan of `cluster_counts`)."""
    c = wp.tid()
    if c == table:
        clusters[offsets[table]] = n
    else:
        first = start[c]
        for m in range(offsets[c + 1] - offsets[c]):
            clusters[offsets[c] + m] = first + m * size


def bound(n: int, table: int, size: int) -> int:
    """Static: at most this many clusters for ``n`` particles in ``table``
    cells (each non-empty cell adds at most one partial cluster)."""
    return max(1, min(n, -(-n // size) + min(table, n)))


def _cluster_kernel(scalar, static_bits, hoist, size, prune, unroll):
    """The cluster walk (module docstring) for positions of ``scalar``;
    ``static_bits``/``hoist`` as `warp_kernels.walk_kernel`'s, ``size``
    particles per cluster, ``prune`` the bounding-box test, ``unroll`` the
    loops over the cluster unrolled."""
    vector = wp.types.vector(3, scalar)
    sums_t = wp.types.vector(size, scalar)
    hits_t = wp.types.vector(size, wp.int32)
    points_t = wp.types.matrix((size, 3), scalar)
    lj, lj_forces, x_ranges, row, rounded = wk.pair_functions(scalar)
    generic = static_bits is None
    fixed = 0 if generic else int(static_bits)
    fast = bool(hoist) and not generic and not fixed & wk.HAS_RADII
    options = dict(_OPTIONS, max_unroll=size if unroll else 1)
    # Larger than any coordinate (the box of an empty slot never counts).
    huge = 1e30 if scalar == wp.float32 else 1e300

    @wp.func
    def gap(lo: scalar, hi: scalar, x: scalar, off: int):
        # The distance from x to [lo, hi] (zero inside, or on a rounded
        # axis), as the pairs' differences round it.
        g = scalar(0.0)
        if off == 0:
            if x < lo:
                g = lo - x
            elif x > hi:
                g = x - hi
        return g

    @wp.kernel(module="unique", module_options=options)
    def cluster_sums(position: wp.array(dtype=vector),
                     keys: wp.array(dtype=wp.int32),
                     values: wp.array(dtype=wp.int32),
                     radius: wp.array(dtype=scalar),
                     start: wp.array(dtype=wp.int32),
                     offsets: wp.array(dtype=wp.int32), table: int,
                     clusters: wp.array(dtype=wp.int32),
                     grid: wp.array(dtype=vector),
                     cells: wp.array(dtype=wp.int32),
                     params: wp.array(dtype=scalar), flags: int,
                     forces: wp.array(dtype=vector),
                     energy: wp.array(dtype=scalar),
                     d_sigma: wp.array(dtype=scalar),
                     d_epsilon: wp.array(dtype=scalar),
                     count: wp.array(dtype=wp.int32)):
        cluster = wp.tid()
        if cluster >= offsets[table]:
            return
        first = clusters[cluster]
        members = clusters[cluster + 1] - first
        low = flags & wk.STATIC_BITS
        if wp.static(not generic):
            low = wp.static(fixed)
        has_radii = low & wk.HAS_RADII
        derivatives = low & wk.DERIVATIVES
        counting = low & wk.COUNT
        px, py, pz = (flags >> 3) & 1, (flags >> 4) & 1, (flags >> 5) & 1
        nx, ny, nz = cells[0], cells[1], cells[2]
        ax, ay, az = cells[3], cells[4], cells[5]
        side = grid[wk.SIDE]
        sigma, epsilon = params[wk.SIGMA], params[wk.EPSILON]
        r_onset, r_cutoff = params[wk.R_ONSET], params[wk.R_CUTOFF]
        ry = wp.where(py != 0 and ny < 2 * ay + 1, 1, 0)
        rz = wp.where(pz != 0 and nz < 2 * az + 1, 1, 0)
        rx = wp.where(px != 0 and nx < 2 * ax + 1, 1, 0)
        key = keys[first]
        cx = key % nx
        cy = (key / nx) % ny
        cz = key / (nx * ny)
        # The cluster in registers: positions, cuts and bounding box.
        p = points_t()
        r = sums_t()
        big = scalar(wp.static(huge))
        lo = vector(big, big, big)
        hi = -lo
        r_max = r_cutoff
        for k in range(wp.static(size)):
            if k < members:
                q = position[first + k]
                p[k] = q
                lo = wp.min(lo, q)
                hi = wp.max(hi, q)
                if has_radii != 0:
                    r[k] = radius[first + k]
        if has_radii != 0:
            r_max = r[0]
            for k in range(1, wp.static(size)):
                if k < members:
                    r_max = wp.max(r_max, r[k])
        cut2 = r_cutoff * r_cutoff
        sigma2 = sigma * sigma
        ro2 = r_onset * r_onset
        band = cut2 - ro2
        inverse_cube = scalar(1.0) / (band * band * band)
        f = points_t()
        e_sum = sums_t()
        ds_sum = sums_t()
        de_sum = sums_t()
        hits = hits_t()
        lo0, hi0, ox0, lo1, hi1, ox1 = x_ranges(cx, ax, nx, px, rx)
        # A loop bound read at run time: kept a loop where ``size`` unrolls.
        parts = wp.where(hi1 >= lo1, 2, 1)
        for dz in range(-az, az + 1):
            z, oz, okz = row(cz, dz, nz, pz, az)
            if okz:
                for dy in range(-ay, ay + 1):
                    y, oy, oky = row(cy, dy, ny, py, ay)
                    if oky:
                        base = nx * (y + ny * z)
                        for part in range(parts):
                            lo_x = wp.where(part == 0, lo0, lo1)
                            hi_x = wp.where(part == 0, hi0, hi1)
                            ox = wp.where(part == 0, ox0, ox1)
                            shift = vector(scalar(ox) * side[0],
                                           scalar(oy) * side[1],
                                           scalar(oz) * side[2])
                            box_lo = lo - shift
                            box_hi = hi - shift
                            for j in range(start[base + lo_x],
                                           start[base + hi_x + 1]):
                                pj = position[j]
                                rj = scalar(0.0)
                                cut_j = r_cutoff
                                if has_radii != 0:
                                    rj = radius[j]
                                    cut_j = wp.max(r_max, rj)
                                visit = True
                                if wp.static(prune):
                                    g = vector(gap(box_lo[0], box_hi[0],
                                                   pj[0], rx),
                                               gap(box_lo[1], box_hi[1],
                                                   pj[1], ry),
                                               gap(box_lo[2], box_hi[2],
                                                   pj[2], rz))
                                    visit = wp.dot(g, g) < cut_j * cut_j
                                if visit:
                                    for k in range(wp.static(size)):
                                        if k < members:
                                            d = (p[k] - shift) - pj
                                            d = vector(
                                                rounded(d[0], side[0], rx),
                                                rounded(d[1], side[1], ry),
                                                rounded(d[2], side[2], rz))
                                            d2 = wp.dot(d, d)
                                            cut = r_cutoff
                                            if has_radii != 0:
                                                cut = wp.max(r[k], rj)
                                                cut2 = cut * cut
                                            if (counting != 0 and d2 < cut2
                                                    and j != first + k):
                                                hits[k] = hits[k] + 1
                                            if (d2 < cut2
                                                    and d2 > scalar(0.0)):
                                                if wp.static(fast):
                                                    e, gf, ds, de = lj_forces(
                                                        d2, sigma2, epsilon,
                                                        ro2, cut2,
                                                        inverse_cube)
                                                    ds = ds / sigma
                                                else:
                                                    scale = cut / r_cutoff
                                                    e, gf, ds, de = lj(
                                                        d2, sigma * scale,
                                                        epsilon,
                                                        r_onset * scale, cut,
                                                        sigma)
                                                f[k] = f[k] + gf * d
                                                e_sum[k] = e_sum[k] + e
                                                if derivatives != 0:
                                                    ds_sum[k] = ds_sum[k] + ds
                                                    de_sum[k] = de_sum[k] + de
        for k in range(wp.static(size)):
            if k < members:
                i = first + k
                forces[values[i]] = vector(f[k, 0], f[k, 1], f[k, 2])
                energy[i] = e_sum[k]
                d_sigma[i] = ds_sum[k]
                d_epsilon[i] = de_sum[k]
                count[i] = hits[k]

    return cluster_sums


_WALKS: dict = {}


def cluster_kernel(scalar, flags: int, *, size: int = CLUSTER_SIZE,
                   prune: bool = True, unroll: bool = False,
                   specialize: bool = True, hoist: bool = True):
    """The cluster walk for positions of ``scalar`` and ``flags``, built
    (and compiled) on first use (`_cluster_kernel`; ``specialize`` and
    ``hoist`` as `warp_kernels.walk_kernel`'s)."""
    if size not in SIZES:
        raise ValueError(f"cluster size={size!r}: choose one of {SIZES}.")
    bits = (int(flags) & wk.STATIC_BITS) if specialize else None
    key = (scalar, bits, bool(hoist), int(size), bool(prune), bool(unroll))
    if key not in _WALKS:
        _WALKS[key] = _cluster_kernel(scalar, bits, bool(hoist), int(size),
                                      bool(prune), bool(unroll))
    return _WALKS[key]


def build_clusters(start, counts, offsets, clusters, *, n: int,
                   size: int = CLUSTER_SIZE) -> None:
    """Steps 1 to 3 of the module docstring: the cluster table of the
    cell table ``start`` (int32 ``(T + 1,)``) of ``n`` sorted particles.
    ``counts``, ``offsets``: int32 ``(T + 1,)`` scratch / out (``offsets
    [T]`` the number of clusters); ``clusters``: int32 ``(bound + 1,)``
    out (`bound`)."""
    device = start.device
    table = start.shape[0] - 1
    wp.launch(cluster_counts, dim=table + 1, device=device,
              inputs=[start, table, size, counts])
    wp.utils.array_scan(counts, offsets, inclusive=False)
    wp.launch(cluster_table, dim=table + 1, device=device,
              inputs=[start, offsets, table, size, n, clusters])


def launch_walk(walk, *, position, keys, values, radius, start, offsets,
                clusters, grid, cells, params, flags: int, forces, energy,
                d_sigma, d_epsilon, count, size: int = CLUSTER_SIZE,
                block_dim: int = CLUSTER_BLOCK) -> None:
    """Step 4: ``walk`` (`cluster_kernel`) over the bound on the clusters."""
    n = position.shape[0]
    table = start.shape[0] - 1
    wp.launch(walk, dim=bound(n, table, size), device=position.device,
              block_dim=block_dim,
              inputs=[position, keys, values, radius, start, offsets, table,
                      clusters, grid, cells, params, flags, forces, energy,
                      d_sigma, d_epsilon, count])


def lj_sums(points, radii, grid, cells, params, flags: int, *, forces,
            energy, d_sigma, d_epsilon, count, keys, values, wrapped, start,
            position, radius, counts, offsets, clusters,
            size: int = CLUSTER_SIZE, prune: bool = True,
            specialize: bool = True, hoist: bool = True,
            block_dim: int | None = None, native: bool = False) -> None:
    """`jaxrt.backends.cell.warp_kernels.lj_sums` with the cluster walk:
    the same arguments and outputs, and

    Args:
      counts, offsets: int32 ``(T + 1,)`` scratch, ``T`` ``start``'s size
        less one; clusters: int32 ``(bound(N, T, size) + 1,)`` scratch.
      size: particles per cluster (`SIZES`); prune: skip candidates beyond
        the cut of the cluster's bounding box; block_dim: threads per
        block (None: `CLUSTER_BLOCK`, `NATIVE_BLOCK`). The loops over a
        cluster are unrolled on CUDA.
      native: on CUDA, the warp-cooperative walk (a warp per cluster,
        `NATIVE_SIZES`, always pruned); elsewhere the cluster walk.
    """
    n = points.shape[0]
    if n == 0:
        return
    wk.sort_cells(points, radii, grid, cells, flags, keys=keys,
                  values=values, wrapped=wrapped, start=start,
                  position=position, radius=radius)
    build_clusters(start, counts, offsets, clusters, n=n, size=size)
    if native and points.device.is_cuda:
        walk = native_kernel(wk.scalar_of(points.dtype), flags, size=size,
                             specialize=specialize, hoist=hoist)
        launch_native(walk, position=position, keys=keys, values=values,
                      radius=radius, start=start, offsets=offsets,
                      clusters=clusters, grid=grid, cells=cells,
                      params=params, flags=flags, forces=forces,
                      energy=energy, d_sigma=d_sigma, d_epsilon=d_epsilon,
                      count=count, size=size,
                      block_dim=block_dim or NATIVE_BLOCK)
        return
    walk = cluster_kernel(wk.scalar_of(points.dtype), flags, size=size,
                          prune=prune, unroll=points.device.is_cuda,
                          specialize=specialize, hoist=hoist)
    launch_walk(walk, position=position, keys=keys, values=values,
                radius=radius, start=start, offsets=offsets,
                clusters=clusters, grid=grid, cells=cells, params=params,
                flags=flags, forces=forces, energy=energy, d_sigma=d_sigma,
                d_epsilon=d_epsilon, count=count, size=size,
                block_dim=block_dim or CLUSTER_BLOCK)


# ---------------------------------------------------------------------------
# The warp-cooperative cluster walk (CUDA only; ``native=True``).
#
# A warp of 32 threads per cluster of ``size`` particles: lane ``l`` holds
# particle ``l % size`` of the cluster and is slot ``l // size`` of ``32 /
# size``. The warp reads each stencil row in chunks of 32 candidates (one
# per lane, coalesced), tests them against the cluster's bounding box,
# and compacts the survivors with a ballot; each step then hands one
# survivor to every slot (a shuffle from its lane), so the ``size`` lanes
# of a slot test it against the cluster. The slots' sums are added by
# shuffles at the end. Each particle adds the thread walk's terms, in
# another order (the sums agree to rounding, not bit for bit). Warp's
# CPU device runs no warps: `lj_sums` takes the cluster walk there, and
# the tests run this kernel built for one lane (``lanes=1``: the
# shuffles and ballots of a lone lane, everything else as on CUDA).

_LANES = 32


@wp.func_native("""
#if defined(__CUDA_ARCH__)
return (int)__ballot_sync(0xffffffffu, pred != 0);
#else
return pred != 0 ? 1 : 0;
#endif
""")
def _ballot(pred: int) -> int:
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
return __ffs(mask) - 1;
#else
return mask == 0 ? -1 : __builtin_ctz((unsigned)mask);
#endif
""")
def _lowest(mask: int) -> int:
    ...


@wp.func_native("""
unsigned m = (unsigned)mask;
return (int)(m & (m - 1u));
""")
def _drop_lowest(mask: int) -> int:
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
return __shfl_sync(0xffffffffu, x, lane);
#else
return x;
#endif
""")
def _shfl_i(x: int, lane: int) -> int:
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
return __shfl_sync(0xffffffffu, x, lane);
#else
return x;
#endif
""")
def _shfl_f32(x: wp.float32, lane: int) -> wp.float32:
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
return __shfl_sync(0xffffffffu, x, lane);
#else
return x;
#endif
""")
def _shfl_f64(x: wp.float64, lane: int) -> wp.float64:
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
return __shfl_xor_sync(0xffffffffu, x, m);
#else
return x;
#endif
""")
def _xor_i(x: int, m: int) -> int:
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
return __shfl_xor_sync(0xffffffffu, x, m);
#else
return x;
#endif
""")
def _xor_f32(x: wp.float32, m: int) -> wp.float32:
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
return __shfl_xor_sync(0xffffffffu, x, m);
#else
return x;
#endif
""")
def _xor_f64(x: wp.float64, m: int) -> wp.float64:
    ...


# Sizes of the warp-cooperative walk: a whole number of slots per warp.
NATIVE_SIZES = (4, 8, 16, 32)
# Threads per block of the warp-cooperative walk (whole warps).
NATIVE_BLOCK = 128


def _native_kernel(scalar, static_bits, hoist, size, lanes):
    """The warp-cooperative walk (the section's comment) for positions of
    ``scalar``; ``static_bits``/``hoist`` as `warp_kernels.walk_kernel`'s,
    ``size`` particles per cluster, ``lanes`` threads per cluster (32 on
    CUDA)."""
    vector = wp.types.vector(3, scalar)
    lj, lj_forces, x_ranges, row, rounded = wk.pair_functions(scalar)
    generic = static_bits is None
    fixed = 0 if generic else int(static_bits)
    fast = bool(hoist) and not generic and not fixed & wk.HAS_RADII
    shfl = _shfl_f32 if scalar == wp.float32 else _shfl_f64
    xor = _xor_f32 if scalar == wp.float32 else _xor_f64
    slots = lanes // size
    huge = 1e30 if scalar == wp.float32 else 1e300

    @wp.func
    def gap(lo: scalar, hi: scalar, x: scalar, off: int):
        g = scalar(0.0)
        if off == 0:
            if x < lo:
                g = lo - x
            elif x > hi:
                g = x - hi
        return g

    @wp.func
    def box_min(x: scalar, m: int):
        # The least of ``x`` over the lanes of this lane's slot.
        y = x
        s = int(1)
        while s < m:
            y = wp.min(y, xor(y, s))
            s = s * 2
        return y

    @wp.func
    def box_max(x: scalar, m: int):
        y = x
        s = int(1)
        while s < m:
            y = wp.max(y, xor(y, s))
            s = s * 2
        return y

    @wp.func
    def slot_sum(x: scalar, m: int):
        # The sum of ``x`` over the slots (lanes ``m`` apart).
        y = x
        s = int(m)
        while s < wp.static(lanes):
            y = y + xor(y, s)
            s = s * 2
        return y

    @wp.kernel(module="unique", module_options=_OPTIONS)
    def native_sums(position: wp.array(dtype=vector),
                    keys: wp.array(dtype=wp.int32),
                    values: wp.array(dtype=wp.int32),
                    radius: wp.array(dtype=scalar),
                    start: wp.array(dtype=wp.int32),
                    offsets: wp.array(dtype=wp.int32), table: int,
                    clusters: wp.array(dtype=wp.int32),
                    grid: wp.array(dtype=vector),
                    cells: wp.array(dtype=wp.int32),
                    params: wp.array(dtype=scalar), flags: int,
                    forces: wp.array(dtype=vector),
                    energy: wp.array(dtype=scalar),
                    d_sigma: wp.array(dtype=scalar),
                    d_epsilon: wp.array(dtype=scalar),
                    count: wp.array(dtype=wp.int32)):
        tid = wp.tid()
        cluster = tid / wp.static(lanes)
        lane = tid % wp.static(lanes)
        # Warp-uniform: every lane of a warp leaves here or none does.
        if cluster >= offsets[table]:
            return
        first = clusters[cluster]
        members = clusters[cluster + 1] - first
        k = lane % wp.static(size)
        slot = lane / wp.static(size)
        mine = k < members
        i = first + wp.min(k, members - 1)
        low = flags & wk.STATIC_BITS
        if wp.static(not generic):
            low = wp.static(fixed)
        has_radii = low & wk.HAS_RADII
        derivatives = low & wk.DERIVATIVES
        counting = low & wk.COUNT
        px, py, pz = (flags >> 3) & 1, (flags >> 4) & 1, (flags >> 5) & 1
        nx, ny, nz = cells[0], cells[1], cells[2]
        ax, ay, az = cells[3], cells[4], cells[5]
        side = grid[wk.SIDE]
        sigma, epsilon = params[wk.SIGMA], params[wk.EPSILON]
        r_onset, r_cutoff = params[wk.R_ONSET], params[wk.R_CUTOFF]
        ry = wp.where(py != 0 and ny < 2 * ay + 1, 1, 0)
        rz = wp.where(pz != 0 and nz < 2 * az + 1, 1, 0)
        rx = wp.where(px != 0 and nx < 2 * ax + 1, 1, 0)
        key = keys[first]
        cx = key % nx
        cy = (key / nx) % ny
        cz = key / (nx * ny)
        # Lanes past the cluster's end repeat its last particle: the box
        # and the cut's bound are the cluster's; they add nothing.
        p = position[i]
        ri = scalar(0.0)
        if has_radii != 0:
            ri = radius[i]
        lo = vector(box_min(p[0], wp.static(size)),
                    box_min(p[1], wp.static(size)),
                    box_min(p[2], wp.static(size)))
        hi = vector(box_max(p[0], wp.static(size)),
                    box_max(p[1], wp.static(size)),
                    box_max(p[2], wp.static(size)))
        r_max = box_max(ri, wp.static(size))
        cut2 = r_cutoff * r_cutoff
        sigma2 = sigma * sigma
        ro2 = r_onset * r_onset
        band = cut2 - ro2
        inverse_cube = scalar(1.0) / (band * band * band)
        f = vector()
        e_sum = scalar(0.0)
        ds_sum = scalar(0.0)
        de_sum = scalar(0.0)
        hits = int(0)
        lo0, hi0, ox0, lo1, hi1, ox1 = x_ranges(cx, ax, nx, px, rx)
        parts = wp.where(hi1 >= lo1, 2, 1)
        for dz in range(-az, az + 1):
            z, oz, okz = row(cz, dz, nz, pz, az)
            if okz:
                for dy in range(-ay, ay + 1):
                    y, oy, oky = row(cy, dy, ny, py, ay)
                    if oky:
                        base = nx * (y + ny * z)
                        for part in range(parts):
                            lo_x = wp.where(part == 0, lo0, lo1)
                            hi_x = wp.where(part == 0, hi0, hi1)
                            ox = wp.where(part == 0, ox0, ox1)
                            shift = vector(scalar(ox) * side[0],
                                           scalar(oy) * side[1],
                                           scalar(oz) * side[2])
                            box_lo = lo - shift
                            box_hi = hi - shift
                            q = p - shift
                            begin = start[base + lo_x]
                            end = start[base + hi_x + 1]
                            for chunk in range(begin, end, wp.static(lanes)):
                                # One candidate per lane, kept if it is
                                # within the cut of the box.
                                j = chunk + lane
                                keep = int(0)
                                pj = vector()
                                rj = scalar(0.0)
                                if j < end:
                                    pj = position[j]
                                    cut_j = r_cutoff
                                    if has_radii != 0:
                                        rj = radius[j]
                                        cut_j = wp.max(r_max, rj)
                                    g = vector(gap(box_lo[0], box_hi[0],
                                                   pj[0], rx),
                                               gap(box_lo[1], box_hi[1],
                                                   pj[1], ry),
                                               gap(box_lo[2], box_hi[2],
                                                   pj[2], rz))
                                    if wp.dot(g, g) < cut_j * cut_j:
                                        keep = 1
                                mask = _ballot(keep)
                                while mask != 0:
                                    # A survivor for each slot (-1: none).
                                    source = int(-1)
                                    for s in range(wp.static(slots)):
                                        low_bit = _lowest(mask)
                                        if s == slot:
                                            source = low_bit
                                        mask = _drop_lowest(mask)
                                    src = wp.max(source, 0)
                                    qj = vector(shfl(pj[0], src),
                                                shfl(pj[1], src),
                                                shfl(pj[2], src))
                                    jj = _shfl_i(j, src)
                                    rjj = rj
                                    if has_radii != 0:
                                        rjj = shfl(rj, src)
                                    if source >= 0 and mine:
                                        d = q - qj
                                        d = vector(
                                            rounded(d[0], side[0], rx),
                                            rounded(d[1], side[1], ry),
                                            rounded(d[2], side[2], rz))
                                        d2 = wp.dot(d, d)
                                        cut = r_cutoff
                                        if has_radii != 0:
                                            cut = wp.max(ri, rjj)
                                            cut2 = cut * cut
                                        if (counting != 0 and d2 < cut2
                                                and jj != i):
                                            hits = hits + 1
                                        if d2 < cut2 and d2 > scalar(0.0):
                                            if wp.static(fast):
                                                e, gf, ds, de = lj_forces(
                                                    d2, sigma2, epsilon, ro2,
                                                    cut2, inverse_cube)
                                                ds = ds / sigma
                                            else:
                                                scale = cut / r_cutoff
                                                e, gf, ds, de = lj(
                                                    d2, sigma * scale,
                                                    epsilon, r_onset * scale,
                                                    cut, sigma)
                                            f = f + gf * d
                                            e_sum = e_sum + e
                                            if derivatives != 0:
                                                ds_sum = ds_sum + ds
                                                de_sum = de_sum + de
        # Every lane adds its slots' sums (uniform shuffles), slot 0 writes.
        f = vector(slot_sum(f[0], wp.static(size)),
                   slot_sum(f[1], wp.static(size)),
                   slot_sum(f[2], wp.static(size)))
        e_sum = slot_sum(e_sum, wp.static(size))
        if derivatives != 0:
            ds_sum = slot_sum(ds_sum, wp.static(size))
            de_sum = slot_sum(de_sum, wp.static(size))
        if counting != 0:
            s = int(wp.static(size))
            while s < wp.static(lanes):
                hits = hits + _xor_i(hits, s)
                s = s * 2
        if mine and slot == 0:
            forces[values[i]] = f
            energy[i] = e_sum
            d_sigma[i] = ds_sum
            d_epsilon[i] = de_sum
            count[i] = hits

    return native_sums


def native_kernel(scalar, flags: int, *, size: int = CLUSTER_SIZE,
                  specialize: bool = True, hoist: bool = True,
                  lanes: int = _LANES):
    """The warp-cooperative walk for positions of ``scalar`` and
    ``flags``, built on first use (`_native_kernel`): for CUDA, or with
    ``lanes=1`` (and ``size=1``) for any device."""
    if lanes == _LANES and size not in NATIVE_SIZES:
        raise ValueError(f"native cluster size={size!r}: choose one of "
                         f"{NATIVE_SIZES}.")
    if lanes not in (1, _LANES) or lanes % size:
        raise ValueError(f"native lanes={lanes!r}, size={size!r}: lanes is "
                         f"{_LANES} (or 1, tests), a multiple of size.")
    bits = (int(flags) & wk.STATIC_BITS) if specialize else None
    key = ("native", scalar, bits, bool(hoist), int(size), int(lanes))
    if key not in _WALKS:
        _WALKS[key] = _native_kernel(scalar, bits, bool(hoist), int(size),
                                     int(lanes))
    return _WALKS[key]


def launch_native(walk, *, position, keys, values, radius, start, offsets,
                  clusters, grid, cells, params, flags: int, forces, energy,
                  d_sigma, d_epsilon, count, size: int = CLUSTER_SIZE,
                  block_dim: int = NATIVE_BLOCK, lanes: int = _LANES) -> None:
    """``walk`` (`native_kernel`, of these ``size`` and ``lanes``): a warp
    per cluster over the bound on the clusters."""
    n = position.shape[0]
    table = start.shape[0] - 1
    wp.launch(walk, dim=bound(n, table, size) * lanes,
              device=position.device, block_dim=block_dim,
              inputs=[position, keys, values, radius, start, offsets, table,
                      clusters, grid, cells, params, flags, forces, energy,
                      d_sigma, d_epsilon, count])
