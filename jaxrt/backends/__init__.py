"""The search backends, as values: ``backend=`` takes a name or one of these.

Each is a frozen, hashable dataclass of its options, so that options are
static (part of what ``jit`` caches on) and no module state decides what a
list does:

* `Cell` (``"cell"``, the default): the sorted cell list of
  `jaxrt.backends.cell.search`; ``kernel=`` picks its candidate pass.
* `Brute` (``"brute"``, jax-md's ``disable_cell_list=True``): all pairs.
* `BySize`: one backend for small N, another for the rest (``"auto"``'s
  on a CPU: `Brute` for small lists, `Cell` for the rest).
* `Bvh` (``"bvh"``; ``"bvh-unsorted"`` is ``Bvh(sort=False)``): the
  ray-traced custom AABB BVH of `jaxrt.backends.rt.aabb`, kept across calls by the
  list factory that owns it.
* `Spheres`, `Squares` (``"spheres"``, ``"squares"``): seed 001's other
  ray-traced methods (`jaxrt.backends.rt.spheres`, `jaxrt.backends.rt.squares`).
* `Delaunay` (``"delaunay"``): seed 004's 2D Delaunay triangulation kept by
  edge flips and searched by BFS (`jaxrt.backends.delaunay`); float64, its
  triangulation travels with the list; ``Delaunay(engine="warp")`` runs
  the flips and the BFS as Warp kernels.

A backend of one's own is any object following `Backend` (see
`jaxrt.backends.contract`, re-exported here with the layout helpers a backend
needs), passed as ``backend=`` directly; no registration is needed.
"""
from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Callable

from jaxrt import lazy as _lazy

if TYPE_CHECKING:
    from jaxrt.backends.contract import Backend

# Every name loads on first use: the ray-traced ones import Warp, and a
# list on the cell list never needs it.
_NAMES = {
    "Backend": "jaxrt.backends.contract:Backend",
    "Brute": "jaxrt.backends.brute:Brute",
    "Bvh": "jaxrt.backends.rt.ffi:Bvh",
    "BySize": "jaxrt.backends.bysize:BySize",
    "Capabilities": "jaxrt.backends.contract:Capabilities",
    "Capacity": "jaxrt.backends.contract:Capacity",
    "Cell": "jaxrt.backends.cell.search:Cell",
    "Delaunay": "jaxrt.backends.delaunay:Delaunay",
    "Geometry": "jaxrt.backends.contract:Geometry",
    "MetricSq": "jaxrt.backends.contract:MetricSq",
    "Query": "jaxrt.backends.contract:Query",
    "SearchResult": "jaxrt.backends.contract:SearchResult",
    "Spheres": "jaxrt.backends.rt.ffi:Spheres",
    "Squares": "jaxrt.backends.rt.ffi:Squares",
    "bind": "jaxrt.backends.contract:bind",
    "capabilities": "jaxrt.backends.contract:capabilities",
    "dense_to_sparse": "jaxrt.layouts.rows:dense_to_sparse",
    "format_dense_rows": "jaxrt.backends.contract:format_dense_rows",
    "pack_rows": "jaxrt.layouts.rows:pack_rows",
}
__all__ = sorted([*_NAMES, "available", "resolve"])
__getattr__, __dir__ = _lazy.exports(__name__, _NAMES)


def _backend(target: str) -> Callable[[], Backend]:
    """A factory of the backend class ``"module:Class"`` (imported then)."""
    module, _, name = target.partition(":")
    return lambda **options: getattr(importlib.import_module(module),
                                     name)(**options)


_RAY_TRACED: dict[str, Callable[[], Backend]] = {
    "bvh": lambda: _backend(_NAMES["Bvh"])(),
    "bvh-unsorted": lambda: _backend(_NAMES["Bvh"])(sort=False),
    "spheres": lambda: _backend(_NAMES["Spheres"])(),
    "squares": lambda: _backend(_NAMES["Squares"])(),
}
_PURE_JAX: dict[str, Callable[[], Backend]] = {
    "brute": lambda: _backend(_NAMES["Brute"])(),
    "cell": lambda: _backend(_NAMES["Cell"])(),
    "delaunay": lambda: _backend(_NAMES["Delaunay"])(),
}
_WARP: list[ImportError | None] = []  # [the error importing Warp, or None]


def _warp_error() -> ImportError | None:
    """Why the ray-traced backends cannot load (None: they can); tried once.
    Warp is a dependency, but a broken install must not break the rest."""
    if not _WARP:
        try:
            importlib.import_module("jaxrt.backends.rt.ffi")
        except ImportError as e:
            _WARP.append(e)
        else:
            _WARP.append(None)
    return _WARP[0]


def _named() -> dict[str, Callable[[], Backend]]:
    return {**_PURE_JAX, **(_RAY_TRACED if _warp_error() is None else {})}


def available() -> list[str]:
    """The names ``backend=`` accepts (besides ``"auto"``); the ray-traced
    ones only where Warp imports (tried at the first call)."""
    return sorted(_named())


def resolve(backend: str | Backend) -> Backend:
    """The backend a ``backend=`` argument names (``"auto"`` excluded).

    Raises:
      ValueError: an unknown name, or a ray-traced one without Warp.
      TypeError: an object that is not a `Backend`.
    """
    if isinstance(backend, str):
        if backend in _PURE_JAX:
            return _PURE_JAX[backend]()
        if backend in _RAY_TRACED:
            if _warp_error() is not None:
                raise ValueError(f"backend={backend!r} needs warp-lang, "
                                 f"which failed to import: {_warp_error()}")
            return _RAY_TRACED[backend]()
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
