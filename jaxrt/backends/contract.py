"""The contract between `jaxrt.neighbor_list` and the search backends
(re-exported by `jaxrt.backends`, which holds the backends themselves).

A backend finds, for every particle ``i``, the particles ``j`` whose distance
is strictly below the search radius, and writes them in one of jax-md's
three layouts. With per-particle radii (`Geometry.reach`, seed 003 §3) the
radius of a pair is ``max(reach_i, reach_j)``: a symmetric rule, so both
directions of every pair are listed. The front (`jaxrt.lists.neighbors`) owns everything else: argument
checks, the skin, capacity sizing, ``custom_mask_function`` and errors.

Layouts (``N`` particles, padding index ``N`` everywhere):

* Dense: ``idx`` int32 ``(N, capacity)``, row ``i`` left-packed with the
  neighbours of ``i``.
* Sparse: ``idx`` int32 ``(2, capacity)`` = (receivers ``j``, senders ``i``),
  valid edges a prefix, both directions present.
* OrderedSparse: as Sparse, only edges with ``j < i``.

A backend is a `Backend`: a frozen, hashable value holding its options
(static, part of what ``jit`` caches on). ``measure`` runs eagerly (from
``allocate``) and returns the exact sizes the static buffers need;
``search`` must be jit/scan/vmap-able and must count exactly even where it
cannot store, so that overflow is never silent. A backend that keeps state
between calls does so in the object its ``bind`` returns, one per
`jaxrt.neighbor_list` call (the ray-traced BVHs), or in the list itself
(``stateful``: the Delaunay triangulation), never in module globals.
"""
from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple, Protocol

import jax
import jax.numpy as jnp
from jax_md.partition import NeighborListFormat

from jaxrt.layouts.rows import dense_to_sparse, pack_rows
from jaxrt.lists import metric as _space
from jaxrt.errors import ListTooLargeError

Array = jax.Array


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class MetricSq:
    """The caller's squared metric as a pytree: ``metric_sq(Ra, Rb)``.

    ``fn`` is static (part of the tree structure, so jit caches by it) and
    ``kwargs`` are traced (e.g. a ``box=`` given to ``update``). Backends
    that compute distances in JAX call it so that their pair decisions are
    bit-identical to jax-md's; kernels may use their own arithmetic.

    Attributes:
      fn: ``fn(Ra, Rb, **kwargs)`` -> float scalar, Ra and Rb float ``(dim,)``.
      kwargs: dict of arrays passed through to ``fn``.
    """

    fn: Callable = dataclasses.field(metadata=dict(static=True))
    kwargs: dict = dataclasses.field(default_factory=dict)

    def __call__(self, ra: Array, rb: Array) -> Array:
        return self.fn(ra, rb, **self.kwargs)


@dataclasses.dataclass(frozen=True)
class Query:
    """What to search for; static (hashable), one per `neighbor_list` call.

    Attributes:
      cutoff: search radius in Cartesian units (``r_cutoff + dr_threshold``).
        Pairs with ``d(i, j)**2 < cutoff**2`` are neighbours.
      periodic: one bool per spatial axis.
      mask_self: drop ``i == i`` pairs.
      format: the jax-md layout to write.
      decide_by_metric: the caller's metric decides every candidate pair
        (it is not the Euclidean minimum-image distance of ``Geometry``, or
        the box is triclinic): the grid only proposes candidates, which
        holds as long as the metric is never shorter than that distance.
        Backends that cannot do this are refused by the front.
      fixed_box: the box is the same at every search of the list (no
        ``box=`` passed to ``update``): a backend may size its grid for it
        once, at ``allocate``.
    """

    cutoff: float
    periodic: tuple[bool, ...]
    mask_self: bool
    format: NeighborListFormat
    decide_by_metric: bool = False
    fixed_box: bool = False

    @property
    def dim(self) -> int:
        return len(self.periodic)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Geometry:
    """Where the particles live, as arrays (traced under jit).

    Attributes:
      side: float ``(dim,)``, the box side per axis in Cartesian units; only
        read on periodic axes.
      scale: float ``(dim,)``; Cartesian position = ``position * scale``
        (ones, unless jax-md's ``fractional_coordinates`` is on, or the
        metric is scaled per axis), after ``transform``.
      transform: None, or float ``(dim, dim)`` ``T``: positions are first
        mapped to ``position @ T.T`` (Cartesian positions in a triclinic
        box, to fractional coordinates). Then ``side`` and ``scale`` are the
        box's heights, and the grid's distance only bounds the metric's
        from below (`Query.decide_by_metric` is set).
      reach: None (every pair's radius is `Query.cutoff`), or float
        ``(N,)`` per-particle search radii (``radii + dr_threshold``, in
        Cartesian units, at most `Query.cutoff`): ``i`` and ``j`` are
        neighbours iff ``d(i, j)**2 < max(reach_i, reach_j)**2``. Only
        backends with ``supports_radii`` get one.
    """

    side: Array
    scale: Array
    transform: Array | None = None
    reach: Array | None = None

    def grid_coordinates(self, position: Array) -> Array:
        """float ``(N, dim)``: ``position`` in the grid's Cartesian frame."""
        if self.transform is not None:
            position = _space.apply(self.transform.astype(position.dtype),
                                    position)
        return position * self.scale.astype(position.dtype)


@dataclasses.dataclass(frozen=True)
class Capacity:
    """Static buffer sizes, chosen at ``allocate`` from `Backend.measure`.

    Attributes:
      neighbors: the layout's capacity (Dense row width, or Sparse edges).
      internal: backend-specific sizes as sorted ``(name, size)`` pairs.
      metric_decides: `Query.decide_by_metric`, as ``allocate`` found it.
      orthorhombic: the metric's Gram matrix was diagonal at ``allocate``
        (`jaxrt.lists.metric`); a shear appearing later sets an error bit.
      slack: how much (relatively) farther the grid searches, for a metric
        found up to that much shorter than its model (`jaxrt.lists.metric`).
      radii: the list was allocated with per-particle radii.
    """

    neighbors: int
    internal: tuple[tuple[str, int], ...] = ()
    metric_decides: bool = False
    orthorhombic: bool = True
    slack: float = 0.0
    radii: bool = False

    def __getitem__(self, name: str) -> int:
        return dict(self.internal)[name]


class SearchResult(NamedTuple):
    """What `Backend.search` returns.

    Attributes:
      idx: int32 neighbour indices in ``query.format`` (module docstring).
      occupancy: int32 scalar, the exact size the layout needed: the largest
        row count (Dense) or the number of edges (Sparse, OrderedSparse).
      overflow: bool scalar, True when anything was dropped for lack of room,
        in ``idx`` or in an internal buffer.
      error: None, or uint8 scalar: `jaxrt.errors.ErrorCode` bits the
        backend sets itself (the Delaunay backend's failed rebuild); the
        front ORs them into the list's error code.
    """

    idx: Array
    occupancy: Array
    overflow: Array
    error: Array | None = None


# int32 indices address at most this many entries (the default of
# `Capabilities.max_list_entries`).
MAX_LIST_ENTRIES = 2 ** 31 - 1

# XLA's options for programs run once or a few times at small N on a CPU
# (`jaxrt.lists.metric.QUICK_COMPILE_OPTIONS`).
QUICK_COMPILE_OPTIONS = _space.QUICK_COMPILE_OPTIONS
# XLA's options for other programs a CPU runs eagerly
# (`jaxrt.lists.metric.CPU_COMPILE_OPTIONS`).
CPU_COMPILE_OPTIONS = _space.CPU_COMPILE_OPTIONS


@dataclasses.dataclass(frozen=True)
class Capabilities:
    """What a backend can do beyond ``name``, ``measure`` and ``search``,
    each with its default: the one place the front reads them
    (`capabilities`). A backend declares one by an attribute of that name
    (a class attribute, usually); one it does not declare has the default
    here, so a backend of one's own needs none of them.

    Attributes:
      max_list_entries: the largest int32 buffer the backend can index:
        `jaxrt.neighbor_list` refuses larger lists at ``allocate``.
      decides_by_metric: it honours `Query.decide_by_metric` (a triclinic
        box, a metric that is not the Euclidean minimum image); the front
        refuses such lists otherwise.
      exact_for_any_metric: it asks the caller's metric about every pair,
        so the front skips its checks of the metric.
      sparse_without_rows: it writes Sparse layouts without Dense rows
        first, so the front does not bound ``N x row``.
      supports_radii: it honours `Geometry.reach`; the front refuses
        ``radii=`` otherwise.
      small_boxes: it lists periodic boxes less than twice the cutoff
        across (each pair once, through the image the caller's metric
        picks, every candidate image tested once); the front refuses such
        boxes otherwise.
      build_at_exact_capacity: ``allocate`` builds the list at exactly its
        capacity, not at sizes rounded up for a compiled program that data
        of other sizes reuse (`compile_size`): for a backend whose state
        lives with the compiled call (the kept BVH).
      fixed_sizes: names of internal sizes from ``measure`` that are counts
        of things, not buffers, so the front takes them as measured (no
        ``capacity_multiplier``, no cap at N).
      stateful: the backend keeps a pytree of arrays *in the list* (the
        Delaunay backend's triangulation) and has ``init_state(position,
        geometry, query)``, which runs eagerly at ``allocate``; then
        ``measure`` and ``search`` get the state as ``state=``, and
        ``search`` returns ``(SearchResult, new_state)``. The front puts
        the state in `jaxrt.lists.neighbors.StatefulNeighborList.
        backend_state`, so that it travels with the list through ``jit``
        and ``lax.scan``.
      binds: the backend has ``bind()``, called once per
        `jaxrt.neighbor_list` call, which returns the backend that searches
        for that factory's lists: a fresh object owning its state (the
        ray-traced BVHs). Without it the backend searches itself (`bind`).
    """

    max_list_entries: int = MAX_LIST_ENTRIES
    decides_by_metric: bool = False
    exact_for_any_metric: bool = False
    sparse_without_rows: bool = False
    supports_radii: bool = False
    small_boxes: bool = False
    build_at_exact_capacity: bool = False
    fixed_sizes: tuple[str, ...] = ()
    stateful: bool = False
    binds: bool = False


def capabilities(backend) -> Capabilities:
    """``backend``'s `Capabilities`: each one it declares, else the
    default. Duck-typed: ``backend`` need not subclass anything."""
    found = {f.name: getattr(backend, f.name, f.default)
             for f in dataclasses.fields(Capabilities) if f.name != "binds"}
    found["fixed_sizes"] = tuple(found["fixed_sizes"])
    return Capabilities(**found, binds=callable(getattr(backend, "bind",
                                                        None)))


class Backend(Protocol):
    """A search backend: ``name``, ``measure`` and ``search``, plus any of
    the optional `Capabilities` (attributes of the same names; their
    defaults are `Capabilities`' and hold for a backend that leaves them
    out), ``bind()`` and, with ``stateful``, ``init_state``."""

    name: str

    def measure(self, position: Array, geometry: Geometry, query: Query,
                metric_sq: MetricSq) -> dict[str, int]:
        """Exact sizes needed now: always ``"row"`` (largest row count) and
        ``"edges"`` (edges in ``query.format``), plus any internal buffer
        the backend sizes statically. Eager; may use host syncs."""

    def search(self, position: Array, geometry: Geometry, query: Query,
               capacity: Capacity, metric_sq: MetricSq) -> SearchResult:
        """Neighbour list of ``position`` (float ``(N, dim)``). jit-able."""


def max_list_entries(backend) -> int:
    """The largest int32 buffer ``backend`` can index."""
    return capabilities(backend).max_list_entries


def compile_size(size: int) -> int:
    """``size`` rounded up to the next of 1, 2, 3, 4, 6, 8, 12, 16, 24, ...
    (two sizes an octave, at most 1.5x).

    Sizes that become static shapes of a compiled program at ``allocate``:
    data of one N measured a little differently then reuse the program
    instead of compiling another (a compile is most of an ``allocate`` on
    a CPU: benchmarks/RESULTS.md)."""
    size = int(size)
    if size <= 4:
        return size
    power = 1 << (size - 1).bit_length()  # the power of two >= size
    three_quarters = 3 * power // 4
    return three_quarters if three_quarters >= size else power


def list_too_large(backend_name: str, entries: int, what: str, n: int,
                   limit: int) -> ListTooLargeError:
    """The error for a list of ``entries`` int32 entries (``what``: which
    buffer) past ``limit``, the most a backend can index."""
    return ListTooLargeError(
        f"the neighbour list needs {entries:,} int32 entries ({what}, N = "
        f"{n:,}), more than backend={backend_name!r} can address "
        f"({limit:,}). Use fewer particles or a smaller r_cutoff + "
        "dr_threshold, OrderedSparse (half the edges of Sparse), or, for "
        "the ray-traced backends, backend='cell'. Energies need no list: "
        "jaxrt.energy.lennard_jones_fused(..., backend='cell').")


def is_stateful(backend: Backend) -> bool:
    """Whether ``backend`` keeps state in the list (`Capabilities`)."""
    return bool(capabilities(backend).stateful)


def bind(backend: Backend) -> Backend:
    """The object that searches for one `jaxrt.neighbor_list` factory:
    ``backend.bind()`` where it has one (`Capabilities.binds`), else
    ``backend`` itself."""
    return backend.bind() if capabilities(backend).binds else backend


# ---------------------------------------------------------------------------
# The layout helper shared by backends that build Dense rows first (the
# others, `pack_rows` and `dense_to_sparse`, are `jaxrt.layouts.rows`').


def format_dense_rows(dense: Array, counts: Array, query: Query,
                      capacity: Capacity, *, lower_only: bool = False
                      ) -> SearchResult:
    """Turn exact Dense rows (wide enough for ``capacity["row"]``) into the
    requested layout.

    Args:
      dense: int32 ``(N, capacity["row"])`` left-packed rows.
      counts: int32 ``(N,)`` exact row counts (may exceed the width).
      lower_only: the rows hold only neighbours ``j < i`` (an OrderedSparse
        search that wrote its edges as half rows): they are the edges, in
        order, with no rank along the rows.
    """
    if lower_only and query.format is not NeighborListFormat.OrderedSparse:
        raise ValueError(f"format_dense_rows: lower_only=True holds "
                         f"OrderedSparse's edges, not {query.format.name}'s.")
    row_overflow = jnp.any(counts > dense.shape[1])
    if query.format is NeighborListFormat.Dense:
        occupancy = jnp.max(counts, initial=0)
        width = capacity.neighbors
        if width < dense.shape[1]:
            dense = dense[:, :width]
        elif width > dense.shape[1]:
            pad = jnp.full((dense.shape[0], width - dense.shape[1]),
                           dense.shape[0], jnp.int32)
            dense = jnp.concatenate([dense, pad], axis=1)
        return SearchResult(dense, occupancy.astype(jnp.int32),
                            row_overflow | (occupancy > width))
    # With truncated rows the edge count is a lower bound, but then
    # ``row_overflow`` is already set and allocate re-measures exactly.
    # Full rows into OrderedSparse: ranked along each row. Otherwise the
    # rows are the edges, and their counts (clipped to the rows) are known.
    ranked = (query.format is NeighborListFormat.OrderedSparse
              and not lower_only)
    idx, edges = dense_to_sparse(
        dense, capacity.neighbors, ranked,
        counts=None if ranked else jnp.minimum(counts, dense.shape[1]))
    return SearchResult(idx, edges, row_overflow | (edges > capacity.neighbors))
