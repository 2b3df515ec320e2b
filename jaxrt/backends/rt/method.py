"""The protocol every pure-Warp neighbour method follows.

A method finds, for each particle ``i``, every ``j`` with
``|r_i - r_j|² < cutoff²`` (minimum image on periodic axes), with Warp
kernels only: it knows nothing of JAX. `jaxrt.backends.rt.ffi.method_backend` turns
any `RTMethod` into a jaxrt backend (``jaxrt.backends.Backend``) in one line,
so the seed's three methods (custom AABB, spheres, double squares) plug in
the same way.

`FindArguments` and `check_find_arguments` are ``find``'s arguments checked
and normalised, for methods to share (the sphere and double-square methods
do); the cutoff's periodic limit is the one rule of all the ray-traced
methods, `jaxrt.backends.rt.periodic.check_cutoff`.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Protocol

import numpy as np
import warp as wp

from jaxrt.backends.rt.periodic import check_cutoff


class RTMethod(Protocol):
    name: str

    def find(self, points: wp.array,
             *, cutoff: float, side: tuple[float, float, float] | None,
             periodic: tuple[bool, bool, bool],
             mask_self: bool, out_idx: wp.array2d,
             out_count: wp.array,
             ) -> None:
        """Writes each i's neighbours (any order) into out_idx[i, :width]
        (rest untouched or N), and the exact count into out_count[i].

        Args:
          points: ``(N,)`` ``wp.vec3`` (float32) or ``wp.vec3d`` (float64),
            Cartesian, not wrapped into the box; 2D/1D padded with zeros.
          cutoff: neighbours iff squared distance ``< cutoff**2`` (strict);
            below half the side on periodic axes
            (`jaxrt.backends.rt.periodic.check_cutoff` refuses the rest).
          side: box side per axis, read on periodic axes; None when no axis
            is periodic.
          periodic: one bool per axis.
          mask_self: drop ``i == i``.
          out_idx: int32 ``(N, width)``; row ``i`` receives its first
            ``min(count, width)`` neighbours in its first slots. The caller
            fills it with ``N`` beforehand.
          out_count: int32 ``(N,)``, the exact number of neighbours, which
            may exceed ``width`` (the caller then reports overflow).
        """


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
    Raises:
      TypeError, ValueError: the message names the argument; a cutoff not
        below half a periodic side gets `jaxrt.backends.rt.periodic.check_cutoff`'s
        error, as from every ray-traced method.
    """
    n = _check_points(f"{method}.find", points)
    if not isinstance(out_idx, wp.array) or out_idx.dtype != wp.int32 or out_idx.ndim != 2 \
            or out_idx.shape[0] != n:
        raise TypeError(
            f"{method}.find: out_idx must be a wp.array2d of int32 with shape (N, width) = "
            f"({n}, width); got {describe(out_idx)}.")
    if not isinstance(out_count, wp.array) or out_count.dtype != wp.int32 \
            or out_count.shape != (n,):
        raise TypeError(
            f"{method}.find: out_count must be a wp.array of int32 with shape ({n},); "
            f"got {describe(out_count)}.")
    for name, array in (("out_idx", out_idx), ("out_count", out_count)):
        _check_device(f"{method}.find", name, array, points)
    return _check_geometry(f"{method}.find", cutoff, side, periodic, mask_self)


def check_energy_arguments(method: str, points: wp.array, cutoff: float, side,
                           periodic, params: wp.array, out_energy: wp.array,
                           out_count: wp.array) -> FindArguments:
    """Validate the fused mode's ``energy`` arguments (`jaxrt.backends.rt.seed_energy`)
    as `check_find_arguments` does ``find``'s; ``mask_self`` is True.

    Args:
      points: ``(N,)`` wp.vec3 or wp.vec3d.
      params: ``(seed_energy.N_PARAMS,)``, out_energy ``(N,)``: the
        positions' scalar type (float32 for wp.vec3, float64 for wp.vec3d);
        out_count: int32 ``(N,)``; all on the points' device.
    """
    from jaxrt.backends.rt.seed_energy import N_PARAMS
    n = _check_points(f"{method}.energy", points)
    scalar = wp.float64 if points.dtype == wp.vec3d else wp.float32
    for name, array, dtype, shape in (("params", params, scalar, (N_PARAMS,)),
                                      ("out_energy", out_energy, scalar, (n,)),
                                      ("out_count", out_count, wp.int32, (n,))):
        if not isinstance(array, wp.array) or array.dtype != dtype \
                or array.shape != shape:
            raise TypeError(
                f"{method}.energy: {name} must be a wp.array of "
                f"{wp.types.type_repr(dtype)} with shape {shape} (the positions' "
                f"precision); got {describe(array)}.")
        _check_device(f"{method}.energy", name, array, points)
    return _check_geometry(f"{method}.energy", cutoff, side, periodic, True)


def _check_points(call: str, points) -> int:
    """N of ``points``, a 1-D wp.array of wp.vec3 / wp.vec3d, else TypeError
    naming ``call``."""
    if not isinstance(points, wp.array) or points.dtype not in (wp.vec3, wp.vec3d) \
            or points.ndim != 1:
        raise TypeError(
            f"{call}: points must be a 1-D wp.array of wp.vec3 (float32) or "
            f"wp.vec3d (float64); got {describe(points)}. Pad 2-D positions with z = 0.")
    return points.shape[0]


def _check_device(call: str, name: str, array, points) -> None:
    if array.device != points.device:
        raise ValueError(
            f"{call}: {name} is on {array.device} but points are on "
            f"{points.device}; allocate it on the points' device.")


def _check_geometry(method: str, cutoff, side, periodic, mask_self) -> FindArguments:
    """The cutoff, box and flags of `check_find_arguments`; ``method``
    names the call in messages."""
    if isinstance(cutoff, (bool, np.bool_)) \
            or not isinstance(cutoff, (int, float, np.floating, np.integer)) \
            or not math.isfinite(cutoff) or cutoff <= 0:
        raise ValueError(f"{method}: cutoff must be a finite number > 0; got {cutoff!r}.")
    cutoff = float(cutoff)
    if not isinstance(mask_self, (bool, np.bool_)):
        raise TypeError(f"{method}: mask_self must be a bool; got {mask_self!r}.")
    periodic = tuple(periodic)
    if len(periodic) != 3 or not all(isinstance(p, (bool, np.bool_)) for p in periodic):
        raise ValueError(
            f"{method}: periodic must be three bools (x, y, z; pad 2-D with False); "
            f"got {periodic!r}.")
    periodic = tuple(bool(p) for p in periodic)
    if not any(periodic):
        return FindArguments(cutoff, (0.0, 0.0, 0.0), periodic, bool(mask_self))
    if side is None or len(tuple(side)) != 3:
        raise ValueError(
            f"{method}: periodic={periodic} needs side=(Lx, Ly, Lz), the box side "
            f"per axis; got side={side!r}.")
    side = tuple(float(s) for s in side)
    for axis in range(3):
        if periodic[axis] and not (math.isfinite(side[axis]) and side[axis] > 0):
            raise ValueError(
                f"{method}: side[{axis}] must be finite and > 0 on a periodic axis; "
                f"got {side[axis]!r}.")
    check_cutoff(cutoff, side, periodic)
    side = tuple(s if p else 0.0 for s, p in zip(side, periodic))
    return FindArguments(cutoff, side, periodic, bool(mask_self))


def describe(value) -> str:
    """``value`` in an error message: a wp.array's dtype and shape, else its
    type's name."""
    if isinstance(value, wp.array):
        return f"wp.array(dtype={wp.types.type_repr(value.dtype)}, shape={value.shape})"
    return type(value).__name__
