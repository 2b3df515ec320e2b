"""The protocol every pure-Warp neighbour method follows.

A method finds, for each particle ``i``, every ``j`` with
``|r_i - r_j|² < cutoff²`` (minimum image on periodic axes), with Warp
kernels only: it knows nothing of JAX. `jaxrt.rt.ffi.method_backend` turns
any `RTMethod` into a jaxrt backend (``jaxrt.backends.Backend``) in one line,
so the seed's three methods (custom AABB, spheres, double squares) plug in
the same way.
"""
from __future__ import annotations

from typing import Protocol

import warp as wp


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
          cutoff: neighbours iff squared distance ``< cutoff**2`` (strict).
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
