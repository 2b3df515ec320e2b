"""jaxrt: fast, exact fixed-radius neighbour lists for JAX and jax-md.

Public API:
  neighbor_list            drop-in for jax_md.partition.neighbor_list
  Dense, Sparse, OrderedSparse   jax-md's layouts (re-exported)
  check, NeighborListError, ErrorCode   host-side error check
  available_backends()     names usable as backend=
  Scene                    a simulation that computes only the effects it names
"""
from jaxrt import brute as _brute  # noqa: F401  (registers "brute")
from jaxrt import cell_list as _cell_list  # noqa: F401  (registers "cell")
from jaxrt.backends import available as available_backends
from jaxrt.errors import ErrorCode, NeighborListError, check
from jaxrt.neighbors import Dense, OrderedSparse, Sparse, neighbor_list
from jaxrt.scene import Scene

try:  # Warp is optional at import time: without it the RT backends are absent.
    from jaxrt import rt as _rt  # noqa: F401
except ImportError:
    pass

__version__ = "0.1.0"

__all__ = [
    "Dense", "ErrorCode", "NeighborListError", "OrderedSparse", "Scene", "Sparse",
    "available_backends", "check", "neighbor_list",
]
