"""Periodic boundaries by gamma rays: Meneses et al., "Advancing RT
Core-Accelerated Fixed-Radius Nearest Neighbor Search", §3.3.

No ghost particles: the BVH holds each particle's box once, at its wrapped
position. A particle within the search radius of a face also casts a ray
from its image across that face ("gamma" ray), one per combination of the
faces it is near: up to 7 extra rays at a 3D corner (the seed's
``γ_x, γ_y, γ_{x,y}``, and ``z`` combinations).

Each pair must be reported once. For a cutoff below half the box side only
one image of ``j`` can be within reach of ``i``; to make that hold under
rounding as well, the custom AABB method (`jaxrt.backends.rt.aabb`) keeps a hit only
from the ray whose shift is the pair's *canonical image*, a deterministic
function of the two box centres (`is_canonical_image`). That ray is always
cast when the pair is in range (`ray_is_cast`), so no pair is lost and none
is doubled.

Items refitted rather than rebuilt may sit up to a ``band`` outside the box
(they follow the image nearest where the last build put them while it lies
within the band, and are wrapped beyond it, see `jaxrt.backends.rt.aabb`);
rays account for that through ``face_reach``. Only where the items sit
matters, not how far they moved: with every centre within the band of the
box, the band below a quarter of the cutoff and the cutoff below half the
side, a pair at minimum-image displacement ``m`` (``|m| < cutoff``) has
centre difference ``m + kL`` with ``k`` in ``{-1, 0, 1}``, so the canonical
rule picks ``k``, whose ray is cast.

The seed-001 methods (`jaxrt.backends.rt.spheres`, `jaxrt.backends.rt.squares`) number and
place their gamma rays the same way (`ray_shift`, `shifted`) but choose
which to cast differently (`near_faces`, `crosses_near_faces`): in float64,
split at half the side so that a particle casts at most one image per axis,
and a hair early (by their ε) so that the float64 pair test, which may round
a pair at exactly the cutoff in, always has the ray it needs. They need no
canonical-image filter: with the cutoff below half the side at most one
image of a target is within the cutoff of a source.

All three methods refuse the same cutoffs with the same message:
`check_cutoff` (the rule `cutoff_fits`, the message `cutoff_error`).

Warp functions here are generic over the position type (``wp.vec3`` or
``wp.vec3d``), with ``box`` a vector of the same type, except those of the
seed-001 methods, which are float64 (their ε contract needs it).
"""
from __future__ import annotations

from typing import Any

import warp as wp

# The half-box rule, re-exported for the methods that import it from here.
from jaxrt.backends.rt.halfbox import (CUTOFF_MARGIN,  # noqa: F401
                                       check_cutoff, cutoff_error,
                                       cutoff_fits)

RAYS_PER_PARTICLE = wp.constant(27)  # all shift combinations; ray 0 is direct


# ---------------------------------------------------------------------------
# Positions wrapped into the box: one formula (`wrap_coordinate`), two
# variants. The AABB method's (`wrap_point`, float32 or float64) turns
# non-finite coordinates into 0, since its boxes must not be NaN. The
# seed-001 methods' (`wrap_into_box`, float64) keeps them non-finite, so that
# their exact tests reject every pair of such a particle, and leaves points
# already in the box untouched, so that their pair tests round as the float64
# oracle's by construction.


@wp.func
def wrap_coordinate(v: Any, side: Any):
    """``v`` in ``[0, side)``: ``v - side * floor(v / side)``, with the
    rounding of that expression folded back into the interval."""
    w = v - side * wp.floor(v / side)
    if w < type(w)(0.0):
        w = w + side
    if w >= side:
        w = type(w)(0.0)
    return w


@wp.func
def wrap_point(x: Any, box: Any, periodic: wp.vec3i):
    """``x`` wrapped into ``[0, box)`` on periodic axes; non-finite
    coordinates become 0 so that no box is NaN (their pairs fail the exact
    distance test anyway)."""
    w = x
    for a in range(3):
        v = x[a]
        if periodic[a] != 0:
            v = wrap_coordinate(v, box[a])
        if not wp.isfinite(v):
            v = type(v)(0.0)
        w[a] = v
    return w


@wp.func
def wrap_into_box(p: wp.vec3d, side: wp.vec3d, periodic: wp.vec3i) -> wp.vec3d:
    """``p`` wrapped into ``[0, side)`` on periodic axes, for the seed-001
    methods (callers pass positions unwrapped). Points already in the box are
    returned bit for bit, so their pair tests round exactly as the float64
    oracle's. Non-finite coordinates stay non-finite: every exact test on
    them is false."""
    wrapped = p
    for axis in range(3):
        if periodic[axis] != 0:
            v = p[axis]
            if v < wp.float64(0.0) or v >= side[axis]:
                v = wrap_coordinate(v, side[axis])
            wrapped[axis] = v
    return wrapped


@wp.func
def nearest_image(u: Any, reference: wp.vec3, box: Any, periodic: wp.vec3i):
    """The image of ``u`` nearest ``reference`` on periodic axes."""
    out = u
    for a in range(3):
        if periodic[a] != 0:
            r = type(u[a])(reference[a])
            d = u[a] - r
            d = d - box[a] * wp.round(d / box[a])
            out[a] = r + d
    return out


@wp.func
def largest_side(box: Any, periodic: wp.vec3i):
    """Largest periodic side as float32 (0 without periodic axes)."""
    largest = wp.float32(0.0)
    for a in range(3):
        if periodic[a] != 0:
            largest = wp.max(largest, wp.float32(box[a]))
    return largest


# ---------------------------------------------------------------------------
# The gamma rays: numbered and placed alike by all three methods.


@wp.func
def ray_shift(ray: int):
    """Shift, in box sides per axis, of ray ``ray`` in ``[0, 27)``: base-3
    digits mapped 0 -> 0, 1 -> +1, 2 -> -1 (ray 0 is the direct ray)."""
    shift = wp.vec3i(0, 0, 0)
    rest = ray
    for a in range(3):
        digit = rest % 3
        rest = rest // 3
        if digit == 1:
            shift[a] = 1
        elif digit == 2:
            shift[a] = -1
    return shift


@wp.func
def shifted(u: Any, shift: wp.vec3i, box: Any):
    """Origin of the ray with ``shift``: ``u + shift * box`` (``u`` itself on
    unshifted axes)."""
    out = u
    for a in range(3):
        if shift[a] != 0:
            out[a] = u[a] + type(u[a])(shift[a]) * box[a]
    return out


# ---------------------------------------------------------------------------
# Which gamma rays are cast: two rules, side by side.
#
# The AABB method (`ray_is_cast`) tests in float32 against ``face_reach``
# (its box reach plus the band of refitted items), may cast both a +1 and a
# -1 ray on one axis, and keeps each pair from one ray only through
# `is_canonical_image`. The seed-001 methods (`near_faces`,
# `crosses_near_faces`) test in float64 against ``cutoff + ε``, split at half
# the side so that at most one image per axis is cast, and keep every hit of
# their exact tests: their rows must equal the float64 oracle's bit for bit.


@wp.func
def ray_is_cast(shift: wp.vec3i, u: Any, box: Any, periodic: wp.vec3i,
                face_reach: wp.float32):
    """AABB method: is the ray shifted by ``shift`` cast for a particle at
    ``u``? Only across periodic faces that ``u`` is within ``face_reach`` of:
    a shift of +1 side serves particles near the low face, -1 those near the
    high face."""
    cast = True
    for a in range(3):
        if shift[a] != 0:
            if periodic[a] == 0:
                cast = False
            elif shift[a] > 0:
                if not (wp.float32(u[a]) < face_reach):
                    cast = False
            else:
                if not (wp.float32(u[a]) > wp.float32(box[a]) - face_reach):
                    cast = False
    return cast


@wp.func
def near_faces(u: wp.vec3d, cutoff: wp.float64, box: wp.vec3d, periodic: wp.vec3i,
               slack: wp.float64) -> wp.vec3i:
    """Seed-001 methods: per axis, the shift (+1, -1 or 0 sides) of the one
    image that a target at ``u`` (wrapped) casts across that axis's faces.

    +1 within ``cutoff + slack`` of the low face, -1 within it of the high
    face, 0 elsewhere and on free axes. ``slack`` (ε) casts images a hair
    early: the pair test rounds ``(s − t) − shift`` in float64 and may accept
    a pair that exact arithmetic puts exactly at the cutoff. Splitting at
    ``box / 2`` keeps a target from casting both a +1 and a -1 image.
    """
    faces = wp.vec3i(0, 0, 0)
    for a in range(3):
        if periodic[a] != 0:
            if u[a] < wp.float64(0.5) * box[a]:
                if u[a] < cutoff + slack:
                    faces[a] = 1
            else:
                if u[a] > box[a] - cutoff - slack:
                    faces[a] = -1
    return faces


@wp.func
def crosses_near_faces(shift: wp.vec3i, faces: wp.vec3i) -> bool:
    """Seed-001 methods: is the ray shifted by ``shift`` cast, given the
    target's `near_faces`? Every shifted axis must be a near face, in that
    direction. Ray 0 (no shift) always is; of the 27, at most 8 are."""
    for a in range(3):
        if shift[a] != 0 and shift[a] != faces[a]:
            return False
    return True


@wp.func
def is_canonical_image(shift: wp.vec3i, ui: Any, uj: Any, box: Any,
                       periodic: wp.vec3i):
    """Is ``shift`` the image through which the pair (i, j) is reported?

    Per periodic axis, with ``D = uj - ui``: shift +1 if ``D > L/2``, -1 if
    ``D < -L/2``, else 0. Depends on the pair only, not on the ray, so
    exactly one of i's rays keeps j.
    """
    canonical = True
    for a in range(3):
        if periodic[a] != 0:
            d = uj[a] - ui[a]
            half = box[a] * type(d)(0.5)
            image = int(0)
            if d > half:
                image = 1
            elif d < -half:
                image = -1
            if image != shift[a]:
                canonical = False
    return canonical
