"""The jax-md front: `neighbor_list`, a drop-in for
``jax_md.partition.neighbor_list`` (`jaxrt.lists.neighbors`), and the model
of the caller's metric it checks (`jaxrt.lists.metric`).

The names load on first use: `jaxrt.backends.contract` (which the front
imports) needs `jaxrt.lists.metric` alone.
"""
import importlib

__all__ = ["Dense", "OrderedSparse", "Sparse", "StatefulNeighborList",
           "neighbor_list"]


def __getattr__(name):
    if name in __all__:
        value = getattr(importlib.import_module("jaxrt.lists.neighbors"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'jaxrt.lists' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))
