"""The jax-md front: `neighbor_list`, a drop-in for
``jax_md.partition.neighbor_list`` (`jaxrt.lists.neighbors`), the model
of the caller's metric it checks (`jaxrt.lists.metric`), and spatial
orderings of particles (`jaxrt.lists.order`).

The names load on first use: `jaxrt.backends.contract` (which the front
imports) needs `jaxrt.lists.metric` alone.
"""
import importlib

_ORDER = ("inverse_order", "reorder", "spatial_order")
__all__ = ["Dense", "OrderedSparse", "Sparse", "StatefulNeighborList",
           "inverse_order", "neighbor_list", "reorder", "spatial_order"]


def __getattr__(name):
    if name in __all__:
        module = "jaxrt.lists.order" if name in _ORDER else \
            "jaxrt.lists.neighbors"
        value = getattr(importlib.import_module(module), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'jaxrt.lists' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))
