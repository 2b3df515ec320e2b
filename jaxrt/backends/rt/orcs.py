"""ORCS: Lennard-Jones interactions computed during the BVH traversal, with
no neighbour list. Meneses et al., "Advancing RT Core-Accelerated
Fixed-Radius Nearest Neighbor Search" (seed 003), §3.2.

Both variants cast the custom AABB method's rays (`jaxrt.backends.rt.aabb`: one
infinitesimal ray per particle, one box per particle, the periodic gamma
rays of §3.3 in `jaxrt.backends.rt.periodic`) and evaluate the pair as soon as the
exact distance test accepts it, instead of writing the neighbour index:

* **ORCS-forces** (§3.2.2, Fig. 5; `forces`): each unordered pair is
  evaluated once, by the particle with the smaller radius (the smaller
  index on ties, and always with equal radii). Its ray lies inside the
  other's box whenever ``d < max(r_i, r_j)``, so it is the one that finds
  the pair. The force on the owner is kept in registers and added once per
  particle; only the partner's ``-F_ij`` needs atomics (an optimisation
  over the paper, which adds both atomically). Energy, ``dE/dsigma``,
  ``dE/depsilon`` and the interaction count go to the owner's own slot
  (no atomics; summed afterwards). Any radius.
* **ORCS-persé** (§3.2.1; `perse_step`): thread i sums its own force over
  every neighbour (each pair seen twice, no atomics) and then moves its own
  particle: one leapfrog step, ``v' = v + dt F / m``, ``x' = x + dt v'``,
  wrapped on periodic axes. Other threads still read the old positions (the
  BVH's copy of them), and the new ones go to a separate buffer: the
  double buffer the paper's in-launch write needs. Equal radii only
  (§3.2.3): with different radii detection is one-sided.

The potential is the one jaxrt's lists use (`jaxrt.energy.lj`): jax-md's
Lennard-Jones with its smooth switch from ``r_onset`` to ``r_cutoff``, and
for per-particle radii the pair cut at ``R = max(r_i, r_j)`` with the whole
potential stretched by ``s = R / r_cutoff`` (`lennard_jones_radii`).

**The paper's Eq. 4 is wrong by a factor 2.** It prints
``F = 24 eps [(sigma/r)**12 - (sigma/r)**6] / r``; the force is
``-dU/dr = 24 eps [2 (sigma/r)**12 - (sigma/r)**6] / r``. Here the true
``-dU/dr`` (switch included) is used; the tests check it against
``jax.grad`` of the list path.

Precision as in `jaxrt.backends.rt.aabb`: a float32 BVH whose boxes are padded past
rounding, and the distance test and the pair terms in the positions' own
precision (float32 or float64; one generic kernel, overloaded for both).
Two particles at the same position contribute no energy and no force.
float32 atomics make float32 forces vary in their last bits from run to run
on a GPU.

Pure Warp: nothing here knows of JAX (`jaxrt.backends.rt.ffi` wraps it).
"""
from __future__ import annotations

from typing import Any

import numpy as np
import warp as wp

from jaxrt.backends.rt import aabb
from jaxrt.backends.rt import periodic as gamma

# Bit-compatibility with jax-md and the list kernels: no FMA contraction.
wp.set_module_options({"fuse_fp": False})

# Layout of the ``params`` array (position precision) of both kernels.
SIGMA, EPSILON, R_ONSET, R_CUTOFF, RADIUS_BOUND, DT, MASS = range(7)
N_PARAMS = 7

# Bits of ``error[0]`` (`jaxrt.energy.listfree.lj.InputBit` values, so the
# JAX side reports them in jaxrt's words).
ERROR_NONFINITE = wp.constant(1 << 4)  # InputBit.NONFINITE_POSITION
ERROR_RADII = wp.constant(1 << 7)      # InputBit.BAD_RADII


@wp.func
def lj_terms(d2: Any, sigma: Any, epsilon: Any, r_onset: Any, r_cutoff: Any,
             sigma_base: Any):
    """One pair of jax-md's smoothly switched LJ at squared distance ``d2``.

    Returns ``(e, g, de_dsigma, de_depsilon)``: the pair energy ``e``, the
    force factor ``g`` with ``F_i = g * (x_i - x_j)`` (``g = -(1/r) dE/dr``),
    and the derivatives of ``e`` in the caller's sigma (``sigma_base``;
    ``sigma`` is the pair's, possibly stretched, value) and epsilon. The
    cutoffs do not move with sigma (as in jax-md). ``d2 == 0`` gives zeros.
    """
    zero = type(d2)(0.0)
    if d2 == zero:
        return zero, zero, zero, zero
    # jax_md.energy.lennard_jones's arithmetic, so energies round alike.
    dr = wp.sqrt(d2)
    idr = sigma / dr
    idr = idr * idr
    idr6 = idr * idr * idr
    idr12 = idr6 * idr6
    lj_unit = type(d2)(4.0) * (idr12 - idr6)
    lj = type(d2)(4.0) * epsilon * (idr12 - idr6)
    # -r dLJ/dr / epsilon: note the 2 that the paper's Eq. 4 drops.
    repulsion = type(d2)(24.0) * (type(d2)(2.0) * idr12 - idr6)
    # jax_md.energy.multiplicative_isotropic_cutoff, S(u) with u = r**2.
    switch = type(d2)(1.0)
    dswitch_du = zero
    if not (dr < r_onset):
        switch = zero
        if dr < r_cutoff:
            rc2 = r_cutoff * r_cutoff
            ro2 = r_onset * r_onset
            u = dr * dr
            denom = (rc2 - ro2) * (rc2 - ro2) * (rc2 - ro2)
            switch = (rc2 - u) * (rc2 - u) * (rc2 + type(d2)(2.0) * u
                                              - type(d2)(3.0) * ro2) / denom
            dswitch_du = type(d2)(-6.0) * (rc2 - u) * (u - ro2) / denom
    e = switch * lj
    g = switch * epsilon * repulsion / d2 - type(d2)(2.0) * dswitch_du * lj
    de_dsigma = switch * epsilon * repulsion / sigma_base
    de_depsilon = switch * lj_unit
    return e, g, de_dsigma, de_depsilon


@wp.func
def pair_cut(i: int, j: int, has_radii: wp.int32, radii: wp.array(dtype=Any),
             r_cutoff: Any):
    """``R_ij``: ``max(r_i, r_j)`` with radii, else ``r_cutoff``."""
    if has_radii != 0:
        return wp.max(radii[i], radii[j])
    return r_cutoff


@wp.func
def owns(i: int, j: int, has_radii: wp.int32, radii: wp.array(dtype=Any)):
    """Does particle i evaluate the pair (i, j)? The smaller radius, then
    the smaller index (§3.2.2)."""
    if has_radii != 0:
        if radii[i] != radii[j]:
            return radii[i] < radii[j]
    return i < j


@wp.func
def is_finite3(x: Any):
    return wp.isfinite(x[0]) and wp.isfinite(x[1]) and wp.isfinite(x[2])


@wp.kernel
def _forces_kernel(bvh: wp.uint64, item_points: wp.array(dtype=Any),
                   item_coords: wp.array(dtype=Any),
                   order: wp.array(dtype=wp.int32), side: wp.array(dtype=Any),
                   periodic: wp.vec3i, has_radii: wp.int32,
                   radii: wp.array(dtype=Any), params: wp.array(dtype=Any),
                   half_width: wp.float32, extent: wp.array(dtype=wp.float32),
                   band: wp.float32,
                   forces: wp.array(dtype=Any), energy: wp.array(dtype=Any),
                   d_sigma: wp.array(dtype=Any), d_epsilon: wp.array(dtype=Any),
                   count: wp.array(dtype=wp.int32), error: wp.array(dtype=wp.int32)):
    """ORCS-forces for the particle of item k (``forces`` zeroed before)."""
    k = wp.tid()
    i = order[k]
    xi = item_points[k]
    ui = item_coords[k]
    box = side[0]
    sigma = params[SIGMA]
    epsilon = params[EPSILON]
    r_onset = params[R_ONSET]
    r_cutoff = params[R_CUTOFF]
    if not is_finite3(xi):
        wp.atomic_or(error, 0, ERROR_NONFINITE)
    if has_radii != 0:
        r = radii[i]
        if not (r >= type(r)(0.0) and r <= params[RADIUS_BOUND]):
            wp.atomic_or(error, 0, ERROR_RADII)
    # Gamma rays reach the largest radius (§3.3), plus the refit band.
    reach = aabb.box_reach(half_width, extent[0], gamma.largest_side(box, periodic))
    face_reach = reach + band
    any_periodic = periodic[0] != 0 or periodic[1] != 0 or periodic[2] != 0
    f_i = xi - xi
    e_i = sigma - sigma
    ds_i = e_i
    de_i = e_i
    n = int(0)
    for ray in range(gamma.RAYS_PER_PARTICLE):
        shift = gamma.ray_shift(ray)
        if gamma.ray_is_cast(shift, ui, box, periodic, face_reach):
            origin = wp.vec3(gamma.shifted(ui, shift, box))
            query = wp.bvh_query_ray(bvh, origin, aabb.RAY_DIRECTION)
            hit = int(0)
            while wp.bvh_query_next(query, hit, 0.0):
                j = order[hit]
                if j == i or not owns(i, j, has_radii, radii):
                    continue
                if any_periodic and not gamma.is_canonical_image(
                        shift, ui, item_coords[hit], box, periodic):
                    continue
                d = aabb.displacement(xi, item_points[hit], box, periodic)
                d2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
                cut = pair_cut(i, j, has_radii, radii, r_cutoff)
                if not (d2 < cut * cut):
                    continue
                scale = cut / r_cutoff
                e, g, ds, de = lj_terms(d2, sigma * scale, epsilon,
                                        r_onset * scale, r_cutoff * scale, sigma)
                f = g * d
                f_i = f_i + f
                wp.atomic_sub(forces, j, f)
                e_i = e_i + e
                ds_i = ds_i + ds
                de_i = de_i + de
                n = n + 1
    wp.atomic_add(forces, i, f_i)
    energy[i] = e_i
    d_sigma[i] = ds_i
    d_epsilon[i] = de_i
    count[i] = n


@wp.kernel
def _perse_kernel(bvh: wp.uint64, item_points: wp.array(dtype=Any),
                  item_coords: wp.array(dtype=Any),
                  order: wp.array(dtype=wp.int32), side: wp.array(dtype=Any),
                  periodic: wp.vec3i, params: wp.array(dtype=Any),
                  half_width: wp.float32, extent: wp.array(dtype=wp.float32),
                  band: wp.float32, velocities: wp.array(dtype=Any),
                  positions_out: wp.array(dtype=Any),
                  velocities_out: wp.array(dtype=Any),
                  energy: wp.array(dtype=Any), count: wp.array(dtype=wp.int32),
                  error: wp.array(dtype=wp.int32)):
    """ORCS-persé for the particle of item k: its force over all its
    neighbours, then its leapfrog step into the other buffers."""
    k = wp.tid()
    i = order[k]
    xi = item_points[k]
    ui = item_coords[k]
    box = side[0]
    sigma = params[SIGMA]
    epsilon = params[EPSILON]
    r_onset = params[R_ONSET]
    r_cutoff = params[R_CUTOFF]
    if not is_finite3(xi):
        wp.atomic_or(error, 0, ERROR_NONFINITE)
    reach = aabb.box_reach(half_width, extent[0], gamma.largest_side(box, periodic))
    face_reach = reach + band
    any_periodic = periodic[0] != 0 or periodic[1] != 0 or periodic[2] != 0
    cut2 = r_cutoff * r_cutoff
    f_i = xi - xi
    e_i = sigma - sigma
    n = int(0)
    for ray in range(gamma.RAYS_PER_PARTICLE):
        shift = gamma.ray_shift(ray)
        if gamma.ray_is_cast(shift, ui, box, periodic, face_reach):
            origin = wp.vec3(gamma.shifted(ui, shift, box))
            query = wp.bvh_query_ray(bvh, origin, aabb.RAY_DIRECTION)
            hit = int(0)
            while wp.bvh_query_next(query, hit, 0.0):
                j = order[hit]
                if j == i:
                    continue
                if any_periodic and not gamma.is_canonical_image(
                        shift, ui, item_coords[hit], box, periodic):
                    continue
                d = aabb.displacement(xi, item_points[hit], box, periodic)
                d2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
                if not (d2 < cut2):
                    continue
                e, g, ds, de = lj_terms(d2, sigma, epsilon, r_onset, r_cutoff,
                                        sigma)
                f_i = f_i + g * d
                e_i = e_i + type(e)(0.5) * e
                n = n + 1
    dt = params[DT]
    v = velocities[i] + (dt / params[MASS]) * f_i
    x = xi + dt * v
    for a in range(3):
        if periodic[a] != 0:
            x[a] = gamma.wrap_coordinate(x[a], box[a])
    positions_out[i] = x
    velocities_out[i] = v
    energy[i] = e_i
    count[i] = n


aabb.instantiate(_forces_kernel,
                  vectors=("item_points", "item_coords", "side", "forces"),
                  scalar_arrays=("radii", "params", "energy", "d_sigma",
                                 "d_epsilon"))
aabb.instantiate(_perse_kernel,
                  vectors=("item_points", "item_coords", "side", "velocities",
                           "positions_out", "velocities_out"),
                  scalar_arrays=("params", "energy"))


def load(device) -> None:
    """Compile/load this module's kernels (and the tree's) on ``device``."""
    aabb.load(device)
    wp.load_module(module=__name__, device=device)


def _launch_args(search: "aabb.AabbSearch"):
    if search.bvh is None:
        raise RuntimeError("ORCS before update: call search.update(...) first.")
    if search.cluster_size != 1:
        raise ValueError("ORCS casts one box per particle: use cluster_size=1 "
                         f"(got {search.cluster_size}).")
    flags = wp.vec3i(*(int(p) for p in search._periodic))
    return ([wp.uint64(search.bvh.id), search.item_points, search.item_coords,
             search.order], flags,
            [float(np.float32(search._cutoff)), search.extent,
             search.band(search._cutoff)])


def forces(search: "aabb.AabbSearch", side: wp.array, params: wp.array, *,
           radii: wp.array | None, forces: wp.array, energy: wp.array,
           d_sigma: wp.array, d_epsilon: wp.array, count: wp.array,
           error: wp.array) -> None:
    """ORCS-forces on the tree of the last ``search.update`` (which must
    have been given the same ``radii`` as its reach, and their bound, or
    the cutoff, as its cutoff).

    Args:
      search: an `aabb.AabbSearch` fitted to the positions.
      side: ``vector`` ``(1,)`` box sides.
      params: position-precision ``(N_PARAMS,)``: sigma, epsilon, r_onset,
        r_cutoff (absolute; the reference cut that radii stretch), the
        radius bound (the tree's cutoff), dt, mass.
      radii: None, or position-precision ``(N,)`` per-particle radii in
        ``[0, params[RADIUS_BOUND]]``.
      forces: ``vector`` ``(N,)`` output, F_i (zeroed here).
      energy, d_sigma, d_epsilon: position-precision ``(N,)`` outputs, the
        sums over the pairs each particle owns (total = their sum).
      count: int32 ``(N,)`` output, pairs owned (unordered pairs in all).
      error: int32 ``(1,)`` output, `ERROR_NONFINITE` | `ERROR_RADII`.
    """
    head, flags, tail = _launch_args(search)
    with wp.ScopedDevice(search.device):
        forces.zero_()
        error.zero_()
        has_radii = int(radii is not None)
        reach = radii if has_radii else search.no_reach
        wp.launch(aabb.overload(_forces_kernel, search.scalar), search.n,
                  inputs=head + [side, flags, has_radii, reach, params] + tail
                  + [forces, energy, d_sigma, d_epsilon, count, error])


def perse_step(search: "aabb.AabbSearch", side: wp.array, params: wp.array, *,
               velocities: wp.array, positions_out: wp.array,
               velocities_out: wp.array, energy: wp.array, count: wp.array,
               error: wp.array) -> None:
    """One ORCS-persé leapfrog step on the tree of the last
    ``search.update(positions, ...)`` (equal radii: no reach).

    Args:
      params: as in `forces`, with ``params[DT]`` the time step and
        ``params[MASS]`` the particle mass.
      velocities: ``vector`` ``(N,)``, half-step velocities v(t - dt/2).
      positions_out, velocities_out: ``vector`` ``(N,)`` outputs, x(t + dt)
        (wrapped on periodic axes) and v(t + dt/2).
      energy: position-precision ``(N,)`` output, half of each particle's
        pair energies at x(t) (total = their sum).
      count: int32 ``(N,)`` output, neighbours of each particle (each pair
        counted twice).
      error: int32 ``(1,)`` output, `ERROR_NONFINITE`.
    """
    if search._reach is not None:
        raise ValueError("ORCS-persé needs equal radii (seed 003 §3.2.3): fit "
                         "the tree without reach.")
    head, flags, tail = _launch_args(search)
    with wp.ScopedDevice(search.device):
        error.zero_()
        wp.launch(aabb.overload(_perse_kernel, search.scalar), search.n,
                  inputs=head + [side, flags, params] + tail
                  + [velocities, positions_out, velocities_out, energy, count,
                     error])
