"""Periodic boundaries by gamma rays: Meneses et al., "Advancing RT
Core-Accelerated Fixed-Radius Nearest Neighbor Search", §3.3.

No ghost particles: the BVH holds each particle's box once, at its wrapped
position. A particle within the search radius of a face also casts a ray
from its image across that face ("gamma" ray), one per combination of the
faces it is near: up to 7 extra rays at a 3D corner (the seed's
``γ_x, γ_y, γ_{x,y}``, and ``z`` combinations).

Each pair must be reported once. For a cutoff below half the box side only
one image of ``j`` can be within reach of ``i``; to make that hold under
rounding as well, a hit is kept only from the ray whose shift is the
pair's *canonical image*, a deterministic function of the two box centres
(`is_canonical_image`). That ray is always cast when the pair is in range
(`ray_is_cast`), so no pair is lost and none is doubled.

Items refitted rather than rebuilt may sit up to ``drift`` outside the box
(they follow their nearest image, see `jaxrt.rt.aabb`); rays account for
that through ``face_reach``. With drift below a quarter of the cutoff and
the cutoff below half the side, a pair at minimum-image displacement ``m``
(``|m| < cutoff``) has centre difference ``m + kL`` with ``k`` in
``{-1, 0, 1}``, so the canonical rule picks ``k``, whose ray is cast.

Warp functions here are generic over the position type (``wp.vec3`` or
``wp.vec3d``); ``box`` is a vector of the same type.
"""
from __future__ import annotations

from typing import Any

import warp as wp

RAYS_PER_PARTICLE = wp.constant(27)  # all shift combinations; ray 0 is direct

# Cutoffs must stay this far (relatively) below half the side, so that
# rounding of box centres can never make two images both canonical-looking.
CUTOFF_MARGIN = 2.0 ** -16


def cutoff_fits(cutoff: float, side: float) -> bool:
    """Does ``cutoff`` allow gamma rays on a periodic axis of ``side``?"""
    return side > 0 and cutoff < 0.5 * side * (1.0 - CUTOFF_MARGIN)


def cutoff_error(cutoff: float, side: float, axis: int) -> str:
    return (f"the search radius r_cutoff + dr_threshold = {cutoff:g} must be "
            f"below half the periodic box side {side:g} on axis {axis} for the "
            "ray-traced backends (they report each pair through its nearest "
            "image only). Use a larger box, a smaller r_cutoff / dr_threshold, "
            "or backend='cell'.")


@wp.func
def wrap_point(x: Any, box: Any, periodic: wp.vec3i):
    """``x`` wrapped into ``[0, box)`` on periodic axes; non-finite
    coordinates become 0 so that no box is NaN (their pairs fail the exact
    distance test anyway)."""
    w = x
    for a in range(3):
        v = x[a]
        if periodic[a] != 0:
            v = v - box[a] * wp.floor(v / box[a])
            if v < type(v)(0.0):
                v = v + box[a]
            if v >= box[a]:
                v = type(v)(0.0)
        if not wp.isfinite(v):
            v = type(v)(0.0)
        w[a] = v
    return w


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
def ray_is_cast(shift: wp.vec3i, u: Any, box: Any, periodic: wp.vec3i,
                face_reach: wp.float32):
    """Is the ray shifted by ``shift`` cast for a particle at ``u``? Only
    across periodic faces that ``u`` is within ``face_reach`` of: a shift of
    +1 side serves particles near the low face, -1 those near the high face."""
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
def shifted(u: Any, shift: wp.vec3i, box: Any):
    """Origin of the ray with ``shift``: ``u + shift * box``."""
    out = u
    for a in range(3):
        if shift[a] != 0:
            out[a] = u[a] + type(u[a])(shift[a]) * box[a]
    return out


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
