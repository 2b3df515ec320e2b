"""Ray-traced neighbour search on Warp BVHs (needs ``warp-lang``).

Importing this package registers the backends:

* ``"bvh"``: custom AABB boxes in a Morton-sorted BVH kept across calls
  (Algis & Bramas 2024, §4.4 and §5; periodic gamma rays of Meneses et al.,
  §3.3). See `jaxrt.rt.aabb`, `jaxrt.rt.periodic`, `jaxrt.rt.ffi`.
* ``"bvh-unsorted"``: the same without sorting the particles.

Other pure-Warp methods follow `jaxrt.rt._method.RTMethod` and become
backends through `jaxrt.rt.ffi.method_backend`.
"""
import warp as _wp  # noqa: F401  (ImportError here: Warp absent, no RT backends)

from jaxrt import backends as _backends
from jaxrt.rt._method import RTMethod
from jaxrt.rt.aabb import AabbMethod, RebuildPolicy
from jaxrt.rt.ffi import AabbBackend, MethodBackend, method_backend

_backends.register("bvh", lambda: AabbBackend("bvh", sort=True))
_backends.register("bvh-unsorted", lambda: AabbBackend("bvh-unsorted", sort=False))

__all__ = ["AabbBackend", "AabbMethod", "MethodBackend", "RTMethod",
           "RebuildPolicy", "SpheresMethod", "SquaresMethod", "method_backend"]

from jaxrt.rt.spheres import SpheresMethod  # noqa: E402
from jaxrt.rt.squares import SquaresMethod  # noqa: E402

_backends.register("spheres", lambda: method_backend(SpheresMethod()))
_backends.register("squares", lambda: method_backend(SquaresMethod()))
