"""JAX bindings of the ray-traced methods: the only module that touches
Warp's JAX interop (``wp.jax_callable``, XLA FFI; CPU and CUDA).

Two ways in:

* `AabbBackend` (``backend="bvh"`` and ``"bvh-unsorted"``): the custom AABB
  method of `jaxrt.rt.aabb` with a BVH kept across calls (refit or rebuilt,
  see `jaxrt.rt.aabb.choose_update`), Dense rows written directly and
  Sparse / OrderedSparse edges by count, scan and fill.
* `method_backend`: any `jaxrt.rt._method.RTMethod` (spheres, double
  squares, ...) as a backend, through Dense rows and
  `jaxrt.backends.format_dense_rows`.

How the Warp calls behave under JAX:

* ``jit``, ``lax.scan``, ``fori_loop``, ``lax.cond``: the calls are XLA
  custom calls. The BVH backend's calls are marked ``has_side_effect`` so
  XLA neither hoists them out of loops nor drops them.
* Persistence: every traced call site gets its own *slot*, and each slot
  owns one `jaxrt.rt.aabb.AabbSearch` (LRU, at most `MAX_KEPT_TREES`). A
  compiled loop body calls the same slot every step, so its BVH is refit or
  rebuilt in place. Lists never depend on the kept state being right for
  them: every call refits or rebuilds to the positions it is given.
* ``vmap``: `jax.custom_batching.custom_vmap` runs the systems one after
  the other, each through its own call site (own slot, own BVH), so no
  system sees another's particles. Beyond `MAX_UNROLLED_SYSTEMS` systems
  one call site is looped with ``lax.map`` (one BVH, rebuilt per system).
* Graph capture is off (``graph_mode=NONE``): the refit/rebuild decision
  reads one flag back to the host, and building a new ``wp.Bvh`` inside a
  CUDA graph crashed (DESIGN.md).
* float64 positions (``jax_enable_x64``) run the float64 kernels: exact
  float64 distance test on a padded float32 BVH.

Distances are computed in the kernels in Cartesian coordinates with jax-md's
own arithmetic (``periodic_displacement`` then ``square_distance``); the
caller's ``metric_sq`` is not called.
"""
import collections
import itertools
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
import warp as wp
from jax_md.partition import NeighborListFormat

from jaxrt import backends
from jaxrt.backends import Capacity, Geometry, MetricSq, Query, SearchResult
from jaxrt.rt import aabb, periodic as gamma
from jaxrt.rt._method import RTMethod

# Kept BVHs (one per traced call site and system); the oldest is dropped.
MAX_KEPT_TREES = 8
# vmap over more systems than this loops one call site instead of unrolling.
MAX_UNROLLED_SYSTEMS = 16
# Warp kernels compute byte offsets in 32-bit ints (warp/native/array.h):
# an int32 output of 2**29 entries or more would wrap (seen as an illegal
# address on the H100 at N = 8.4e6, k = 288).
MAX_LIST_ENTRIES = 2 ** 29 - 1

Dense = NeighborListFormat.Dense
OrderedSparse = NeighborListFormat.OrderedSparse

_VECTORS = {np.dtype(np.float32): wp.vec3f, np.dtype(np.float64): wp.vec3d}

# ---------------------------------------------------------------------------
# Persistent state (touched only inside FFI callbacks, which Warp serialises).

_TREES: "collections.OrderedDict[tuple, aabb.AabbSearch]" = collections.OrderedDict()
_SLOTS = itertools.count()
# What the kept trees did, for tests and benchmarks: {"build": .., ...}.
update_counts: collections.Counter = collections.Counter()


def _new_slot() -> int:
    return next(_SLOTS)


def forget_trees() -> None:
    """Drop every kept BVH (frees their memory; the next calls rebuild)."""
    _TREES.clear()


def _tree(slot: int, n: int, vector, device, sort: bool,
          policy: aabb.RebuildPolicy, cluster: int) -> aabb.AabbSearch:
    """The BVH kept for ``slot`` (a fresh, unkept one for slot < 0)."""
    def new():
        return aabb.AabbSearch(n, vector, device, sort=sort, policy=policy,
                               cluster_size=cluster)

    if slot < 0:
        return new()
    key = (slot, n, vector, str(device), sort, policy, cluster)
    tree = _TREES.pop(key, None)
    if tree is None:
        tree = new()
    _TREES[key] = tree
    while len(_TREES) > MAX_KEPT_TREES:
        _TREES.popitem(last=False)
    return tree


def _axes(bits) -> tuple[bool, bool, bool]:
    """Periodic flags from the static int (a ``wp.int32`` in callbacks)."""
    return tuple(bool(int(bits) >> a & 1) for a in range(3))


def _bits(periodic) -> int:
    return sum(1 << a for a, p in enumerate(periodic) if p)


# ---------------------------------------------------------------------------
# The Warp functions given to jax_callable, one set per position type.

_CALLABLES: dict = {}


def _aabb_callables(vector):
    """(dense, sparse) jax callables for positions of type ``vector``."""
    if vector in _CALLABLES:
        return _CALLABLES[vector]

    def dense(points: wp.array(dtype=vector), side: wp.array(dtype=vector),
              cutoff: wp.float64, periodic: wp.int32, mask_self: wp.int32,
              sort: wp.int32, drift: wp.float64, cluster: wp.int32,
              slot: wp.int32, rows: wp.array2d(dtype=wp.int32),
              count: wp.array(dtype=wp.int32)):
        tree = _tree(int(slot), points.shape[0], vector, points.device,
                     bool(sort), aabb.RebuildPolicy(float(drift)), int(cluster))
        update_counts[tree.update(points, side, _axes(periodic), float(cutoff))] += 1
        tree.query_dense(side, mask_self=bool(mask_self), rows=rows, count=count)

    def sparse(points: wp.array(dtype=vector), side: wp.array(dtype=vector),
               cutoff: wp.float64, periodic: wp.int32, mask_self: wp.int32,
               lower_only: wp.int32, sort: wp.int32, drift: wp.float64,
               cluster: wp.int32, slot: wp.int32,
               pairs: wp.array2d(dtype=wp.int32),
               count: wp.array(dtype=wp.int32), offset: wp.array(dtype=wp.int32),
               total: wp.array(dtype=wp.int32)):
        tree = _tree(int(slot), points.shape[0], vector, points.device,
                     bool(sort), aabb.RebuildPolicy(float(drift)), int(cluster))
        update_counts[tree.update(points, side, _axes(periodic), float(cutoff))] += 1
        tree.query_sparse(side, mask_self=bool(mask_self),
                          lower_only=bool(lower_only), pairs=pairs, count=count,
                          offset=offset, total=total)

    # jax_callable loads the module named by __module__ before each call: name
    # the kernels' module, so no kernel-less module is compiled for nothing.
    dense.__module__ = sparse.__module__ = aabb.__name__
    options = dict(graph_mode=wp.JaxCallableGraphMode.NONE, vmap_method=None,
                   has_side_effect=True)
    _CALLABLES[vector] = (wp.jax_callable(dense, num_outputs=2, **options),
                          wp.jax_callable(sparse, num_outputs=4, **options))
    return _CALLABLES[vector]


_METHOD_CALLABLES: dict = {}


def _method_callable(method: RTMethod, vector):
    """jax callable running ``method.find`` on positions of type ``vector``."""
    key = (id(method), vector)
    if key in _METHOD_CALLABLES:
        return _METHOD_CALLABLES[key][1]

    def find(points: wp.array(dtype=vector), side: wp.array(dtype=vector),
             cutoff: wp.float64, periodic: wp.int32, mask_self: wp.int32,
             rows: wp.array2d(dtype=wp.int32), count: wp.array(dtype=wp.int32)):
        axes = _axes(periodic)
        box = tuple(float(s) for s in side.numpy()[0]) if any(axes) else None
        method.find(points, cutoff=float(cutoff), side=box, periodic=axes,
                    mask_self=bool(mask_self), out_idx=rows, out_count=count)

    find.__module__ = type(method).__module__  # see _aabb_callables
    callable_ = wp.jax_callable(find, num_outputs=2, in_out_argnames=["rows"],
                                graph_mode=wp.JaxCallableGraphMode.NONE,
                                vmap_method=None)
    _METHOD_CALLABLES[key] = (method, callable_)  # keeps method alive with its id
    return callable_


# ---------------------------------------------------------------------------
# JAX side.


def _load_kernels() -> None:
    """Compile the kernels for JAX's default device before the first call
    (otherwise the first call compiles inside the XLA custom call)."""
    platform = jax.default_backend()
    aabb.load("cuda" if platform in ("gpu", "cuda") else "cpu")


def _vector_of(position) -> type:
    dtype = np.dtype(position.dtype)
    if dtype not in _VECTORS:
        raise TypeError("position must be float32 or float64 for the ray-traced "
                        f"backends; got {dtype}. Convert with "
                        ".astype(jnp.float32).")
    return _VECTORS[dtype]


def _points(position, geometry: Geometry, query: Query):
    """Cartesian positions for the kernels.

    Args:
      position: float ``(N, dim)``, dim in 1..3.
    Returns:
      float ``(N, 3)`` zero-padded Cartesian positions; float ``(1, 3)`` box
      sides (1 on padded axes); the 3 periodic flags; bool scalar, True when
      the cutoff is too large for the current box (reported as overflow, so
      that ``allocate`` re-measures and raises).
    """
    dim = query.dim
    if position.ndim != 2 or position.shape[1] != dim or dim not in (1, 2, 3):
        raise ValueError(f"position must be (N, {dim}) with dim in 1..3; got "
                         f"shape {position.shape}.")
    dtype = position.dtype
    cart = position * geometry.scale.astype(dtype)
    padding = 3 - dim
    cart = jnp.pad(cart, ((0, 0), (0, padding)))
    side = jnp.concatenate([geometry.side.astype(dtype), jnp.ones(padding, dtype)])
    axes = tuple(query.periodic) + (False,) * padding
    # Only integers come out, so no gradient flows through the search; this
    # lets jax.grad trace through update() (FFI calls have no JVP).
    cart, side = jax.lax.stop_gradient((cart, side))
    too_large = jnp.zeros((), bool)
    limit = 0.5 * (1.0 - gamma.CUTOFF_MARGIN)
    for a, p in enumerate(axes):
        if p:
            too_large |= ~(query.cutoff < limit * side[a])
    return cart, side[None, :], axes, too_large


def _sequential_vmap(call: Callable) -> Callable:
    """``call(points, side, slot)`` -> tuple of arrays, as a function of
    ``(points, side)`` whose ``vmap`` runs one system after the other, each
    through its own call site (own slot)."""

    @jax.custom_batching.custom_vmap
    def one_system(points, side):
        return call(points, side, _new_slot())

    @one_system.def_vmap
    def systems(axis_size, in_batched, points, side):
        points_batched, side_batched = in_batched
        if not points_batched:
            points = jnp.broadcast_to(points, (axis_size,) + points.shape)
        if not side_batched:
            side = jnp.broadcast_to(side, (axis_size,) + side.shape)
        if axis_size <= MAX_UNROLLED_SYSTEMS:
            outs = [one_system(points[b], side[b]) for b in range(axis_size)]
            out = jax.tree.map(lambda *xs: jnp.stack(xs), *outs)
        else:
            out = jax.lax.map(lambda ps: one_system(*ps), (points, side))
        return out, jax.tree.map(lambda _: True, out)

    return one_system


class AabbBackend:
    """Backend over `jaxrt.rt.aabb`: custom AABB BVH, kept across calls.

    Attributes:
      name: the ``backend=`` name.
      sort: Morton-sort particles at each build (the seed's sorted AABB).
      policy: when to rebuild rather than refit (`jaxrt.rt.aabb.RebuildPolicy`).
      cluster_size: particles per BVH box (`jaxrt.rt.aabb.AabbSearch`); 1,
        the seed's box per particle, was the fastest in every measured case
        (`benchmarks/rt_neighbors.py`).
    """

    max_list_entries = MAX_LIST_ENTRIES

    def __init__(self, name: str, *, sort: bool,
                 policy: aabb.RebuildPolicy = aabb.RebuildPolicy(),
                 cluster_size: int = 1):
        if int(cluster_size) < 1:
            raise ValueError(f"cluster_size must be >= 1; got {cluster_size}.")
        self.name = name
        self.sort = sort
        self.policy = policy
        self.cluster_size = int(cluster_size)
        _load_kernels()

    def _dense(self, points, side, query: Query, axes, width: int, slot=None):
        """Dense rows int32 ``(N, width)`` and exact counts int32 ``(N,)``."""
        dense, _ = _aabb_callables(_vector_of(points))
        n = points.shape[0]
        stored = max(width, 1)  # XLA may hand out no buffer for empty outputs

        def call(points, side, slot):
            return tuple(dense(points, side, query.cutoff, _bits(axes),
                               int(query.mask_self), int(self.sort),
                               self.policy.drift_fraction, self.cluster_size,
                               slot,
                               output_dims={"rows": (n, stored), "count": (n,)}))

        if slot is not None:
            rows, count = call(points, side, slot)
        else:
            rows, count = _sequential_vmap(call)(points, side)
        return rows[:, :width], count

    def _sparse(self, points, side, query: Query, axes, capacity: int,
                lower_only: bool, slot=None):
        """Edges int32 ``(2, capacity)``, counts int32 ``(N,)``, int32 total."""
        _, sparse = _aabb_callables(_vector_of(points))
        n = points.shape[0]
        stored = max(capacity, 1)

        def call(points, side, slot):
            return tuple(sparse(points, side, query.cutoff, _bits(axes),
                                int(query.mask_self), int(lower_only),
                                int(self.sort), self.policy.drift_fraction,
                                self.cluster_size, slot,
                                output_dims={"pairs": (2, stored), "count": (n,),
                                             "offset": (n,), "total": (1,)}))

        if slot is not None:
            pairs, count, _, total = call(points, side, slot)
        else:
            pairs, count, _, total = _sequential_vmap(call)(points, side)
        return pairs[:, :capacity], count, total[..., 0]

    def measure(self, position, geometry: Geometry, query: Query,
                metric_sq: MetricSq) -> dict[str, int]:
        """Exact ``row`` and ``edges`` at ``position`` (eager).

        Raises ValueError when the cutoff is not below half a periodic side.
        """
        del metric_sq  # distances use jax-md's arithmetic in the kernel
        points, side, axes, _ = _points(jnp.asarray(position), geometry, query)
        aabb.check_cutoff(query.cutoff, np.asarray(side)[0], axes)
        _, count, _ = self._sparse(points, side, query, axes, 0, False, slot=-1)
        sizes = {"row": int(np.max(np.asarray(count), initial=0)),
                 "edges": int(np.sum(np.asarray(count)))}
        if query.format is OrderedSparse:
            _, _, total = self._sparse(points, side, query, axes, 0, True, slot=-1)
            sizes["edges"] = int(total)
        return sizes

    def search(self, position, geometry: Geometry, query: Query,
               capacity: Capacity, metric_sq: MetricSq) -> SearchResult:
        """Neighbour list of ``position`` (float ``(N, dim)``) in
        ``query.format``; jit/scan/vmap-able."""
        del metric_sq
        points, side, axes, too_large = _points(position, geometry, query)
        width = capacity.neighbors
        if query.format is Dense:
            rows, count = self._dense(points, side, query, axes, width)
            occupancy = jnp.max(count, initial=0, axis=-1)
            return SearchResult(rows, occupancy, (occupancy > width) | too_large)
        pairs, _, total = self._sparse(points, side, query, axes, width,
                                       query.format is OrderedSparse)
        return SearchResult(pairs, total, (total > width) | too_large)


class MethodBackend:
    """Any `RTMethod` as a backend: Dense rows from ``method.find`` (no
    state kept), other layouts by `jaxrt.backends.format_dense_rows`.

    Attributes:
      name: the ``backend=`` name.
      method: the wrapped `RTMethod`.
    """

    max_list_entries = MAX_LIST_ENTRIES

    def __init__(self, method: RTMethod, name: str):
        self.method = method
        self.name = name

    def _rows(self, points, side, query: Query, axes, width: int):
        """Dense rows int32 ``(N, width)`` (padded with N) and counts ``(N,)``."""
        find = _method_callable(self.method, _vector_of(points))
        n = points.shape[0]
        stored = max(width, 1)

        def call(points, side, slot):
            del slot  # nothing is kept between calls
            rows = jnp.full(points.shape[:-2] + (n, stored), n, jnp.int32)
            return tuple(find(points, side, query.cutoff, _bits(axes),
                              int(query.mask_self), rows,
                              output_dims={"count": (n,)}))

        rows, count = _sequential_vmap(call)(points, side)
        return rows[:, :width], count

    def measure(self, position, geometry: Geometry, query: Query,
                metric_sq: MetricSq) -> dict[str, int]:
        del metric_sq
        points, side, axes, _ = _points(jnp.asarray(position), geometry, query)
        aabb.check_cutoff(query.cutoff, np.asarray(side)[0], axes)
        _, count = self._rows(points, side, query, axes, 0)
        count = np.asarray(count)
        row = int(np.max(count, initial=0))
        edges = int(np.sum(count))
        if query.format is OrderedSparse:
            rows, _ = self._rows(points, side, query, axes, row)
            rows = np.asarray(rows)
            edges = int(np.sum(rows < np.arange(rows.shape[0])[:, None]))
        return {"row": row, "edges": edges}

    def search(self, position, geometry: Geometry, query: Query,
               capacity: Capacity, metric_sq: MetricSq) -> SearchResult:
        del metric_sq
        points, side, axes, too_large = _points(position, geometry, query)
        width = capacity.neighbors if query.format is Dense else capacity["row"]
        rows, count = self._rows(points, side, query, axes, width)
        result = backends.format_dense_rows(rows, count, query, capacity)
        return result._replace(overflow=result.overflow | too_large)


def method_backend(method: RTMethod, name: str | None = None) -> MethodBackend:
    """``method`` as a jaxrt backend, e.g.
    ``backends.register("spheres", lambda: method_backend(SpheresMethod()))``."""
    return MethodBackend(method, method.name if name is None else name)
