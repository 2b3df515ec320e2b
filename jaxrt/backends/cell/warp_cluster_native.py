"""The warp-cooperative cluster walk of the list-free Lennard-Jones sums
(CUDA only; ``walk="native"`` of `jaxrt.backends.rt.ffi.cell_lj_sums`):
Warp, CUDA intrinsics in `wp.func_native` snippets, and NumPy (no JAX).

The clusters are `jaxrt.backends.cell.warp_cluster`'s. A warp of 32
threads walks one cluster of ``size`` particles: lane ``l`` holds particle
``l % size`` of the cluster and is slot ``l // size`` of ``32 / size``.
The warp reads each stencil row in chunks of 32 candidates (one per lane,
coalesced), tests them against the cluster's bounding box, and compacts
the survivors with a ballot; each step then hands one survivor to every
slot (a shuffle from its lane), so that the ``size`` lanes of a slot test
it against the cluster. The slots' sums are added by shuffles at the
end. Each particle adds the thread walk's terms in another order: the
sums agree to rounding, not bit for bit.

Warp's CPU device runs no warps: there `lj_sums` takes the cluster walk,
and the tests run this kernel built for one lane (``lanes=1``: the
snippets' lone-lane branches, every candidate in the thread walk's
order), which leaves the cross-lane shuffles to be checked on a GPU.
"""

import warp as wp

from jaxrt.backends.cell import warp_cluster as wc
from jaxrt.backends.cell import warp_kernels as wk

_OPTIONS = {"enable_backward": False, "max_unroll": 1, "fast_math": True}
wp.set_module_options(_OPTIONS)

# Threads per cluster on CUDA.
LANES = 32
# Particles per cluster: a whole number of slots per warp.
SIZES = (4, 8, 16, 32)
# Threads per block (whole warps).
BLOCK = 128


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


# Shuffles of an int, float32 or float64 (overloads of one name): from
# lane ``lane``, and from the lane ``m`` apart (xor).
_SHFL = """
#if defined(__CUDA_ARCH__)
return __shfl_sync(0xffffffffu, x, lane);
#else
return x;
#endif
"""
_SHFL_XOR = _SHFL.replace("__shfl_sync(0xffffffffu, x, lane)",
                          "__shfl_xor_sync(0xffffffffu, x, m)")
for _type in (int, wp.float32, wp.float64):
    @wp.func_native(_SHFL)
    def _shfl(x: _type, lane: int) -> _type:
        ...

    @wp.func_native(_SHFL_XOR)
    def _xor(x: _type, m: int) -> _type:
        ...
del _type


def _lane_functions(scalar, size, lanes):
    """(box, survivor, reduce_slots): the cluster's box over a slot's
    lanes, each slot's next survivor of a ballot, the sums over the
    slots."""
    vector = wp.types.vector(3, scalar)
    slots = lanes // size

    @wp.func
    def box(p: vector, radius: wp.array(dtype=scalar), i: int,
            has_radii: int, r_cutoff: scalar):
        # Lo, hi and the largest cut over the lanes of this lane's slot
        # (xor partners below ``size`` stay in the slot), and the lane's
        # cut.
        ri = r_cutoff
        if has_radii != 0:
            ri = radius[i]
        # Fresh values, not names of ``p`` and ``ri``: Warp gives a plain
        # ``a = b`` the variable of ``b``, and the loop below would then
        # write lo's, hi's and r_max's updates into one variable each.
        lo = vector(p[0], p[1], p[2])
        hi = vector(p[0], p[1], p[2])
        r_max = wp.max(ri, ri)
        s = int(1)
        while s < wp.static(size):
            lo = wp.min(lo, vector(_xor(lo[0], s), _xor(lo[1], s),
                                   _xor(lo[2], s)))
            hi = wp.max(hi, vector(_xor(hi[0], s), _xor(hi[1], s),
                                   _xor(hi[2], s)))
            r_max = wp.max(r_max, _xor(r_max, s))
            s = s * 2
        return lo, hi, r_max, ri

    @wp.func
    def slot_sum(x: scalar):
        # The sum of ``x`` over the slots (lanes ``size`` apart or more).
        y = x
        s = int(wp.static(size))
        while s < wp.static(lanes):
            y = y + _xor(y, s)
            s = s * 2
        return y

    @wp.func
    def survivor(mask: int, slot: int, j: int, pj: vector, rj: scalar,
                 has_radii: int):
        # This slot's survivor of ``mask`` (source < 0: none), shuffled
        # from its lane, and the mask less the slots' survivors.
        left = int(mask)
        source = int(-1)
        for s in range(wp.static(slots)):
            low_bit = _lowest(left)
            if s == slot:
                source = low_bit
            left = _drop_lowest(left)
        src = wp.max(source, 0)
        qj = vector(_shfl(pj[0], src), _shfl(pj[1], src), _shfl(pj[2], src))
        r = rj
        if has_radii != 0:
            r = _shfl(rj, src)
        return left, source, _shfl(j, src), qj, r

    @wp.func
    def reduce_slots(f: vector, e: scalar, ds: scalar, de: scalar, hits: int,
                     derivatives: int):
        # The sums over the slots (every lane joins the shuffles).
        h = int(hits)
        s = int(wp.static(size))
        while s < wp.static(lanes):
            h = h + _xor(h, s)
            s = s * 2
        ds_sum, de_sum = ds, de
        if derivatives != 0:
            ds_sum, de_sum = slot_sum(ds), slot_sum(de)
        return (vector(slot_sum(f[0]), slot_sum(f[1]), slot_sum(f[2])),
                slot_sum(e), ds_sum, de_sum, h)

    return box, survivor, reduce_slots


def _native_kernel(scalar, static_bits, hoist, size, lanes):
    """The warp-cooperative walk (module docstring) for positions of
    ``scalar``; ``static_bits``/``hoist`` as `warp_kernels.walk_kernel`'s,
    ``size`` particles per cluster, ``lanes`` threads per cluster."""
    vector = wp.types.vector(3, scalar)
    span, difference = wk.stencil_functions(scalar)
    terms = wk.pair_functions(scalar, static_bits, hoist)
    near = wc.cluster_functions(scalar)
    box, survivor, reduce_slots = _lane_functions(scalar, size, lanes)
    fixed = -1 if static_bits is None else int(static_bits)

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
        cluster, lane = tid / wp.static(lanes), tid % wp.static(lanes)
        # Warp-uniform: every lane of a warp leaves here or none does.
        if cluster >= offsets[table]:
            return
        first = clusters[cluster]
        members = clusters[cluster + 1] - first
        slot = lane / wp.static(size)
        mine = lane % wp.static(size) < members
        # Lanes past the cluster's end repeat its last particle (the box
        # is the cluster's) and add nothing.
        i = first + wp.min(lane % wp.static(size), members - 1)
        low = flags & wk.STATIC_BITS
        if wp.static(fixed >= 0):
            low = wp.static(fixed)
        has_radii, counting = low & wk.HAS_RADII, low & wk.COUNT
        side = grid[wk.SIDE]
        sigma, epsilon = params[wk.SIGMA], params[wk.EPSILON]
        r_onset, r_cutoff = params[wk.R_ONSET], params[wk.R_CUTOFF]
        s = wk.stencil(flags, cells, keys[first])
        p = position[i]
        lo, hi, r_max, ri = box(p, radius, i, has_radii, r_cutoff)
        cut2 = r_cutoff * r_cutoff
        band = cut2 - r_onset * r_onset
        inverse_cube = scalar(1.0) / (band * band * band)
        f, hits = vector(), int(0)
        e_sum, ds_sum, de_sum = scalar(0.0), scalar(0.0), scalar(0.0)
        for dz in range(-s.az, s.az + 1):
            for piece in range(s.pieces):
                begin, end, shift = span(s, start, side, dz, piece)
                for chunk in range(begin, end, wp.static(lanes)):
                    # A candidate per lane, kept within the box's cut.
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
                        keep = wp.where(near(lo - shift, hi - shift, pj,
                                             cut_j, s), 1, 0)
                    mask = _ballot(keep)
                    while mask != 0:
                        mask, source, jj, qj, rjj = survivor(
                            mask, slot, j, pj, rj, has_radii)
                        if source < 0 or not mine:
                            continue
                        d, d2 = difference(p - shift, qj, side, s)
                        cut = r_cutoff
                        if has_radii != 0:
                            cut = wp.max(ri, rjj)
                            cut2 = cut * cut
                        if counting != 0 and d2 < cut2 and jj != i:
                            hits = hits + 1
                        if d2 < cut2 and d2 > scalar(0.0):
                            e, g, ds, de = terms(d2, cut, cut2, sigma,
                                                 epsilon, r_onset, r_cutoff,
                                                 inverse_cube)
                            f = f + g * d
                            e_sum = e_sum + e
                            if low & wk.DERIVATIVES != 0:
                                ds_sum = ds_sum + ds
                                de_sum = de_sum + de
        f, e_sum, ds_sum, de_sum, hits = reduce_slots(
            f, e_sum, ds_sum, de_sum, hits, low & wk.DERIVATIVES)
        if mine and slot == 0:
            forces[values[i]] = f
            energy[i] = e_sum
            d_sigma[i] = ds_sum
            d_epsilon[i] = de_sum
            count[i] = hits

    return native_sums


_WALKS: dict = {}


def native_kernel(scalar, flags: int, *, size: int = wc.CLUSTER_SIZE,
                  specialize: bool = True, hoist: bool = True,
                  lanes: int = LANES):
    """The warp-cooperative walk for positions of ``scalar`` and
    ``flags``, built on first use (`_native_kernel`): for CUDA, or with
    ``lanes=1`` (and ``size=1``) for any device (tests)."""
    if lanes == LANES and size not in SIZES:
        raise ValueError(f"native cluster size={size!r}: choose one of "
                         f"{SIZES}.")
    if lanes not in (1, LANES) or lanes % size:
        raise ValueError(f"native lanes={lanes!r}, size={size!r}: lanes is "
                         f"{LANES} (or 1, tests), a multiple of size.")
    bits = (int(flags) & wk.STATIC_BITS) if specialize else None
    key = (scalar, bits, bool(hoist), int(size), int(lanes))
    if key not in _WALKS:
        _WALKS[key] = _native_kernel(scalar, bits, bool(hoist), int(size),
                                     int(lanes))
    return _WALKS[key]


def launch(walk, *, position, keys, values, radius, start, offsets,
           clusters, grid, cells, params, flags: int, forces, energy,
           d_sigma, d_epsilon, count, size: int = wc.CLUSTER_SIZE,
           block_dim: int = BLOCK, lanes: int = LANES) -> None:
    """``walk`` (`native_kernel`, of these ``size`` and ``lanes``): a warp
    per cluster over `warp_cluster.bound` clusters."""
    n = position.shape[0]
    table = start.shape[0] - 1
    wp.launch(walk, dim=wc.bound(n, table, size) * lanes,
              device=position.device, block_dim=block_dim,
              inputs=[position, keys, values, radius, start, offsets, table,
                      clusters, grid, cells, params, flags, forces, energy,
                      d_sigma, d_epsilon, count])


def lj_sums(points, radii, grid, cells, params, flags: int, *, forces,
            energy, d_sigma, d_epsilon, count, keys, values, wrapped, start,
            position, radius, counts, offsets, clusters,
            size: int = wc.CLUSTER_SIZE, specialize: bool = True,
            hoist: bool = True, block_dim: int = BLOCK) -> None:
    """`jaxrt.backends.cell.warp_cluster.lj_sums` (the same arguments)
    with the warp-cooperative walk on CUDA (``size`` in `SIZES`); on
    other devices the cluster walk itself."""
    n = points.shape[0]
    if not points.device.is_cuda or n == 0:
        wc.lj_sums(points, radii, grid, cells, params, flags, forces=forces,
                   energy=energy, d_sigma=d_sigma, d_epsilon=d_epsilon,
                   count=count, keys=keys, values=values, wrapped=wrapped,
                   start=start, position=position, radius=radius,
                   counts=counts, offsets=offsets, clusters=clusters,
                   size=size, specialize=specialize, hoist=hoist)
        return
    wk.sort_cells(points, radii, grid, cells, flags, keys=keys,
                  values=values, wrapped=wrapped, start=start,
                  position=position, radius=radius)
    wc.build_clusters(start, counts, offsets, clusters, n=n, size=size)
    walk = native_kernel(wk.scalar_of(points.dtype), flags, size=size,
                         specialize=specialize, hoist=hoist)
    launch(walk, position=position, keys=keys, values=values, radius=radius,
           start=start, offsets=offsets, clusters=clusters, grid=grid,
           cells=cells, params=params, flags=flags, forces=forces,
           energy=energy, d_sigma=d_sigma, d_epsilon=d_epsilon, count=count,
           size=size, block_dim=block_dim)
