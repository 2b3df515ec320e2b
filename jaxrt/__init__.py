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
from jaxrt._lazy import lazy_package

__version__ = "0.1.0"

# Each public name is imported from its module when first read (the
# ``jaxrt`` command starts without JAX, jax-md or Warp): `jaxrt._lazy`.
_EXPORTS = {
    "backends": "jaxrt.backends",
    "available_backends": "jaxrt.backends",
    "ErrorCode": "jaxrt.errors", "ListTooLargeError": "jaxrt.errors",
    "NeighborListError": "jaxrt.errors", "check": "jaxrt.errors",
    "ase_neighbor_list": "jaxrt.ase_bridge",
    "pairs_from_ase": "jaxrt.ase_bridge", "pairs_to_ase": "jaxrt.ase_bridge",
    "Dense": "jaxrt.neighbors", "OrderedSparse": "jaxrt.neighbors",
    "Sparse": "jaxrt.neighbors", "neighbor_list": "jaxrt.neighbors",
    "Pairs": "jaxrt.pairs", "PairsError": "jaxrt.pairs",
    "PairSizes": "jaxrt.pairs", "pairs": "jaxrt.pairs",
    "pairs_sizes": "jaxrt.pairs",
    "Scene": "jaxrt.sim",
}
# Names whose module defines them under another name.
_RENAMED = {"available_backends": "available",
            "ase_neighbor_list": "neighbor_list"}

__all__ = [
    "Dense", "ErrorCode", "ListTooLargeError", "NeighborListError",
    "OrderedSparse", "PairSizes", "Pairs", "PairsError", "Scene", "Sparse",
    "ase_neighbor_list", "available_backends", "backends", "check",
    "neighbor_list", "pairs", "pairs_from_ase", "pairs_sizes", "pairs_to_ase",
]

lazy_package(__name__, _EXPORTS, shadowed=("pairs",), renamed=_RENAMED)
