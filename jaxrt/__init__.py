"""jaxrt: fast, exact fixed-radius neighbour lists for JAX and jax-md.

Public API:
  neighbor_list            drop-in for jax_md.partition.neighbor_list
  Dense, Sparse, OrderedSparse   jax-md's layouts (re-exported)
  check, NeighborListError, ErrorCode   host-side error check
  backends                 the backends as options values (Cell, Brute, Bvh, ...)
  available_backends()     names usable as backend=
  Scene                    a simulation of only the effects it names (jaxrt.sim)
  pairs, Pairs, pairs_sizes, PairsError   pairs with lattice shifts (i, j, S)
                           in any cell, jit/vmap/grad-able (jaxrt.pairs)
  pairs_from_ase, pairs_to_ase, ase_neighbor_list   ASE in and out
"""
from jaxrt import backends
from jaxrt.backends import available as available_backends
from jaxrt.errors import (ErrorCode, ListTooLargeError, NeighborListError,
                          check)
from jaxrt.pairs.ase import neighbor_list as ase_neighbor_list
from jaxrt.pairs.ase import pairs_from_ase, pairs_to_ase
from jaxrt.lists.neighbors import Dense, OrderedSparse, Sparse, neighbor_list
from jaxrt.pairs.search import Pairs, PairsError, PairSizes, pairs, pairs_sizes
from jaxrt.sim import Scene

__version__ = "0.1.0"

__all__ = [
    "Dense", "ErrorCode", "ListTooLargeError", "NeighborListError",
    "OrderedSparse", "PairSizes", "Pairs", "PairsError", "Scene", "Sparse",
    "ase_neighbor_list", "available_backends", "backends", "check",
    "neighbor_list", "pairs", "pairs_from_ase", "pairs_sizes", "pairs_to_ase",
]
