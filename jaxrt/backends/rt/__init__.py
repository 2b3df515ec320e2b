"""Ray-traced neighbour search on Warp BVHs (needs ``warp-lang``).

The backends (`jaxrt.backends.rt.ffi`, re-exported by `jaxrt.backends`):

* `Bvh` (``"bvh"``): custom AABB boxes in a Morton-sorted BVH kept across
  calls (Algis & Bramas 2024, §4.4 and §5; periodic gamma rays of Meneses
  et al., §3.3); ``Bvh(sort=False)`` is ``"bvh-unsorted"``. See
  `jaxrt.backends.rt.aabb`, `jaxrt.backends.rt.periodic`,
  `jaxrt.backends.rt.ffi`.
* `Spheres`, `Squares`: seed 001's other methods
  (`jaxrt.backends.rt.spheres`, `jaxrt.backends.rt.squares`).
* `FusedEnergy`: seed 001's fused mode for those three methods, the LJ
  energy summed during the traversal, no list and no gradient
  (`jaxrt.backends.rt.seed_energy`); the differentiable list-free energies
  are `jaxrt.energy.listfree`'s.

The Warp kernels live here because they traverse the same BVH: the
lists' (`aabb`, `spheres`, `squares`), seed 001's fused energies
(`seed_energy`) and ORCS' forces (`orcs`, which
`jaxrt.energy.lennard_jones_fused(backend="bvh")` calls). They know nothing
of JAX: `jaxrt.backends.rt.ffi` is the one module that wraps them for JAX.
Seed 004's Delaunay flips and BFS are Warp kernels here too
(`delaunay_kernels`, driven by `delaunay_engine`; the backend is
``jaxrt.backends.Delaunay(engine="warp")``). Other pure-Warp methods follow `jaxrt.backends.rt.method.RTMethod` and
become backends through `jaxrt.backends.rt.ffi.method_backend`.

The names load on first use (Warp with them); `halfbox`, the half-box rule,
needs no Warp.
"""
from jaxrt import lazy as _lazy

_NAMES = {
    "AabbMethod": "jaxrt.backends.rt.aabb:AabbMethod",
    "Bvh": "jaxrt.backends.rt.ffi:Bvh",
    "FusedEnergy": "jaxrt.backends.rt.ffi:FusedEnergy",
    "MethodBackend": "jaxrt.backends.rt.ffi:MethodBackend",
    "RTMethod": "jaxrt.backends.rt.method:RTMethod",
    "Spheres": "jaxrt.backends.rt.ffi:Spheres",
    "SpheresMethod": "jaxrt.backends.rt.spheres:SpheresMethod",
    "Squares": "jaxrt.backends.rt.ffi:Squares",
    "SquaresMethod": "jaxrt.backends.rt.squares:SquaresMethod",
    "method_backend": "jaxrt.backends.rt.ffi:method_backend",
    "policy": "jaxrt.backends.rt.policy",
}
__all__ = sorted(_NAMES)
__getattr__, __dir__ = _lazy.exports(__name__, _NAMES)
