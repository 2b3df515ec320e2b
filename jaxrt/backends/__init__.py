"""The search backends, as values: ``backend=`` takes a name or one of these.

Each is a frozen, hashable dataclass of its options, so that options are
static (part of what ``jit`` caches on) and no module state decides what a
list does:

* `Cell` (``"cell"``, the default): the sorted cell list of
  `jaxrt.cell_list`; ``kernel=`` picks its candidate pass.
* `Brute` (``"brute"``, jax-md's ``disable_cell_list=True``): all pairs.
* `Bvh` (``"bvh"``; ``"bvh-unsorted"`` is ``Bvh(sort=False)``): the
  ray-traced custom AABB BVH of `jaxrt.rt.aabb`, kept across calls by the
  list factory that owns it.
* `Spheres`, `Squares` (``"spheres"``, ``"squares"``): seed 001's other
  ray-traced methods (`jaxrt.rt.spheres`, `jaxrt.rt.squares`).
* `Delaunay` (``"delaunay"``): seed 004's 2D Delaunay triangulation kept by
  edge flips and searched by BFS (`jaxrt.delaunay`); float64, its
  triangulation travels with the list.

A backend of one's own is any object following `Backend` (see
`jaxrt._backend`, re-exported here with the layout helpers a backend
needs), passed as ``backend=`` directly; no registration is needed.
"""
from __future__ import annotations

from typing import Callable

from jaxrt.backends.contract import (Backend, Capacity, Geometry, MetricSq,
                                     Query, SearchResult, bind,
                                     dense_to_sparse, format_dense_rows,
                                     pack_rows)
from jaxrt.backends.brute import Brute
from jaxrt.backends.cell.search import Cell
from jaxrt.backends.delaunay import Delaunay

try:  # Warp is a dependency, but a broken install must not break the rest.
    from jaxrt.backends.rt.ffi import Bvh, Spheres, Squares
except ImportError as _warp_error:
    _WARP_ERROR: ImportError | None = _warp_error
else:
    _WARP_ERROR = None

__all__ = ["Backend", "Brute", "Bvh", "Capacity", "Cell", "Delaunay",
           "Geometry",
           "MetricSq", "Query", "SearchResult", "Spheres", "Squares",
           "available", "bind", "dense_to_sparse", "format_dense_rows",
           "pack_rows", "resolve"]

_RAY_TRACED: dict[str, Callable[[], Backend]] = {
    "bvh": lambda: Bvh(),
    "bvh-unsorted": lambda: Bvh(sort=False),
    "spheres": lambda: Spheres(),
    "squares": lambda: Squares(),
}
_NAMED: dict[str, Callable[[], Backend]] = {
    "brute": lambda: Brute(),
    "cell": lambda: Cell(),
    "delaunay": lambda: Delaunay(),
    **(_RAY_TRACED if _WARP_ERROR is None else {}),
}


def available() -> list[str]:
    """The names ``backend=`` accepts (besides ``"auto"``)."""
    return sorted(_NAMED)


def resolve(backend: str | Backend) -> Backend:
    """The backend a ``backend=`` argument names (``"auto"`` excluded).

    Raises:
      ValueError: an unknown name, or a ray-traced one without Warp.
      TypeError: an object that is not a `Backend`.
    """
    if isinstance(backend, str):
        if backend in _NAMED:
            return _NAMED[backend]()
        if backend in _RAY_TRACED:  # named, but Warp failed to import
            raise ValueError(f"backend={backend!r} needs warp-lang, which "
                             f"failed to import: {_WARP_ERROR}")
        raise ValueError(
            f"backend={backend!r} is not known; choose one of {available()}, "
            "'auto', or pass an options object such as "
            "jaxrt.backends.Cell(kernel='xla').")
    missing = [a for a in ("name", "measure", "search")
               if not hasattr(backend, a)]
    if missing:
        raise TypeError(
            f"backend must be a name ({', '.join(available())}) or a backend "
            f"object with name, measure and search (jaxrt.backends.Backend); "
            f"got {type(backend).__name__}, which lacks {missing}.")
    try:
        hash(backend)
    except TypeError as e:
        raise TypeError(
            f"backend {type(backend).__name__} must be hashable (a frozen "
            "dataclass): its options are static under jit.") from e
    return backend
