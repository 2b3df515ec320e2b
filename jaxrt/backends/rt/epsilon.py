"""The ε of the sphere and double-square methods, and what follows from it.

This module holds the seed's ε (`seed_epsilon`) and the sphere method's
resolution (`sphere_resolution`), the padding of the float32 BVH geometry
(`bvh_padding`, `geometry_point`), the survey of the points' scale that sets
both (`survey`), and the separation check (`pair_below`,
`closest_pair_below`, `ParticlesTooCloseError`). ``find``'s argument checks
live with the protocol (`jaxrt.backends.rt.method`), the periodic images with the
gamma rays (`jaxrt.backends.rt.periodic`).

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
  `jaxrt.backends.rt.squares`), so coincident particles are found too.
* `closest_pair_below` answers the same question for any points, for a
  caller that wants to check before choosing a method.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import warp as wp

from jaxrt.errors import Error

from jaxrt.backends.rt.method import FindArguments, describe
from jaxrt.backends.rt.periodic import wrap_into_box

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


class ParticlesTooCloseError(Error, ValueError):
    """Two particles are closer than a method's resolution (module docstring).

    Attributes:
      pair: the indices ``(i, j)`` of one offending pair.
      distance: the resolution that they are closer than.
    """

    def __init__(self, message: str, pair: tuple[int, int], distance: float):
        super().__init__(message)
        self.pair = pair
        self.distance = distance


def seed_epsilon(scale: float, relative: float = EPSILON_RELATIVE) -> float:
    """The ε of seed 001 §4.2/§4.3 for data of the given scale (module
    docstring); ``relative``: ε as a fraction of the scale."""
    return relative * scale


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
# The float32 geometry of the BVH.


@wp.func
def geometry_point(p: wp.vec3d) -> wp.vec3:
    """float32 position for BVH boxes and ray origins; a non-finite particle
    is placed at the origin so that no box is NaN (the exact tests, on the
    real coordinates, then reject all its pairs)."""
    if not wp.isfinite(p):
        return wp.vec3(0.0)
    return wp.vec3(p)


# ---------------------------------------------------------------------------
# The survey: the points' scale, hence ε and the padding.


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


def survey(points: wp.array, args: FindArguments,
           epsilon_relative: float = EPSILON_RELATIVE) -> Survey:
    """The points' scale, hence ε (``epsilon_relative`` of it) and the BVH
    padding (a Warp reduction; reads one float64 back to the host, a device
    sync)."""
    n = points.shape[0]
    max_abs = wp.zeros(1, dtype=wp.float64, device=points.device)
    if n:
        wp.launch(_survey_kernel, dim=n, device=points.device,
                  inputs=[points, args.side_vec, args.periodic_vec], outputs=[max_abs])
    scale = max(args.cutoff, float(max_abs.numpy()[0]), *args.side)
    return Survey(scale=scale, epsilon=seed_epsilon(scale, epsilon_relative),
                  padding=bvh_padding(scale))


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
                        f"got {describe(points)}.")
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
