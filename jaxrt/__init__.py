"""jaxrt: fast, exact fixed-radius neighbour lists for JAX and jax-md.

Public API:
  neighbor_list            drop-in for jax_md.partition.neighbor_list
  Dense, Sparse, OrderedSparse   jax-md's layouts (re-exported)
  check, Error, NeighborListError, ListTooLargeError, ErrorCode
                           host-side error check; every jaxrt exception is
                           a `jaxrt.Error`
  backends                 the backends as options values (Cell, Brute, Bvh, ...)
  available_backends()     names usable as backend=
  energy                   energies on lists and without one (jaxrt.energy)
  spatial_order, reorder, inverse_order   number particles along a
                           space-filling curve (memory locality of list
                           gathers), and apply it to a state
  Scene                    a simulation of only the effects it names (jaxrt.sim)
  pairs, Pairs, pairs_sizes, PairsError   pairs with lattice shifts (i, j, S)
                           in any cell, jit/vmap/grad-able (jaxrt.pairs)
  pairs_batch, BatchPairs, pairs_batch_sizes   flat batches of systems
                           in jraph's layout (n_node, n_edge, padding graph)
  pairs_from_ase, pairs_to_ase, ase_neighbor_list, batch_from_ase
                           ASE in and out

Every name loads on first use (`jaxrt.lazy`): ``import jaxrt`` imports
neither JAX, jax-md, Warp nor `jaxrt.sim`.
"""
from jaxrt import lazy as _lazy

__version__ = "0.1.0"

_NAMES = {
    "BatchPairs": "jaxrt.pairs.batch:BatchPairs",
    "Dense": "jaxrt.lists.neighbors:Dense",
    "Error": "jaxrt.errors:Error",
    "ErrorCode": "jaxrt.errors:ErrorCode",
    "ListTooLargeError": "jaxrt.errors:ListTooLargeError",
    "Float32Warning": "jaxrt.pairs.search:Float32Warning",
    "NeighborListError": "jaxrt.errors:NeighborListError",
    "OrderedSparse": "jaxrt.lists.neighbors:OrderedSparse",
    "PairSizes": "jaxrt.pairs.search:PairSizes",
    "Pairs": "jaxrt.pairs.search:Pairs",
    "PairsError": "jaxrt.pairs.search:PairsError",
    "Scene": "jaxrt.sim.spec:Scene",
    "Sparse": "jaxrt.lists.neighbors:Sparse",
    "ase_neighbor_list": "jaxrt.pairs.ase:neighbor_list",
    "available_backends": "jaxrt.backends:available",
    "backends": "jaxrt.backends",
    "batch_from_ase": "jaxrt.pairs.ase:batch_from_ase",
    "check": "jaxrt.errors:check",
    "energy": "jaxrt.energy",
    "inverse_order": "jaxrt.lists.order:inverse_order",
    "neighbor_list": "jaxrt.lists.neighbors:neighbor_list",
    "pairs": "jaxrt.pairs.search:pairs",
    "pairs_batch": "jaxrt.pairs.batch:pairs_batch",
    "pairs_batch_sizes": "jaxrt.pairs.batch:pairs_batch_sizes",
    "pairs_from_ase": "jaxrt.pairs.ase:pairs_from_ase",
    "pairs_sizes": "jaxrt.pairs.search:pairs_sizes",
    "pairs_to_ase": "jaxrt.pairs.ase:pairs_to_ase",
    "reorder": "jaxrt.lists.order:reorder",
    "sim": "jaxrt.sim",
    "spatial_order": "jaxrt.lists.order:spatial_order",
}
__all__ = sorted(_NAMES)
__getattr__, __dir__ = _lazy.exports(__name__, _NAMES)

_lazy.keep_functions(__name__, ("pairs",))
