"""jaxrt: fast, exact fixed-radius neighbour lists for JAX and jax-md.

Public API:
  neighbor_list            drop-in for jax_md.partition.neighbor_list
  Dense, Sparse, OrderedSparse   jax-md's layouts (re-exported)
  check, NeighborListError, ErrorCode   host-side error check
  backends                 the backends as options values (Cell, Brute, Bvh, ...)
  available_backends()     names usable as backend=
  Scene                    a simulation of only the effects it names (jaxrt.sim)
"""
from jaxrt import backends
from jaxrt.backends import available as available_backends
from jaxrt.errors import ErrorCode, NeighborListError, check
from jaxrt.neighbors import Dense, OrderedSparse, Sparse, neighbor_list
from jaxrt.sim import Scene

__version__ = "0.1.0"

__all__ = [
    "Dense", "ErrorCode", "NeighborListError", "OrderedSparse", "Scene", "Sparse",
    "available_backends", "backends", "check", "neighbor_list",
]
