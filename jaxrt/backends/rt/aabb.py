"""Custom AABB method: Algis & Bramas (2024), §4.4 ("Custom AABB"), with the
particle sorting of §5 ("Custom sorted AABB") and the periodic gamma rays of
Meneses et al. (seed 003), §3.3 (the geometry is in `jaxrt.backends.rt.periodic`).

Each particle owns an axis-aligned box of half-width ``cutoff`` (plus a pad
that absorbs float32 rounding) in a `wp.Bvh`. From each particle an
infinitesimal ray is cast: the intersection program does no geometry, it
only asks "is the ray's origin inside this box" (a ray query whose
``max_dist`` is 0 keeps exactly the boxes that contain the origin), then
runs the exact distance test in the positions' own precision with jax-md's
arithmetic. Every neighbour is counted; indices are stored while there is
room, so counts are exact and overflow is never silent.

Clusters (an extension, ``cluster_size`` g > 1): one box around each run of
g consecutive Morton-sorted particles, grown by the cutoff, so the BVH has
g times fewer leaves and a ray that lands in a box tests the g particles
exactly. The result is the same. On a GPU without RT cores it did not pay
(docs/benchmarks-notes.md), so g = 1 is the default and clusters stay an
option for other hardware.

The BVH is float32 (Warp's only kind). float64 positions get float32 boxes
padded beyond float32 rounding and a float64 distance test, so float64 lists
are exact. Every kernel is generic over the position type (``wp.vec3`` or
``wp.vec3d``) and instantiated for both when this module loads, so the
module compiles once.

Pure Warp: nothing here knows of JAX (`jaxrt.backends.rt.ffi` wraps it).

One module past 800 lines on purpose: one method's Warp kernels and the
host side that builds and refits their tree.
"""
from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import warp as wp

from jaxrt.backends.rt import periodic as gamma
from jaxrt.backends.rt import policy as _policy
from jaxrt.backends.rt import seed_energy
# The one cutoff rule of the ray-traced methods (also `jaxrt.backends.rt.ffi`'s
# ``aabb.check_cutoff``).
from jaxrt.backends.rt.periodic import check_cutoff

# Bit-compatibility with jax-md: no FMA contraction in ``dx*dx + dy*dy + dz*dz``.
wp.set_module_options({"fuse_fp": False})

# What a query launch writes (one kernel for all three, so one compile).
MODE_DENSE = wp.constant(0)  # rows[i, :] = neighbours of i, padded with N
MODE_COUNT = wp.constant(1)  # count[i] only
MODE_FILL = wp.constant(2)   # pairs[:, row_offset[i] + n] = (j, i)

# Boxes are padded by this fraction of (largest |coordinate| + largest
# periodic side + cutoff), 8 float32 epsilons: more than the rounding of box
# corners, ray origins and the periodic wrap (and of float64 to float32).
PAD_FRACTION = wp.constant(2.0 ** -20)

# Morton keys: 10 bits per axis (int32 keys) on a grid of cells of half the
# cutoff; coordinates beyond 1024 cells wrap, which only costs locality.
_MORTON_CELLS_PER_CUTOFF = 2.0

# An infinitesimal ray: any direction with no zero component (zero
# components make the slab test compute 0 * inf).
RAY_DIRECTION = wp.constant(wp.vec3(0.57735026, 0.57735026, 0.57735026))


@wp.func
def box_reach(half_width: wp.float32, extent: wp.float32, largest_side: wp.float32):
    """Half-width of every box: the cutoff plus the rounding pad."""
    return half_width + wp.float32(PAD_FRACTION) * (extent + largest_side + half_width)


@wp.kernel
def _extent_kernel(points: wp.array(dtype=Any), extent: wp.array(dtype=wp.float32)):
    """extent[0] = max |coordinate| over finite coordinates (extent zeroed)."""
    i = wp.tid()
    x = points[i]
    largest = wp.float32(0.0)
    for a in range(3):
        v = wp.float32(wp.abs(x[a]))
        if wp.isfinite(v) and v > largest:
            largest = v
    # Reading first keeps atomics (and their contention on a GPU) rare.
    if largest > extent[0]:
        wp.atomic_max(extent, 0, largest)


@wp.kernel
def _morton_kernel(points: wp.array(dtype=Any), side: wp.array(dtype=Any),
                   periodic: wp.vec3i, order: wp.array(dtype=wp.int32),
                   cells_per_unit: wp.float32,
                   keys: wp.array(dtype=wp.int32),
                   values: wp.array(dtype=wp.int32)):
    """keys[k] = Morton code of particle order[k] (wrapped), values[k] = order[k]."""
    k = wp.tid()
    i = order[k]
    box = side[0]
    w = gamma.wrap_point(points[i], box, periodic)
    key = int(0)
    for a in range(3):
        c = wp.clamp(wp.float32(w[a]) * cells_per_unit, -1.0e9, 1.0e9)
        cell = int(wp.floor(c)) & 1023
        cell = (cell | (cell << 16)) & 0x030000FF
        cell = (cell | (cell << 8)) & 0x0300F00F
        cell = (cell | (cell << 4)) & 0x030C30C3
        cell = (cell | (cell << 2)) & 0x09249249
        key = key | (cell << a)
    keys[k] = key
    values[k] = i


@wp.func
def within_band(u: Any, box: Any, periodic: wp.vec3i, band: wp.float32):
    """Is ``u`` within ``band`` of the box ``[0, box)`` on every periodic
    axis (free axes are not bounded)?"""
    inside = True
    for a in range(3):
        if periodic[a] != 0:
            v = wp.float32(u[a])
            if not (v >= -band and v < wp.float32(box[a]) + band):
                inside = False
    return inside


@wp.kernel
def _place_kernel(points: wp.array(dtype=Any), side: wp.array(dtype=Any),
                  periodic: wp.vec3i, order: wp.array(dtype=wp.int32),
                  has_reference: wp.int32, band: wp.float32,
                  reference: wp.array(dtype=wp.vec3),
                  item_points: wp.array(dtype=Any),
                  item_coords: wp.array(dtype=Any),
                  moved_far: wp.array(dtype=wp.int32)):
    """Item k is particle order[k]: its position and box centre.

    Without a reference (a (re)build) the item sits at its wrapped position
    and that position becomes the reference. With one (a refit), it sits at
    the image nearest its reference while that image lies within ``band``
    of the box, so a particle that steps across a periodic face does not
    jump; farther out it is wrapped (its ancestors' boxes then span the
    box: slower queries, never a missed pair). moved_far[0] = 1 if an item
    drifted more than ``band`` from its reference (the drift policy's
    signal).
    """
    k = wp.tid()
    i = order[k]
    x = points[i]
    box = side[0]
    u = gamma.wrap_point(x, box, periodic)
    if has_reference != 0:
        v = gamma.nearest_image(u, reference[k], box, periodic)
        drift = wp.vec3(v) - reference[k]
        if wp.max(wp.abs(drift)) > band:
            moved_far[0] = 1
        if within_band(v, box, periodic, band):
            u = v
    else:
        reference[k] = wp.vec3(u)
    item_points[k] = x
    item_coords[k] = u


@wp.kernel
def _cluster_box_kernel(item_coords: wp.array(dtype=Any), side: wp.array(dtype=Any),
                        periodic: wp.vec3i, cluster_size: wp.int32,
                        half_width: wp.float32, extent: wp.array(dtype=wp.float32),
                        has_radii: wp.int32, item_reach: wp.array(dtype=wp.float32),
                        lowers: wp.array(dtype=wp.vec3),
                        uppers: wp.array(dtype=wp.vec3)):
    """Box of cluster c: the union of the boxes of items
    [c * cluster_size, (c + 1) * cluster_size), i.e. their centres' bounds
    grown by the reach (each item's own with radii, seed 003 §3). With
    cluster_size 1 it is the seed's box per particle."""
    c = wp.tid()
    first = c * cluster_size
    last = wp.min(first + cluster_size, item_coords.shape[0])
    pad = box_reach(half_width, extent[0], gamma.largest_side(side[0], periodic)) - half_width
    low = wp.vec3(1.0e30, 1.0e30, 1.0e30)
    high = -low
    for m in range(first, last):
        u = wp.vec3(item_coords[m])
        reach = half_width
        if has_radii != 0:
            reach = item_reach[m]
        grow = wp.vec3(reach + pad, reach + pad, reach + pad)
        low = wp.min(low, u - grow)
        high = wp.max(high, u + grow)
    lowers[c] = low
    uppers[c] = high


@wp.kernel
def _item_reach_kernel(order: wp.array(dtype=wp.int32), reach: wp.array(dtype=Any),
                       item_reach: wp.array(dtype=wp.float32)):
    """item_reach[k] = reach of particle order[k], in float32 (the boxes'
    pad absorbs the rounding)."""
    k = wp.tid()
    item_reach[k] = wp.float32(reach[order[k]])


@wp.func
def displacement(xi: Any, xj: Any, box: Any, periodic: wp.vec3i):
    """jax-md's ``periodic_displacement(side, Ra - Rb)`` on periodic axes
    (``Ra - Rb`` on free ones), operation for operation (``jnp.mod`` is
    fmod plus a sign fix). Also the ORCS kernels' pair vector
    (`jaxrt.backends.rt.orcs`)."""
    d = xi - xj
    for a in range(3):
        if periodic[a] != 0:
            half = box[a] * type(box[a])(0.5)
            r = wp.mod(d[a] + half, box[a])
            if r != type(r)(0.0) and (r < type(r)(0.0)) != (box[a] < type(r)(0.0)):
                r = r + box[a]
            d[a] = r - half
    return d


@wp.func
def _square_distance(xi: Any, xj: Any, box: Any, periodic: wp.vec3i):
    """jax-md's ``square_distance(periodic_displacement(side, Ra - Rb))``."""
    d = displacement(xi, xj, box, periodic)
    return d[0] * d[0] + d[1] * d[1] + d[2] * d[2]


@wp.func
def _visit(item: int, i: int, shift: wp.vec3i, xi: Any, ui: Any,
           item_points: wp.array(dtype=Any), item_coords: wp.array(dtype=Any),
           order: wp.array(dtype=wp.int32), box: Any, periodic: wp.vec3i,
           any_periodic: bool, cutoff_sq: Any, mask_self: wp.int32,
           lower_only: wp.int32, mode: wp.int32, base: int, n: int,
           rows: wp.array2d(dtype=wp.int32), pairs: wp.array2d(dtype=wp.int32)):
    """The intersection program: is ``item`` a neighbour of particle ``i``
    seen through the ray with ``shift``? Stores it while there is room.
    Returns the updated neighbour count ``n``."""
    j = order[item]
    if mask_self != 0 and j == i:
        return n
    if lower_only != 0 and j >= i:
        return n
    # Free space has one ray, so no image to choose.
    if any_periodic and not gamma.is_canonical_image(shift, ui, item_coords[item],
                                                     box, periodic):
        return n
    if not (_square_distance(xi, item_points[item], box, periodic) < cutoff_sq):
        return n
    if mode == MODE_DENSE:
        if n < rows.shape[1]:
            rows[i, n] = j
    elif mode == MODE_FILL:
        slot = base + n
        if slot >= 0 and slot < pairs.shape[1]:
            pairs[0, slot] = j
            pairs[1, slot] = i
    return n + 1


@wp.func
def _store(row: int, value: int, mode: wp.int32, rows: wp.array2d(dtype=wp.int32),
           row_offset: wp.array(dtype=wp.int32), pairs: wp.array2d(dtype=wp.int32),
           count: wp.array(dtype=wp.int32)):
    """Append ``value`` to ``row`` through the row's atomic cursor (rows
    are written from both ends of a pair, by different threads)."""
    slot = wp.atomic_add(count, row, 1)
    if mode == MODE_DENSE:
        if slot < rows.shape[1]:
            rows[row, slot] = value
    elif mode == MODE_FILL:
        s = row_offset[row] + slot
        # Offsets wrap past 2**31 edges (the front refuses such lists at
        # allocate, after this count): never write through a wrapped one.
        if s >= 0 and s < pairs.shape[1]:
            pairs[0, s] = value
            pairs[1, s] = row


@wp.func
def _visit_radii(item: int, i: int, shift: wp.vec3i, xi: Any, ui: Any,
                 item_points: wp.array(dtype=Any), item_coords: wp.array(dtype=Any),
                 order: wp.array(dtype=wp.int32), reach: wp.array(dtype=Any),
                 box: Any, periodic: wp.vec3i, any_periodic: bool,
                 mask_self: wp.int32, lower_only: wp.int32, mode: wp.int32,
                 rows: wp.array2d(dtype=wp.int32), row_offset: wp.array(dtype=wp.int32),
                 pairs: wp.array2d(dtype=wp.int32), count: wp.array(dtype=wp.int32)):
    """The intersection program with per-particle radii (seed 003 §3): the
    ray of i lies in j's box, so i finds j when d < r_j. The pair's rule is
    d < max(r_i, r_j); when d >= r_i, j's ray will not find i, so i also
    writes itself into j's row and the pair is never one-sided."""
    j = order[item]
    if mask_self != 0 and j == i:
        return
    if any_periodic and not gamma.is_canonical_image(shift, ui, item_coords[item],
                                                     box, periodic):
        return
    d2 = _square_distance(xi, item_points[item], box, periodic)
    rj = reach[j]
    if not (d2 < rj * rj):
        return
    if lower_only == 0 or j < i:
        _store(i, j, mode, rows, row_offset, pairs, count)
    ri = reach[i]
    if not (d2 < ri * ri):
        if lower_only == 0 or i < j:
            _store(j, i, mode, rows, row_offset, pairs, count)


@wp.kernel
def _query_radii_kernel(bvh: wp.uint64, item_points: wp.array(dtype=Any),
                        item_coords: wp.array(dtype=Any),
                        order: wp.array(dtype=wp.int32), side: wp.array(dtype=Any),
                        periodic: wp.vec3i, reach: wp.array(dtype=Any),
                        half_width: wp.float32, extent: wp.array(dtype=wp.float32),
                        band: wp.float32, mask_self: wp.int32,
                        lower_only: wp.int32, mode: wp.int32, cluster_size: wp.int32,
                        rows: wp.array2d(dtype=wp.int32),
                        row_offset: wp.array(dtype=wp.int32),
                        pairs: wp.array2d(dtype=wp.int32),
                        count: wp.array(dtype=wp.int32)):
    """`_query_kernel` with per-particle radii: rows are appended to with
    atomics (count zeroed before the launch, Dense rows padded with N
    after it by `_pad_rows_kernel`).
    Gamma rays reach the largest radius (``half_width``, §3.3): a small
    particle near a face must still find a large one across it."""
    k = wp.tid()
    n_particles = item_points.shape[0]
    i = order[k]
    xi = item_points[k]
    ui = item_coords[k]
    box = side[0]
    face_reach = box_reach(half_width, extent[0], gamma.largest_side(box, periodic)) + band
    any_periodic = periodic[0] != 0 or periodic[1] != 0 or periodic[2] != 0
    for ray in range(gamma.RAYS_PER_PARTICLE):
        shift = gamma.ray_shift(ray)
        if gamma.ray_is_cast(shift, ui, box, periodic, face_reach):
            origin = wp.vec3(gamma.shifted(ui, shift, box))
            query = wp.bvh_query_ray(bvh, origin, RAY_DIRECTION)
            hit = int(0)
            while wp.bvh_query_next(query, hit, 0.0):
                first = hit * cluster_size
                for item in range(first, wp.min(first + cluster_size, n_particles)):
                    _visit_radii(item, i, shift, xi, ui, item_points, item_coords,
                                 order, reach, box, periodic, any_periodic, mask_self,
                                 lower_only, mode, rows, row_offset, pairs, count)


@wp.kernel
def _query_kernel(bvh: wp.uint64, item_points: wp.array(dtype=Any),
                  item_coords: wp.array(dtype=Any),
                  order: wp.array(dtype=wp.int32), side: wp.array(dtype=Any),
                  periodic: wp.vec3i, cutoff_sq: Any, half_width: wp.float32,
                  extent: wp.array(dtype=wp.float32), band: wp.float32,
                  mask_self: wp.int32, lower_only: wp.int32, mode: wp.int32,
                  cluster_size: wp.int32,
                  rows: wp.array2d(dtype=wp.int32),
                  row_offset: wp.array(dtype=wp.int32),
                  pairs: wp.array2d(dtype=wp.int32),
                  count: wp.array(dtype=wp.int32)):
    """Neighbours of particle order[k], from the ray at its item and, near a
    periodic face, the gamma rays (Meneses et al. §3.3). A hit is a box of
    ``cluster_size`` consecutive items; size 1 (the seed's method) has its
    own branch without the member loop, which measured twice as fast on a
    GPU."""
    k = wp.tid()
    n_particles = item_points.shape[0]
    i = order[k]
    xi = item_points[k]
    ui = item_coords[k]
    box = side[0]
    reach = box_reach(half_width, extent[0], gamma.largest_side(box, periodic))
    # Refit items may sit up to band outside the box.
    face_reach = reach + band
    any_periodic = periodic[0] != 0 or periodic[1] != 0 or periodic[2] != 0
    base = int(0)
    if mode == MODE_FILL:
        base = row_offset[i]
    n = int(0)
    for ray in range(gamma.RAYS_PER_PARTICLE):
        shift = gamma.ray_shift(ray)
        if gamma.ray_is_cast(shift, ui, box, periodic, face_reach):
            origin = wp.vec3(gamma.shifted(ui, shift, box))
            query = wp.bvh_query_ray(bvh, origin, RAY_DIRECTION)
            hit = int(0)
            if cluster_size == 1:
                while wp.bvh_query_next(query, hit, 0.0):
                    n = _visit(hit, i, shift, xi, ui, item_points, item_coords,
                               order, box, periodic, any_periodic, cutoff_sq,
                               mask_self, lower_only, mode, base, n, rows, pairs)
            else:
                while wp.bvh_query_next(query, hit, 0.0):
                    first = hit * cluster_size
                    for item in range(first, wp.min(first + cluster_size, n_particles)):
                        n = _visit(item, i, shift, xi, ui, item_points, item_coords,
                                   order, box, periodic, any_periodic, cutoff_sq,
                                   mask_self, lower_only, mode, base, n, rows,
                                   pairs)
    count[i] = n
    if mode == MODE_DENSE:
        width = rows.shape[1]
        for s in range(wp.min(n, width), width):
            rows[i, s] = n_particles


@wp.kernel
def _energy_kernel(bvh: wp.uint64, item_points: wp.array(dtype=Any),
                   item_coords: wp.array(dtype=Any),
                   order: wp.array(dtype=wp.int32), side: wp.array(dtype=Any),
                   periodic: wp.vec3i, cutoff_sq: Any, half_width: wp.float32,
                   extent: wp.array(dtype=wp.float32), band: wp.float32,
                   params: wp.array(dtype=Any), energy: wp.array(dtype=Any),
                   count: wp.array(dtype=wp.int32)):
    """Seed 001 §4.4's fused mode (`jaxrt.backends.rt.seed_energy`): the rays of
    `_query_kernel` with ``cluster_size`` 1 and ``mask_self``, whose
    intersection program adds ``U`` of every accepted pair to the ray's
    payload instead of storing ``j``; one atomic add per ray into
    ``energy[i]`` (zeroed before the launch), as the seed's code does.
    ``count[i]``: pairs of i (the Dense row count)."""
    k = wp.tid()
    i = order[k]
    xi = item_points[k]
    ui = item_coords[k]
    box = side[0]
    reach = box_reach(half_width, extent[0], gamma.largest_side(box, periodic))
    face_reach = reach + band
    any_periodic = periodic[0] != 0 or periodic[1] != 0 or periodic[2] != 0
    n = int(0)
    for ray in range(gamma.RAYS_PER_PARTICLE):
        shift = gamma.ray_shift(ray)
        if gamma.ray_is_cast(shift, ui, box, periodic, face_reach):
            origin = wp.vec3(gamma.shifted(ui, shift, box))
            query = wp.bvh_query_ray(bvh, origin, RAY_DIRECTION)
            payload = cutoff_sq - cutoff_sq
            hit = int(0)
            while wp.bvh_query_next(query, hit, 0.0):
                j = order[hit]
                if j == i:
                    continue
                if any_periodic and not gamma.is_canonical_image(
                        shift, ui, item_coords[hit], box, periodic):
                    continue
                d2 = _square_distance(xi, item_points[hit], box, periodic)
                if not (d2 < cutoff_sq):
                    continue
                payload = payload + seed_energy.clamped_lj(d2, params)
                n = n + 1
            wp.atomic_add(energy, i, payload)
    count[i] = n


@wp.kernel
def _pad_rows_kernel(count: wp.array(dtype=wp.int32), n_particles: wp.int32,
                     rows: wp.array2d(dtype=wp.int32)):
    """Pad row i past its count with N (after a query that appended to
    rows from both ends of each pair)."""
    i = wp.tid()
    width = rows.shape[1]
    for s in range(wp.min(count[i], width), width):
        rows[i, s] = n_particles


@wp.kernel
def _total_kernel(count: wp.array(dtype=wp.int32), offset: wp.array(dtype=wp.int32),
                  total: wp.array(dtype=wp.int32)):
    """total[0] = exclusive-scan end (launched with dim 1)."""
    last = count.shape[0] - 1
    total[0] = offset[last] + count[last]


@wp.kernel
def _pad_pairs_kernel(total: wp.array(dtype=wp.int32), n_particles: wp.int32,
                      pairs: wp.array2d(dtype=wp.int32)):
    """Pad the edge slots past the last edge with N."""
    s = wp.tid()
    if s >= total[0]:
        pairs[0, s] = n_particles
        pairs[1, s] = n_particles


# The overloads of the generic kernels, by (kernel, scalar type). Launching
# the overload itself skips Warp's inference of a generic kernel's argument
# types on every launch, which costs more than the rest of the launch
# and is paid by every kernel of every search call: the calls' fixed cost
# in Python.
_OVERLOADS: dict = {}


def instantiate(kernel, vectors=(), scalars=(), scalar_arrays=()):
    """Overload ``kernel`` for float32 and float64: ``vectors`` name arrays
    of positions, ``scalars`` name position-precision scalars,
    ``scalar_arrays`` arrays of them."""
    for scalar, vector in ((wp.float32, wp.vec3f), (wp.float64, wp.vec3d)):
        types = {name: wp.array(dtype=vector) for name in vectors}
        types.update({name: scalar for name in scalars})
        types.update({name: wp.array(dtype=scalar) for name in scalar_arrays})
        _OVERLOADS[kernel, scalar] = wp.overload(kernel, types)


def overload(kernel, scalar):
    """The overload of generic ``kernel`` (made by `instantiate`) for
    position precision ``scalar`` (``wp.float32`` or ``wp.float64``), to
    launch directly; Warp still checks every argument against it."""
    try:
        return _OVERLOADS[kernel, scalar]
    except KeyError:
        raise TypeError(f"{kernel.key} runs on float32 or float64 data; got "
                        f"{getattr(scalar, '__name__', scalar)}.") from None


instantiate(_extent_kernel, vectors=("points",))
instantiate(_morton_kernel, vectors=("points", "side"))
instantiate(_place_kernel, vectors=("points", "side", "item_points", "item_coords"))
instantiate(_cluster_box_kernel, vectors=("item_coords", "side"))
instantiate(_query_kernel, vectors=("item_points", "item_coords", "side"),
             scalars=("cutoff_sq",))
instantiate(_energy_kernel, vectors=("item_points", "item_coords", "side"),
             scalars=("cutoff_sq",), scalar_arrays=("params", "energy"))
instantiate(_query_radii_kernel, vectors=("item_points", "item_coords", "side"),
             scalar_arrays=("reach",))
instantiate(_item_reach_kernel, scalar_arrays=("reach",))


def vector_type(points: wp.array):
    """``wp.vec3`` or ``wp.vec3d``: the position type of ``points``."""
    if points.dtype not in (wp.vec3f, wp.vec3d):
        raise TypeError("points must be a Warp array of wp.vec3 (float32) or "
                        f"wp.vec3d (float64); got dtype {points.dtype}.")
    return points.dtype


def scalar_type(vector):
    return wp.float64 if vector is wp.vec3d else wp.float32


def load(device) -> None:
    """Compile/load this module's kernels on ``device`` now, so that the
    first search does not compile inside a JAX call."""
    wp.load_module(module=__name__, device=device)


# Warp's BVH constructors (wp.Bvh(constructor=...)); "cubql" needs CUDA.
BUILDERS = ("sah", "median", "lbvh", "cubql")


# The band outside the box in which a refit leaves items (and the drift
# policy's bound), in cutoffs: below 0.25 so that each pair's canonical
# image stays unique (`jaxrt.backends.rt.periodic`).
MAX_DRIFT_FRACTION = 0.25


def check_drift_fraction(drift_fraction: float) -> float:
    if not 0.0 <= drift_fraction < MAX_DRIFT_FRACTION:
        raise ValueError(f"drift_fraction must be in [0, {MAX_DRIFT_FRACTION})"
                         f"; got {drift_fraction}.")
    return float(drift_fraction)


class _Timer:
    """Times of the tree's updates and queries for the rebuild policy, read
    one call late so that the host never waits for the device: CUDA events
    on a GPU (reused from call to call), the host clock on a CPU (Warp's
    CPU launches are synchronous)."""

    def __init__(self, device):
        self.device = device
        self.events = device.is_cuda
        self.spans: dict[str, list] = {"action": [], "query": []}
        self._spare: list = []

    def start(self):
        if not self.events:
            return time.perf_counter()
        event = (self._spare.pop() if self._spare
                 else wp.Event(self.device, enable_timing=True))
        wp.record_event(event)
        return event

    def stop(self, kind: str, started) -> None:
        self.spans[kind].append((started, self.start()))

    def collect(self) -> tuple[float, float]:
        """(action seconds, query seconds) since the last collect; NaN
        where nothing was timed."""
        out = []
        for kind in ("action", "query"):
            spans, self.spans[kind] = self.spans[kind], []
            if not spans:
                out.append(math.nan)
            elif self.events:
                out.append(sum(wp.get_event_elapsed_time(a, b)
                               for a, b in spans) / 1e3)
                self._spare.extend(e for span in spans for e in span)
            else:
                out.append(sum(b - a for a, b in spans))
        return out[0], out[1]


class AabbSearch:
    """A BVH of custom AABBs over one system's particles, kept across calls.

    Arrays are owned here (a `wp.Bvh` keeps pointers to its bounds). Items
    are the particles in ``order`` (Morton order when ``sort``), so queries
    run in spatial order and index ``order`` to report caller indices.

    Attributes:
      n: number of particles N.
      vector: ``wp.vec3`` or ``wp.vec3d``, the position type.
      device: Warp device holding every array.
      order: int32 ``(N,)``, the particle held by each item.
      item_points: ``vector`` ``(N,)``, positions as given, item order.
      item_coords: ``vector`` ``(N,)``, positions the boxes are centred on
        (wrapped on periodic axes at a build; after a refit, the image
        nearest ``reference`` if within `band` of the box, else wrapped),
        item order.
      reference: ``wp.vec3`` ``(N,)``, ``item_coords`` at the last build.
      lowers, uppers: ``wp.vec3`` ``(ceil(N / cluster_size),)``, the boxes.
      cluster_size: particles per box. 1 is the seed's method (a box per
        particle); g > 1 puts one box around each run of g consecutive
        items (spatially compact when Morton-sorted), so the BVH has g
        times fewer leaves and every hit tests g particles exactly.
      constructor: Warp's builder ("lbvh", "cubql" on CUDA; "sah",
        "median" on CPU); leaf_size: boxes per BVH leaf. None of the three
        changes the result, only the speed (`benchmarks/rt_neighbors.py`
        sweeps them).
      last_update: "build", "rebuild" or "refit": what the last `update` did.
      last_reason: why it (re)built (`jaxrt.backends.rt.policy.REASONS`:
        "new", "setup", "policy"); "" after a refit.
      history: None, or a list to which every call appends ``(action,
        reason, t_action, t_query)`` (seconds, NaN where the policy times
        nothing), one call late (`flush_history` adds the last); for
        benchmarks.
    """

    def __init__(self, n: int, vector, device, *, sort: bool,
                 policy=_policy.Drift(), drift_fraction: float = 0.2,
                 constructor: str | None = None, leaf_size: int = 1,
                 cluster_size: int = 1):
        if n < 1:
            raise ValueError(f"need at least one particle; got n={n}.")
        for name, value in (("leaf_size", leaf_size), ("cluster_size", cluster_size)):
            if int(value) < 1:
                raise ValueError(f"{name} must be >= 1; got {value}.")
        self.n = n
        self.vector = vector
        self.scalar = scalar_type(vector)
        self.device = wp.get_device(device)
        self.sort = sort
        self.policy = _policy.resolve(policy)
        self.state = self.policy.start()
        self.may_refit = not isinstance(self.policy, _policy.Rebuild)
        self.drift_fraction = check_drift_fraction(drift_fraction)
        self._timer = (_Timer(self.device) if self.policy.needs_timing
                       else None)
        self._constructor = constructor
        self.leaf_size = int(leaf_size)
        self.cluster_size = int(cluster_size)
        n_clusters = -(-n // self.cluster_size)
        with wp.ScopedDevice(self.device):
            self.order = wp.array(np.arange(n, dtype=np.int32), dtype=wp.int32)
            self.item_points = wp.empty(n, dtype=vector)
            self.item_coords = wp.empty(n, dtype=vector)
            self.reference = wp.zeros(n, dtype=wp.vec3)
            self.item_reach = wp.empty(n, dtype=wp.float32)
            self.lowers = wp.empty(n_clusters, dtype=wp.vec3)
            self.uppers = wp.empty(n_clusters, dtype=wp.vec3)
            self.extent = wp.zeros(1, dtype=wp.float32)
            self.moved_far = wp.zeros(1, dtype=wp.int32)
            if sort:
                self.keys = wp.empty(2 * n, dtype=wp.int32)
                self.values = wp.empty(2 * n, dtype=wp.int32)
            # Stand-ins for the arrays a launch does not use, made once
            # rather than allocated on every call.
            self.no_rows = wp.empty((1, 0), dtype=wp.int32)
            self.no_ints = wp.empty(0, dtype=wp.int32)
            self.no_reach = wp.empty(1, dtype=self.scalar)
        self.bvh = None
        self.last_update = None
        self.last_reason = ""
        self._cutoff = None
        self._periodic = None
        self._reach = None
        self.history = None

    @property
    def constructor(self) -> str:
        """Warp's BVH builder: as given, else LBVH on CUDA and SAH on CPU."""
        if self._constructor is not None:
            return self._constructor
        return "lbvh" if self.device.is_cuda else "sah"

    def update(self, points: wp.array, side: wp.array, periodic: tuple[bool, bool, bool],
               cutoff: float, reach: wp.array | None = None) -> str:
        """Fit the BVH to ``points``: build, refit or rebuild (`jaxrt.backends.rt.policy`).

        Args:
          points: ``vector`` ``(N,)`` Cartesian positions.
          side: ``vector`` ``(1,)``, box sides (read on periodic axes).
          periodic: one bool per axis.
          cutoff: box half-width (the search radius); with ``reach``, the
            largest radius (it sets the gamma rays' reach and the band).
          reach: None, or position-precision scalars ``(N,)`` in caller
            order: per-particle radii (seed 003 §3), each item's box
            half-width; a pair is listed when ``d < max(r_i, r_j)``.
        Returns:
          what was done: "build", "rebuild" or "refit".
        """
        if points.shape[0] != self.n or points.dtype != self.vector:
            raise ValueError(f"points must be {self.n} {self.vector.__name__}; got "
                             f"{points.shape[0]} {points.dtype.__name__}.")
        flags = wp.vec3i(*(int(bool(p)) for p in periodic))
        half_width = float(np.float32(cutoff))
        band = self.band(cutoff)
        # A refit recomputes every box, so it would be exact here too; a
        # tree built for another cutoff or periodicity is rebuilt because
        # its topology fits another problem (radii may change from call to
        # call: a refit resizes the boxes).
        setup = (cutoff, tuple(periodic), reach is None)
        same_setup = (self._cutoff, self._periodic, self._reach is None) == setup
        if self.history is not None and self._timer is None:
            self._timer = _Timer(self.device)  # a benchmark times every policy
        if self.last_update is not None:
            times = ((math.nan, math.nan) if self._timer is None
                     else self._timer.collect())
            self.state.record(self.last_update, *times)
            if self.history is not None:
                self.history.append((self.last_update, self.last_reason,
                                     *times))
        with wp.ScopedDevice(self.device):
            started = None if self._timer is None else self._timer.start()
            self.extent.zero_()
            wp.launch(overload(_extent_kernel, self.scalar), self.n,
                      inputs=[points, self.extent])
            placed = False
            if self.bvh is None:
                action, reason = "build", "new"
            elif not same_setup:
                action, reason = "rebuild", "setup"
            else:
                drifted = False
                # Only the drift policy reads the drift back: the read
                # stalls the host until the device has caught up.
                if self.policy.needs_drift:
                    self.moved_far.zero_()
                    self._place(points, side, flags, True, band)
                    placed = True
                    drifted = bool(self.moved_far.numpy()[0])
                action = _policy.choose(self.state, has_tree=True,
                                        drifted=drifted)
                reason = "policy" if action == "rebuild" else ""
            self._reach = reach
            if action == "refit":
                if not placed:
                    self._place(points, side, flags, True, band)
                self._item_reach()
                self._boxes(side, flags, half_width)
                self.bvh.refit()
            else:
                if self.sort:
                    wp.launch(overload(_morton_kernel, self.scalar), self.n,
                              inputs=[points, side, flags, self.order,
                                      _MORTON_CELLS_PER_CUTOFF / half_width,
                                      self.keys, self.values])
                    wp.utils.radix_sort_pairs(self.keys, self.values, self.n,
                                              end_bit=30)
                    wp.copy(self.order, self.values, count=self.n)
                self._place(points, side, flags, False, band)
                self._item_reach()
                self._boxes(side, flags, half_width)
                if self.bvh is None:
                    self.bvh = wp.Bvh(self.lowers, self.uppers,
                                      constructor=self.constructor,
                                      leaf_size=self.leaf_size)
                else:
                    self.bvh.rebuild(self.constructor)
            if started is not None:
                self._timer.stop("action", started)
        self._cutoff, self._periodic = cutoff, tuple(periodic)
        self.last_update, self.last_reason = action, reason
        return action

    def flush_history(self) -> None:
        """Append the last call's times to `history` (waits for the device)."""
        if self.history is not None and self.last_update is not None:
            times = ((math.nan, math.nan) if self._timer is None
                     else self._timer.collect())
            self.history.append((self.last_update, self.last_reason, *times))

    def band(self, cutoff: float) -> float:
        """How far outside the box a refit may leave an item (following
        the image of it nearest its build-time position) before it wraps
        it: the drift bound, ``drift_fraction`` of the cutoff (0 for a
        policy that never refits). The gamma rays reach this much farther
        (`jaxrt.backends.rt.periodic`)."""
        return self.drift_fraction * cutoff if self.may_refit else 0.0

    def _place(self, points, side, flags, has_reference, band):
        wp.launch(overload(_place_kernel, self.scalar), self.n,
                  inputs=[points, side, flags, self.order,
                          int(has_reference), band, self.reference,
                          self.item_points, self.item_coords, self.moved_far])

    def _item_reach(self):
        if self._reach is not None:
            wp.launch(overload(_item_reach_kernel,
                               self._reach.dtype), self.n,
                      inputs=[self.order, self._reach, self.item_reach])

    def _boxes(self, side, flags, half_width):
        wp.launch(overload(_cluster_box_kernel, self.scalar),
                  self.lowers.shape[0],
                  inputs=[self.item_coords, side, flags, self.cluster_size,
                          half_width, self.extent, int(self._reach is not None),
                          self.item_reach, self.lowers, self.uppers])

    def query(self, side: wp.array, *, mask_self: bool, lower_only: bool, mode: int,
              rows: wp.array | None = None, row_offset: wp.array | None = None,
              pairs: wp.array | None = None, count: wp.array) -> None:
        """One query pass over the tree built by the last `update`.

        Args:
          side: as in `update`.
          mask_self: drop ``j == i``; lower_only: keep only ``j < i``.
          mode: MODE_DENSE (fills ``rows``), MODE_COUNT, or MODE_FILL (fills
            ``pairs`` at ``row_offset``).
          rows: int32 ``(N, width)``; each row left-packed, padded with N.
          row_offset: int32 ``(N,)``, first edge slot of each particle.
          pairs: int32 ``(2, capacity)`` = (receivers j, senders i).
          count: int32 ``(N,)`` output, exact neighbours per particle.
        """
        if self.bvh is None:
            raise RuntimeError("query before update: call update(points, ...) first.")
        with wp.ScopedDevice(self.device):
            started = None if self._timer is None else self._timer.start()
            empty2, empty1 = self.no_rows, self.no_ints
            flags = wp.vec3i(*(int(p) for p in self._periodic))
            if self._reach is not None:
                # Rows grow from both ends of a pair: cursors from zero.
                count.zero_()
                wp.launch(overload(_query_radii_kernel, self.scalar), self.n,
                          inputs=[wp.uint64(self.bvh.id), self.item_points,
                                  self.item_coords, self.order, side, flags,
                                  self._reach, float(np.float32(self._cutoff)),
                                  self.extent, self.band(self._cutoff),
                                  int(mask_self), int(lower_only), int(mode),
                                  self.cluster_size,
                                  empty2 if rows is None else rows,
                                  empty1 if row_offset is None else row_offset,
                                  empty2 if pairs is None else pairs, count])
                if mode == MODE_DENSE:
                    wp.launch(_pad_rows_kernel, self.n,
                              inputs=[count, self.n, rows])
            else:
                wp.launch(overload(_query_kernel, self.scalar), self.n,
                          inputs=[wp.uint64(self.bvh.id), self.item_points, self.item_coords,
                                  self.order, side, flags,
                                  self.scalar(float(self._cutoff) ** 2),
                                  float(np.float32(self._cutoff)), self.extent,
                                  self.band(self._cutoff),
                                  int(mask_self), int(lower_only), int(mode),
                                  self.cluster_size,
                                  empty2 if rows is None else rows,
                                  empty1 if row_offset is None else row_offset,
                                  empty2 if pairs is None else pairs, count])
            if started is not None:
                self._timer.stop("query", started)

    def query_dense(self, side, *, mask_self: bool, rows: wp.array, count: wp.array):
        """Dense rows: int32 ``rows`` ``(N, width)`` and exact ``count`` ``(N,)``."""
        self.query(side, mask_self=mask_self, lower_only=False, mode=MODE_DENSE,
                   rows=rows, count=count)

    def energy(self, side: wp.array, params: wp.array, *, energy: wp.array,
               count: wp.array) -> None:
        """Seed 001's fused mode on the tree of the last `update`: the LJ
        energy of `jaxrt.backends.rt.seed_energy` summed during the traversal, no
        list (self pairs dropped).

        Args:
          side: as in `update`.
          params: position-precision ``(seed_energy.N_PARAMS,)``
            (`seed_energy.lj_params`).
          energy: position-precision ``(N,)`` output, ``E_i = sum_j U(r_ij)``
            (zeroed here).
          count: int32 ``(N,)`` output, pairs of each particle (the Dense
            row count with ``mask_self``).
        Raises:
          ValueError: a tree with per-particle radii or clusters (the
            seed's method has neither), or arrays of the wrong type.
        """
        if self.bvh is None:
            raise RuntimeError("energy before update: call update(points, ...) first.")
        if self._reach is not None or self.cluster_size != 1:
            raise ValueError(
                "the fused energy is the seed's custom AABB method: one box of "
                "half-width cutoff per particle. Fit the tree without reach "
                f"(radii) and with cluster_size=1 (got cluster_size="
                f"{self.cluster_size}, radii={self._reach is not None}).")
        for name, array, dtype in (("params", params, self.scalar),
                                   ("energy", energy, self.scalar),
                                   ("count", count, wp.int32)):
            if array.dtype != dtype:
                raise ValueError(f"{name} must hold {dtype.__name__} for "
                                 f"{self.vector.__name__} positions; got "
                                 f"{array.dtype.__name__}.")
        if energy.shape != (self.n,) or count.shape != (self.n,) \
                or params.shape != (seed_energy.N_PARAMS,):
            raise ValueError(f"energy and count must be ({self.n},), params "
                             f"({seed_energy.N_PARAMS},); got {energy.shape}, "
                             f"{count.shape}, {params.shape}.")
        with wp.ScopedDevice(self.device):
            started = None if self._timer is None else self._timer.start()
            energy.zero_()
            flags = wp.vec3i(*(int(p) for p in self._periodic))
            wp.launch(overload(_energy_kernel, self.scalar), self.n,
                      inputs=[wp.uint64(self.bvh.id), self.item_points,
                              self.item_coords, self.order, side, flags,
                              self.scalar(float(self._cutoff) ** 2),
                              float(np.float32(self._cutoff)), self.extent,
                              self.band(self._cutoff), params, energy,
                              count])
            if started is not None:
                self._timer.stop("query", started)

    def query_sparse(self, side, *, mask_self: bool, lower_only: bool,
                     pairs: wp.array, count: wp.array, offset: wp.array,
                     total: wp.array) -> None:
        """Edges without an N x capacity detour: count, scan, fill.

        Args:
          pairs: int32 ``(2, capacity)`` output, (receivers j, senders i),
            edges grouped by sender in ascending order, padded with N.
          count, offset: int32 ``(N,)`` outputs, edges per sender and where
            they start.
          total: int32 ``(1,)`` output, the exact number of edges (may
            exceed capacity).
        """
        self.query(side, mask_self=mask_self, lower_only=lower_only,
                   mode=MODE_COUNT, count=count)
        with wp.ScopedDevice(self.device):
            wp.utils.array_scan(count, offset, inclusive=False)
            wp.launch(_total_kernel, 1, inputs=[count, offset, total])
        self.query(side, mask_self=mask_self, lower_only=lower_only,
                   mode=MODE_FILL, row_offset=offset, pairs=pairs, count=count)
        with wp.ScopedDevice(self.device):
            wp.launch(_pad_pairs_kernel, pairs.shape[1],
                      inputs=[total, self.n, pairs])


class AabbMethod:
    """The `RTMethod` of the custom AABB (one BVH per call, nothing kept).

    Attributes:
      name: "aabb" or "aabb-unsorted".
      sort: Morton-sort particles before building.
    """

    def __init__(self, sort: bool = True):
        self.sort = sort
        self.name = "aabb" if sort else "aabb-unsorted"

    def _fresh_search(self, points: wp.array, cutoff: float, side, periodic):
        """An `AabbSearch` built on ``points`` (arguments checked) and its
        ``(1,)`` side array."""
        vector = vector_type(points)
        periodic = tuple(bool(p) for p in periodic)
        if len(periodic) != 3:
            raise ValueError(f"periodic must hold 3 bools; got {periodic}.")
        if any(periodic) and side is None:
            raise ValueError("side must give the box sides when an axis is periodic.")
        box = (1.0, 1.0, 1.0) if side is None else tuple(float(s) for s in side)
        check_cutoff(cutoff, box, periodic)
        search = AabbSearch(points.shape[0], vector, points.device, sort=self.sort)
        side_array = wp.array([box], dtype=vector, device=points.device)
        search.update(points, side_array, periodic, cutoff)
        return search, side_array

    def find(self, points: wp.array, *, cutoff: float,
             side: tuple[float, float, float] | None,
             periodic: tuple[bool, bool, bool], mask_self: bool,
             out_idx: wp.array2d, out_count: wp.array) -> None:
        """See `jaxrt.backends.rt.method.RTMethod.find`."""
        search, side_array = self._fresh_search(points, cutoff, side, periodic)
        search.query_dense(side_array, mask_self=mask_self, rows=out_idx,
                           count=out_count)

    def energy(self, points: wp.array, *, cutoff: float,
               side: tuple[float, float, float] | None,
               periodic: tuple[bool, bool, bool], params: wp.array,
               out_energy: wp.array, out_count: wp.array) -> None:
        """The fused mode (`jaxrt.backends.rt.seed_energy`) on a fresh tree; see
        `jaxrt.backends.rt.spheres.SpheresMethod.energy` for the arguments."""
        search, side_array = self._fresh_search(points, cutoff, side, periodic)
        search.energy(side_array, params, energy=out_energy, count=out_count)
