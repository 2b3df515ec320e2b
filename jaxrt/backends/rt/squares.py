"""Neighbours by rays against double squares: seed 001 §4.3, Algorithm 2, Code 1.

Algis & Bramas, "Exploiting ray tracing technology through OptiX to compute
particle interactions with cutoff in a 3D environment on GPU".

Every particle (a *source*) is two squares normal to x, at ``x ± C/2``, each
of two triangles (Code 1: triangles ``4i, 4i+1`` at ``x − C/2`` with
corners (y, z) = (−,−), (−,+), (+,+) and (−,−), (+,−), (+,+); ``4i+2, 4i+3``
the same at ``x + C/2``), reaching ``C/2 + ε`` from the particle in y and z.
Every particle (a *target*) casts four rays along +x from ``x − C/2``, of
length ``C + ε``, at the corners of its own square: ray ``k`` at
``(y + σ_y·(C/2 + ε), z + σ_z·(C/2 + ε))`` with ``σ_y = −`` iff bit 0 of
``k`` is set and ``σ_z = −`` iff bit 1 is. Each particle is thus a box of
sides (C, C + 2ε, C + 2ε); two boxes overlap iff some ray of one pierces a
square of the other, and every triangle a ray pierces goes through
Algorithm 2: rebuild the source, drop self hits, keep it if closer than C
and if this ray is the one the y/z-equality rules pick. The ray numbering
is the one Algorithm 2's rules need: with equal y and ``z_t < z_s`` the
rays that pierce are 0 and 1, and the rules pick 0; with ``z_t > z_s``,
rays 2 and 3, and they pick 2; and so on.

In Warp: the triangles' bounding boxes go in a `wp.Bvh` (float32, padded
by `epsilon.bvh_padding`); ``wp.bvh_query_ray`` returns every candidate
along a ray (all hits, not only the closest); the ray–triangle test and
Algorithm 2 run on the caller's positions in float64, in one kernel generic
over wp.vec3 / wp.vec3d.

The ray–triangle test is exact. With float vertices, a ray that runs along
a square's edge (equal y or equal z: exactly the cases Algorithm 2's rules
are for) is in or out by rounding, and the rules then count a pair twice or
never. Here the test is the exact-arithmetic value of the geometric one,
written on the particles' coordinates: ray ``k`` is within a source's
square in y iff ``σ_y·(y_s − y_t) ∈ [0, C + 2ε]`` (a sign and a bound, no
rounding at the sign), likewise in z; the triangle index comes from the
BVH primitive, and the source from ``primitive // 4`` (Algorithm 2 rebuilds
the same position from the vertices).

Resolved ambiguities (each also noted where it is coded):

* Square side: §4.3 says ``C + ε``, Code 1 builds ``C + 2ε`` (corners at
  ``±(C/2 + ε)``). Code 1 is followed; only the exact test's bounds see it.
* Which plane a ray pierces: the rays span ``[x_t − C/2, x_t + C/2 + ε]``,
  so for ``0 ≤ x_s − x_t ≤ ε`` a ray pierces both squares of one source and
  the seed counts the pair twice. Here a ray pierces the plane
  ``x_s − C/2`` iff ``x_s > x_t`` and the plane ``x_s + C/2`` iff
  ``x_s ≤ x_t``: the ray's exact span is taken half-open, ``(−C/2, C/2]``
  from the target, and the ``+ε`` only widens the BVH search.
* A ray through a square's diagonal touches both of its triangles; the hit
  belongs to the first triangle where ``z ≥ y`` (square-local) and to the
  second elsewhere, as a watertight tracer gives a shared edge to one side.
* Self hits are dropped by index, not by the seed's ``dist > ε``, so pairs
  closer than ε (coincident particles included) are found: this method has
  no separation limit (`jaxrt.backends.rt.epsilon`).
* "Reported once" is per direction: target t finds s and s finds t, so
  each target's thread writes its own complete row, without atomics.
* Periodic boxes: seed 003 §3.3's gamma rays, cast as `jaxrt.backends.rt.periodic`
  says for the seed-001 methods (float64, at most one image per axis).
"""
from __future__ import annotations

import dataclasses
from typing import Any

import warp as wp

from jaxrt.backends.rt import periodic as gamma
from jaxrt.backends.rt import seed_energy
from jaxrt.backends.rt.method import (check_energy_arguments,
                                      check_find_arguments)
from jaxrt.backends.rt.epsilon import (
    Survey,
    geometry_point,
    survey,
)

# Bit-compatibility with the float64 oracle: no FMA contraction in the
# distances and in Algorithm 1's closest-axis sums (contracted differently
# in each unrolled ray, a tie went to two rays or none on the H200).
wp.set_module_options({"fuse_fp": False})

_TRIANGLES_PER_PARTICLE = wp.constant(4)
_RAYS_PER_TARGET = wp.constant(4)


@wp.kernel
def _triangle_boxes_kernel(points: wp.array(dtype=Any), side: wp.vec3d, periodic: wp.vec3i,
                           half_cutoff: wp.float64, half_side: wp.float64, padding: float,
                           lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3)):
    """Bounding boxes of Code 1's four triangles of each particle, padded.

    The two triangles of a square share its bounding box.
    """
    i = wp.tid()
    p = wp.vec3d(geometry_point(gamma.wrap_into_box(wp.vec3d(points[i]), side, periodic)))
    for square in range(2):
        plane = p[0] - half_cutoff
        if square == 1:
            plane = p[0] + half_cutoff
        lower = wp.vec3(wp.vec3d(plane, p[1] - half_side, p[2] - half_side)) - wp.vec3(padding)
        upper = wp.vec3(wp.vec3d(plane, p[1] + half_side, p[2] + half_side)) + wp.vec3(padding)
        for half in range(2):
            lowers[_TRIANGLES_PER_PARTICLE * i + 2 * square + half] = lower
            uppers[_TRIANGLES_PER_PARTICLE * i + 2 * square + half] = upper


@wp.func
def ray_hits_triangle(offset: wp.vec3d, triangle: int, sign_y: wp.float64,
                      sign_z: wp.float64, half_side: wp.float64) -> bool:
    """Exact test: does the target's ray (corner signs ``sign_y``, ``sign_z``)
    pierce triangle ``triangle`` (0–3, Code 1's order) of the source at
    ``offset`` (source − target)?
    """
    square = triangle // 2
    # Half-open span of the ray (module docstring): each ray pierces exactly
    # one of a source's two planes.
    pierces_plane = offset[0] > wp.float64(0.0)
    if square == 1:
        pierces_plane = offset[0] <= wp.float64(0.0)
    # Within the square in y and z. sign·offset is exact, so a ray on the
    # square's edge (equal y or z) is inside for both rays of that edge, as
    # Algorithm 2's rules expect.
    toward_y = sign_y * offset[1]
    toward_z = sign_z * offset[2]
    full_side = wp.float64(2.0) * half_side
    inside_square = (toward_y >= wp.float64(0.0) and toward_y <= full_side
                     and toward_z >= wp.float64(0.0) and toward_z <= full_side)
    # Where the ray meets the plane, relative to the square's centre; the
    # diagonal from corner (−,−) to (+,+) splits it between the triangles.
    local_y = sign_y * half_side - offset[1]
    local_z = sign_z * half_side - offset[2]
    in_this_triangle = local_z >= local_y
    if triangle % 2 == 1:
        in_this_triangle = local_z < local_y
    return pierces_plane and inside_square and in_this_triangle


@wp.func
def is_ray_for_compute(offset: wp.vec3d, ray: int) -> bool:
    """Algorithm 2's choice among the rays that pierce one source.

    ``offset`` = source − target, so the seed's ``point.z < q.z`` (target
    below source) is ``offset.z > 0``.
    """
    zero = wp.float64(0.0)
    y_equal = offset[1] == zero
    z_equal = offset[2] == zero
    if not y_equal and not z_equal:
        return True  # only this ray pierces
    if y_equal and not z_equal:
        return (offset[2] > zero and ray == 0) or (offset[2] < zero and ray == 2)
    if z_equal and not y_equal:
        return (offset[1] > zero and ray == 0) or (offset[1] < zero and ray == 1)
    return ray == 0  # all four rays pierce


@wp.kernel
def _square_rays_kernel(
    bvh: wp.uint64,
    points: wp.array(dtype=Any),        # (N,) vec3 or vec3d
    cutoff: wp.float64,
    epsilon: wp.float64,
    padding: float,                     # float32 widening of the query ray
    side: wp.vec3d,
    periodic: wp.vec3i,
    mask_self: int,
    params: wp.array(dtype=Any),        # fused mode's (seed_energy.N_PARAMS,)
    out_idx: wp.array2d(dtype=wp.int32),   # (N, width)
    out_count: wp.array(dtype=wp.int32),   # (N,)
    energy: wp.array(dtype=Any),        # (N,) fused mode, zeroed; else (0,)
):
    """Algorithm 2 for every target's four rays (and their gamma images).

    List mode (``energy`` empty): row ``target`` of ``out_idx``. Fused mode
    (``energy`` of N; `jaxrt.backends.rt.seed_energy`; width 0, ``mask_self``): the
    computation Algorithm 2 calls adds ``U`` to the ray's payload, and each
    ray adds its payload to ``energy[target]`` atomically, as the seed's
    code does. Either way ``out_count`` gets the exact count.
    """
    target = wp.tid()
    fused = energy.shape[0] > 0
    n = points.shape[0]
    width = out_idx.shape[1]
    position = gamma.wrap_into_box(wp.vec3d(points[target]), side, periodic)
    cutoff_sq = cutoff * cutoff
    half_cutoff = wp.float64(0.5) * cutoff
    half_side = half_cutoff + epsilon
    max_dist = float(cutoff + epsilon) + wp.float32(2.0) * padding
    direction = wp.vec3(1.0, 0.0, 0.0)
    count = int(0)
    if mask_self == 0:
        if count < width:
            out_idx[target, count] = target
        count += 1
    faces = gamma.near_faces(position, cutoff, side, periodic, epsilon)
    # A non-finite target casts no rays: it has no neighbours but itself.
    images = gamma.RAYS_PER_PARTICLE  # image 0 is the target itself
    if not wp.isfinite(position):
        images = 0
    for image in range(images):
        shift = gamma.ray_shift(image)
        if not gamma.crosses_near_faces(shift, faces):
            continue
        translation = gamma.shifted(wp.vec3d(wp.float64(0.0)), shift, side)  # ±side per axis
        centre = position + translation
        for ray in range(_RAYS_PER_TARGET):
            sign_y = wp.float64(1.0)
            if ray & 1 == 1:
                sign_y = wp.float64(-1.0)
            sign_z = wp.float64(1.0)
            if ray & 2 == 2:
                sign_z = wp.float64(-1.0)
            ray_start = wp.vec3(wp.vec3d(centre[0] - half_cutoff,
                                         centre[1] + sign_y * half_side,
                                         centre[2] + sign_z * half_side))
            ray_start[0] = ray_start[0] - padding
            query = wp.bvh_query_ray(bvh, ray_start, direction)
            payload = wp.float64(0.0)
            primitive = int(0)
            while wp.bvh_query_next(query, primitive, max_dist):
                source = primitive // _TRIANGLES_PER_PARTICLE
                # (s − t) − translation: the rounding of the float64 oracle's
                # minimum-image difference, so boundary pairs agree bit for bit.
                source_position = gamma.wrap_into_box(wp.vec3d(points[source]), side, periodic)
                offset = source_position - position - translation
                if not ray_hits_triangle(offset, primitive % _TRIANGLES_PER_PARTICLE,
                                         sign_y, sign_z, half_side):
                    continue
                # Algorithm 2.
                if source == target and image == 0:
                    continue  # the target's own squares
                offset_sq = wp.cw_mul(offset, offset)
                dist_sq = offset_sq[0] + offset_sq[1] + offset_sq[2]
                if dist_sq < cutoff_sq and is_ray_for_compute(offset, ray):
                    if fused:
                        payload = payload + seed_energy.clamped_lj(dist_sq, params)
                    elif count < width:
                        out_idx[target, count] = source
                    count += 1
            if fused:
                wp.atomic_add(energy, target, type(energy[target])(payload))
    for slot in range(wp.min(count, width), width):
        out_idx[target, slot] = n
    out_count[target] = count


for _point_type, _scalar in ((wp.vec3, wp.float32), (wp.vec3d, wp.float64)):
    wp.overload(_triangle_boxes_kernel, {"points": wp.array(dtype=_point_type)})
    wp.overload(_square_rays_kernel, {"points": wp.array(dtype=_point_type),
                                      "params": wp.array(dtype=_scalar),
                                      "energy": wp.array(dtype=_scalar)})


class SquaresMethod:
    """Seed 001 §4.3: two squares (four triangles) per particle, four x rays.

    Implements the ``RTMethod`` protocol of `jaxrt.rt`: ``find`` writes each
    particle's full neighbour row (both directions of every pair). Exact for
    any separation, coincident particles included (module docstring).

    Attributes:
      last_survey: the `Survey` (scale, ε, padding) of the last ``find``.
    """

    name = "squares"

    def __init__(self):
        self.last_survey: Survey | None = None
        # The BVH reads its bounds arrays while a launch may still be running
        # (on a GPU); keep them until the next find replaces them.
        self._scene: tuple | None = None

    def find(self, points: wp.array, *, cutoff: float,
             side: tuple[float, float, float] | None,
             periodic: tuple[bool, bool, bool], mask_self: bool,
             out_idx: wp.array, out_count: wp.array) -> None:
        """Write each particle's neighbours (distance² < cutoff²) into its row.

        Args:
          points: ``(N,)`` wp.vec3 (float32) or wp.vec3d (float64), Cartesian,
            wrapped or not (wrapped here on periodic axes). A non-finite
            particle gets no neighbours (only itself when ``mask_self`` is
            False) and is nobody's neighbour.
          cutoff: C > 0, below ``side / 2`` on periodic axes
            (`jaxrt.backends.rt.periodic.cutoff_fits`, as for every RT method).
          side: box side per axis, read on periodic axes only.
          periodic: three bools.
          mask_self: False lists ``i`` as its own neighbour.
          out_idx: int32 ``(N, width)``: row i gets i's neighbours in any
            order, then ``N`` up to ``width``.
          out_count: int32 ``(N,)``: i's exact neighbour count; a count above
            ``width`` means the row overflowed (the first ``width`` are kept).
        Raises:
          TypeError, ValueError: a bad argument (the message names it).
        """
        args = check_find_arguments(self.name, points, cutoff, side, periodic,
                                    mask_self, out_idx, out_count)
        if points.shape[0] == 0:
            return
        self.query(self.build(points, args), out_idx=out_idx, out_count=out_count)

    def energy(self, points: wp.array, *, cutoff: float,
               side: tuple[float, float, float] | None,
               periodic: tuple[bool, bool, bool], params: wp.array,
               out_energy: wp.array, out_count: wp.array) -> None:
        """Seed 001's fused mode (`jaxrt.backends.rt.seed_energy`): each particle's
        LJ energy summed inside Algorithm 2, no list (self pairs dropped).
        Arguments as `jaxrt.backends.rt.spheres.SpheresMethod.energy`; coincident
        particles are found and clamped (`jaxrt.backends.rt.seed_energy`)."""
        args = check_energy_arguments(self.name, points, cutoff, side, periodic,
                                      params, out_energy, out_count)
        out_energy.zero_()
        if points.shape[0] == 0:
            return
        self.query(self.build(points, args), params=params, out_energy=out_energy,
                   out_count=out_count)

    def build(self, points: wp.array, args) -> "SquareScene":
        """The scene (init step): Code 1's triangles' boxes and their BVH.

        Args:
          points: ``(N,)`` wp.vec3 / wp.vec3d, N >= 1.
          args: `jaxrt.backends.rt.method.FindArguments` (checked).
        """
        device = points.device
        n = points.shape[0]
        scan = survey(points, args)
        self.last_survey = scan
        half_cutoff = 0.5 * args.cutoff
        half_side = half_cutoff + scan.epsilon
        lowers = wp.empty(_TRIANGLES_PER_PARTICLE * n, dtype=wp.vec3, device=device)
        uppers = wp.empty(_TRIANGLES_PER_PARTICLE * n, dtype=wp.vec3, device=device)
        wp.launch(_triangle_boxes_kernel, dim=n, device=device,
                  inputs=[points, args.side_vec, args.periodic_vec, wp.float64(half_cutoff),
                          wp.float64(half_side), float(scan.padding)],
                  outputs=[lowers, uppers])
        bvh = wp.Bvh(lowers, uppers)
        self._scene = SquareScene(points, args, scan, bvh, lowers, uppers)
        return self._scene

    def query(self, scene: "SquareScene", *, out_idx: wp.array | None = None,
              out_count: wp.array, params: wp.array | None = None,
              out_energy: wp.array | None = None) -> None:
        """The rays (compute step) on a `build`'s scene: Dense rows into
        ``out_idx`` (as `find`), or, with ``params`` and ``out_energy``
        (zeroed by the caller), the fused energy (as `energy`)."""
        points, args, scan = scene.points, scene.args, scene.survey
        device = points.device
        scalar = wp.float64 if points.dtype == wp.vec3d else wp.float32
        fused = out_energy is not None
        if not fused:
            params = wp.empty(0, dtype=scalar, device=device)
            out_energy = wp.empty(0, dtype=scalar, device=device)
        else:
            out_idx = wp.empty((1, 0), dtype=wp.int32, device=device)
        wp.launch(_square_rays_kernel, dim=points.shape[0], device=device,
                  inputs=[wp.uint64(scene.bvh.id), points, wp.float64(args.cutoff),
                          wp.float64(scan.epsilon), float(scan.padding), args.side_vec,
                          args.periodic_vec, int(args.mask_self or fused), params],
                  outputs=[out_idx, out_count, out_energy])


@dataclasses.dataclass
class SquareScene:
    """What `SquaresMethod.build` made: the inputs it was built for, the
    survey (ε, padding), and the BVH with the bounds arrays it points into."""

    points: wp.array
    args: object
    survey: Survey
    bvh: wp.Bvh
    lowers: wp.array
    uppers: wp.array
