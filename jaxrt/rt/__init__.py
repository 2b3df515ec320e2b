"""`jaxrt.backends.rt` under its former name: the same public names (the
modules themselves are under `jaxrt.backends.rt`). They load on first use,
Warp with them."""
from jaxrt import lazy as _lazy

_NAMES = {name: f"jaxrt.backends.rt:{name}" for name in (
    "AabbMethod", "Bvh", "FusedEnergy", "MethodBackend", "RTMethod",
    "Spheres", "SpheresMethod", "Squares", "SquaresMethod", "method_backend",
    "policy")}
__all__ = sorted(_NAMES)
__getattr__, __dir__ = _lazy.exports(__name__, _NAMES)
