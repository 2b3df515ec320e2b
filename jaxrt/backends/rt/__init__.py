"""Ray-traced neighbour search on Warp BVHs (needs ``warp-lang``).

The backends (`jaxrt.rt.ffi`, re-exported by `jaxrt.backends`):

* `Bvh` (``"bvh"``): custom AABB boxes in a Morton-sorted BVH kept across
  calls (Algis & Bramas 2024, §4.4 and §5; periodic gamma rays of Meneses
  et al., §3.3); ``Bvh(sort=False)`` is ``"bvh-unsorted"``. See
  `jaxrt.rt.aabb`, `jaxrt.rt.periodic`, `jaxrt.rt.ffi`.
* `Spheres`, `Squares`: seed 001's other methods (`jaxrt.rt.spheres`,
  `jaxrt.rt.squares`).
* `FusedEnergy`: seed 001's fused mode for those three methods, the LJ
  energy summed during the traversal, no list (`jaxrt.rt.seed_energy`).

Other pure-Warp methods follow `jaxrt.rt._method.RTMethod` and become
backends through `jaxrt.rt.ffi.method_backend`.
"""
import warp as _wp  # noqa: F401  (ImportError here: Warp absent, no RT backends)

from jaxrt.backends.rt.method import RTMethod
from jaxrt.backends.rt import policy
from jaxrt.backends.rt.aabb import AabbMethod
from jaxrt.backends.rt.ffi import (Bvh, FusedEnergy, MethodBackend, Spheres,
                                   Squares, method_backend)
from jaxrt.backends.rt.spheres import SpheresMethod
from jaxrt.backends.rt.squares import SquaresMethod

__all__ = ["AabbMethod", "Bvh", "FusedEnergy", "MethodBackend", "RTMethod", "policy",
           "Spheres", "SpheresMethod", "Squares", "SquaresMethod",
           "method_backend"]
