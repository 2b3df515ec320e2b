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

The pipeline after `jaxrt.backends.cell.warp_kernels.sort_cells` (bin, sort,
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


def _gap(scalar):
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
    return gap


def cluster_functions(scalar):
    """``near(lo, hi, x, cut, s)``: whether ``x`` is within ``cut`` of the
    box ``[lo, hi]`` (not pruning the rounded axes of `warp_kernels.Stencil`
    ``s``), for ``scalar``."""
    vector = wp.types.vector(3, scalar)
    gap = _gap(scalar)

    @wp.func
    def near(lo: vector, hi: vector, x: vector, cut: scalar, s: wk.Stencil):
        g = vector(gap(lo[0], hi[0], x[0], s.rx),
                   gap(lo[1], hi[1], x[1], s.ry),
                   gap(lo[2], hi[2], x[2], s.rz))
        return wp.dot(g, g) < cut * cut

    return near


def _cluster_load(scalar, size):
    vector = wp.types.vector(3, scalar)
    points_t = wp.types.matrix((size, 3), scalar)
    sums_t = wp.types.vector(size, scalar)
    # Larger than any coordinate (the box of an empty slot never counts).
    huge = 1e30 if scalar == wp.float32 else 1e300

    @wp.func
    def load(position: wp.array(dtype=vector), radius: wp.array(dtype=scalar),
             first: int, members: int, has_radii: int, r_cutoff: scalar):
        # The cluster in registers: positions, cuts, bounding box and the
        # largest cut.
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
        return p, r, lo, hi, r_max

    return load


def _cluster_kernel(scalar, static_bits, hoist, size, prune, unroll):
    """The cluster walk (module docstring) for positions of ``scalar``;
    ``static_bits``/``hoist`` as `warp_kernels.walk_kernel`'s, ``size``
    particles per cluster, ``prune`` the bounding-box test, ``unroll`` the
    loops over the cluster unrolled."""
    vector = wp.types.vector(3, scalar)
    sums_t = wp.types.vector(size, scalar)
    hits_t = wp.types.vector(size, wp.int32)
    points_t = wp.types.matrix((size, 3), scalar)
    span, difference = wk.stencil_functions(scalar)
    terms = wk.pair_functions(scalar, static_bits, hoist)
    near = cluster_functions(scalar)
    load = _cluster_load(scalar, size)
    fixed = -1 if static_bits is None else int(static_bits)

    @wp.kernel(module="unique",
               module_options=dict(_OPTIONS, max_unroll=size if unroll else 1))
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
        if wp.static(fixed >= 0):
            low = wp.static(fixed)
        has_radii, counting = low & wk.HAS_RADII, low & wk.COUNT
        side = grid[wk.SIDE]
        sigma, epsilon = params[wk.SIGMA], params[wk.EPSILON]
        r_onset, r_cutoff = params[wk.R_ONSET], params[wk.R_CUTOFF]
        s = wk.stencil(flags, cells, keys[first])
        p, r, lo, hi, r_max = load(position, radius, first, members,
                                   has_radii, r_cutoff)
        cut2 = r_cutoff * r_cutoff
        band = cut2 - r_onset * r_onset
        inverse_cube = scalar(1.0) / (band * band * band)
        f = points_t()
        e_sum, ds_sum, de_sum = sums_t(), sums_t(), sums_t()
        hits = hits_t()
        # Bounds read at run time: loops still where ``size`` unrolls.
        for dz in range(-s.az, s.az + 1):
            for piece in range(s.pieces):
                begin, end, shift = span(s, start, side, dz, piece)
                for j in range(begin, end):
                    pj = position[j]
                    rj = scalar(0.0)
                    cut_j = r_cutoff
                    if has_radii != 0:
                        rj = radius[j]
                        cut_j = wp.max(r_max, rj)
                    if wp.static(prune):
                        if not near(lo - shift, hi - shift, pj, cut_j, s):
                            continue
                    for k in range(wp.static(size)):
                        if k < members:
                            d, d2 = difference(p[k] - shift, pj, side, s)
                            cut = r_cutoff
                            if has_radii != 0:
                                cut = wp.max(r[k], rj)
                                cut2 = cut * cut
                            if counting != 0 and d2 < cut2 and j != first + k:
                                hits[k] = hits[k] + 1
                            if d2 < cut2 and d2 > scalar(0.0):
                                e, g, ds, de = terms(
                                    d2, cut, cut2, sigma, epsilon, r_onset,
                                    r_cutoff, inverse_cube)
                                f[k] = f[k] + g * d
                                e_sum[k] = e_sum[k] + e
                                if low & wk.DERIVATIVES != 0:
                                    ds_sum[k] = ds_sum[k] + ds
                                    de_sum[k] = de_sum[k] + de
        for k in range(wp.static(size)):
            if k < members:
                forces[values[first + k]] = vector(f[k, 0], f[k, 1], f[k, 2])
                energy[first + k] = e_sum[k]
                d_sigma[first + k] = ds_sum[k]
                d_epsilon[first + k] = de_sum[k]
                count[first + k] = hits[k]

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
            block_dim: int = CLUSTER_BLOCK) -> None:
    """`jaxrt.backends.cell.warp_kernels.lj_sums` with the cluster walk:
    the same arguments and outputs, and

    Args:
      counts, offsets: int32 ``(T + 1,)`` scratch, ``T`` ``start``'s size
        less one; clusters: int32 ``(bound(N, T, size) + 1,)`` scratch.
      size: particles per cluster (`SIZES`); prune: skip candidates beyond
        the cut of the cluster's bounding box; block_dim: threads per
        block. The loops over a cluster are unrolled on CUDA.
    """
    n = points.shape[0]
    if n == 0:
        return
    wk.sort_cells(points, radii, grid, cells, flags, keys=keys,
                  values=values, wrapped=wrapped, start=start,
                  position=position, radius=radius)
    build_clusters(start, counts, offsets, clusters, n=n, size=size)
    walk = cluster_kernel(wk.scalar_of(points.dtype), flags, size=size,
                          prune=prune, unroll=points.device.is_cuda,
                          specialize=specialize, hoist=hoist)
    launch_walk(walk, position=position, keys=keys, values=values,
                radius=radius, start=start, offsets=offsets,
                clusters=clusters, grid=grid, cells=cells, params=params,
                flags=flags, forces=forces, energy=energy, d_sigma=d_sigma,
                d_epsilon=d_epsilon, count=count, size=size,
                block_dim=block_dim)

