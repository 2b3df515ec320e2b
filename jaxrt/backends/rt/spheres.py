"""Neighbours by rays against spheres: seed 001 §4.2, Algorithm 1, Appendix 7.

Algis & Bramas, "Exploiting ray tracing technology through OptiX to compute
particle interactions with cutoff in a 3D environment on GPU".

Every particle (a *source*) is a sphere of radius ``r = C·√2/√3 + ε``;
every particle (a *target*) casts three rays, along x, y and z, from
``−l`` to ``l`` around itself with ``l = C·√2/√3``. A ray that really
crosses a source's sphere surface (what OptiX's built-in sphere
intersection reports) runs Algorithm 1: keep the source iff it is closer
than C and this ray's axis is the one closest to the source's centre.
Appendix 7: with ``r = l + ε`` the closest-axis ray always crosses the
sphere of a source within C, unless the two particles are closer than
about ε (the sphere then swallows the whole cross; `jaxrt.backends.rt.epsilon`).

In Warp: the spheres' bounding boxes go in a `wp.Bvh` (float32, padded by
`epsilon.bvh_padding`); ``wp.bvh_query_ray`` proposes candidates along each
ray; the crossing test and Algorithm 1 run in float64 on the caller's
positions, in one kernel generic over wp.vec3 / wp.vec3d.

Resolved ambiguities (each also noted where it is coded):

* A ray may cross a sphere twice. The seed's lemma says the closest-axis
  ray crosses "at most once", which fails in 3-D: a source at
  ``C/√3·(1, 1, 1)`` is entered and left by all three rays within
  ``[−l, l]``. Algorithm 1 runs per (ray, sphere) when the segment crosses
  the surface at least once, not per crossing, so no pair is counted twice.
* "Reported exactly once" is per *direction*: the rule is symmetric (the
  closest axis of ``s − t`` is that of ``t − s``), so target t finds s and
  target s finds t. Each target's thread therefore writes its own complete
  row, without atomics.
* Ties between axes (``|dx| = |dy|``, ...) go to the lowest axis, as a
  plain ``argmin`` of Algorithm 1's ``dist_axis_squared`` does.
* Periodic boxes: seed 003 §3.3's gamma rays, cast as `jaxrt.backends.rt.periodic`
  says for the seed-001 methods (float64, at most one image per axis).
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import warp as wp

from jaxrt.backends.rt import periodic as gamma
from jaxrt.backends.rt import seed_energy
from jaxrt.backends.rt.method import (check_energy_arguments,
                                      check_find_arguments)
from jaxrt.backends.rt.epsilon import (
    EPSILON_RELATIVE,
    ParticlesTooCloseError,
    Survey,
    geometry_point,
    sphere_resolution,
    survey,
)

# Bit-compatibility with the float64 oracle: no FMA contraction in the
# distances and in Algorithm 1's closest-axis sums (contracted differently
# in each unrolled ray, a tie went to two rays or none on the H200).
wp.set_module_options({"fuse_fp": False})


@wp.kernel
def _sphere_boxes_kernel(points: wp.array(dtype=Any), side: wp.vec3d, periodic: wp.vec3i,
                         half_width: float,
                         lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3)):
    """Bounding box of each source's sphere, widened by the BVH padding."""
    i = wp.tid()
    centre = geometry_point(gamma.wrap_into_box(wp.vec3d(points[i]), side, periodic))
    lowers[i] = centre - wp.vec3(half_width)
    uppers[i] = centre + wp.vec3(half_width)


@wp.func
def segment_crosses_sphere(offset: wp.vec3d, offset_sq: wp.vec3d, axis: int,
                           half_length: wp.float64, epsilon: wp.float64) -> bool:
    """Does the segment ``[−l, l]`` along ``axis`` cross the surface of the
    sphere of radius ``l + ε`` centred at ``offset`` (source − target)?

    The squared distance from the centre along the segment is a convex
    quadratic, so the surface is crossed iff the nearest point of the
    segment is inside (or on) the sphere and the farthest (an endpoint) is
    outside (or on). The second test is written without the cancellation of
    ``(|d_k| + l)² − (l + ε)²``, which would swamp ε.
    """
    along = wp.abs(offset[axis])
    off_axis_sq = offset_sq[(axis + 1) % 3] + offset_sq[(axis + 2) % 3]
    beyond_end = wp.max(along - half_length, wp.float64(0.0))
    radius = half_length + epsilon
    nearest_inside = off_axis_sq + beyond_end * beyond_end <= radius * radius
    farthest_outside = (off_axis_sq + along * along + wp.float64(2.0) * half_length * along
                        >= epsilon * (wp.float64(2.0) * half_length + epsilon))
    return nearest_inside and farthest_outside


@wp.func
def closest_axis(offset_sq: wp.vec3d) -> int:
    """Algorithm 1's ``getClosestAxis(dist_axis_squared)``; ties go to the
    lowest axis."""
    dist_axis_sq = wp.vec3d(offset_sq[1] + offset_sq[2],
                            offset_sq[0] + offset_sq[2],
                            offset_sq[0] + offset_sq[1])
    closest = int(0)
    if dist_axis_sq[1] < dist_axis_sq[closest]:
        closest = 1
    if dist_axis_sq[2] < dist_axis_sq[closest]:
        closest = 2
    return closest


@wp.kernel
def _sphere_rays_kernel(
    bvh: wp.uint64,
    points: wp.array(dtype=Any),        # (N,) vec3 or vec3d
    cutoff: wp.float64,
    half_length: wp.float64,            # l = C·√2/√3
    epsilon: wp.float64,
    padding: float,                     # float32 widening of the query ray
    side: wp.vec3d,
    periodic: wp.vec3i,
    mask_self: int,
    resolution_sq: wp.float64,          # pairs closer than this are flagged
    params: wp.array(dtype=Any),        # fused mode's (seed_energy.N_PARAMS,)
    out_idx: wp.array2d(dtype=wp.int32),   # (N, width)
    out_count: wp.array(dtype=wp.int32),   # (N,)
    too_close: wp.array(dtype=wp.int32),   # (3,): flag, target, source
    energy: wp.array(dtype=Any),        # (N,) fused mode, zeroed; else (0,)
):
    """Algorithm 1 for every target's three rays (and their gamma images).

    List mode (``energy`` empty): row ``target`` of ``out_idx``. Fused mode
    (``energy`` of N; `jaxrt.backends.rt.seed_energy`; width 0, ``mask_self``): the
    "computation kernel" Algorithm 1 calls adds ``U`` to the ray's payload,
    and each ray adds its payload to ``energy[target]`` atomically, as the
    seed's code does. Either way ``out_count`` gets the exact count.
    """
    target = wp.tid()
    fused = energy.shape[0] > 0
    n = points.shape[0]
    width = out_idx.shape[1]
    position = gamma.wrap_into_box(wp.vec3d(points[target]), side, periodic)
    cutoff_sq = cutoff * cutoff
    max_dist = float(wp.float64(2.0) * half_length) + wp.float32(2.0) * padding
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
        for axis in range(3):
            direction = wp.vec3(0.0)
            direction[axis] = 1.0
            start = centre
            start[axis] = start[axis] - half_length
            ray_start = wp.vec3(start)
            ray_start[axis] = ray_start[axis] - padding
            query = wp.bvh_query_ray(bvh, ray_start, direction)
            payload = wp.float64(0.0)
            source = int(0)
            while wp.bvh_query_next(query, source, max_dist):
                # (s − t) − translation: the rounding of the float64 oracle's
                # minimum-image difference, so boundary pairs agree bit for bit.
                source_position = gamma.wrap_into_box(wp.vec3d(points[source]), side, periodic)
                offset = source_position - position - translation
                offset_sq = wp.cw_mul(offset, offset)
                dist_sq = offset_sq[0] + offset_sq[1] + offset_sq[2]
                if dist_sq < resolution_sq and (source != target or image != 0):
                    if wp.atomic_cas(too_close, 0, 0, 1) == 0:
                        too_close[1] = target
                        too_close[2] = source
                # The target's own sphere never counts: it contains the whole
                # cross (offset 0), so the crossing test is false.
                if segment_crosses_sphere(offset, offset_sq, axis, half_length, epsilon):
                    # Algorithm 1.
                    if dist_sq < cutoff_sq and closest_axis(offset_sq) == axis:
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
    wp.overload(_sphere_boxes_kernel, {"points": wp.array(dtype=_point_type)})
    wp.overload(_sphere_rays_kernel, {"points": wp.array(dtype=_point_type),
                                      "params": wp.array(dtype=_scalar),
                                      "energy": wp.array(dtype=_scalar)})


class SpheresMethod:
    """Seed 001 §4.2: spheres of radius ``C·√2/√3 + ε``, three axis rays.

    Implements the ``RTMethod`` protocol of `jaxrt.rt`: ``find`` writes each
    particle's full neighbour row (both directions of every pair).

    Args:
      check_separation: raise `ParticlesTooCloseError` from ``find`` when two
        particles are closer than `sphere_resolution` (the method may have
        missed them). With False, ``find`` never reads back from the device
        for this; read `separation_flag` instead.
      epsilon_relative: ε as a fraction of the data's scale
        (`jaxrt.backends.rt.epsilon`; default 2**-40). A larger ε widens the blind
        zone (pairs closer than `sphere_resolution` may be missed, and the
        separation check reports them) and slightly enlarges the spheres.

    Attributes:
      separation_flag: int32 ``(3,)`` wp.array from the last ``find``:
        ``[1, i, j]`` if particles i and j (one pair) were closer than the
        resolution, ``[0, 0, 0]`` otherwise.
      last_survey: the `Survey` (scale, ε, padding) of the last ``find``.
    """

    name = "spheres"

    def __init__(self, *, check_separation: bool = True,
                 epsilon_relative: float = EPSILON_RELATIVE):
        if not isinstance(check_separation, bool):
            raise TypeError(f"SpheresMethod: check_separation must be a bool; "
                            f"got {check_separation!r}.")
        if isinstance(epsilon_relative, bool) or not (
                isinstance(epsilon_relative, (int, float))
                and 0.0 < epsilon_relative < 0.5):
            raise ValueError("SpheresMethod: epsilon_relative (the sphere "
                             "method's ε as a fraction of the data's scale) "
                             "must be a float in (0, 0.5); got "
                             f"{epsilon_relative!r}. The default is 2**-40.")
        self.check_separation = check_separation
        self.epsilon_relative = float(epsilon_relative)
        self.separation_flag: wp.array | None = None
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
          ParticlesTooCloseError: (``check_separation``) two particles are
            closer than `sphere_resolution`.
          TypeError, ValueError: a bad argument (the message names it).
        """
        args = check_find_arguments(self.name, points, cutoff, side, periodic,
                                    mask_self, out_idx, out_count)
        if points.shape[0] == 0:
            self.separation_flag = wp.zeros(3, dtype=wp.int32, device=points.device)
            return
        self.query(self.build(points, args), out_idx=out_idx, out_count=out_count)

    def energy(self, points: wp.array, *, cutoff: float,
               side: tuple[float, float, float] | None,
               periodic: tuple[bool, bool, bool], params: wp.array,
               out_energy: wp.array, out_count: wp.array) -> None:
        """Seed 001's fused mode (`jaxrt.backends.rt.seed_energy`): each particle's
        LJ energy summed inside Algorithm 1, no list (self pairs dropped).

        Args:
          points, cutoff, side, periodic: as in `find`.
          params: position-precision ``(seed_energy.N_PARAMS,)``
            (`seed_energy.lj_params`).
          out_energy: position-precision ``(N,)`` output,
            ``E_i = sum_j U(r_ij)`` over the pairs `find` would list.
          out_count: int32 ``(N,)`` output, the pairs of each particle
            (`find`'s count with ``mask_self``).
        Raises:
          ParticlesTooCloseError: as `find` (the pair may be missing from
            the energy).
          TypeError, ValueError: a bad argument (the message names it).
        """
        args = check_energy_arguments(self.name, points, cutoff, side, periodic,
                                      params, out_energy, out_count)
        out_energy.zero_()
        if points.shape[0] == 0:
            self.separation_flag = wp.zeros(3, dtype=wp.int32, device=points.device)
            return
        self.query(self.build(points, args), params=params, out_energy=out_energy,
                   out_count=out_count)

    def build(self, points: wp.array, args) -> "SphereScene":
        """The scene (init step): the spheres' boxes and their BVH.

        Args:
          points: ``(N,)`` wp.vec3 / wp.vec3d, N >= 1.
          args: `jaxrt.backends.rt.method.FindArguments` (checked).
        """
        device = points.device
        n = points.shape[0]
        scan = survey(points, args, self.epsilon_relative)
        self.last_survey = scan
        half_length = args.cutoff * math.sqrt(2.0) / math.sqrt(3.0)
        radius = half_length + scan.epsilon
        lowers = wp.empty(n, dtype=wp.vec3, device=device)
        uppers = wp.empty(n, dtype=wp.vec3, device=device)
        wp.launch(_sphere_boxes_kernel, dim=n, device=device,
                  inputs=[points, args.side_vec, args.periodic_vec, float(radius + scan.padding)],
                  outputs=[lowers, uppers])
        bvh = wp.Bvh(lowers, uppers)
        self._scene = SphereScene(points, args, scan, half_length, bvh, lowers, uppers)
        return self._scene

    def query(self, scene: "SphereScene", *, out_idx: wp.array | None = None,
              out_count: wp.array, params: wp.array | None = None,
              out_energy: wp.array | None = None) -> None:
        """The rays (compute step) on a `build`'s scene: Dense rows into
        ``out_idx`` (as `find`), or, with ``params`` and ``out_energy``
        (zeroed by the caller), the fused energy (as `energy`)."""
        points, args, scan = scene.points, scene.args, scene.survey
        device = points.device
        n = points.shape[0]
        scalar = wp.float64 if points.dtype == wp.vec3d else wp.float32
        fused = out_energy is not None
        if not fused:
            params = wp.empty(0, dtype=scalar, device=device)
            out_energy = wp.empty(0, dtype=scalar, device=device)
        else:
            out_idx = wp.empty((1, 0), dtype=wp.int32, device=device)
        self.separation_flag = wp.zeros(3, dtype=wp.int32, device=device)
        resolution = sphere_resolution(scan.epsilon)
        wp.launch(_sphere_rays_kernel, dim=n, device=device,
                  inputs=[wp.uint64(scene.bvh.id), points, wp.float64(args.cutoff),
                          wp.float64(scene.half_length), wp.float64(scan.epsilon),
                          float(scan.padding), args.side_vec, args.periodic_vec,
                          int(args.mask_self or fused), wp.float64(resolution * resolution),
                          params],
                  outputs=[out_idx, out_count, self.separation_flag, out_energy])
        if self.check_separation:
            _raise_if_too_close(self.separation_flag, resolution, scan)


@dataclasses.dataclass
class SphereScene:
    """What `SpheresMethod.build` made: the inputs it was built for, the
    survey (ε, padding), the rays' half-length, and the BVH with the bounds
    arrays it points into."""

    points: wp.array
    args: object
    survey: Survey
    half_length: float
    bvh: wp.Bvh
    lowers: wp.array
    uppers: wp.array


def _raise_if_too_close(flag: wp.array, resolution: float, scan: Survey) -> None:
    found, i, j = (int(v) for v in flag.numpy())
    if found:
        raise ParticlesTooCloseError(
            f"spheres.find: particles {i} and {j} are closer than {resolution:.3g} "
            f"(2ε, ε = 2**-40 × scale {scan.scale:.3g}); the sphere method (seed 001 "
            f"§4.2, Appendix 7) cannot see pairs that close and may have missed it. "
            f"Use the double-square method or backend='bvh'/'cell', or keep particles "
            f"apart.", pair=(i, j), distance=resolution)
