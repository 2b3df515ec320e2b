"""An alias of `jaxrt.backends.rt`, the ray-traced Warp backends, under its
former name: its public names only (modules are under
`jaxrt.backends.rt`)."""
from jaxrt.backends.rt import (AabbMethod, Bvh, FusedEnergy, MethodBackend,
                               RTMethod, Spheres, SpheresMethod, Squares,
                               SquaresMethod, method_backend, policy)

__all__ = ["AabbMethod", "Bvh", "FusedEnergy", "MethodBackend", "RTMethod",
           "policy", "Spheres", "SpheresMethod", "Squares", "SquaresMethod",
           "method_backend"]
