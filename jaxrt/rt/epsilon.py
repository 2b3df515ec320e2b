"""What the sphere and double-square methods share: their ε, checks, images.

Seed 001 (Algis & Bramas), §4.2, §4.3 and Appendix 7: the sphere method
gives each particle a sphere of radius ``r = C·√2/√3 + ε`` and casts three
axis rays of half-length ``l = C·√2/√3``; the double-square method widens its
squares and rays by ε. Appendix 7 requires "that it must be impossible that
two particles are closer than ε, or some intersections will be missed":
when a source lies within ε of a target, the source's sphere swallows the
target's whole cross of rays and no ray crosses its surface.

The rule chosen here
--------------------
``ε = 2**-40 · scale`` with ``scale = max(C, max |coordinate|, side on
periodic axes)``.

Why this size: ε must exceed the rounding error of the arithmetic that
decides the intersections, and nothing else. Both methods decide every
intersection in float64 on positions converted exactly from the caller's
float32 or float64 (the float32 BVH only proposes candidates, its boxes
padded by `bvh_padding`), so the error of a coordinate difference is at most
half an ulp of ``scale`` in float64, ``2**-53 · scale``; the sphere test's
margin at separation ``2ε`` is ``0.31·l·ε`` (see `sphere_resolution`), which
is then ~10³ times that error. A float32-sized ε (2**-20 · scale, say) would
flag particles a micrometre apart in a metre box for no reason.

What the contract promises
--------------------------
* Spheres: every pair separated by at least ``sphere_resolution(ε) = 2ε``
  is found exactly once per direction. Closer pairs may be missed (a pair
  closer than ε always is; on the cube diagonal the blind zone reaches √3·ε).
  The sphere kernel flags any candidate pair closer than ``2ε`` while it
  searches, and `SpheresMethod.find` raises `ParticlesTooCloseError` (or, with
  ``check_separation=False``, leaves the flag for the caller to read).
* Double squares: no separation limit. The seed drops self hits with
  ``dist > ε``, which also drops real pairs closer than ε; jaxrt drops self
  hits by index instead, and decides the ray–square hits exactly (see
  `jaxrt.rt.squares`), so coincident particles are found too.
* `closest_pair_below` answers the same question for any points, for a
  caller that wants to check before choosing a method.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import warp as wp

EPSILON_RELATIVE = 2.0 ** -40
"""ε as a fraction of the data's scale (module docstring)."""

SPHERE_RESOLUTION_FACTOR = 2.0
"""The sphere method finds every pair at least this many ε apart."""

_BVH_PADDING_RELATIVE = 2.0 ** -16
"""float32 BVH boxes are widened by this fraction of the scale: 128 float32
ulps, far above the rounding of a float64 → float32 conversion plus the few
float32 operations that build a box or a ray origin. It also keeps every
needed candidate's box strictly around the axis-aligned rays: Warp's
``bvh_query_ray`` slab test computes ``0·inf = NaN`` for a ray lying exactly
in a node's face, which can prune that node."""


class ParticlesTooCloseError(ValueError):
    """Two particles are closer than a method's resolution (module docstring).

    Attributes:
      pair: the indices ``(i, j)`` of one offending pair.
      distance: the resolution that they are closer than.
    """

    def __init__(self, message: str, pair: tuple[int, int], distance: float):
        super().__init__(message)
        self.pair = pair
        self.distance = distance


def seed_epsilon(scale: float) -> float:
    """The ε of seed 001 §4.2/§4.3 for data of the given scale (module docstring)."""
    return EPSILON_RELATIVE * scale


def sphere_resolution(epsilon: float) -> float:
    """Smallest separation the sphere method is guaranteed to resolve.

    The closest-axis ray crosses the source's sphere iff its far endpoint is
    outside, ``|d|² + 2·l·|d_k| ≥ 2·l·ε + ε²`` (``d`` the separation, ``k``
    its largest component). With ``|d_k| ≥ |d|/√3`` this holds for
    ``|d| ≥ √3·ε``; at ``2ε`` the left side exceeds the right by ``0.31·l·ε``.
    """
    return SPHERE_RESOLUTION_FACTOR * epsilon


def bvh_padding(scale: float) -> float:
    """How far the float32 BVH boxes and rays are widened beyond the exact
    geometry, so that rounding never hides a candidate."""
    return _BVH_PADDING_RELATIVE * scale


# ---------------------------------------------------------------------------
# Positions as the kernels see them.


@wp.func
def wrap_into_box(p: wp.vec3d, side: wp.vec3d, periodic: wp.vec3i) -> wp.vec3d:
    """``p`` wrapped into ``[0, side)`` on periodic axes (callers pass
    positions unwrapped). Points already in the box are returned bit for bit,
    so their pair tests round exactly as the float64 oracle's. Non-finite
    coordinates stay non-finite: every exact test on them is false."""
    wrapped = p
    for axis in range(3):
        if periodic[axis] != 0:
            v = p[axis]
            if v < wp.float64(0.0) or v >= side[axis]:
                v = v - side[axis] * wp.floor(v / side[axis])
                if v < wp.float64(0.0):
                    v = v + side[axis]
                if v >= side[axis]:
                    v = wp.float64(0.0)
            wrapped[axis] = v
    return wrapped


@wp.func
def geometry_point(p: wp.vec3d) -> wp.vec3:
    """float32 position for BVH boxes and ray origins; a non-finite particle
    is placed at the origin so that no box is NaN (the exact tests, on the
    real coordinates, then reject all its pairs)."""
    if not wp.isfinite(p):
        return wp.vec3(0.0)
    return wp.vec3(p)


@wp.kernel
def _survey_kernel(
    points: wp.array(dtype=Any),
    side: wp.vec3d,
    periodic: wp.vec3i,
    max_abs: wp.array(dtype=wp.float64),  # (1,): largest finite |coordinate|
):
    i = wp.tid()
    p = wrap_into_box(wp.vec3d(points[i]), side, periodic)
    largest = wp.float64(0.0)
    for axis in range(3):
        if wp.isfinite(p[axis]):
            largest = wp.max(largest, wp.abs(p[axis]))
    wp.atomic_max(max_abs, 0, largest)


for _point_type in (wp.vec3, wp.vec3d):
    wp.overload(_survey_kernel, {"points": wp.array(dtype=_point_type)})


@dataclasses.dataclass(frozen=True)
class Survey:
    """The data's scale and what follows from it.

    Attributes:
      scale: ``max(C, max finite |coordinate| after wrapping, side on
        periodic axes)``.
      epsilon: `seed_epsilon` of ``scale``.
      padding: `bvh_padding` of ``scale``.
    """

    scale: float
    epsilon: float
    padding: float


@dataclasses.dataclass(frozen=True)
class FindArguments:
    """The arguments of ``RTMethod.find``, checked and normalised.

    Attributes:
      cutoff: the search radius C (> 0, finite).
      side: box side per axis; zeros on axes that are not periodic.
      periodic: one bool per axis.
      mask_self: drop ``i == i`` pairs.
    """

    cutoff: float
    side: tuple[float, float, float]
    periodic: tuple[bool, bool, bool]
    mask_self: bool

    @property
    def side_vec(self) -> wp.vec3d:
        return wp.vec3d(*self.side)

    @property
    def periodic_vec(self) -> wp.vec3i:
        return wp.vec3i(*(int(p) for p in self.periodic))


def check_find_arguments(method: str, points: wp.array, cutoff: float,
                         side, periodic, mask_self, out_idx: wp.array,
                         out_count: wp.array) -> FindArguments:
    """Validate ``find``'s arguments; raise a clear error naming the bad one.

    Args:
      method: the method's name, for messages.
      points: ``(N,)`` wp.vec3 or wp.vec3d.
      out_idx: int32 ``(N, width)``; out_count: int32 ``(N,)``, same device.
    """
    if not isinstance(points, wp.array) or points.dtype not in (wp.vec3, wp.vec3d) \
            or points.ndim != 1:
        raise TypeError(
            f"{method}.find: points must be a 1-D wp.array of wp.vec3 (float32) or "
            f"wp.vec3d (float64); got {_describe(points)}. Pad 2-D positions with z = 0.")
    n = points.shape[0]
    if not isinstance(out_idx, wp.array) or out_idx.dtype != wp.int32 or out_idx.ndim != 2 \
            or out_idx.shape[0] != n:
        raise TypeError(
            f"{method}.find: out_idx must be a wp.array2d of int32 with shape (N, width) = "
            f"({n}, width); got {_describe(out_idx)}.")
    if not isinstance(out_count, wp.array) or out_count.dtype != wp.int32 \
            or out_count.shape != (n,):
        raise TypeError(
            f"{method}.find: out_count must be a wp.array of int32 with shape ({n},); "
            f"got {_describe(out_count)}.")
    for name, array in (("out_idx", out_idx), ("out_count", out_count)):
        if array.device != points.device:
            raise ValueError(
                f"{method}.find: {name} is on {array.device} but points are on "
                f"{points.device}; allocate it on the points' device.")
    if isinstance(cutoff, (bool, np.bool_)) \
            or not isinstance(cutoff, (int, float, np.floating, np.integer)) \
            or not math.isfinite(cutoff) or cutoff <= 0:
        raise ValueError(f"{method}.find: cutoff must be a finite number > 0; got {cutoff!r}.")
    cutoff = float(cutoff)
    if not isinstance(mask_self, (bool, np.bool_)):
        raise TypeError(f"{method}.find: mask_self must be a bool; got {mask_self!r}.")
    periodic = tuple(periodic)
    if len(periodic) != 3 or not all(isinstance(p, (bool, np.bool_)) for p in periodic):
        raise ValueError(
            f"{method}.find: periodic must be three bools (x, y, z; pad 2-D with False); "
            f"got {periodic!r}.")
    periodic = tuple(bool(p) for p in periodic)
    if not any(periodic):
        return FindArguments(cutoff, (0.0, 0.0, 0.0), periodic, bool(mask_self))
    if side is None or len(tuple(side)) != 3:
        raise ValueError(
            f"{method}.find: periodic={periodic} needs side=(Lx, Ly, Lz), the box side "
            f"per axis; got side={side!r}.")
    side = tuple(float(s) for s in side)
    for axis in range(3):
        if not periodic[axis]:
            continue
        if not (math.isfinite(side[axis]) and side[axis] > 0):
            raise ValueError(
                f"{method}.find: side[{axis}] must be finite and > 0 on a periodic axis; "
                f"got {side[axis]!r}.")
        if cutoff > side[axis] / 2:
            raise ValueError(
                f"{method}.find: cutoff={cutoff} exceeds side[{axis}]/2 = {side[axis] / 2}. "
                f"The periodic images (seed 003 §3.3 gamma rays) assume at most one image "
                f"of a particle within the cutoff; use backend='cell' or 'brute' for boxes "
                f"this small.")
    side = tuple(s if p else 0.0 for s, p in zip(side, periodic))
    return FindArguments(cutoff, side, periodic, bool(mask_self))


def survey(points: wp.array, args: FindArguments) -> Survey:
    """The points' scale, hence ε and the BVH padding (a Warp reduction;
    reads one float64 back to the host, a device sync)."""
    n = points.shape[0]
    max_abs = wp.zeros(1, dtype=wp.float64, device=points.device)
    if n:
        wp.launch(_survey_kernel, dim=n, device=points.device,
                  inputs=[points, args.side_vec, args.periodic_vec], outputs=[max_abs])
    scale = max(args.cutoff, float(max_abs.numpy()[0]), *args.side)
    return Survey(scale=scale, epsilon=seed_epsilon(scale), padding=bvh_padding(scale))


def _describe(value) -> str:
    if isinstance(value, wp.array):
        return f"wp.array(dtype={wp.types.type_repr(value.dtype)}, shape={value.shape})"
    return type(value).__name__


# ---------------------------------------------------------------------------
# Periodic images: the gamma rays of seed 003 §3.3.
#
# A target within the cutoff of a periodic face also casts its rays from its
# image one box away (on every combination of such axes: up to 7 images).
# With ``cutoff <= side / 2`` at most one image of a target lies within the
# cutoff of a source, so each pair is still found once per direction.


@wp.func
def image_shifts(target: wp.vec3d, cutoff: wp.float64, side: wp.vec3d,
                 periodic: wp.vec3i, slack: wp.float64) -> wp.vec3d:
    """The shift of the target's image on each axis, 0 where none is cast.

    ``slack`` (ε) casts images a hair early: the pair test rounds
    ``(s − t) − shift`` in float64 and may accept a pair that exact
    arithmetic puts exactly at the cutoff. Splitting at ``side / 2`` keeps a
    target from casting both a +side and a −side image.
    """
    shifts = wp.vec3d(wp.float64(0.0))
    for axis in range(3):
        if periodic[axis] != 0:
            if target[axis] < wp.float64(0.5) * side[axis]:
                if target[axis] < cutoff + slack:
                    shifts[axis] = side[axis]
            else:
                if target[axis] > side[axis] - cutoff - slack:
                    shifts[axis] = -side[axis]
    return shifts


@wp.func
def image_is_cast(image: int, shifts: wp.vec3d) -> bool:
    """Image ``image`` (bit k set: shifted on axis k) exists for these shifts."""
    for axis in range(3):
        if (image >> axis) & 1 == 1 and shifts[axis] == wp.float64(0.0):
            return False
    return True


@wp.func
def image_offset(image: int, shifts: wp.vec3d) -> wp.vec3d:
    offset = wp.vec3d(wp.float64(0.0))
    for axis in range(3):
        if (image >> axis) & 1 == 1:
            offset[axis] = shifts[axis]
    return offset


# ---------------------------------------------------------------------------
# The separation check on its own.


@wp.kernel
def _point_boxes_kernel(points: wp.array(dtype=Any), half_width: float,
                        lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    centre = geometry_point(wp.vec3d(points[i]))
    lowers[i] = centre - wp.vec3(half_width)
    uppers[i] = centre + wp.vec3(half_width)


@wp.kernel
def _pair_below_kernel(bvh: wp.uint64, points: wp.array(dtype=Any),
                       distance_sq: wp.float64,
                       lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3),
                       pair: wp.array(dtype=wp.int32)):  # (3,): found flag, i, j
    i = wp.tid()
    p = wp.vec3d(points[i])
    query = wp.bvh_query_aabb(bvh, lowers[i], uppers[i])
    j = int(0)
    while wp.bvh_query_next(query, j):
        if j > i:
            d = wp.vec3d(points[j]) - p
            if d[0] * d[0] + d[1] * d[1] + d[2] * d[2] < distance_sq:
                # Any offending pair will do; the compare-and-swap keeps i and j
                # from the same thread.
                if wp.atomic_cas(pair, 0, 0, 1) == 0:
                    pair[1] = i
                    pair[2] = j


for _point_type in (wp.vec3, wp.vec3d):
    wp.overload(_point_boxes_kernel, {"points": wp.array(dtype=_point_type)})
    wp.overload(_pair_below_kernel, {"points": wp.array(dtype=_point_type)})


def pair_below(points: wp.array, distance: float) -> tuple[int, int] | None:
    """One pair ``(i, j)``, ``i < j``, with ``|p_i − p_j| < distance`` (float64
    test), or None. Free space (no periodic images); non-finite points are
    never close to anything.

    Args:
      points: ``(N,)`` wp.vec3 or wp.vec3d.
      distance: float ≥ 0.
    """
    if not isinstance(points, wp.array) or points.dtype not in (wp.vec3, wp.vec3d):
        raise TypeError(f"pair_below: points must be a wp.array of wp.vec3 or wp.vec3d; "
                        f"got {_describe(points)}.")
    if not (math.isfinite(distance) and distance >= 0):
        raise ValueError(f"pair_below: distance must be finite and >= 0; got {distance!r}.")
    n = points.shape[0]
    if n < 2 or distance == 0:
        return None
    device = points.device
    free_space = FindArguments(float(distance), (0.0, 0.0, 0.0), (False, False, False), True)
    half_width = distance + survey(points, free_space).padding
    lowers = wp.empty(n, dtype=wp.vec3, device=device)
    uppers = wp.empty(n, dtype=wp.vec3, device=device)
    wp.launch(_point_boxes_kernel, dim=n, device=device,
              inputs=[points, float(half_width)], outputs=[lowers, uppers])
    bvh = wp.Bvh(lowers, uppers)
    pair = wp.zeros(3, dtype=wp.int32, device=device)
    wp.launch(_pair_below_kernel, dim=n, device=device,
              inputs=[wp.uint64(bvh.id), points, wp.float64(distance * distance), lowers, uppers],
              outputs=[pair])
    found, i, j = (int(v) for v in pair.numpy())
    return (i, j) if found else None


def closest_pair_below(points: wp.array, distance: float) -> bool:
    """True iff two of ``points`` are closer than ``distance`` (float64 test).

    A Warp kernel over a BVH of the points; free space. To check the sphere
    method's contract call it with ``sphere_resolution(ε)``.

    Args:
      points: ``(N,)`` wp.vec3 or wp.vec3d.
      distance: float ≥ 0.
    """
    return pair_below(points, distance) is not None
