"""JAX bindings of the ray-traced methods: the only module that touches
Warp's JAX interop (``wp.jax_callable``, XLA FFI; CPU and CUDA).

Two ways in:

* `Bvh` (``backend="bvh"``; ``"bvh-unsorted"`` is ``Bvh(sort=False)``): the
  custom AABB method of `jaxrt.backends.rt.aabb` with a BVH kept across calls
  (refit or rebuilt, see `jaxrt.backends.rt.policy`), Dense rows
  written directly and Sparse / OrderedSparse edges by count, scan and
  fill.
* `Spheres`, `Squares`, and `method_backend` for any other
  `jaxrt.backends.rt.method.RTMethod`: a backend through Dense rows and
  `jaxrt.backends.format_dense_rows`.

* `FusedEnergy`: seed 001's fused mode (`jaxrt.backends.rt.seed_energy`), the LJ
  energy summed during the traversal of the custom AABB, spheres or
  squares method, no list.
* `orcs_forces`, `orcs_perse`: the list-free ORCS kernels of
  `jaxrt.backends.rt.orcs` (used by `jaxrt.energy.listfree.lj`), on trees kept per call
  site exactly as `Bvh`'s (same slots, `TreeOwner` and policy).

The backends are frozen options; ``bind`` (called by `jaxrt.neighbor_list`)
returns the searcher of one list factory, which owns that factory's BVHs.

How the Warp calls behave under JAX:

* ``jit``, ``lax.scan``, ``fori_loop``, ``lax.cond``: the calls are XLA
  custom calls, declared free of side effects: a call's outputs depend on
  its inputs alone (the kept tree only makes it faster, see Persistence),
  so XLA may drop a call whose outputs are unused or hoist one whose
  inputs do not change in a loop, and no two calls merge (each carries its
  own call id). Declared with side effects (as they were), the calls made
  every program that holds one effectful, and JAX dispatches effectful
  programs through Python, not its C++ fast path: a fixed cost per call
  on the host, on top of the callback's own.
* Persistence: every traced call site gets its own *slot*, and each slot
  keeps one `jaxrt.backends.rt.aabb.AabbSearch`. A compiled loop body calls the
  same slot every step, so its BVH is refit or rebuilt in place. Slots
  belong to the `TreeOwner` of the list factory whose trace made them and
  are freed with it (so as many lists as the caller keeps alive keep their
  trees; nothing is evicted behind their back). Lists never depend on the
  kept state being right for them: every call refits or rebuilds to the
  positions it is given.
* ``vmap``: `jax.custom_batching.custom_vmap` runs the systems one after
  the other, each through its own call site (own slot, own BVH), so no
  system sees another's particles. Beyond `MAX_UNROLLED_SYSTEMS` systems
  one call site is looped with ``lax.map`` (one BVH, rebuilt per system).
* Graph capture is off (``graph_mode=NONE``): the drift policy's decision
  reads one flag back to the host, and building a new ``wp.Bvh`` inside a
  CUDA graph crashed.
* float64 positions (``jax_enable_x64``) run the float64 kernels: exact
  float64 distance test on a padded float32 BVH.

Distances are computed in the kernels in Cartesian coordinates with jax-md's
own arithmetic (``periodic_displacement`` then ``square_distance``); the
caller's ``metric_sq`` is not called.

One module past 800 lines on purpose: the one module that wraps Warp
for JAX.
"""
import collections
import dataclasses
import itertools
import weakref
from typing import Callable, ClassVar

import jax
import jax.numpy as jnp
import numpy as np
import warp as wp
from jax_md.partition import NeighborListFormat

from jaxrt.backends import contract as _backend
from jaxrt.backends.contract import (Capacity, Geometry, MetricSq, Query,
                                     SearchResult)
from jaxrt.backends.rt import aabb
from jaxrt.backends.rt import delaunay_engine
from jaxrt.backends.rt import delaunay_kernels
from jaxrt.backends.rt import orcs
from jaxrt.backends.rt import periodic as gamma
from jaxrt.backends.rt import seed_energy
from jaxrt.backends.rt import policy as _policy
from jaxrt.backends.rt.method import RTMethod
from jaxrt.backends.rt.spheres import SpheresMethod
from jaxrt.backends.rt.squares import SquaresMethod

# vmap over more systems than this loops one call site instead of unrolling.
MAX_UNROLLED_SYSTEMS = 16
# Warp kernels compute byte offsets in 32-bit ints (warp/native/array.h):
# an int32 output of 2**29 entries or more would wrap (seen as an illegal
# address on the GPU at N = 8.4e6, k = 288).
MAX_LIST_ENTRIES = 2 ** 29 - 1

Dense = NeighborListFormat.Dense
OrderedSparse = NeighborListFormat.OrderedSparse

_VECTORS = {np.dtype(np.float32): wp.vec3f, np.dtype(np.float64): wp.vec3d}

# ---------------------------------------------------------------------------
# Persistent state (touched only inside FFI callbacks, which Warp serialises,
# and by TreeOwner at trace time).


@dataclasses.dataclass
class _Slot:
    """One traced call site: the options its tree is built with, whether
    the tree is kept between calls, and the tree once a call has built it."""

    options: "Bvh"
    keep: bool = True
    tree: "aabb.AabbSearch | None" = None
    history: "list | None" = None


_SLOTS: dict[int, _Slot] = {}
_SLOT_IDS = itertools.count()
# What the kept trees did, for tests and benchmarks: {"build": .., ...},
# and why they built or rebuilt (`jaxrt.backends.rt.policy.REASONS`).
update_counts: collections.Counter = collections.Counter()
rebuild_reasons: collections.Counter = collections.Counter()


def _release(slots: list[int]) -> None:
    for slot in slots:
        _SLOTS.pop(slot, None)
    slots.clear()


class TreeOwner:
    """The BVHs of one list factory: one slot per traced call site (and
    per system under ``vmap``), freed when the factory is garbage
    collected. JAX's caches of compiled programs hold the factory (through
    the programs' static arguments), so its trees live exactly as long as a
    program that may call them.

    Attributes:
      options: the `Bvh` its trees are built with.
      keep: keep each slot's tree between calls (False: every call builds
        a fresh tree, as ``allocate``'s measurements do).
      slots: the slot ids it owns.
    """

    def __init__(self, options: "Bvh", *, keep: bool = True):
        self.options = options
        self.keep = keep
        self.slots: list[int] = []
        self.history: list | None = None
        # Not at interpreter exit: programs dispatched before may still run.
        weakref.finalize(self, _release, self.slots).atexit = False

    def new_slot(self) -> int:
        slot = next(_SLOT_IDS)
        _SLOTS[slot] = _Slot(self.options, self.keep, history=self.history)
        self.slots.append(slot)
        return slot

    def keep_history(self) -> list:
        """From now on, every tree of this owner appends ``(action, reason,
        t_action, t_query)`` per call to the returned list
        (`jaxrt.backends.rt.aabb.AabbSearch.history`); for benchmarks."""
        self.history = []
        for s in self.slots:
            if s in _SLOTS:
                _SLOTS[s].history = self.history
                if _SLOTS[s].tree is not None:
                    _SLOTS[s].tree.history = self.history
        return self.history

    def release(self) -> None:
        """Free the slots now (their calls must have completed)."""
        _release(self.slots)

    def trees(self) -> "list[aabb.AabbSearch]":
        """The trees kept so far (for tests and benchmarks)."""
        return [_SLOTS[s].tree for s in self.slots
                if s in _SLOTS and _SLOTS[s].tree is not None]


def owner_of(neighbor_fns) -> TreeOwner:
    """The `TreeOwner` of a ``jaxrt.neighbor_list(..., backend="bvh")``
    factory (its trees, their history); for tests and benchmarks."""
    searcher = getattr(getattr(neighbor_fns.allocate, "__self__", None),
                       "searcher", None)
    owner = getattr(searcher, "owner", None)
    if not isinstance(owner, TreeOwner):
        raise TypeError("neighbor_fns is not a jaxrt.neighbor_list factory "
                        "with a BVH backend.")
    return owner


def forget_trees() -> None:
    """Drop every kept BVH (frees their memory; the next calls rebuild)."""
    for record in _SLOTS.values():
        record.tree = None


def _tree(slot: int, n: int, vector, device) -> aabb.AabbSearch:
    """The BVH kept for ``slot``, (re)made for these particles if needed."""
    record = _SLOTS.get(slot)
    if record is None:
        raise RuntimeError(
            f"BVH slot {slot} was freed with the neighbour-list factory that "
            "owned it, yet a program still calls it; keep the factory (the "
            "object jaxrt.neighbor_list returned) alive while its lists run.")
    tree = record.tree
    if (tree is None or tree.n != n or tree.vector is not vector
            or tree.device != wp.get_device(device)):
        tree = record.options.search_structure(n, vector, device)
        tree.history = record.history
        if record.keep:
            record.tree = tree
    return tree


def _axes(bits) -> tuple[bool, bool, bool]:
    """Periodic flags from the static int (a ``wp.int32`` in callbacks)."""
    return tuple(bool(int(bits) >> a & 1) for a in range(3))


def _bits(periodic) -> int:
    return sum(1 << a for a, p in enumerate(periodic) if p)


# ---------------------------------------------------------------------------
# The Warp functions given to jax_callable, one set per position type.

_CALLABLES: dict = {}


def _fit(slot, points, side, cutoff, periodic, reach, has_radii
         ) -> aabb.AabbSearch:
    """The slot's tree, refit or rebuilt to ``points`` (inside a callback)."""
    tree = _tree(int(slot), points.shape[0], points.dtype, points.device)
    action = tree.update(points, side, _axes(periodic), float(cutoff),
                         reach if int(has_radii) else None)
    update_counts[action] += 1
    if action != "refit":
        rebuild_reasons[tree.last_reason] += 1
    return tree


def _aabb_callables(vector):
    """(dense, sparse) jax callables for positions of type ``vector``."""
    if vector in _CALLABLES:
        return _CALLABLES[vector]
    scalar = aabb.scalar_type(vector)
    fit = _fit

    def dense(points: wp.array(dtype=vector), side: wp.array(dtype=vector),
              reach: wp.array(dtype=scalar), cutoff: wp.float64,
              periodic: wp.int32, mask_self: wp.int32, has_radii: wp.int32,
              slot: wp.int32, rows: wp.array2d(dtype=wp.int32),
              count: wp.array(dtype=wp.int32)):
        tree = fit(slot, points, side, cutoff, periodic, reach, has_radii)
        tree.query_dense(side, mask_self=bool(mask_self), rows=rows, count=count)

    def sparse(points: wp.array(dtype=vector), side: wp.array(dtype=vector),
               reach: wp.array(dtype=scalar), cutoff: wp.float64,
               periodic: wp.int32, mask_self: wp.int32, has_radii: wp.int32,
               lower_only: wp.int32, slot: wp.int32,
               pairs: wp.array2d(dtype=wp.int32),
               count: wp.array(dtype=wp.int32), offset: wp.array(dtype=wp.int32),
               total: wp.array(dtype=wp.int32)):
        tree = fit(slot, points, side, cutoff, periodic, reach, has_radii)
        tree.query_sparse(side, mask_self=bool(mask_self),
                          lower_only=bool(lower_only), pairs=pairs, count=count,
                          offset=offset, total=total)

    # jax_callable loads the module named by __module__ before each call: name
    # the kernels' module, so no kernel-less module is compiled for nothing.
    dense.__module__ = sparse.__module__ = aabb.__name__
    options = dict(graph_mode=wp.JaxCallableGraphMode.NONE, vmap_method=None)
    _CALLABLES[vector] = (wp.jax_callable(dense, num_outputs=2, **options),
                          wp.jax_callable(sparse, num_outputs=4, **options))
    return _CALLABLES[vector]


_ORCS_CALLABLES: dict = {}


def _orcs_callables(vector):
    """(forces, perse) jax callables of `jaxrt.backends.rt.orcs` for positions of
    type ``vector``; the tree is the slot's, kept and refit or rebuilt as
    the list backend's (`Bvh`'s policy)."""
    if vector in _ORCS_CALLABLES:
        return _ORCS_CALLABLES[vector]
    scalar = aabb.scalar_type(vector)

    def forces(points: wp.array(dtype=vector), side: wp.array(dtype=vector),
               reach: wp.array(dtype=scalar), params: wp.array(dtype=scalar),
               cutoff: wp.float64, periodic: wp.int32, has_radii: wp.int32,
               slot: wp.int32, forces: wp.array(dtype=vector),
               energy: wp.array(dtype=scalar), d_sigma: wp.array(dtype=scalar),
               d_epsilon: wp.array(dtype=scalar),
               count: wp.array(dtype=wp.int32),
               error: wp.array(dtype=wp.int32)):
        tree = _fit(slot, points, side, cutoff, periodic, reach, has_radii)
        orcs.forces(tree, side, params, radii=reach if int(has_radii) else None,
                    forces=forces, energy=energy, d_sigma=d_sigma,
                    d_epsilon=d_epsilon, count=count, error=error)

    def perse(points: wp.array(dtype=vector), velocities: wp.array(dtype=vector),
              side: wp.array(dtype=vector), params: wp.array(dtype=scalar),
              cutoff: wp.float64, periodic: wp.int32, slot: wp.int32,
              positions_out: wp.array(dtype=vector),
              velocities_out: wp.array(dtype=vector),
              energy: wp.array(dtype=scalar), count: wp.array(dtype=wp.int32),
              error: wp.array(dtype=wp.int32)):
        tree = _fit(slot, points, side, cutoff, periodic, params, 0)
        orcs.perse_step(tree, side, params, velocities=velocities,
                        positions_out=positions_out,
                        velocities_out=velocities_out, energy=energy,
                        count=count, error=error)

    forces.__module__ = perse.__module__ = orcs.__name__  # see _aabb_callables
    options = dict(graph_mode=wp.JaxCallableGraphMode.NONE, vmap_method=None)
    _ORCS_CALLABLES[vector] = (wp.jax_callable(forces, num_outputs=6, **options),
                               wp.jax_callable(perse, num_outputs=5, **options))
    return _ORCS_CALLABLES[vector]


def orcs_forces(owner: TreeOwner, points, side, reach, params, *,
                cutoff: float, periodic, has_radii: bool):
    """ORCS-forces (`jaxrt.backends.rt.orcs.forces`) on the trees of ``owner``.

    Args:
      owner: the `TreeOwner` of the calling energy function.
      points: float ``(N, 3)`` Cartesian positions (float32 or float64).
      side: float ``(1, 3)`` box sides (1 on free axes).
      reach: float ``(N,)`` radii, or ``(1,)`` placeholder.
      params: float ``(orcs.N_PARAMS,)``, `jaxrt.backends.rt.orcs`'s layout.
      cutoff: static, the largest radius (or the cutoff): boxes and gamma
        rays reach this far.
      periodic: 3 static bools.
      has_radii: whether ``reach`` holds radii.
    Returns:
      ``(forces (N, 3), energy (N,), d_sigma (N,), d_epsilon (N,),
      count int32 (N,), error int32 (1,))``, per-particle sums over the
      pairs each particle owns. ``vmap`` runs systems one after the other.
    """
    call_forces, _ = _orcs_callables(_vector_of(points))
    n = points.shape[0]

    def call(points, side, reach, params, slot):
        return tuple(call_forces(
            points, side, reach, params, float(cutoff), _bits(periodic),
            int(has_radii), slot,
            output_dims={"forces": (n, 3), "energy": (n,), "d_sigma": (n,),
                         "d_epsilon": (n,), "count": (n,), "error": (1,)}))

    return _sequential_vmap(call, owner)(points, side, reach, params)


def orcs_perse(owner: TreeOwner, points, velocities, side, params, *,
               cutoff: float, periodic):
    """One ORCS-persé leapfrog step (`jaxrt.backends.rt.orcs.perse_step`).

    Returns ``(positions (N, 3), velocities (N, 3), energy (N,), count
    int32 (N,), error int32 (1,))``: x(t + dt), v(t + dt/2), half the pair
    energies at x(t) per particle, neighbours per particle.
    """
    _, call_perse = _orcs_callables(_vector_of(points))
    n = points.shape[0]

    def call(points, velocities, side, params, slot):
        return tuple(call_perse(
            points, velocities, side, params, float(cutoff), _bits(periodic),
            slot, output_dims={"positions_out": (n, 3),
                               "velocities_out": (n, 3), "energy": (n,),
                               "count": (n,), "error": (1,)}))

    return _sequential_vmap(call, owner)(points, velocities, side, params)


def load_orcs() -> None:
    """Compile the ORCS kernels for JAX's default device now."""
    platform = jax.default_backend()
    orcs.load("cuda" if platform in ("gpu", "cuda") else "cpu")


_METHOD_CALLABLES: dict = {}


def _method_callable(backend: "MethodBackend", vector):
    """jax callable running the method of ``backend`` (hashable options, one
    method object per value: it keeps nothing that changes results) on
    positions of type ``vector``."""
    key = (backend, vector)
    if key in _METHOD_CALLABLES:
        return _METHOD_CALLABLES[key][1]
    method = backend.method()

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


def _sequential_vmap(call: Callable, owner: "TreeOwner | None") -> Callable:
    """``call(*arrays, slot)`` -> tuple of arrays, as a function of the
    arrays (positions, sides, ...) whose ``vmap`` runs one system after the
    other, each through its own call site (own slot of ``owner``; -1
    without one)."""

    @jax.custom_batching.custom_vmap
    def one_system(*arrays):
        return call(*arrays, -1 if owner is None else owner.new_slot())

    @one_system.def_vmap
    def systems(axis_size, in_batched, *arrays):
        arrays = [a if batched else jnp.broadcast_to(a, (axis_size,) + a.shape)
                  for a, batched in zip(arrays, in_batched)]
        if axis_size <= MAX_UNROLLED_SYSTEMS:
            outs = [one_system(*(a[b] for a in arrays))
                    for b in range(axis_size)]
            out = jax.tree.map(lambda *xs: jnp.stack(xs), *outs)
        else:
            out = jax.lax.map(lambda xs: one_system(*xs), tuple(arrays))
        return out, jax.tree.map(lambda _: True, out)

    return one_system


@dataclasses.dataclass(frozen=True)
class Bvh:
    """Options of the custom AABB BVH backend (`jaxrt.backends.rt.aabb`), kept
    across calls by the list factory that owns it (`TreeOwner`).

    None of the options changes the list, only the speed
    (`benchmarks/rt_neighbors.py` sweeps them).

    Attributes:
      sort: Morton-sort particles at each build (the seed's sorted AABB).
      cluster_size: particles per BVH box (`jaxrt.backends.rt.aabb.AabbSearch`); 1 is
        the seed's box per particle.
      leaf_size: boxes per BVH leaf.
      builder: Warp's BVH constructor (``"lbvh"``, ``"sah"``, ``"median"``;
        ``"cubql"`` on CUDA), or None for Warp's choice per device.
      policy: when to rebuild rather than refit: ``"drift"`` (once a
        particle drifted ``drift_fraction`` cutoffs), ``"rebuild"``,
        ``"refit"`` (never), ``"fixed"``, ``"avg"``, ``"gradient"``, or a
        value of `jaxrt.backends.rt.policy` (e.g. ``policy.Fixed(k=50)``);
        each tree keeps its own policy state. Every refit is exact: only
        the policy rebuilds a tree.
      drift_fraction: in cutoffs, below 0.25: the drift policy's bound, and
        how far outside a periodic box a refit leaves a particle (beyond,
        it wraps it, which slows the queries of that tree).
    """

    sort: bool = True
    cluster_size: int = 1
    leaf_size: int = 1
    builder: "str | None" = None
    policy: object = "drift"
    drift_fraction: float = 0.2

    max_list_entries: ClassVar[int] = MAX_LIST_ENTRIES
    supports_radii: ClassVar[bool] = True

    def __post_init__(self):
        if not isinstance(self.sort, bool):
            raise TypeError(f"Bvh(sort={self.sort!r}): must be a bool.")
        for name in ("cluster_size", "leaf_size"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"Bvh({name}={value!r}): must be an int >= 1.")
        if self.builder not in (None,) + aabb.BUILDERS:
            raise ValueError(f"Bvh(builder={self.builder!r}): choose one of "
                             f"{aabb.BUILDERS}, or None for Warp's default.")
        object.__setattr__(self, "policy", _policy.resolve(self.policy))
        object.__setattr__(self, "drift_fraction",
                           aabb.check_drift_fraction(self.drift_fraction))

    @property
    def name(self) -> str:
        return "bvh" if self.sort else "bvh-unsorted"

    def search_structure(self, n: int, vector, device) -> aabb.AabbSearch:
        """A fresh `jaxrt.backends.rt.aabb.AabbSearch` with these options."""
        return aabb.AabbSearch(n, vector, device, sort=self.sort,
                               policy=self.policy,
                               drift_fraction=self.drift_fraction,
                               constructor=self.builder,
                               leaf_size=self.leaf_size,
                               cluster_size=self.cluster_size)

    def bind(self) -> "BvhSearch":
        _load_kernels()
        return BvhSearch(self, TreeOwner(self))

    # A Bvh used without bind (not through jaxrt.neighbor_list) searches
    # with trees of its own call; the front always binds.
    def measure(self, position, geometry, query, metric_sq):
        return self.bind().measure(position, geometry, query, metric_sq)

    def search(self, position, geometry, query, capacity, metric_sq):
        return self.bind().search(position, geometry, query, capacity,
                                  metric_sq)


def _reach(points, geometry: Geometry):
    """(float ``(N,)`` per-particle radii in the positions' dtype, or one
    placeholder, and 1 or 0: whether they are radii)."""
    if geometry.reach is None:
        return jnp.zeros((1,), points.dtype), 0
    return jax.lax.stop_gradient(geometry.reach.astype(points.dtype)), 1


class BvhSearch:
    """The `Bvh` searcher of one list factory: its options and the
    `TreeOwner` of its trees."""

    max_list_entries = MAX_LIST_ENTRIES
    supports_radii = True
    # Sparse layouts are counted, scanned and filled: no Dense rows first.
    sparse_without_rows = True
    # Each traced call site owns its tree (`TreeOwner`): allocate's build
    # must be the program that later builds and refits, at its sizes.
    build_at_exact_capacity = True

    def __init__(self, options: Bvh, owner: TreeOwner):
        self.options = options
        self.owner = owner

    @property
    def name(self) -> str:
        return self.options.name

    def _dense(self, points, side, reach, query: Query, axes, width: int,
               owner: TreeOwner):
        """Dense rows int32 ``(N, width)`` and exact counts int32 ``(N,)``;
        ``reach``: `_reach`."""
        dense, _ = _aabb_callables(_vector_of(points))
        n = points.shape[0]
        stored = max(width, 1)  # XLA may hand out no buffer for empty outputs
        reach, has_radii = reach

        def call(points, side, reach, slot):
            return tuple(dense(points, side, reach, query.cutoff, _bits(axes),
                               int(query.mask_self), has_radii, slot,
                               output_dims={"rows": (n, stored), "count": (n,)}))

        rows, count = _sequential_vmap(call, owner)(points, side, reach)
        return rows[:, :width], count

    def _sparse(self, points, side, reach, query: Query, axes, capacity: int,
                lower_only: bool, owner: TreeOwner):
        """Edges int32 ``(2, capacity)``, counts int32 ``(N,)``, int32 total;
        ``reach``: `_reach`."""
        _, sparse = _aabb_callables(_vector_of(points))
        n = points.shape[0]
        stored = max(capacity, 1)
        reach, has_radii = reach

        def call(points, side, reach, slot):
            return tuple(sparse(points, side, reach, query.cutoff, _bits(axes),
                                int(query.mask_self), has_radii,
                                int(lower_only), slot,
                                output_dims={"pairs": (2, stored), "count": (n,),
                                             "offset": (n,), "total": (1,)}))

        pairs, count, _, total = _sequential_vmap(call, owner)(points, side,
                                                               reach)
        return pairs[:, :capacity], count, total[..., 0]

    def measure(self, position, geometry: Geometry, query: Query,
                metric_sq: MetricSq) -> dict[str, int]:
        """Exact ``row`` and ``edges`` at ``position`` (eager, on trees of
        its own that are freed on return).

        Raises ValueError when the cutoff is not below half a periodic side.
        """
        del metric_sq  # distances use jax-md's arithmetic in the kernel
        points, side, axes, _ = _points(jnp.asarray(position), geometry, query)
        aabb.check_cutoff(query.cutoff, np.asarray(side)[0], axes)
        reach = _reach(points, geometry)
        scratch = TreeOwner(self.options, keep=False)
        try:
            _, count, _ = self._sparse(points, side, reach, query, axes, 0,
                                       False, scratch)
            sizes = {"row": int(np.max(np.asarray(count), initial=0)),
                     "edges": int(np.sum(np.asarray(count), dtype=np.int64))}
            if query.format is OrderedSparse:
                _, lower, _ = self._sparse(points, side, reach, query, axes, 0,
                                           True, scratch)
                # Summed in int64: the kernels' int32 total wraps past 2**31.
                sizes["edges"] = int(np.sum(np.asarray(lower), dtype=np.int64))
        finally:
            scratch.release()
        return sizes

    def search(self, position, geometry: Geometry, query: Query,
               capacity: Capacity, metric_sq: MetricSq) -> SearchResult:
        """Neighbour list of ``position`` (float ``(N, dim)``) in
        ``query.format``; jit/scan/vmap-able."""
        del metric_sq
        points, side, axes, too_large = _points(position, geometry, query)
        reach = _reach(points, geometry)
        width = capacity.neighbors
        if query.format is Dense:
            rows, count = self._dense(points, side, reach, query, axes, width,
                                      self.owner)
            occupancy = jnp.max(count, initial=0, axis=-1)
            return SearchResult(rows, occupancy, (occupancy > width) | too_large)
        pairs, _, total = self._sparse(points, side, reach, query, axes, width,
                                       query.format is OrderedSparse,
                                       self.owner)
        # A total past 2**31 edges wraps negative.
        return SearchResult(pairs, total, (total > width) | (total < 0)
                            | too_large)


class MethodBackend:
    """Any `RTMethod` as a backend: Dense rows from ``method.find`` (no
    state kept), other layouts by `jaxrt.backends.format_dense_rows`.

    Subclasses are frozen dataclasses of the method's options with a
    ``name`` and a ``method()`` that makes the `RTMethod`.
    """

    max_list_entries: ClassVar[int] = MAX_LIST_ENTRIES
    name: ClassVar[str]

    def method(self) -> RTMethod:
        raise NotImplementedError

    def _rows(self, points, side, query: Query, axes, width: int):
        """Dense rows int32 ``(N, width)`` (padded with N) and counts ``(N,)``."""
        find = _method_callable(self, _vector_of(points))
        n = points.shape[0]
        stored = max(width, 1)

        def call(points, side, slot):
            del slot  # nothing is kept between calls
            rows = jnp.full(points.shape[:-2] + (n, stored), n, jnp.int32)
            return tuple(find(points, side, query.cutoff, _bits(axes),
                              int(query.mask_self), rows,
                              output_dims={"count": (n,)}))

        rows, count = _sequential_vmap(call, None)(points, side)
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
        result = _backend.format_dense_rows(rows, count, query, capacity)
        return result._replace(overflow=result.overflow | too_large)


@dataclasses.dataclass(frozen=True)
class Spheres(MethodBackend):
    """Seed 001 §4.2's spheres (`jaxrt.backends.rt.spheres`) as a backend.

    Attributes:
      check_separation: raise when two particles are closer than the
        method's resolution (`jaxrt.backends.rt.spheres.SpheresMethod`).
      epsilon_relative: the method's ε as a fraction of the data's scale
        (default 2**-40; `jaxrt.backends.rt.epsilon`).
    """

    check_separation: bool = True
    epsilon_relative: float = 2.0 ** -40
    name: ClassVar[str] = "spheres"

    def __post_init__(self):
        self.method()  # the method's checks, at construction

    def method(self) -> RTMethod:
        return SpheresMethod(check_separation=self.check_separation,
                             epsilon_relative=self.epsilon_relative)


@dataclasses.dataclass(frozen=True)
class Squares(MethodBackend):
    """Seed 001 §4.3's double squares (`jaxrt.backends.rt.squares`) as a backend."""

    name: ClassVar[str] = "squares"

    def method(self) -> RTMethod:
        return SquaresMethod()


@dataclasses.dataclass(frozen=True)
class _Wrapped(MethodBackend):
    """An `RTMethod` object as a backend (`method_backend`); equal and
    hashed by the object's identity, as RTMethods define no ``__eq__``."""

    wrapped: RTMethod
    name: str  # type: ignore[misc]

    def method(self) -> RTMethod:
        return self.wrapped


def method_backend(method: RTMethod, name: str | None = None) -> MethodBackend:
    """``method`` (an `RTMethod` object) as a jaxrt backend, to pass as
    ``backend=``."""
    return _Wrapped(method, method.name if name is None else name)


# ---------------------------------------------------------------------------
# Seed 001's fused (list-free) mode.

_FUSED_CALLABLES: dict = {}


def _fused_callable(options, vector):
    """jax callable of the fused energy (`jaxrt.backends.rt.seed_energy`) of
    ``options`` (`Bvh`, `Spheres` or `Squares`) for positions of type
    ``vector``. The custom AABB keeps its tree in a slot (refit or rebuilt
    as `Bvh`'s lists); spheres and squares build a scene per call, as their
    lists do."""
    key = (options, vector)
    if key in _FUSED_CALLABLES:
        return _FUSED_CALLABLES[key][1]
    scalar = aabb.scalar_type(vector)
    if isinstance(options, Bvh):
        method = None

        def fused(points: wp.array(dtype=vector), side: wp.array(dtype=vector),
                  params: wp.array(dtype=scalar), cutoff: wp.float64,
                  periodic: wp.int32, slot: wp.int32,
                  energy: wp.array(dtype=scalar), count: wp.array(dtype=wp.int32)):
            tree = _fit(slot, points, side, cutoff, periodic, params, 0)
            tree.energy(side, params, energy=energy, count=count)

        fused.__module__ = aabb.__name__  # see _aabb_callables
    else:
        method = options.method()

        def fused(points: wp.array(dtype=vector), side: wp.array(dtype=vector),
                  params: wp.array(dtype=scalar), cutoff: wp.float64,
                  periodic: wp.int32, slot: wp.int32,
                  energy: wp.array(dtype=scalar), count: wp.array(dtype=wp.int32)):
            del slot  # nothing is kept between calls
            axes = _axes(periodic)
            box = tuple(float(s) for s in side.numpy()[0]) if any(axes) else None
            method.energy(points, cutoff=float(cutoff), side=box, periodic=axes,
                          params=params, out_energy=energy, out_count=count)

        fused.__module__ = type(method).__module__
    # No side effect, as the lists' calls (module docstring).
    callable_ = wp.jax_callable(fused, num_outputs=2,
                                graph_mode=wp.JaxCallableGraphMode.NONE,
                                vmap_method=None)
    _FUSED_CALLABLES[key] = (method, callable_)
    return callable_


_FUSED_NAMES = {"aabb": lambda: Bvh(), "bvh": lambda: Bvh(),
                "aabb-unsorted": lambda: Bvh(sort=False),
                "bvh-unsorted": lambda: Bvh(sort=False),
                "spheres": lambda: Spheres(), "squares": lambda: Squares()}


class FusedEnergy:
    """Seed 001's fused mode as a JAX function: each particle's LJ energy
    summed during the traversal of a ray-traced method (Algis & Bramas 2024,
    §4.2-4.4 and §5; `jaxrt.backends.rt.seed_energy` defines the quantity), with no
    neighbour list::

        energy, count = FusedEnergy("aabb", cutoff=C, sigma=C / 2)(R)

    ``energy`` (positions' dtype, ``(N,)``) is ``E_i = sum_j U(r_ij)`` over
    the ``j != i`` with ``|r_ij| < cutoff`` (each pair in both rows, as the
    seed's per-ray sums; ``U`` clamped below ``r_min``); ``count`` (int32,
    ``(N,)``) the number of such ``j``, the method's Dense row count; the
    number of interacting pairs is ``count.sum()`` (ordered; half that
    unordered; sum it in int64 past 2**31).

    jit, scan and vmap work as for the lists (`jaxrt.backends.rt.ffi`'s docstring);
    the custom AABB keeps one tree per traced call site (owned by this
    object) and refits or rebuilds it as the ``"bvh"`` lists do. No
    gradient: the call is an FFI custom call without a JVP (use a list and
    `jaxrt.energy` for forces). The spheres method raises
    `jaxrt.backends.rt.epsilon.ParticlesTooCloseError` as its lists do (two
    particles closer than its resolution may be missing from the energy);
    the other two count coincident particles (clamped energy).

    Args:
      method: ``"aabb"`` (= ``"bvh"``, Morton-sorted), ``"aabb-unsorted"``
        (= ``"bvh-unsorted"``), ``"spheres"``, ``"squares"``, or a `Bvh`
        (``cluster_size=1``), `Spheres` or `Squares` options value.
      cutoff: C > 0; below half the side on periodic axes.
      box: None (free space), or the box side (scalar or one per axis),
        needed on periodic axes.
      periodic: bool, or one bool per axis.
      sigma, epsilon, r_min: the pair's parameters
        (`jaxrt.backends.rt.seed_energy.lj_params`; ``r_min`` defaults to
        ``sigma / 10``).
    Raises:
      ValueError, TypeError: a bad argument, named in the message.
    """

    def __init__(self, method="aabb", *, cutoff: float, box=None,
                 periodic=False, sigma: float, epsilon: float = 1.0,
                 r_min: float | None = None):
        if isinstance(method, str):
            if method not in _FUSED_NAMES:
                raise ValueError(f"FusedEnergy(method={method!r}): choose one of "
                                 f"{sorted(_FUSED_NAMES)}, or pass a Bvh, "
                                 "Spheres or Squares options value.")
            method = _FUSED_NAMES[method]()
        if not isinstance(method, (Bvh, Spheres, Squares)):
            raise TypeError(f"FusedEnergy(method={method!r}): the fused mode "
                            "exists for the seed's three methods: Bvh, Spheres, "
                            "Squares (or their names).")
        if isinstance(method, Bvh) and method.cluster_size != 1:
            raise ValueError("FusedEnergy: the seed's custom AABB has one box per "
                             f"particle; use Bvh(cluster_size=1) (got "
                             f"{method.cluster_size}).")
        self.options = method
        self.cutoff = float(cutoff)
        if not (np.isfinite(self.cutoff) and self.cutoff > 0):
            raise ValueError(f"FusedEnergy(cutoff={cutoff!r}): must be finite and > 0.")
        self.periodic = periodic
        self.box = box
        # Checked now, in the positions' precision later.
        seed_energy.lj_params(sigma=sigma, epsilon=epsilon, r_min=r_min)
        self.lj = dict(sigma=sigma, epsilon=epsilon, r_min=r_min)
        self.owner = TreeOwner(method) if isinstance(method, Bvh) else None
        if isinstance(method, Bvh):
            _load_kernels()

    @property
    def name(self) -> str:
        base = {"bvh": "aabb", "bvh-unsorted": "aabb-unsorted"}.get(
            self.options.name, self.options.name)
        return base + "-fused"

    def _geometry(self, dim: int, dtype):
        """float ``(1, 3)`` sides (1 on free and padded axes), 3 periodic flags."""
        periodic = self.periodic
        if isinstance(periodic, (bool, np.bool_)):
            periodic = (bool(periodic),) * dim
        periodic = tuple(bool(p) for p in periodic)
        if len(periodic) != dim:
            raise ValueError(f"FusedEnergy(periodic={self.periodic!r}): need one "
                             f"bool per axis of the (N, {dim}) positions.")
        if self.box is None:
            if any(periodic):
                raise ValueError("FusedEnergy: periodic axes need box= (the side).")
            side = np.ones(dim)
        else:
            side = np.broadcast_to(np.asarray(self.box, float), (dim,))
        axes = periodic + (False,) * (3 - dim)
        side3 = np.concatenate([side, np.ones(3 - dim)])
        side3 = np.where(axes, side3, 1.0)
        aabb.check_cutoff(self.cutoff, side3, axes)
        return jnp.asarray(side3[None, :], dtype), axes

    def __call__(self, position):
        """``(energy (N,), count int32 (N,))`` at ``position``: float32 or
        float64 ``(N, dim)`` Cartesian, dim 1..3 (unwrapped positions are
        wrapped on periodic axes)."""
        position = jnp.asarray(position)
        if position.ndim != 2 or position.shape[1] not in (1, 2, 3):
            raise ValueError("FusedEnergy: position must be (N, dim) with dim in "
                             f"1..3; got shape {position.shape}.")
        vector = _vector_of(position)
        dtype = position.dtype
        n, dim = position.shape
        side, axes = self._geometry(dim, dtype)
        points = jax.lax.stop_gradient(
            jnp.pad(position, ((0, 0), (0, 3 - dim))))
        params = jnp.asarray(seed_energy.lj_params(**self.lj, dtype=np.dtype(dtype)))
        call_fused = _fused_callable(self.options, vector)

        def call(points, side, params, slot):
            return tuple(call_fused(points, side, params, self.cutoff,
                                    _bits(axes), slot,
                                    output_dims={"energy": (n,), "count": (n,)}))

        return _sequential_vmap(call, self.owner)(points, side, params)


# ---------------------------------------------------------------------------
# Seed 004's Delaunay engine on Warp (`jaxrt.backends.delaunay`,
# ``Delaunay(engine="warp")``): maintenance and BFS in one call.

_DELAUNAY_CALLABLES: dict = {}


def _warp_device() -> str:
    return "cuda" if jax.default_backend() in ("gpu", "cuda") else "cpu"


def _delaunay_callable():
    """The jax callable of one Delaunay step (`delaunay_step`)."""
    if "step" in _DELAUNAY_CALLABLES:
        return _DELAUNAY_CALLABLES["step"]

    def step(target: wp.array(dtype=wp.vec2d), points: wp.array(dtype=wp.vec2d),
             side: wp.array(dtype=wp.float64), cutoff: wp.float64,
             periodic: wp.int32, local_repair: wp.int32,
             max_flip_rounds: wp.int32, max_splits: wp.int32,
             position: wp.array(dtype=wp.vec2d), tri: wp.array2d(dtype=wp.int32),
             twin: wp.array2d(dtype=wp.int32), shift: wp.array2d(dtype=wp.vec2i),
             safe: wp.array(dtype=wp.vec2d), found: wp.array2d(dtype=wp.int32),
             count: wp.array(dtype=wp.int32), stats: wp.array(dtype=wp.int32)):
        torus = bool(periodic)
        L = side.numpy() if torus else None
        m = delaunay_engine.Mesh(position, tri, twin, shift,
                                 L if torus else np.zeros(2), safe.numpy(),
                                 points.shape[0], torus)

        def rebuild(p):
            return delaunay_host(p, L, float(cutoff))

        done = delaunay_engine.step(
            m, target, rebuild, local_repair=bool(local_repair),
            max_flip_rounds=int(max_flip_rounds), max_splits=int(max_splits))
        if done.rebuilt and not torus:
            wp.copy(safe, wp.array(m.safe, dtype=wp.vec2d, device=safe.device))
        dummy = wp.zeros((1, 2), dtype=wp.int32, device=found.device)
        out = delaunay_engine.Search(found, count, dummy,
                                     wp.zeros(1, dtype=wp.int32,
                                              device=found.device))
        delaunay_engine.radius_search(m, float(cutoff), width=found.shape[1],
                                      points=points, out=out)
        numbers = np.array([done.rebuilt, done.failed, done.flips,
                            done.splits], np.int32)
        wp.copy(stats, wp.array(numbers, dtype=wp.int32, device=stats.device))

    step.__module__ = delaunay_kernels.__name__  # see _aabb_callables
    _DELAUNAY_CALLABLES["step"] = wp.jax_callable(
        step, num_outputs=8,
        in_out_argnames=["position", "tri", "twin", "shift", "safe"],
        graph_mode=wp.JaxCallableGraphMode.NONE, vmap_method=None)
    return _DELAUNAY_CALLABLES["step"]


def delaunay_host(points, side, cutoff: float):
    """A triangulation from scratch on the host (Qhull): see
    `jaxrt.backends.delaunay.host_triangulate`."""
    from jaxrt.backends import delaunay
    return delaunay.host_triangulate(points, side, cutoff)


def delaunay_step(target, points, side, state, *, cutoff: float,
                  periodic: bool, width: int, local_repair: bool = True,
                  max_flip_rounds: int = 64, max_splits: int = 64):
    """One step of the Warp Delaunay engine under JAX: move the
    triangulation ``state`` (`jaxrt.backends.delaunay.Triangulation`) to
    ``target`` (float64 ``(V, 2)``, grid coordinates, frame vertices last
    in free space) by local repair (or rebuild it, see
    `jaxrt.backends.rt.delaunay_engine.step`), then search it.

    ``points``: float64 ``(N, 2)``, the positions that decide the pairs
    (jax-md's periodic displacement on a torus); ``side``: float64
    ``(2,)``. Returns ``(position, tri, twin, shift, safe, found, count,
    stats)``: the new triangulation arrays, int32 ``(N, width)`` rows (the
    vertex first, padded with N), int32 ``(N,)`` counts (the vertex
    included; past ``width`` a lower bound) and int32 ``(4,)``: rebuilt,
    failed, flips, splits.
    """
    call = _delaunay_callable()
    n = points.shape[0]
    args = jax.lax.stop_gradient((target, points, side))
    outs = call(*args, float(cutoff), int(periodic), int(local_repair),
                int(max_flip_rounds), int(max_splits), state.position,
                state.tri, state.twin, state.shift, state.safe,
                output_dims={"found": (n, max(width, 1)), "count": (n,),
                             "stats": (4,)})
    return tuple(outs)


def _eager_mesh(position, tri, twin, shift, side, safe, n: int, periodic):
    return delaunay_engine.mesh(np.asarray(position), np.asarray(tri),
                                np.asarray(twin), np.asarray(shift), n=n,
                                side=np.asarray(side) if periodic else None,
                                safe=np.asarray(safe), device=_warp_device())


def delaunay_flip(position, tri, twin, shift, side, *, periodic: bool,
                  max_rounds: int):
    """Eager (at ``allocate``): flip to Delaunay at ``position`` on JAX's
    device. Returns numpy ``(tri, twin, shift)``, flips and done."""
    n = position.shape[0] if periodic else position.shape[0] - 4
    m = _eager_mesh(position, tri, twin, shift, side, np.zeros((2, 2)), n,
                    periodic)
    flips, done = delaunay_engine.flip_to_delaunay(m, max_rounds=max_rounds)
    h = m.numpy()
    return h["tri"], h["twin"], h["shift"], flips, done


def delaunay_counts(points, state, side, *, n: int, periodic: bool,
                    cutoff: float, width: int):
    """Eager (``measure``): numpy BFS rows ``(N, width)`` and counts
    ``(N,)`` of a triangulation as it is."""
    m = _eager_mesh(state.position, state.tri, state.twin, state.shift, side,
                    state.safe, n, periodic)
    pts = wp.array(np.asarray(points, np.float64), dtype=wp.vec2d,
                   device=m.device)
    s = delaunay_engine.radius_search(m, cutoff, width=width, points=pts)
    return s.found.numpy(), s.count.numpy()


# ---------------------------------------------------------------------------
# The list-free LJ sums on a cell grid (`jaxrt.backends.cell.warp_kernels`).

_CELL_LJ_CALLABLES: dict = {}


_GRAPH_MODES = {"none": wp.JaxCallableGraphMode.NONE,
                "jax": wp.JaxCallableGraphMode.JAX,
                "warp": wp.JaxCallableGraphMode.WARP}


def _cell_lj_callable(vector, graph: str, walk: str = "thread",
                      cluster_size: int = 8):
    """The jax callable of `jaxrt.backends.cell.warp_kernels.lj_sums` for
    positions of type ``vector``; ``graph``: who captures its launches in a
    CUDA graph (`_GRAPH_MODES`; nothing in the pipeline reads back to the
    host); ``walk``: "thread", or "cluster" / "native" (`jaxrt.backends.
    cell.warp_cluster.lj_sums`, `jaxrt.backends.cell.warp_cluster_native.
    lj_sums`: three more scratch outputs) of ``cluster_size`` particles."""
    from jaxrt.backends.cell import (warp_cluster, warp_cluster_native,
                                     warp_kernels)
    key = (vector, graph, walk, cluster_size)
    if key in _CELL_LJ_CALLABLES:
        return _CELL_LJ_CALLABLES[key]
    scalar = warp_kernels.scalar_of(vector)

    def sums(points: wp.array(dtype=vector), radii: wp.array(dtype=scalar),
             grid: wp.array(dtype=vector), cells: wp.array(dtype=wp.int32),
             params: wp.array(dtype=scalar), flags: wp.int32,
             forces: wp.array(dtype=vector), energy: wp.array(dtype=scalar),
             d_sigma: wp.array(dtype=scalar),
             d_epsilon: wp.array(dtype=scalar),
             count: wp.array(dtype=wp.int32), keys: wp.array(dtype=wp.int32),
             values: wp.array(dtype=wp.int32),
             wrapped: wp.array(dtype=vector), start: wp.array(dtype=wp.int32),
             position: wp.array(dtype=vector),
             radius: wp.array(dtype=scalar)):
        warp_kernels.lj_sums(points, radii, grid, cells, params, int(flags),
                             forces=forces, energy=energy, d_sigma=d_sigma,
                             d_epsilon=d_epsilon, count=count, keys=keys,
                             values=values, wrapped=wrapped, start=start,
                             position=position, radius=radius)

    def cluster_sums(points: wp.array(dtype=vector),
                     radii: wp.array(dtype=scalar),
                     grid: wp.array(dtype=vector),
                     cells: wp.array(dtype=wp.int32),
                     params: wp.array(dtype=scalar), flags: wp.int32,
                     forces: wp.array(dtype=vector),
                     energy: wp.array(dtype=scalar),
                     d_sigma: wp.array(dtype=scalar),
                     d_epsilon: wp.array(dtype=scalar),
                     count: wp.array(dtype=wp.int32),
                     keys: wp.array(dtype=wp.int32),
                     values: wp.array(dtype=wp.int32),
                     wrapped: wp.array(dtype=vector),
                     start: wp.array(dtype=wp.int32),
                     position: wp.array(dtype=vector),
                     radius: wp.array(dtype=scalar),
                     counts: wp.array(dtype=wp.int32),
                     offsets: wp.array(dtype=wp.int32),
                     clusters: wp.array(dtype=wp.int32)):
        engine = warp_cluster_native if walk == "native" else warp_cluster
        engine.lj_sums(points, radii, grid, cells, params, int(flags),
                       forces=forces, energy=energy, d_sigma=d_sigma,
                       d_epsilon=d_epsilon, count=count, keys=keys,
                       values=values, wrapped=wrapped, start=start,
                       position=position, radius=radius, counts=counts,
                       offsets=offsets, clusters=clusters, size=cluster_size)

    function = sums if walk == "thread" else cluster_sums
    function.__module__ = warp_kernels.__name__  # see _aabb_callables
    mode = _GRAPH_MODES[graph]
    _CELL_LJ_CALLABLES[key] = wp.jax_callable(
        function, num_outputs=11 if walk == "thread" else 14,
        graph_mode=mode, vmap_method="sequential")
    return _CELL_LJ_CALLABLES[key]


# `cell_lj_sums`' walks.
CELL_WALKS = ("thread", "cluster", "native")


def cell_lj_sums(points, radii, grid, cells, params, *, flags: int,
                 table: int, graph: str = "none", walk: str = "thread",
                 cluster_size: int = 8):
    """The per-particle LJ sums of `jaxrt.backends.cell.warp_kernels.lj_sums`
    in one call.

    Args:
      points: float32 or float64 ``(N, 3)`` Cartesian positions.
      radii: ``(N,)`` per-particle cuts, or ``(1,)`` without radii.
      grid: ``(3, 3)`` origin, cell width, side per axis; cells: int32
        ``(6,)``, cells per axis (their product at most ``table``) and the
        stencil's reach per axis.
      params: ``(warp_kernels.N_PARAMS,)``; flags: static int,
        `jaxrt.backends.cell.warp_kernels`' bits.
      table: static, the cell-start table's size less one.
      graph: static, ``"none"`` (the callback runs at every call),
        ``"jax"`` (JAX captures the launches in its graphs: fails inside
        ``lax.scan`` on the H200 measured, "operation not supported"),
        ``"warp"`` (Warp captures them, reused for the same buffers).
      walk: static, ``"thread"`` (a thread per particle) or ``"cluster"``
        (a thread per cluster of a cell's particles,
        `jaxrt.backends.cell.warp_cluster`): the same sums; ``"native"``
        (on CUDA a warp per cluster, its lanes sharing the candidates by
        shuffles; elsewhere ``"cluster"``): the same sums to rounding;
      cluster_size: static, the cluster walk's particles per cluster
        (`jaxrt.backends.cell.warp_cluster.SIZES`).
    Returns:
      ``(forces (N, 3) in the caller's order, energy (N,), d_sigma (N,),
      d_epsilon (N,), count int32 (N,))``: per particle (sorted order for
      all but the forces), each pair in both of its particles' sums.
    """
    from jaxrt.backends.cell import (warp_cluster, warp_cluster_native,
                                     warp_kernels)
    if walk not in CELL_WALKS:
        raise ValueError(f"cell_lj_sums(walk={walk!r}): choose one of "
                         f"{CELL_WALKS}.")
    n = points.shape[0]
    vector = _vector_of(points)
    scalar = warp_kernels.scalar_of(vector)
    device = _warp_device()
    # The walk lives in a module of its own, built for these flags: load
    # it now, not inside the callback (where a graph capture may be open).
    cuda = wp.get_device(device).is_cuda
    if walk == "native" and cuda:
        kernel = warp_cluster_native.native_kernel(scalar, flags,
                                                   size=cluster_size)
        wp.load_module(kernel.module, device=device,
                       block_dim=warp_cluster_native.BLOCK)
    elif walk != "thread":
        kernel = warp_cluster.cluster_kernel(
            scalar, flags, size=cluster_size, unroll=cuda)
        wp.load_module(kernel.module, device=device,
                       block_dim=warp_cluster.CLUSTER_BLOCK)
    else:
        kernel = warp_kernels.walk_kernel(scalar, flags)
        wp.load_module(kernel.module, device=device,
                       block_dim=warp_kernels.WALK_BLOCK)
    call = _cell_lj_callable(vector, graph, walk, cluster_size)
    has_radii = bool(flags & warp_kernels.HAS_RADII)
    dims = {"forces": (n, 3), "energy": (n,), "d_sigma": (n,),
            "d_epsilon": (n,), "count": (n,), "keys": (2 * n,),
            "values": (2 * n,), "wrapped": (n, 3), "start": (table + 1,),
            "position": (n, 3), "radius": (n if has_radii else 1,)}
    if walk != "thread":
        dims.update(counts=(table + 1,), offsets=(table + 1,), clusters=(
            warp_cluster.bound(n, table, cluster_size) + 1,))
    outs = call(*jax.lax.stop_gradient((points, radii, grid, cells, params)),
                int(flags), output_dims=dims)
    return tuple(outs[:5])


# ---------------------------------------------------------------------------
# The list-free SPH sums on the same grid: the sort
# (`jaxrt.backends.cell.warp_kernels.sort_cells`) in one call, each walk
# (`jaxrt.backends.cell.warp_sph`) in one more, so that the densities go
# through the equation of state in JAX between them.

_CELL_SPH_CALLABLES: dict = {}


def _cell_sort_callable(vector):
    from jaxrt.backends.cell import warp_kernels
    key = ("sort", vector)
    if key in _CELL_SPH_CALLABLES:
        return _CELL_SPH_CALLABLES[key]
    scalar = warp_kernels.scalar_of(vector)

    def sort(points: wp.array(dtype=vector), radii: wp.array(dtype=scalar),
             grid: wp.array(dtype=vector), cells: wp.array(dtype=wp.int32),
             flags: wp.int32, keys: wp.array(dtype=wp.int32),
             values: wp.array(dtype=wp.int32),
             wrapped: wp.array(dtype=vector), start: wp.array(dtype=wp.int32),
             position: wp.array(dtype=vector),
             radius: wp.array(dtype=scalar)):
        warp_kernels.sort_cells(points, radii, grid, cells, int(flags),
                                keys=keys, values=values, wrapped=wrapped,
                                start=start, position=position, radius=radius)

    sort.__module__ = warp_kernels.__name__  # see _aabb_callables
    _CELL_SPH_CALLABLES[key] = wp.jax_callable(
        sort, num_outputs=6, graph_mode=wp.JaxCallableGraphMode.NONE,
        vmap_method="sequential")
    return _CELL_SPH_CALLABLES[key]


def cell_sort(points, grid, cells, *, flags: int, table: int):
    """`jaxrt.backends.cell.warp_kernels.sort_cells` in one call (no radii).

    Args:
      points: float32 or float64 ``(N, 3)``; grid, cells, table: as
        `cell_lj_sums`'; flags: static, ``PERIODIC << axis`` bits.
    Returns:
      ``(keys int32 (2N,), values int32 (2N,), start int32 (table + 1,),
      position (N, 3))``: the sorted cell keys and caller's indices (the
      first N entries), the cell-start table, the wrapped positions in
      the sorted order.
    """
    from jaxrt.backends.cell import warp_kernels
    n = points.shape[0]
    call = _cell_sort_callable(_vector_of(points))
    radii = jnp.zeros((1,), points.dtype)
    flags = int(flags) & ~warp_kernels.HAS_RADII
    keys, values, _, start, position, _ = call(
        *jax.lax.stop_gradient((points, radii, grid, cells)), flags,
        output_dims={"keys": (2 * n,), "values": (2 * n,),
                     "wrapped": (n, 3), "start": (table + 1,),
                     "position": (n, 3), "radius": (1,)})
    return keys, values, start, position


def _cell_sph_callable(vector, kind: str, which: str):
    from jaxrt.backends.cell import warp_kernels, warp_sph
    key = (which, vector, kind)
    if key in _CELL_SPH_CALLABLES:
        return _CELL_SPH_CALLABLES[key]
    scalar = warp_kernels.scalar_of(vector)
    if which == "density":
        def call(position: wp.array(dtype=vector),
                 keys: wp.array(dtype=wp.int32),
                 start: wp.array(dtype=wp.int32),
                 grid: wp.array(dtype=vector),
                 cells: wp.array(dtype=wp.int32),
                 params: wp.array(dtype=scalar), flags: wp.int32,
                 mass: wp.array(dtype=scalar), rho: wp.array(dtype=scalar)):
            warp_sph.density_sums(kind, position, keys, start, grid, cells,
                                  params, int(flags), mass, rho)
        outputs = 1
    else:
        def call(position: wp.array(dtype=vector),
                 keys: wp.array(dtype=wp.int32),
                 start: wp.array(dtype=wp.int32),
                 grid: wp.array(dtype=vector),
                 cells: wp.array(dtype=wp.int32),
                 params: wp.array(dtype=scalar), flags: wp.int32,
                 velocity: wp.array(dtype=vector),
                 mass: wp.array(dtype=scalar), rho: wp.array(dtype=scalar),
                 q: wp.array(dtype=scalar), sound: wp.array(dtype=scalar),
                 pressure: wp.array(dtype=vector),
                 viscosity: wp.array(dtype=vector)):
            warp_sph.force_sums(kind, position, keys, start, grid, cells,
                                params, int(flags), velocity, mass, rho, q,
                                sound, pressure, viscosity)
        outputs = 2
    call.__module__ = warp_sph.__name__  # see _aabb_callables
    _CELL_SPH_CALLABLES[key] = wp.jax_callable(
        call, num_outputs=outputs, graph_mode=wp.JaxCallableGraphMode.NONE,
        vmap_method="sequential")
    return _CELL_SPH_CALLABLES[key]


def _load_sph_walk(vector, kind: str, which: int) -> None:
    """Load a walk's module now, not inside the callback (see
    `cell_lj_sums`)."""
    from jaxrt.backends.cell import warp_kernels, warp_sph
    walk = warp_sph.walks(warp_kernels.scalar_of(vector), kind)[which]
    wp.load_module(walk.module, device=_warp_device(),
                   block_dim=warp_sph.BLOCK)


def cell_sph_density(position, keys, start, grid, cells, params, mass, *,
                     flags: int, kind: str):
    """`jaxrt.backends.cell.warp_sph.density_sums` in one call.

    Args:
      position, keys, start: `cell_sort`'s (sorted order); grid, cells:
        the sort's; params: ``(warp_sph.N_PARAMS,)`` in the positions'
        dtype; mass: ``(N,)`` sorted; flags: static, the sort's; kind:
        static, one of `jaxrt.backends.cell.warp_sph.KINDS`.
    Returns:
      ``(N,)`` per sorted particle, ``sum_{j != i} m_j W(r_ij)``.
    """
    n = position.shape[0]
    vector = _vector_of(position)
    _load_sph_walk(vector, kind, 0)
    (rho,) = _cell_sph_callable(vector, kind, "density")(
        *jax.lax.stop_gradient((position, keys, start, grid, cells, params)),
        int(flags), jax.lax.stop_gradient(mass), output_dims={"rho": (n,)})
    return rho


def cell_sph_forces(position, keys, start, grid, cells, params, velocity,
                    mass, rho, q, sound, *, flags: int, kind: str):
    """`jaxrt.backends.cell.warp_sph.force_sums` in one call.

    Args: as `cell_sph_density`'s, and ``velocity`` ``(N, 3)``, ``mass``,
    ``rho``, ``q`` (``P / rho^2``), ``sound`` ``(N,)``, all sorted.
    Returns:
      ``(pressure (N, 3), viscosity (N, 3))`` per sorted particle.
    """
    n = position.shape[0]
    vector = _vector_of(position)
    _load_sph_walk(vector, kind, 1)
    pressure, viscosity = _cell_sph_callable(vector, kind, "forces")(
        *jax.lax.stop_gradient((position, keys, start, grid, cells, params)),
        int(flags), *jax.lax.stop_gradient((velocity, mass, rho, q, sound)),
        output_dims={"pressure": (n, 3), "viscosity": (n, 3)})
    return pressure, viscosity


def _cell_sph_step_callable(vector, kind: str, graph: str):
    from jaxrt.backends.cell import warp_kernels, warp_sph
    key = ("step", vector, kind, graph)
    if key in _CELL_SPH_CALLABLES:
        return _CELL_SPH_CALLABLES[key]
    scalar = warp_kernels.scalar_of(vector)

    def step(points: wp.array(dtype=vector),
             velocity: wp.array(dtype=vector), mass: wp.array(dtype=scalar),
             grid: wp.array(dtype=vector), cells: wp.array(dtype=wp.int32),
             params: wp.array(dtype=scalar), flags: wp.int32,
             keys: wp.array(dtype=wp.int32),
             values: wp.array(dtype=wp.int32),
             wrapped: wp.array(dtype=vector), start: wp.array(dtype=wp.int32),
             position: wp.array(dtype=vector),
             mass_sorted: wp.array(dtype=scalar),
             velocity_sorted: wp.array(dtype=vector),
             rho: wp.array(dtype=scalar), q: wp.array(dtype=scalar),
             sound: wp.array(dtype=scalar),
             pressure: wp.array(dtype=vector),
             viscosity: wp.array(dtype=vector),
             density: wp.array(dtype=scalar)):
        warp_sph.step_sums(
            kind, points, velocity, mass, grid, cells, params, int(flags),
            keys=keys, values=values, wrapped=wrapped, start=start,
            position=position, mass_sorted=mass_sorted,
            velocity_sorted=velocity_sorted, rho=rho, q=q, sound=sound,
            pressure=pressure, viscosity=viscosity, density=density)

    # See _aabb_callables: the sort's kernels' module, loaded before each
    # call (the walks' own modules are loaded when the call is traced).
    step.__module__ = warp_kernels.__name__
    _CELL_SPH_CALLABLES[key] = wp.jax_callable(
        step, num_outputs=13, graph_mode=_GRAPH_MODES[graph],
        vmap_method="sequential")
    return _CELL_SPH_CALLABLES[key]


def cell_sph_step(points, velocity, mass, grid, cells, params, *,
                  flags: int, table: int, kind: str, graph: str = "none"):
    """`jaxrt.backends.cell.warp_sph.step_sums` in one call: a whole SPH
    step's sums (sort, densities, Tait, forces).

    Args:
      points, velocity: float32 or float64 ``(N, 3)``; mass: ``(N,)``;
        grid, cells, table, flags: as `cell_sort`'s; params:
        ``(warp_sph.N_PARAMS,)``, every row; kind: static, one of
        `jaxrt.backends.cell.warp_sph.KINDS`; graph: static, as
        `cell_lj_sums`'.
    Returns:
      ``(pressure (N, 3), viscosity (N, 3), density (N,))``, the caller's
      order.
    """
    from jaxrt.backends.cell import warp_kernels, warp_sph
    n = points.shape[0]
    vector = _vector_of(points)
    for walk in warp_sph.walks(warp_kernels.scalar_of(vector), kind):
        wp.load_module(walk.module, device=_warp_device(),
                       block_dim=warp_sph.BLOCK)
    call = _cell_sph_step_callable(vector, kind, graph)
    flags = int(flags) & ~warp_kernels.HAS_RADII
    outs = call(*jax.lax.stop_gradient((points, velocity, mass, grid, cells,
                                        params)), flags,
                output_dims={
                    "keys": (2 * n,), "values": (2 * n,), "wrapped": (n, 3),
                    "start": (table + 1,), "position": (n, 3),
                    "mass_sorted": (n,), "velocity_sorted": (n, 3),
                    "rho": (n,), "q": (n,), "sound": (n,),
                    "pressure": (n, 3), "viscosity": (n, 3),
                    "density": (n,)})
    return tuple(outs[-3:])


# The cell list's candidate rows on the same grid (`jaxrt.backends.cell.warp_rows`).
_CELL_ROWS_CALLABLES: dict = {}


def _cell_rows_callable(vector, graph: str):
    """The jax callable of `jaxrt.backends.cell.warp_rows.candidate_rows`
    for positions of type ``vector``; ``graph``: `_GRAPH_MODES`' key."""
    from jaxrt.backends.cell import warp_kernels, warp_rows
    key = (vector, graph)
    if key in _CELL_ROWS_CALLABLES:
        return _CELL_ROWS_CALLABLES[key]
    scalar = warp_kernels.scalar_of(vector)

    def walk(points: wp.array(dtype=vector), grid: wp.array(dtype=vector),
             cells: wp.array(dtype=wp.int32),
             thresholds: wp.array(dtype=scalar), flags: wp.int32,
             row_width: wp.int32, shell: wp.int32,
             rows: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32),
             shells: wp.array(dtype=wp.int32),
             shell_count: wp.array(dtype=wp.int32),
             keys: wp.array(dtype=wp.int32), values: wp.array(dtype=wp.int32),
             wrapped: wp.array(dtype=vector), start: wp.array(dtype=wp.int32),
             position: wp.array(dtype=vector),
             radius: wp.array(dtype=scalar)):
        warp_rows.candidate_rows(
            points, grid, cells, thresholds, int(flags),
            row_width=int(row_width), shell=int(shell), rows=rows,
            count=count, shells=shells, shell_count=shell_count, keys=keys,
            values=values, wrapped=wrapped, start=start, position=position,
            radius=radius)

    # The sort's kernels' module (see _aabb_callables); the walk's own
    # module is loaded by cell_candidate_rows.
    walk.__module__ = warp_kernels.__name__
    _CELL_ROWS_CALLABLES[key] = wp.jax_callable(
        walk, num_outputs=10, graph_mode=_GRAPH_MODES[graph],
        vmap_method="sequential")
    return _CELL_ROWS_CALLABLES[key]


def cell_candidate_rows(points, grid, cells, thresholds, *, flags: int,
                        table: int, row_width: int, shell: int,
                        graph: str = "none"):
    """The cell list's candidate pass on the Warp grid
    (`jaxrt.backends.cell.warp_rows.candidate_rows`) in one call.

    Args:
      points: float32 or float64 ``(N, 3)`` Cartesian positions.
      grid, cells, table: as `cell_lj_sums`'.
      thresholds: float ``(2,)``, points' dtype: the squared distances
        below which a pair is sure, and below which it is in the shell.
      flags: static int, `jaxrt.backends.cell.warp_rows`' bits.
      row_width, shell: static widths (>= 1) of the rows and shells.
      graph: static, as `cell_lj_sums`' (nothing in the pipeline reads
        back to the host); ``"none"`` on a CPU.
    Returns:
      In the caller's order: int32 ``(N, row_width)`` rows (sure pairs,
      padded with N), int32 ``(N,)`` their exact counts, int32 ``(N,
      shell)`` shell pairs (valid up to the count), int32 ``(N,)`` their
      exact counts.
    """
    from jaxrt.backends.cell import warp_kernels, warp_rows
    n = points.shape[0]
    vector = _vector_of(points)
    # The walk lives in a module of its own: load it now, not inside the
    # callback.
    walk = warp_rows.rows_kernel(warp_kernels.scalar_of(vector))
    wp.load_module(walk.module, device=_warp_device(),
                   block_dim=warp_rows.WALK_BLOCK)
    # Warp captures graphs of CUDA launches only.
    call = _cell_rows_callable(vector, graph if _warp_device() == "cuda"
                               else "none")
    outs = call(*jax.lax.stop_gradient((points, grid, cells, thresholds)),
                int(flags), int(row_width), int(shell), output_dims={
                    "rows": (n * row_width,), "count": (n,),
                    "shells": (n * shell,), "shell_count": (n,),
                    "keys": (2 * n,), "values": (2 * n,), "wrapped": (n, 3),
                    "start": (table + 1,), "position": (n, 3),
                    "radius": (1,)})
    rows, count, shells, shell_count = outs[:4]
    return (rows.reshape(n, row_width), count, shells.reshape(n, shell),
            shell_count)


_PAIR_WALK_CALLABLES: dict = {}


def _pair_walk_callable(vector, graph: str):
    """The jax callable of `jaxrt.pairs.warp_kernels`' walk (count, scan,
    copy, write, padding) for positions of type ``vector``; ``graph``:
    `_GRAPH_MODES`' key."""
    from jaxrt.pairs import warp_kernels as pair_kernels
    key = (vector, graph)
    if key in _PAIR_WALK_CALLABLES:
        return _PAIR_WALK_CALLABLES[key]
    scalar = vector._wp_scalar_type_
    matrix = wp.types.matrix((3, 3), scalar)
    walk = pair_kernels.walk_kernel(scalar)

    def pair_walk(position: wp.array(dtype=vector),
                  sorted_position: wp.array(dtype=vector),
                  sorted_wrap: wp.array(dtype=wp.vec3i),
                  sorted_species: wp.array(dtype=wp.int32),
                  order: wp.array(dtype=wp.int32),
                  coord: wp.array(dtype=wp.vec3i),
                  wrap: wp.array(dtype=wp.vec3i),
                  graph: wp.array(dtype=wp.int32),
                  real: wp.array(dtype=wp.int32),
                  selfs: wp.array(dtype=wp.int32),
                  species: wp.array(dtype=wp.int32),
                  cells: wp.array(dtype=wp.vec3i),
                  base: wp.array(dtype=wp.int32),
                  pbc: wp.array(dtype=wp.vec3i),
                  lattice: wp.array(dtype=matrix),
                  runs: wp.array(dtype=wp.vec2i),
                  limit: wp.array(dtype=scalar), n_species: wp.int32,
                  reach_x: wp.int32, reach_y: wp.int32, reach_z: wp.int32,
                  half: wp.int32, capacity: wp.int32, pad: wp.int32,
                  width: wp.int32,
                  degree: wp.array(dtype=wp.int32),
                  offset: wp.array(dtype=wp.int32),
                  total: wp.array(dtype=wp.int32),
                  scratch: wp.array(dtype=wp.vec4i),
                  rows: wp.array(dtype=wp.int32)):
        n = position.shape[0]
        reach = wp.vec3i(int(reach_x), int(reach_y), int(reach_z))
        inputs = [position, sorted_position, sorted_wrap, sorted_species,
                  order, coord, wrap, graph, real, selfs, species, cells,
                  base, pbc, lattice, runs, limit, int(n_species), reach,
                  int(half)]
        device = position.device
        capacity, width = int(capacity), int(width)
        wp.launch(walk, dim=n, device=device, inputs=inputs + [
            0, capacity, width, offset, degree, scratch, rows])
        wp.utils.array_scan(degree, offset, inclusive=False)
        wp.launch(pair_kernels.last_total, dim=1, device=device,
                  inputs=[degree, offset, n, total])
        if capacity > 0:
            wp.launch(pair_kernels.copy_rows, dim=n * (width + 1),
                      device=device, inputs=[
                degree, selfs, offset, width, capacity, scratch, rows])
            wp.launch(walk, dim=n, device=device, inputs=inputs + [
                1, capacity, width, offset, degree, scratch, rows])
            wp.launch(pair_kernels.fill_padding, dim=capacity,
                      device=device, inputs=[total, int(pad), capacity, rows])

    pair_walk.__module__ = pair_kernels.__name__
    _PAIR_WALK_CALLABLES[key] = wp.jax_callable(
        pair_walk, num_outputs=5, graph_mode=_GRAPH_MODES[graph],
        vmap_method="sequential")
    return _PAIR_WALK_CALLABLES[key]


def pair_walk(arrays, *, n_species: int, reach: tuple[int, int, int],
              half: bool, capacity: int, width: int, graph: str = "none"):
    """`jaxrt.pairs.warp_kernels`' walk in one call: each atom's pairs
    counted, the counts scanned, the pairs written ``i``-major.

    Args:
      arrays: `jaxrt.pairs.warp_search.WalkInputs` (positions float32 or
        float64; everything else int32 but the cells and limits, in the
        positions' dtype).
      n_species: static rows (and columns) of the squared limits.
      reach: static stencil reach per axis.
      half: static; only each pair's representative.
      capacity: static rows to write (0: count only).
      width: static pairs per atom kept in scratch during the count (0:
        none, the walk writes every atom's pairs after the scan); the atoms
        with more are walked again.
      graph: static, as `cell_lj_sums`'; ``"none"`` on a CPU.
    Returns:
      int32 ``(N,)`` rows per atom (its self pair included), int32 ``(1,)``
      rows in all (exact past the capacity), int32 ``(max(capacity, 1),
      5)`` rows ``(i, j, S)`` padded with ``(N, N, 0)``.
    """
    from jaxrt.pairs import warp_kernels as pair_kernels
    n = arrays.position.shape[0]
    vector = _vector_of(arrays.position)
    wp.load_module(pair_kernels.walk_kernel(vector._wp_scalar_type_).module,
                   device=_warp_device())
    wp.load_module(pair_kernels, device=_warp_device())
    stored = max(int(capacity), 1)
    width = max(int(width), 0) if capacity > 0 else 0
    call = _pair_walk_callable(vector, graph if _warp_device() == "cuda"
                               else "none")
    degree, _, total, _, rows = call(
        *jax.lax.stop_gradient(tuple(arrays)), int(n_species),
        *(int(r) for r in reach), int(half), int(capacity), n, width,
        output_dims={"degree": (n,), "offset": (n,), "total": (1,),
                     "scratch": (max(n * width, 1), 4),
                     "rows": (stored * pair_kernels.ROW,)})
    return degree, total, rows.reshape(stored, pair_kernels.ROW)
