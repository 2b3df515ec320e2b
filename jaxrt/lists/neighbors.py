"""`neighbor_list`: a drop-in for ``jax_md.partition.neighbor_list``.

It takes jax-md's arguments, returns jax-md's own `NeighborListFns`, and its
``allocate`` / ``update`` return jax-md's own `NeighborList`, so every jax-md
consumer (``energy.*_neighbor_list``, ``smap.pair_neighbor_list``,
``simulate.*``, ``nbrs.update`` inside ``lax.scan``) works unchanged. The
search itself is delegated to a backend (`jaxrt.backends`).

Where jaxrt differs from jax-md, on purpose (the README's table):

* Keyword arguments jax-md would swallow (its ``**static_kwargs``) are
  accepted with a warning naming them; a near miss of a real argument
  raises ``TypeError`` with "did you mean".
* Periodicity is an explicit keyword, ``periodic=``, or, when omitted,
  inferred by probing ``displacement_or_metric`` along each axis against
  ``box``. Free space needs no box (``box=None`` is accepted).
* The metric is modelled (`jaxrt.lists.metric`: periods, a triclinic box's
  transform, the metric's Gram matrix) and the model is checked against
  the metric: on sampled pairs at ``allocate`` (a mismatch raises, or
  makes the cell list let the metric decide every pair where that is
  safe) and on the extreme particles of each axis at every rebuild under
  ``jit`` (an error bit). A periodic displacement given ``box=None`` is
  caught so.
* A cutoff of half a periodic height or more (a small box) gives the list
  jax-md's rule defines: every pair whose distance under
  ``displacement_or_metric`` is below the cutoff, once, through the image
  the displacement picks, on ``cell`` and ``brute``, with a warning
  (`SmallBoxWarning`) at the first ``allocate`` that meets it: other
  images within the cutoff are in no index-only list (`jaxrt.pairs` lists
  every image). The ray-traced backends and ``delaunay`` refuse such boxes,
  naming ``cell`` and ``brute``.
* Fractional positions that the caller does not announce (jax-md's
  ``energy.stillinger_weber_neighbor_list`` and ``eam_neighbor_list`` do
  not forward ``fractional_coordinates``): where ``displacement_or_metric``
  is periodic with period 1 along the axes rather than with ``box``, the
  positions are taken as fractional, with a warning naming
  ``fractional_coordinates=True``.
* Positions on a periodic axis outside ``[0, L)`` are binned after wrapping,
  so the list is right (jax-md's cell list silently misses pairs there).
* Bad input raises at ``allocate``; under ``jit`` a non-finite position, a
  metric that disagrees with the box, or (on the backends that refuse small
  boxes) a box shrunk below twice the cutoff sets an error bit (see
  `jaxrt.errors`) that also reads as overflow.
* Per-particle radii (``radii=``, seed 003 §3, a jaxrt extension): ``i``
  and ``j`` are neighbours iff ``d(i, j) < max(r_i, r_j) + dr_threshold``;
  ``r_cutoff`` bounds every radius and sizes the search.
* ``NeighborList.cell_list_capacity`` holds a `jaxrt.backends.Capacity`
  (static buffer sizes), not an int; ``cell_size`` and ``cell_list_fn``
  are None.
* A backend that keeps state in the list (``backend="delaunay"``: its
  triangulation) returns a `StatefulNeighborList`, a subclass of jax-md's
  ``NeighborList`` with one more pytree field, ``backend_state``: it is
  still a ``NeighborList`` to every consumer, and ``lax.scan`` carries the
  state with the list.
"""
from __future__ import annotations

import dataclasses
import difflib
import functools
import math
import warnings
from typing import Callable, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax_md import dataclasses as jax_md_dataclasses
from jax_md import space
from jax_md.partition import (NeighborList, NeighborListFns,
                              NeighborListFormat, PartitionError)

from jaxrt import backends, platforms
from jaxrt.backends import contract as _backend
from jaxrt.lists import metric as _space
from jaxrt.backends.contract import (Capacity, Geometry, MetricSq, Query,
                                     capabilities)
from jaxrt.errors import ErrorCode

Dense = NeighborListFormat.Dense
Sparse = NeighborListFormat.Sparse
OrderedSparse = NeighborListFormat.OrderedSparse

_ARGUMENTS = ("displacement_or_metric", "box", "r_cutoff", "dr_threshold",
              "capacity_multiplier", "disable_cell_list", "mask_self",
              "custom_mask_function", "fractional_coordinates", "format",
              "backend", "periodic", "radii")


@jax_md_dataclasses.dataclass
class StatefulNeighborList(NeighborList):
    """jax-md's `NeighborList` plus the backend's state (a pytree of
    arrays, e.g. `jaxrt.backends.delaunay.Triangulation`), made by a backend with
    ``stateful = True`` (`jaxrt.backends.Backend`). ``update`` maintains
    the state at every rebuild and returns the list with the new state."""

    backend_state: object


def _metric_sq_fn(displacement_or_metric: Callable, dim: int) -> Callable:
    """``fn(Ra, Rb, **kw)`` -> squared distance, from a displacement or metric."""
    probe = jax.ShapeDtypeStruct((dim,), jnp.float32)
    try:
        out = jax.eval_shape(displacement_or_metric, probe, probe)
    except Exception as e:  # noqa: BLE001 - re-raised with the argument named
        raise TypeError(
            "displacement_or_metric must be a function d(Ra, Rb) of two "
            f"({dim},) positions (the positions are {dim}-D), as made by "
            f"jax_md.space; calling it failed with: {e} A displacement "
            "made for another dimension (space.periodic(side) with a side "
            f"per axis of another count) fails so: make it for {dim}-D "
            "positions.") from e
    if out.shape not in ((), (dim,)):
        raise TypeError(
            "displacement_or_metric must return a scalar distance or a "
            f"({dim},) displacement; it returned shape {out.shape}.")
    return _SquaredMetric(displacement_or_metric, out.shape == ())


@dataclasses.dataclass(frozen=True)
class _SquaredMetric:
    """``fn(Ra, Rb, **kw)`` -> squared distance, from a displacement or
    (``scalar``) a metric. Equal for equal functions: it is static in the
    jitted programs (`MetricSq.fn`), so a second `neighbor_list` of the
    same displacement reuses their compiled programs."""

    fn: Callable
    scalar: bool

    def __call__(self, ra, rb, **kw):
        if self.scalar:
            return self.fn(ra, rb, **kw) ** 2
        return space.square_distance(self.fn(ra, rb, **kw))


def _box_parts(box, dim: int):
    """The box as float64 ``(dim,)`` sides or a ``(dim, dim)`` triclinic
    matrix (columns are the lattice vectors, jax-md's convention): returns
    ``(sides, matrix)``, at most one of them not None; both None where no
    usable box was given (None, or a side infinite or not positive: free
    space needs none). Raises for a NaN entry and for a box whose shape
    does not fit ``dim``-D positions."""
    if box is None:
        return None, None
    b = np.asarray(box, dtype=np.float64)
    which = f"positions are {dim}-D (shape (N, {dim})) but box"
    if b.ndim == 1 and b.shape != (dim,):
        raise ValueError(
            f"{which} has {b.shape[0]} sides: pass one side per axis "
            f"({dim} sides) or a scalar, or positions with {b.shape[0]} "
            "columns.")
    if b.ndim == 2 and b.shape != (dim, dim):
        raise ValueError(
            f"{which} is a {b.shape} matrix: pass a ({dim}, {dim}) matrix "
            f"(the lattice vectors as columns), {dim} sides or a scalar.")
    if b.ndim > 2:
        raise ValueError(f"box must be a scalar, ({dim},) or ({dim}, {dim}) "
                         f"for {dim}D positions; got shape {b.shape}.")
    if np.any(np.isnan(b)):
        # Dropping the box as unusable (as for an infinite side) would
        # blame the displacement, or the first axis, for a NaN on another.
        at = tuple(int(k) for k in np.argwhere(np.isnan(b))[0])
        if b.ndim == 0:
            raise ValueError("box is nan: pass a finite side > 0 (or "
                             "box=None in free space).")
        if b.ndim == 1:
            raise ValueError(
                f"box has a non-finite side on axis {at[0]} (nan): pass a "
                "finite side > 0 on every axis (a free axis's side is not "
                "read; any positive number will do).")
        raise ValueError(
            f"box has a non-finite entry at [{at[0]}, {at[1]}] (nan): pass a "
            "finite matrix with the lattice vectors as its columns.")
    if b.ndim == 0:
        b = np.full(dim, float(b))
    elif b.ndim == 2:
        if np.any(b - np.diag(np.diag(b))):
            if not np.all(np.isfinite(b)) or abs(np.linalg.det(b)) <= 0:
                raise ValueError("box is a singular or non-finite matrix; "
                                 "pass the lattice vectors as its columns.")
            return None, b
        b = np.diag(b)
    if not np.all(np.isfinite(b) & (b > 0)):
        return None, None
    return b, None


def _grid_space(box, dim: int, fractional: bool, periodic) -> _space.Space:
    """Periods and transform of the grid's space (`jaxrt.lists.metric.Space`);
    ``periodic`` is the per-axis tuple or None (to be inferred)."""
    sides, matrix = _box_parts(box, dim)
    axes = (False,) * dim if periodic is None else periodic
    if fractional:
        if sides is None and matrix is None:
            raise ValueError("fractional_coordinates=True needs box.")
        return _space.Space(axes, np.ones(dim))
    if matrix is not None:
        # Cartesian positions in a triclinic box: bin them in fractional
        # coordinates, where every axis has period 1.
        return _space.Space(axes, np.ones(dim), np.linalg.inv(matrix))
    return _space.Space(axes, np.ones(dim) if sides is None else sides)


def _probe_axes(metric, space: _space.Space, g
                 ) -> tuple[tuple[bool, ...], tuple[bool, ...]]:
    """Probe the metric along each grid axis at 0.75, 1.3 and 7.3 periods:
    does it look free, and does it look periodic with the grid's period?
    ``g``: the metric's Gram matrix in that space (`jaxrt.lists.metric.gram`).
    Returns two tuples of ``dim`` bools."""
    dim = space.dim
    steps = (0.75, 1.3, 7.3)
    q = np.zeros((dim, len(steps), dim))
    for a in range(dim):
        q[a, :, a] = np.asarray(steps) * float(space.period[a])
    lengths = np.asarray(_space.concrete(
        _space.lengths_from_origin, metric, space,
        q.reshape(-1, dim).astype(np.float32))).reshape(dim, -1)
    free, periodic = [], []
    for a in range(dim):
        unit = float(space.period[a])
        length = float(np.sqrt(max(float(g[a, a]), 0.0)))
        looks_free = looks_periodic = True
        for t, r in zip(steps, lengths[a]):
            r = float(r)
            tol = 1e-4 * t * unit * length + 1e-6
            looks_free &= abs(r - t * unit * length) <= tol
            looks_periodic &= abs(r - abs(t - round(t)) * unit * length) <= tol
        free.append(bool(looks_free))
        periodic.append(bool(looks_periodic))
    return tuple(free), tuple(periodic)


def _infer_periodic(free, periodic, box_known: bool
                    ) -> tuple[bool, ...] | None:
    """The periodic axes the probes (`_probe_axes`: ``free``,
    ``periodic``) tell, or None where some axis looks neither free nor
    periodic, or both, or periodic with no box to give the period."""
    if any(f == p or (p and not box_known) for f, p in zip(free, periodic)):
        return None
    return periodic


def _fractional_reading(metric, dim: int) -> tuple[bool, ...] | None:
    """The periodic axes of ``metric`` read as a metric of fractional
    coordinates (period 1 along every periodic axis, as jax-md's
    ``space.periodic_general`` measures by default), or None where that
    reading does not fit it either (some axis neither free nor periodic
    with period 1, or no axis periodic)."""
    unit = _space.Space((False,) * dim, np.ones(dim))
    g = np.asarray(_space.concrete(_space.gram, metric, unit,
                                   np.dtype(np.float32)))
    axes = _infer_periodic(*_probe_axes(metric, unit, g), True)
    return axes if axes is not None and any(axes) else None


def _undetermined_error(free, periodic, box_known: bool) -> ValueError:
    a = next(a for a, (f, p) in enumerate(zip(free, periodic))
             if f == p or (p and not box_known))
    return ValueError(
        f"could not tell from displacement_or_metric whether axis {a} is free"
        " or periodic with the given box. Pass periodic=True/False (or one "
        "bool per axis) explicitly, and check that box matches the "
        "displacement function: box=L for space.periodic(L); for positions "
        "in fractional coordinates (space.periodic_general's default), pass "
        "fractional_coordinates=True.")


def _normalise_periodic(periodic, dim: int) -> tuple[bool, ...]:
    if isinstance(periodic, (bool, np.bool_)):
        return (bool(periodic),) * dim
    periodic = tuple(bool(p) for p in periodic)
    if len(periodic) != dim:
        raise ValueError(f"periodic must be a bool or {dim} bools (one per "
                         f"axis); got {len(periodic)}.")
    return periodic


def _layout_capacity(occupancy: int, n: int, extra: int, fmt, mask_self: bool,
                     multiplier: float) -> int:
    """jax-md's sizing rule for the layout's capacity."""
    sparse = fmt is not Dense
    capacity = int(occupancy * multiplier + (n * extra if sparse else extra))
    if fmt is Dense:
        limit = n - 1 if mask_self else n
    elif fmt is Sparse:
        limit = n * (n - 1) if mask_self else n * n
    else:
        limit = n * (n - 1) // 2
    return max(min(capacity, limit), 0)


def _check_position(position, dim: int | None = None) -> jax.Array:
    if not hasattr(position, "shape") or not hasattr(position, "dtype"):
        position = np.asarray(position)
    if position.ndim != 2 or position.shape[1] not in (1, 2, 3):
        raise ValueError("position must have shape (N, dim) with dim in "
                         f"{{1, 2, 3}}; got shape {position.shape}.")
    if dim is not None and position.shape[1] != dim:
        raise ValueError(f"position has dim {position.shape[1]} but the list "
                         f"was allocated for dim {dim}.")
    if position.shape[0] < 1:
        raise ValueError("position must hold at least one particle.")
    if not jnp.issubdtype(position.dtype, jnp.floating):
        raise TypeError("position must be a floating-point array; got dtype "
                        f"{position.dtype}. Convert with .astype(float).")
    return jnp.asarray(position)


def _all_finite(position) -> bool:
    """Eager: are all of ``position``'s entries finite? On the host where
    the array is (no program to compile for one reduction), else where it
    lives."""
    if _space.on_accelerator(position):
        return bool(jnp.all(jnp.isfinite(position)))
    return bool(np.isfinite(np.asarray(position)).all())


def _static_positive(name: str, value, allow_zero: bool = False) -> float:
    if isinstance(value, jax.core.Tracer):
        raise TypeError(f"{name} must be a concrete number, not a traced value:"
                        " create the neighbour list outside jit.")
    try:
        v = float(np.asarray(value))
    except (TypeError, ValueError) as e:
        raise TypeError(f"{name} must be a number; got {value!r}.") from e
    if not math.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        bound = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{name} must be finite and {bound}; got {v}.")
    return v


def neighbor_list(displacement_or_metric: Callable,
                  box,
                  r_cutoff: float,
                  dr_threshold: float = 0.0,
                  capacity_multiplier: float = 1.25,
                  disable_cell_list: bool = False,
                  mask_self: bool = True,
                  custom_mask_function: Callable | None = None,
                  fractional_coordinates: bool = False,
                  format: NeighborListFormat = Dense,
                  *,
                  backend: str | backends.Backend = "auto",
                  periodic: bool | Sequence[bool] | None = None,
                  radii=None,
                  **unknown) -> NeighborListFns:
    """Neighbour lists with jax-md's interface and jaxrt's backends.

    Args (as jax-md's; see module docstring for the differences):
      displacement_or_metric: ``d(Ra, Rb)`` from ``jax_md.space``.
      box: scalar, ``(dim,)`` or ``(dim, dim)`` box (a triclinic matrix has
        the lattice vectors as columns, as ``space.periodic_general``); may
        be None in free space.
      r_cutoff: interaction radius; ``dr_threshold``: skin. Pairs with
        ``d < r_cutoff + dr_threshold`` (strict) are listed; the list is
        rebuilt when a particle moved more than ``dr_threshold / 2``.
      capacity_multiplier: head-room factor when sizing buffers.
      disable_cell_list: use the all-pairs backend ``"brute"``.
      mask_self: drop ``i``–``i`` pairs (keep them for SPH density sums).
      custom_mask_function: ``f(idx)`` on Dense ``(N, m)`` int32 rows,
        returning them with masked entries set to ``N``.
      fractional_coordinates: positions in ``[0, 1)^dim`` scaled by ``box``.
      format: `Dense`, `Sparse` or `OrderedSparse`.
      backend: ``"auto"``, a name from `jaxrt.backends.available()`, or a
        backend value with its options, e.g.
        ``jaxrt.backends.Cell(kernel="xla")`` (`jaxrt.backends`).
      periodic: bool or one bool per axis; None infers it (module docstring).
      radii: None, or float ``(N,)`` per-particle radii in ``[0, r_cutoff]``
        (concrete): ``i`` and ``j`` are neighbours iff ``d(i, j) <
        max(r_i, r_j) + dr_threshold``, both rows of a Dense list (both
        directions of a Sparse one, OrderedSparse once) holding the pair.
        ``r_cutoff`` must be at least ``max(radii)``: it sizes what depends
        on the largest radius (cells, ray reach, the half-box check).
        ``allocate`` and ``update`` take ``radii=`` too, replacing these for
        that call (``update``'s may be traced: it then always rebuilds, as
        it cannot tell whether they changed; bad values set
        `jaxrt.errors.ErrorCode.SEARCH_FAILED`). Backends ``"brute"``,
        ``"cell"`` and ``"bvh"`` support radii.
    Returns:
      jax-md's `NeighborListFns` (``allocate``, ``update``).
    """
    _check_unknown_keywords(unknown)
    settings = _check_arguments(
        displacement_or_metric, box=box, r_cutoff=r_cutoff,
        dr_threshold=dr_threshold, capacity_multiplier=capacity_multiplier,
        disable_cell_list=disable_cell_list, mask_self=mask_self,
        custom_mask_function=custom_mask_function,
        fractional_coordinates=fractional_coordinates, format=format,
        backend=backend, periodic=periodic, radii=radii)
    lists = _Lists(settings)
    return NeighborListFns(lists.allocate, lists.update)


@dataclasses.dataclass(frozen=True)
class _Settings:
    """`neighbor_list`'s arguments, checked (`_check_arguments`)."""

    metric: Callable
    box: object
    r_cutoff: float
    dr_threshold: float
    capacity_multiplier: float
    mask_self: bool
    custom_mask_function: Callable | None
    fractional_coordinates: bool
    format: NeighborListFormat
    backend: backends.Backend
    periodic: bool | Sequence[bool] | None
    radii: np.ndarray | None = None

    @property
    def cutoff(self) -> float:
        return self.r_cutoff + self.dr_threshold


def _check_arguments(displacement_or_metric, *, box, r_cutoff, dr_threshold,
                     capacity_multiplier, disable_cell_list, mask_self,
                     custom_mask_function, fractional_coordinates, format,
                     backend, periodic, radii=None) -> _Settings:
    """Check `neighbor_list`'s arguments; raise naming the argument."""
    if not callable(displacement_or_metric):
        raise TypeError("displacement_or_metric must be a function d(Ra, Rb) "
                        "from jax_md.space.")
    if format not in tuple(NeighborListFormat):
        raise ValueError("format must be jax_md.partition.Dense, Sparse or "
                         f"OrderedSparse; got {format!r}.")
    if custom_mask_function is not None and not callable(custom_mask_function):
        raise TypeError("custom_mask_function must be a function of the "
                        "(N, m) int32 index array, or None.")
    if disable_cell_list:
        if not (backend == "auto" or backend == "brute"
                or isinstance(backend, backends.Brute)):
            raise ValueError(f"disable_cell_list=True asks for the all-pairs "
                             f"search but backend={backend!r}; drop one.")
        backend = "brute"
    auto = isinstance(backend, str) and backend == "auto"
    if auto:
        backend = _auto_backend(has_radii=radii is not None)
    backend = backends.resolve(backend)
    if auto and backend.name == "cell" and jax.default_backend() == "cpu":
        backend = backends.BySize(small=backends.resolve("brute"),
                                  large=backend, max_small=_BRUTE_MAX_N_CPU)
    r_cutoff = _static_positive("r_cutoff", r_cutoff)
    if radii is not None:
        _check_radii_backend(backend)
        radii = _concrete_radii(radii, r_cutoff, "neighbor_list")
    return _Settings(
        metric=displacement_or_metric, box=box,
        r_cutoff=r_cutoff,
        dr_threshold=_static_positive("dr_threshold", dr_threshold,
                                     allow_zero=True),
        capacity_multiplier=_static_positive("capacity_multiplier",
                                            capacity_multiplier),
        mask_self=bool(mask_self), custom_mask_function=custom_mask_function,
        fractional_coordinates=bool(fractional_coordinates), format=format,
        backend=backend, periodic=periodic, radii=radii)


def _check_radii_backend(backend) -> None:
    if not capabilities(backend).supports_radii:
        raise ValueError(
            f"backend={backend.name!r} has no per-particle radii (its search "
            "radius is one number); use backend='bvh', 'cell' or 'brute' "
            "with radii=.")


def _radii_array(radii, where: str):
    """``radii`` as an array (float ``(N,)`` checked later), or TypeError."""
    if not hasattr(radii, "shape") or not hasattr(radii, "dtype"):
        radii = np.asarray(radii)
    if not jnp.issubdtype(radii.dtype, jnp.floating) and not jnp.issubdtype(
            radii.dtype, jnp.integer):
        raise TypeError(f"{where}: radii must be a float (N,) array; got "
                        f"dtype {radii.dtype}.")
    if radii.ndim != 1:
        raise ValueError(f"{where}: radii must be a float (N,) array, one "
                         f"radius per particle; got shape {radii.shape}.")
    return radii


def _concrete_radii(radii, r_cutoff: float, where: str,
                    n: int | None = None) -> np.ndarray:
    """Check concrete radii (shape, finite, in ``[0, r_cutoff]``); float64."""
    radii = _radii_array(radii, where)
    if isinstance(radii, jax.core.Tracer):
        raise TypeError(f"{where}: radii must be concrete here (not traced); "
                        "pass traced radii to update.")
    if n is not None and radii.shape[0] != n:
        raise ValueError(f"{where}: radii has {radii.shape[0]} entries but "
                         f"position has {n} particles; pass one radius per "
                         "particle.")
    r = np.asarray(radii, np.float64)
    bad = ~np.isfinite(r) | (r < 0)
    if bad.any():
        k = int(np.argmax(bad))
        raise ValueError(f"{where}: radii[{k}] = {r[k]}; radii must be "
                         "finite and >= 0.")
    if r.size and r.max() > r_cutoff:
        k = int(np.argmax(r))
        raise ValueError(
            f"{where}: radii[{k}] = {r[k]:g} is above r_cutoff = "
            f"{r_cutoff:g}, which sizes the search for the largest radius; "
            "pass r_cutoff >= max(radii).")
    return r


def _radii_errors(radii, r_cutoff: float) -> jax.Array:
    """Error bits of traced radii (update's): NaN, negative, too large."""
    bad = ~jnp.all(jnp.isfinite(radii) & (radii >= 0) & (radii <= r_cutoff))
    return _bits(bad, ErrorCode.SEARCH_FAILED | _OVERFLOW)


class _Setup(NamedTuple):
    """What the first ``allocate`` of a dimension fixes: the squared
    metric ``fn(Ra, Rb, **kw)``, the grid's `jaxrt.lists.metric.Space`, the
    `Query`, and the warnings given so far for this factory and dimension
    (``warned``, a mutable set of keys: each warning is given once)."""

    metric_fn: Callable
    grid: _space.Space
    query: Query
    warned: set


class SmallBoxWarning(UserWarning):
    """A periodic box less than twice the cutoff across: the list holds
    each pair once, through the image the caller's displacement picks, and
    other images within the cutoff are in no neighbour list."""


def _setup(settings: _Settings, dim: int, kwargs: dict) -> _Setup:
    """Geometry and periodicity for positions of dimension ``dim`` (the
    keywords of the first ``allocate`` reach the metric's probes).

    Where ``displacement_or_metric`` is neither free nor periodic with
    ``box`` along some axis (inferred periodicity), or not periodic with
    ``box`` along an axis given as periodic, but is periodic with period 1
    there, the positions are fractional coordinates that the caller did not
    announce (jax-md's Stillinger-Weber and EAM wrappers do not forward
    ``fractional_coordinates``): the grid is then fractional, with a
    warning."""
    axes = (None if settings.periodic is None
            else _normalise_periodic(settings.periodic, dim))
    box = settings.box
    fractional = settings.fractional_coordinates
    # The box first: a box of another dimension also breaks the metric's
    # probe, and its error would blame the displacement.
    grid = _grid_space(box, dim, fractional, axes)
    fn = _metric_sq_fn(settings.metric, dim)
    has_box = any(part is not None for part in _box_parts(box, dim))
    metric = MetricSq(fn, dict(kwargs))
    if axes is None or (any(axes) and has_box and not fractional):
        g = np.asarray(_space.concrete(_space.gram, metric, grid,
                                       np.dtype(np.float32)))
        free, periodic = _probe_axes(metric, grid, g)
        if axes is None:
            inferred = _infer_periodic(free, periodic, has_box)
            fits = inferred is not None
        else:
            fits = all(p <= q for p, q in zip(axes, periodic))
        unit = None if fits or not has_box else _fractional_reading(metric,
                                                                    dim)
        if unit is not None and axes not in (None, unit):
            unit = None  # periodic= says otherwise: leave it to allocate
        if unit is not None:
            warnings.warn(
                "displacement_or_metric is periodic with period 1 along "
                f"axes {[a for a in range(dim) if unit[a]]}, not with box: "
                "the positions are taken as fractional coordinates. Pass "
                "fractional_coordinates=True to say so (jax-md's "
                "energy.*_neighbor_list wrappers do not forward it; "
                "functools.partial(jaxrt.neighbor_list, "
                "fractional_coordinates=True) as neighbor_list_fn does).",
                stacklevel=4)
            axes, fractional = unit, True
            grid = _grid_space(box, dim, True, axes)
        elif axes is None:
            if not fits:
                raise _undetermined_error(free, periodic, has_box)
            axes = inferred
        if grid.periodic != axes:
            grid = dataclasses.replace(grid, periodic=axes)
    if any(axes) and not has_box:
        raise ValueError("periodic axes need box: pass the box side(s) "
                         "as box=L or box=(Lx, Ly[, Lz]).")
    if grid.transform is not None and not all(axes):
        raise ValueError(
            "a triclinic box with Cartesian positions needs every axis "
            "periodic (periodic=True); for a slab, use an orthorhombic "
            "box or fractional_coordinates=True.")
    # Only fractional coordinates take box= at update (`check_kwargs`).
    query = Query(cutoff=settings.cutoff, periodic=axes,
                  mask_self=settings.mask_self, format=settings.format,
                  fixed_box=not fractional and not kwargs)
    return _Setup(fn, grid, query, set())


class _Model(NamedTuple):
    """The metric's model at ``allocate`` (`jaxrt.lists.metric`): its Gram matrix
    ``g`` and heights ``h`` (float), whether it is ``diagonal``, whether
    the metric must decide every pair, and the grid's ``slack``."""

    g: jax.Array
    h: jax.Array
    diagonal: bool
    metric_decides: bool
    slack: float


def _model_at_allocate(settings: _Settings, searcher, setup: _Setup,
                       position, metric: MetricSq) -> _Model:
    """Model the metric and check the model on sampled pairs; raise where
    the grid would miss pairs or the backend cannot serve the metric."""
    grid = setup.grid
    g = _space.concrete(_space.gram, metric, grid, position.dtype)
    diagonal = grid.transform is None and _space.is_diagonal(g)
    h = _space.concrete(_space.heights, g, diagonal)
    small = _check_cutoff(settings.cutoff, grid, np.asarray(h, np.float64),
                          searcher)
    if small is not None and "small box" not in setup.warned:
        setup.warned.add("small box")
        warnings.warn(small, SmallBoxWarning, stacklevel=3)
    metric_decides = not diagonal
    slack = 0.0
    if not capabilities(searcher).exact_for_any_metric:
        # A positive slack means some pair deviates (|dev| > 1), so it
        # only ever comes with metric_decides.
        dev, slack, i, j = _space.sample_deviation(position, metric, g, h, grid)
        if slack is None:
            raise _shorter_metric_error(position, metric, g, grid, i, j, dev,
                                        settings.box)
        metric_decides |= bool(np.any(np.abs(dev) > 1))
    if metric_decides and not capabilities(searcher).decides_by_metric:
        raise ValueError(
            f"backend={searcher.name!r} computes Euclidean "
            "minimum-image distances in an orthorhombic box itself, but "
            + ("the box is triclinic" if not diagonal else
               "displacement_or_metric differs from that distance") +
            "; use backend='cell' (its grid then lets the metric decide "
            "every pair) or backend='brute'.")
    return _Model(g, h, diagonal, metric_decides, slack)


def _capacity(settings: _Settings, sizes: dict, n: int, extra: int,
              fixed: tuple = ()) -> Capacity:
    """Static buffer sizes from the backend's exact ``sizes`` (jax-md's
    rule: times ``capacity_multiplier``, plus ``extra_capacity``)."""
    fmt = settings.format
    multiplier = settings.capacity_multiplier
    occupancy = sizes["row"] if fmt is Dense else sizes["edges"]
    neighbors = _layout_capacity(occupancy, n, extra, fmt, settings.mask_self,
                                 multiplier)
    row_sized = sizes.get("row_before_mask", sizes["row"])
    row = _layout_capacity(row_sized, n, extra, Dense, settings.mask_self,
                           multiplier)
    if fmt is Dense and settings.custom_mask_function is None:
        row = neighbors
    # A size that fits in N (a window, rows with a shell) stays within N;
    # larger ones (edge buffers) grow freely.
    internal = {k: v if k in fixed else max(math.ceil(v * multiplier), 1)
                if v > n else min(max(math.ceil(v * multiplier), 1), n)
                for k, v in sizes.items()
                if k not in ("row", "edges", "row_before_mask")}
    internal["row"] = row
    return Capacity(neighbors, tuple(sorted(internal.items())))


def _state_kw(state) -> dict:
    """``state=`` for a stateful backend's calls, nothing otherwise."""
    return {} if state is None else {"state": state}


def _search(searcher, position, geometry, query, capacity, metric, state):
    """``(SearchResult, state)`` of any backend (state None if stateless)."""
    out = searcher.search(position, geometry, query, capacity, metric,
                          **_state_kw(state))
    return out if state is not None else (out, None)


def _measure(settings: _Settings, searcher, position, geometry, query,
             metric, state=None) -> dict[str, int]:
    """The backend's exact sizes, after ``custom_mask_function`` if any."""
    mask = settings.custom_mask_function
    kw = _state_kw(state)
    if mask is None:
        return searcher.measure(position, geometry, query, metric, **kw)
    dense_query = dataclasses.replace(query, format=Dense)
    pre = searcher.measure(position, geometry, dense_query, metric, **kw)
    internal = {k: v for k, v in pre.items() if k not in ("row", "edges")}
    exact = Capacity(pre["row"], tuple(sorted({**internal,
                                               "row": pre["row"]}.items())))
    idx = _search(searcher, position, geometry, dense_query, exact, metric,
                  state)[0].idx
    masked = np.asarray(mask(idx))
    n = position.shape[0]
    keep = masked < n
    i = np.arange(n)[:, None]
    ordered = query.format is OrderedSparse
    edges = (keep & (masked < i)).sum() if ordered else keep.sum()
    return {**internal, "row": int(keep.sum(1).max(initial=0)),
            "edges": int(edges), "row_before_mask": pre["row"]}


def _make_build(searcher, custom_mask_function: Callable | None) -> Callable:
    """The jitted search: ``build(position, geometry, metric, state, *,
    query, capacity)`` -> (idx, overflow, error bits (uint8), state), the
    custom mask applied; ``state`` is None for a stateless backend. One
    per equal (``searcher``, ``custom_mask_function``) where the searcher
    is shared (`_shared_build`), so that factories of equal arguments
    reuse its compiled programs."""

    def bits_of(result):
        return (jnp.uint8(0) if result.error is None
                else result.error.astype(jnp.uint8))

    @functools.partial(jax.jit, static_argnames=("query", "capacity"))
    def build(position, geometry, metric, state, *, query, capacity):
        if custom_mask_function is None:
            result, state = _search(searcher, position, geometry, query,
                                    capacity, metric, state)
            return result.idx, result.overflow, bits_of(result), state
        dense_query = dataclasses.replace(query, format=Dense)
        pre = dataclasses.replace(capacity, neighbors=capacity["row"])
        result, state = _search(searcher, position, geometry, dense_query,
                                pre, metric, state)
        masked = custom_mask_function(result.idx)
        n = position.shape[0]
        rows, counts = backends.pack_rows(masked, masked < n, capacity["row"])
        final = backends.format_dense_rows(rows, counts, query, capacity)
        return (final.idx, final.overflow | result.overflow, bits_of(result),
                state)

    return build


@functools.lru_cache(maxsize=64)
def _shared_build(searcher, custom_mask_function: Callable | None
                  ) -> Callable:
    """`_make_build`'s, one per equal pair (a backend neither bound per
    factory nor stateful: its programs depend on nothing else)."""
    return _make_build(searcher, custom_mask_function)


def _bits(flag, code) -> jax.Array:
    """uint8 ``code`` where ``flag``, else 0."""
    return jnp.where(flag, jnp.uint8(code), jnp.uint8(0))


_OVERFLOW = ErrorCode.NEIGHBOR_LIST_OVERFLOW


def _input_errors(position, grid: _space.Space, h, cutoff: float) -> jax.Array:
    """Error bits that need no search: non-finite positions, and a box
    (passed to ``update``) shrunk below twice the cutoff."""
    bad = ~jnp.all(jnp.isfinite(position))
    too_small = jnp.any(jnp.asarray(grid.periodic) & ~_space.cutoff_fits(
        cutoff, jnp.asarray(grid.period, position.dtype) * h))
    return (_bits(bad, ErrorCode.NONFINITE_POSITION | _OVERFLOW)
            | _bits(too_small, ErrorCode.BOX_TOO_SMALL | _OVERFLOW))


def _metric_errors(position, metric, g, h, grid, capacity: Capacity
                   ) -> jax.Array:
    """Error bits of a rebuild: the extreme particles of each axis, where
    the metric disagrees with its model fixed at ``allocate``. Positions
    with a NaN or infinite entry have their own bit (`_input_errors`): the
    metric of such a particle is not compared."""
    finite = jnp.all(jnp.isfinite(position))
    wrong = finite & _space.extremes_disagree(
        position, metric, g, h, grid, lower_bound_only=capacity.metric_decides,
        slack=capacity.slack)
    if capacity.orthorhombic:
        wrong |= _space.off_diagonal(g)
    return _bits(wrong, ErrorCode.METRIC_MISMATCH | _OVERFLOW)


@dataclasses.dataclass(frozen=True)
class _Program:
    """Everything of a factory that its update's traced program reads,
    for one dimension: static (hashable, equal by value), so that the
    eager update of factories with equal arguments is one jitted program
    (`_update_arrays`), compiled once per process and list structure.

    Attributes: ``searcher`` (the bound backend), ``build`` (its jitted
    search, `_make_build`), ``metric_fn`` (`_SquaredMetric`), ``grid``
    (`jaxrt.lists.metric.Space`), ``query`` (`Query`, before the list's
    ``decide_by_metric``), ``r_cutoff``, ``dr_threshold``, ``box_limit``
    (`_box_limit`), ``checks_metric`` (the metric's model is checked at
    every rebuild) and ``stateful`` (the backend keeps state in the list).
    """

    searcher: object
    build: Callable
    metric_fn: Callable
    grid: _space.Space
    query: Query
    r_cutoff: float
    dr_threshold: float
    box_limit: float
    checks_metric: bool
    stateful: bool


def _update_arrays(position, idx, reference, code, state, force, radii,
                   kwargs, *, program: _Program, capacity: Capacity,
                   given_radii: bool):
    """The update's body on the list's arrays: rebuild where a particle
    moved more than half the skin, or ``force`` (bool, may be traced), or
    ``given_radii`` (radii passed to ``update``: float ``(N,)``, checked).

    Args: ``position`` float ``(N, dim)``; ``idx``, ``reference``,
    ``code`` (uint8 error bits) and ``state`` (the backend's, or None) of
    the list; ``radii`` float ``(N,)`` or None; ``kwargs`` the metric's
    (``box=``). Returns the new ``(idx, reference, code, state)``."""
    query = dataclasses.replace(program.query,
                                decide_by_metric=capacity.metric_decides)
    metric = MetricSq(program.metric_fn, dict(kwargs))
    grid = program.grid
    g = _space.gram(metric, grid, position.dtype)
    h = _space.heights(g, capacity.orthorhombic)
    reach = None if radii is None else (
        jnp.asarray(radii, position.dtype)
        + jnp.asarray(program.dr_threshold, position.dtype))
    geometry = _geometry(grid, h, position.dtype, capacity.slack, reach)
    code = code | _input_errors(position, grid, h, program.box_limit)
    if given_radii:
        code |= _radii_errors(jnp.asarray(radii), program.r_cutoff)

    def rebuild(_):
        new_idx, overflow, bits, new_state = program.build(
            position, geometry, metric, state, query=query, capacity=capacity)
        bits |= _bits(overflow, _OVERFLOW)
        if program.checks_metric:
            bits |= _metric_errors(position, metric, g, h, grid, capacity)
        return new_idx, position, code | bits, new_state

    def keep(_):
        return idx, reference, code, state

    if program.dr_threshold == 0 or given_radii:
        return rebuild(None)
    threshold_sq = (program.dr_threshold / 2) ** 2
    moved = jax.vmap(metric)(position, reference)
    return jax.lax.cond(jnp.any(moved > threshold_sq) | force, rebuild,
                        keep, None)


_UPDATE_STATIC = ("program", "capacity", "given_radii")


def _eager_updates():
    """`_update_arrays` jitted three ways: plain (accelerators), for
    compile speed (`QUICK_COMPILE_OPTIONS`) and with `CPU_COMPILE_OPTIONS`
    (see `_Lists.eager_program`)."""
    return tuple(jax.jit(_update_arrays, static_argnames=_UPDATE_STATIC,
                         compiler_options=options)
                 for options in ({}, _backend.QUICK_COMPILE_OPTIONS,
                                 _backend.CPU_COMPILE_OPTIONS))


# Eager updates of every factory whose programs are shared (`_Lists`).
_SHARED_EAGER_UPDATES = _eager_updates()


class _Lists:
    """``allocate`` and ``update`` of one `neighbor_list` call: its checked
    settings, the backend bound for it (`jaxrt.backends.bind`), the setup
    of each dimension allocated so far, and the jitted search."""

    def __init__(self, settings: _Settings):
        self.settings = settings
        self.searcher = backends.bind(settings.backend)
        # A backend bound per factory (its trees kept per traced call site)
        # or keeping state in the list builds at ``allocate`` through its
        # own build program, which its later updates meet again.
        self.builds_as_update = not (
            _backend.capabilities(settings.backend).binds
            or _backend.is_stateful(self.searcher))
        # `BySize`'s lists are checked as its large backend's at every N, so
        # that what ``"auto"`` accepts does not change with N.
        self.checks_metric = not capabilities(
            self.searcher).exact_for_any_metric
        self.setups: dict[int, _Setup] = {}
        self.programs: dict[int, _Program] = {}
        # Factories of equal arguments share their compiled programs (a
        # second `neighbor_list` compiles nothing), except where the
        # searcher holds per-factory state: its programs stay its own.
        shares_programs = self.builds_as_update
        self.build = (_shared_build if shares_programs else _make_build)(
            self.searcher, settings.custom_mask_function)
        # Per (N, dtype, query): the capacities allocate's build has been
        # compiled for, newest last.
        self.compiled: dict[tuple, list[Capacity]] = {}
        # The capacities ``allocate`` built through `eager_program`'s program
        # (`plan_build`), per (N, dtype, query).
        self.built_as_update: dict[tuple, set[Capacity]] = {}
        # Eager ``update`` calls run the whole update as one jitted program
        # (`_update_arrays`), compiled once per list structure and shape
        # and then reused: run op by op, its ``lax.cond`` closed over new
        # functions at every call and recompiled the search each time.
        # ``allocate`` builds through it too (``force``: rebuild whatever
        # moved), so that the first ``update`` compiles nothing.
        (self.eager_update, self.eager_update_quick,
         self.eager_update_cpu) = (_SHARED_EAGER_UPDATES if shares_programs
                                   else _eager_updates())

    def eager_program(self, position):
        """`eager_update` on an accelerator; on a CPU `eager_update_cpu`
        (`CPU_COMPILE_OPTIONS`), or for small N `eager_update_quick`
        (compiled for compile speed: most of a first ``allocate``; a
        caller's ``jit`` of ``update`` compiles its own program). Concrete
        arrays inside a caller's trace get `eager_update`: JAX refuses
        compile options on a nested ``jit``."""
        if _space.on_accelerator(position) or platforms.under_trace():
            return self.eager_update
        if position.shape[0] <= _QUICK_EAGER_MAX_N:
            return self.eager_update_quick
        return self.eager_update_cpu

    def plan_build(self, n: int, dtype, query: Query, capacity: Capacity,
                   sizes: dict[str, int], limit: int) -> Capacity | None:
        """How ``allocate`` builds: None, through `eager_program`'s program
        at ``capacity`` itself, which the list's first ``update`` then
        reuses (one compile for both), where no build of its kind was
        compiled yet, where that program exists already, or where the build
        must be exact; else `compiled_capacity`'s, a compiled build that
        holds ``capacity`` or a rounded one, trimmed after, so that lists
        of one N whose exact sizes differ a little (a training set's
        structures) share a compile."""
        key = (n, np.dtype(dtype).name, query)
        done = self.built_as_update.setdefault(key, set())
        exact = _compiled_capacity(self.searcher, n, capacity, query, sizes,
                                   limit) is capacity
        if capacity in done or exact or key not in self.compiled:
            if not exact:
                self.compiled.setdefault(key, [])
            done.add(capacity)
            return None
        return self.compiled_capacity(n, dtype, query, capacity, sizes, limit)

    def compiled_capacity(self, n: int, dtype, query: Query,
                          capacity: Capacity, sizes: dict[str, int],
                          limit: int) -> Capacity:
        """The capacity ``allocate`` builds with: one it compiled before
        that holds ``capacity`` (`_reused_capacity`), else
        `_compiled_capacity`'s rounded one (remembered; lists up to
        ``limit`` int32 entries, `_rounded_list_limit`), or ``capacity``
        itself where the build must be exact."""
        rounded = _compiled_capacity(self.searcher, n, capacity, query, sizes,
                                     limit)
        if rounded is capacity:
            return capacity
        built = self.compiled.setdefault((n, np.dtype(dtype).name, query), [])
        fixed = capabilities(self.searcher).fixed_sizes
        reused = _reused_capacity(built, capacity, fixed)
        if reused is not None:
            return reused
        built.append(rounded)
        del built[:-_COMPILED_KEPT]
        return rounded

    def setup(self, dim: int, kwargs: dict) -> _Setup:
        if dim not in self.setups:
            self.setups[dim] = _setup(self.settings, dim, kwargs)
        return self.setups[dim]

    def check_kwargs(self, kwargs: dict, allocating: bool) -> None:
        extra = set(kwargs) - {"box"}
        if extra:
            raise TypeError(f"unexpected keyword argument(s) {sorted(extra)}; "
                            "allocate/update accept only box= (passed to "
                            "displacement_or_metric, as in jax-md) and "
                            "radii=.")
        if ("box" in kwargs and not self.settings.fractional_coordinates
                and not allocating):
            raise ValueError("box= may be passed to update only with "
                             "fractional_coordinates=True (as in jax-md).")

    def allocate(self, position, extra_capacity: int = 0, *, radii=None,
                 **kwargs) -> NeighborList:
        """Measure the list at ``position`` (float ``(N, dim)``) and size it;
        ``radii``: float ``(N,)``, replacing the factory's for this call.

        Eager (not jit-able): buffer sizes depend on the data.
        """
        self.check_kwargs(kwargs, allocating=True)
        position = _check_position(position)
        n, dim = position.shape
        own_radii = radii is not None
        if radii is None:
            radii = self.settings.radii
        else:
            _check_radii_backend(self.searcher)
        if radii is not None:
            radii = _concrete_radii(radii, self.settings.r_cutoff,
                                    "allocate", n)
        if not _all_finite(position):
            bad = np.argwhere(~np.isfinite(np.asarray(position)))[0]
            raise ValueError(f"position has a non-finite value at particle "
                             f"{bad[0]}, axis {bad[1]}; fix the input.")
        extra_capacity = int(extra_capacity)
        if extra_capacity < 0:
            raise ValueError("extra_capacity must be >= 0.")
        setup = self.setup(dim, kwargs)
        metric = MetricSq(setup.metric_fn, dict(kwargs))
        model = _model_at_allocate(self.settings, self.searcher, setup,
                                   position, metric)
        query = dataclasses.replace(setup.query,
                                    decide_by_metric=model.metric_decides)
        geometry = _geometry(setup.grid, model.h, position.dtype, model.slack,
                             self.reach(radii, position.dtype))
        state = (self.searcher.init_state(position, geometry, query)
                 if _backend.is_stateful(self.searcher) else None)
        sizes = _measure(self.settings, self.searcher, position, geometry,
                         query, metric, state)
        capacity = dataclasses.replace(
            _capacity(self.settings, sizes, n, extra_capacity,
                      capabilities(self.searcher).fixed_sizes),
            metric_decides=model.metric_decides, orthorhombic=model.diagonal,
            slack=model.slack, radii=radii is not None)
        _check_list_size(self.searcher, n, capacity, query)
        compiled = self.plan_build(n, position.dtype, query, capacity, sizes,
                                   _rounded_list_limit(position))
        if compiled is None:
            if self.builds_as_update and (
                    not kwargs or self.settings.fractional_coordinates):
                return self.build_as_update(position, capacity, state,
                                            radii if own_radii else None,
                                            kwargs)
            compiled = capacity  # update takes no box=: a build of its own
        idx, overflow, code, state = self.build(
            position, geometry, metric, state, query=query, capacity=compiled)
        if compiled is not capacity:
            idx, overflow = _trimmed(idx, overflow, width=capacity.neighbors,
                                     n=n)
        return self.neighbor_list(
            idx, position, PartitionError(code | _bits(overflow, _OVERFLOW)),
            capacity, state)

    def neighbor_list(self, idx, position, error, capacity: Capacity, state
                      ) -> NeighborList:
        """jax-md's `NeighborList` (a `StatefulNeighborList` where
        ``state`` is not None) of this factory."""
        fields = (idx, position, error, capacity, capacity.neighbors,
                  self.settings.format, None, None, self.update)
        if state is None:
            return NeighborList(*fields)
        return StatefulNeighborList(*fields, state)

    def build_as_update(self, position, capacity: Capacity, state, radii,
                        kwargs: dict) -> NeighborList:
        """``allocate``'s list built by `eager_program`'s program, forced to
        rebuild, from an empty list of ``capacity``: the very program the
        list's first eager ``update`` runs. ``radii``: float64 ``(N,)``
        given to ``allocate``, or None (the factory's, if any)."""
        n = position.shape[0]
        shape = ((n, capacity.neighbors) if self.settings.format is Dense
                 else (2, capacity.neighbors))
        # Host arrays: no program is compiled to make them.
        empty = self.neighbor_list(
            jax.device_put(np.full(shape, n, np.int32)), position,
            PartitionError(jax.device_put(np.zeros((), np.uint8))), capacity,
            state)
        return self.eager_call(position, empty, np.bool_(True), radii,
                               kwargs)

    def reach(self, radii, dtype):
        """float ``(N,)`` ``radii + dr_threshold`` in ``dtype``, or None."""
        if radii is None:
            return None
        return jnp.asarray(radii, dtype) + jnp.asarray(
            self.settings.dr_threshold, dtype)

    def update(self, position, neighbors: NeighborList, *, radii=None,
               **kwargs) -> NeighborList:
        """Rebuild ``neighbors`` at ``position`` if a particle moved more than
        half the skin since the last build, or whenever ``radii`` (float
        ``(N,)``, may be traced) is given. jit/scan/vmap-able; called
        eagerly, it runs one compiled program, reused by later calls with
        lists of the same structure and shapes."""
        self.check_kwargs(kwargs, allocating=False)
        if not isinstance(neighbors, NeighborList):
            raise TypeError("neighbors must be a NeighborList from allocate; "
                            f"got {type(neighbors).__name__}.")
        traced = any(isinstance(leaf, jax.core.Tracer) for leaf in
                     jax.tree_util.tree_leaves((position, neighbors, radii,
                                                kwargs)))
        if traced:
            return self.traced_update(position, neighbors, radii=radii,
                                      **kwargs)
        return self.eager_call(position, neighbors, np.bool_(False), radii,
                               kwargs)

    def eager_call(self, position, neighbors: NeighborList, force, radii,
                   kwargs: dict) -> NeighborList:
        """`update` called eagerly (or ``allocate``'s build, ``force``d):
        `eager_program`'s compiled program on the list's arrays."""
        position, capacity, program, radii, given = self.prepare(
            position, neighbors, radii, kwargs)
        state = neighbors.backend_state if program.stateful else None
        out = self.eager_program(position)(
            position, neighbors.idx, neighbors.reference_position,
            neighbors.error.code, state, force, radii, kwargs,
            program=program, capacity=capacity, given_radii=given)
        return self.replaced(neighbors, program, *out)

    def traced_update(self, position, neighbors: NeighborList, *, radii=None,
                      **kwargs) -> NeighborList:
        """`update`'s body, traced (under the caller's ``jit``)."""
        return self.forced_update(position, neighbors, False, radii=radii,
                                  **kwargs)

    def forced_update(self, position, neighbors: NeighborList, force, *,
                      radii=None, **kwargs) -> NeighborList:
        """`update`'s body, traced (`traced_update`); ``force`` (bool, may
        be traced): rebuild even if nothing moved."""
        position, capacity, program, radii, given = self.prepare(
            position, neighbors, radii, kwargs)
        state = neighbors.backend_state if program.stateful else None
        out = _update_arrays(position, neighbors.idx,
                             neighbors.reference_position,
                             neighbors.error.code, state, force, radii,
                             kwargs, program=program, capacity=capacity,
                             given_radii=given)
        return self.replaced(neighbors, program, *out)

    @staticmethod
    def replaced(neighbors: NeighborList, program: _Program, idx, reference,
                 code, state) -> NeighborList:
        """``neighbors`` with `_update_arrays`' new arrays."""
        new = dict(idx=idx, reference_position=reference,
                   error=PartitionError(code))
        if program.stateful:
            new["backend_state"] = state
        return dataclasses.replace(neighbors, **new)

    def prepare(self, position, neighbors: NeighborList, radii, kwargs: dict):
        """Check `update`'s arguments; returns ``(position, capacity,
        program, radii, given_radii)`` for `_update_arrays` (``radii``:
        those given, else the factory's, else None)."""
        self.check_kwargs(kwargs, allocating=False)
        if not isinstance(neighbors, NeighborList):
            raise TypeError("neighbors must be a NeighborList from allocate; "
                            f"got {type(neighbors).__name__}.")
        position = _check_position(position)
        ref = neighbors.reference_position
        if position.shape != ref.shape or position.dtype != ref.dtype:
            raise ValueError(
                f"position is {position.dtype}{list(position.shape)} but the "
                f"list was allocated for {ref.dtype}{list(ref.shape)}; "
                "reallocate for a new system.")
        capacity = neighbors.cell_list_capacity
        if not isinstance(capacity, Capacity):
            raise TypeError("neighbors was not allocated by jaxrt; use the "
                            "update of the factory that allocated it.")
        given_radii = radii is not None
        if given_radii:
            _check_radii_backend(self.searcher)
            radii = _radii_array(radii, "update")
            if radii.shape[0] != position.shape[0]:
                raise ValueError(
                    f"update: radii has {radii.shape[0]} entries but position "
                    f"has {position.shape[0]} particles.")
        else:
            radii = self.settings.radii
        if (radii is not None) != capacity.radii:
            raise ValueError(
                "the list was allocated " + ("with" if capacity.radii else
                                             "without") + " per-particle radii"
                " but update got " + ("none" if capacity.radii else "radii") +
                ": pass radii= to both, or give them to neighbor_list once.")
        stateful = _backend.is_stateful(self.searcher)
        if stateful != isinstance(neighbors, StatefulNeighborList):
            raise TypeError(
                f"neighbors {'lacks' if stateful else 'carries'} the state "
                f"of backend={self.searcher.name!r}; use the update of the "
                "factory that allocated it.")
        return (position, capacity, self.program(position.shape[1], kwargs),
                radii, given_radii)

    def program(self, dim: int, kwargs: dict) -> _Program:
        """The `_Program` of positions of dimension ``dim``."""
        if dim not in self.programs:
            setup = self.setup(dim, kwargs)
            self.programs[dim] = _Program(
                searcher=self.searcher, build=self.build,
                metric_fn=setup.metric_fn, grid=setup.grid, query=setup.query,
                r_cutoff=self.settings.r_cutoff,
                dr_threshold=self.settings.dr_threshold,
                box_limit=_box_limit(self.searcher, self.settings.cutoff),
                checks_metric=self.checks_metric,
                stateful=_backend.is_stateful(self.searcher))
        return self.programs[dim]


# Eager updates of lists of up to this many particles on a CPU run a
# program compiled for compile speed (`_Lists.eager_program`).
_QUICK_EAGER_MAX_N = 4096


def _geometry(grid: _space.Space, h, dtype, slack: float, reach=None
              ) -> Geometry:
    """The backends' `Geometry` from the heights ``h`` (float ``(dim,)``,
    `jaxrt.lists.metric.heights`); traceable. With ``slack`` (the metric decides
    every pair) the grid's distances shrink by that fraction, so that it
    still holds every neighbour of a metric up to that much shorter than
    its model. ``reach``: None or float ``(N,)`` (`Geometry.reach`)."""
    # Eager (allocate's concrete heights) on the host: no program compiled.
    xp = jnp if isinstance(h, jax.core.Tracer) else np
    h = xp.asarray(h)
    grid_h = h * h.dtype.type(1.0 - slack) if slack else h
    transform = (None if grid.transform is None
                 else jnp.asarray(grid.transform, dtype))
    side = xp.asarray(grid.period, dtype) * grid_h
    if xp is np:  # to the device as they are: no program compiled
        side, grid_h = jax.device_put(side), jax.device_put(grid_h)
    return Geometry(side=side, scale=grid_h, transform=transform, reach=reach)


def _check_unknown_keywords(unknown: dict) -> None:
    """jax-md's ``neighbor_list`` takes ``**static_kwargs`` and ignores them
    (user code passes ``cell_size=``, ``t=``): warn, naming them. A near
    miss of a real argument is a typo, which must not pass silently."""
    if not unknown:
        return
    for name in unknown:
        close = difflib.get_close_matches(name, _ARGUMENTS, n=1, cutoff=0.8)
        if close:
            raise TypeError(
                f"neighbor_list() got an unexpected keyword argument {name!r};"
                f" did you mean {close[0]!r}?")
    warnings.warn(
        f"neighbor_list() ignores the keyword argument(s) {sorted(unknown)}, "
        "as jax-md's neighbor_list does (its **static_kwargs); jaxrt accepts "
        f"{', '.join(_ARGUMENTS)}.", stacklevel=3)


def _lists_small_boxes(backend) -> bool:
    """Whether ``backend`` lists periodic boxes less than twice the cutoff
    across (its ``small_boxes`` capability, `jaxrt.backends.Backend`)."""
    return capabilities(backend).small_boxes


def _check_cutoff(cutoff: float, grid: _space.Space, height: np.ndarray,
                  backend) -> str | None:
    """A cutoff of half a periodic height or more (a small box): the
    warning's text (`SmallBoxWarning`) where ``backend`` lists such boxes
    (`_lists_small_boxes`), else raise; None where the box is not small.

    In a small box an index-only list holds each pair once, through the
    image the caller's displacement picks, which is jax-md's list; the
    other images within the cutoff interact too but are in no such list.
    ``height``: float64 ``(dim,)`` per unit grid step (`_space.heights`).
    """
    span = grid.period * height
    small = [a for a, p in enumerate(grid.periodic)
             if p and not bool(_space.cutoff_fits(cutoff, span[a]))]
    if not small:
        return None
    a = small[0]
    where = (f"r_cutoff + dr_threshold = {cutoff:g} is not below half the "
             f"periodic box's height on axis {a} (L/2 = {span[a] / 2:g})")
    if not _lists_small_boxes(backend):
        raise ValueError(
            f"{where}, which backend={backend.name!r} needs (its search "
            "assumes at most one image of a pair within the cutoff). Use "
            "backend='cell' or backend='brute', which list each pair once "
            "through the image displacement_or_metric picks (jax-md's "
            "list), a larger box (replicate the cell), or a smaller "
            "r_cutoff / dr_threshold.")
    return (f"{where}: the list holds each pair once, through the image "
            "displacement_or_metric picks (as jax-md's does); other periodic "
            "images of a pair within the cutoff are not in a neighbour list, "
            "although they interact too. jaxrt.pairs lists every image, "
            "with its lattice shift.")


def _box_limit(backend, cutoff: float) -> float:
    """The cutoff below half of which a periodic box passed to ``update``
    must stay (else `ErrorCode.BOX_TOO_SMALL`): the list's where
    ``backend`` refuses small boxes; 0 where it lists any box (only a box
    of no height, or a non-finite one, is then flagged)."""
    return 0.0 if _lists_small_boxes(backend) else cutoff


def _shorter_metric_error(position, metric, g, grid, i, j, dev, box
                          ) -> ValueError:
    k = int(np.argmin(dev))
    a, b = int(i[k]), int(j[k])
    with jax.ensure_compile_time_eval():
        pos = jnp.asarray(position)
        m = float(np.sqrt(metric(pos[a], pos[b])))
        q = grid.to_grid(pos)
        d = float(np.sqrt(_space.model_sq(q[a], q[b], g, grid)))
    free = [ax for ax, p in enumerate(grid.periodic) if not p]
    hint = (f" Axes {free} are treated as free space: a periodic displacement"
            " needs box= (the L of space.periodic(L)) so that jaxrt knows it."
            if free and box is None else
            " Check that box is the one the displacement was made with.")
    return ValueError(
        f"displacement_or_metric puts particles {a} and {b} {m:.6g} apart, "
        f"closer than the {d:.6g} that box and periodicity imply "
        f"(periodic={list(grid.periodic)}), so a grid search would miss "
        f"pairs.{hint} A metric that shortens distances in other ways can "
        "only be searched by backend='brute'.")


def _largest_buffer(backend, n: int, capacity: Capacity, query: Query
                    ) -> tuple[str, int]:
    """The name and int32 entries of the largest list buffer a build with
    ``capacity`` writes."""
    entries = {"idx": n * capacity.neighbors if query.format is Dense
               else 2 * capacity.neighbors}
    rows_first = query.format is Dense or not capabilities(
        backend).sparse_without_rows
    if "row" in dict(capacity.internal) and rows_first:
        entries["rows before conversion"] = n * capacity["row"]
    return max(entries.items(), key=lambda kv: kv[1])


def _check_list_size(backend, n: int, capacity: Capacity, query: Query) -> None:
    """Refuse lists larger than the backend can index (never a crash or a
    silently wrapped index): int32 indices address at most 2**31 - 1
    entries, and Warp kernels compute byte offsets in 32-bit ints."""
    limit = _backend.max_list_entries(backend)
    name, largest = _largest_buffer(backend, n, capacity, query)
    if largest > limit:
        raise _backend.list_too_large(backend.name, largest, name, n, limit)


def _compiled_capacity(backend, n: int, capacity: Capacity, query: Query,
                       sizes: dict[str, int], limit: int) -> Capacity:
    """The sizes ``allocate``'s build is compiled for: ``capacity``'s, each
    an eighth larger rounded up by `_backend.compile_size` (at most 1.7x;
    those within N staying within N; counts in ``fixed_sizes`` as they
    are), so that data of one N whose exact sizes differ a little reuse
    one compiled build (`_reused_capacity`); ``allocate`` then trims the
    list to ``capacity`` (`_trimmed`), which gives the list built with
    ``capacity`` itself since every buffer holds what ``sizes`` (measured)
    says it must.

    ``capacity`` itself where a buffer does not (``capacity_multiplier``
    below 1: that build truncates, and flags, as jax-md's does), for a
    stateful backend (its state may be shaped by the sizes) or one that
    asks for it (``build_at_exact_capacity``), or where the rounded list
    would pass ``limit`` int32 entries or what the backend can index."""
    fixed = capabilities(backend).fixed_sizes
    needed = {k: v for k, v in sizes.items()
              if k not in ("row", "edges", "row_before_mask")}
    needed["row"] = sizes.get("row_before_mask", sizes["row"])
    occupancy = sizes["row"] if query.format is Dense else sizes["edges"]
    short = capacity.neighbors < occupancy or any(
        capacity[k] < v for k, v in needed.items()
        if k not in fixed and k in dict(capacity.internal))
    if (short or _backend.is_stateful(backend)
            or capabilities(backend).build_at_exact_capacity):
        return capacity

    def up(size):  # an eighth more first: the next structure's may be larger
        return _backend.compile_size(size + size // 8)

    def rounded(name, size):
        if name in fixed:
            return size
        return min(up(size), n) if size <= n else up(size)

    neighbors = rounded("neighbors", capacity.neighbors) if (
        query.format is Dense) else up(capacity.neighbors)
    internal = tuple((k, rounded(k, v)) for k, v in capacity.internal)
    wider = dataclasses.replace(capacity, neighbors=neighbors,
                                internal=internal)
    _, largest = _largest_buffer(backend, n, wider, query)
    # The cell kernel's int32 offsets also span N x its shell buffer.
    largest = max(largest, n * dict(internal).get("shell", 0))
    return wider if largest <= min(limit, _backend.max_list_entries(
        backend)) else capacity


# The largest list (int32 entries, 256 MiB) built wider and trimmed at
# allocate where the device does not report its free memory: the wide list
# and its trimmed copy live together for a moment, which for lists of
# gigabytes could run out of memory where the exact build fits; larger
# lists build at their exact sizes (a compile per size).
_ROUNDED_LIST_ENTRIES = 2 ** 26
# Where it does (GPUs), the wide list may take up to this share of the
# free memory: with its trimmed copy (no larger) at most twice that.
_ROUNDED_SHARE_OF_FREE_MEMORY = 1 / 8


def _rounded_list_limit(position) -> int:
    """int32 entries up to which ``allocate`` builds a list wider and trims
    it: `_ROUNDED_LIST_ENTRIES`, or more on a device that reports its free
    memory (`_ROUNDED_SHARE_OF_FREE_MEMORY` of it), so that a GPU with
    room to spare reuses compiled builds for lists of millions of
    particles instead of compiling one per exact size."""
    stats = _memory_stats(position)
    if not stats or "bytes_limit" not in stats:
        return _ROUNDED_LIST_ENTRIES
    free = stats["bytes_limit"] - stats.get("bytes_in_use", 0)
    share = int(free * _ROUNDED_SHARE_OF_FREE_MEMORY) // 4
    return max(_ROUNDED_LIST_ENTRIES, share)


def _memory_stats(position) -> dict | None:
    """The memory statistics of ``position``'s device (None on CPUs, and
    for arrays on several devices, where no one device's figure holds)."""
    devices = getattr(position, "devices", None)
    devices = devices() if devices is not None else {jax.devices()[0]}
    if len(devices) != 1:
        return None
    return next(iter(devices)).memory_stats()


# Compiled capacities remembered per (N, dtype, query), newest kept.
_COMPILED_KEPT = 8


def _reused_capacity(built: Sequence[Capacity], capacity: Capacity,
                     fixed: Sequence[str] = ()) -> Capacity | None:
    """The newest of ``built`` that holds ``capacity``: the same options and
    buffer names, fixed counts equal, and every size at least
    ``capacity``'s and at most twice it (a compiled build is reused, but
    never one much larger than the list needs); None if none does.

    Rounding alone (`_compiled_capacity`) puts sizes just either side of a
    rounding step into two programs; this reuses the first for the
    second."""
    def options(c):
        return dataclasses.replace(c, neighbors=0, internal=tuple(
            (k, v if k in fixed else 0) for k, v in c.internal))

    def holds(have: int, need: int) -> bool:
        return need <= have <= 2 * max(need, 4)

    need = dict(capacity.internal)
    for c in reversed(built):
        if options(c) != options(capacity):
            continue
        if holds(c.neighbors, capacity.neighbors) and all(
                holds(v, need[k]) for k, v in c.internal if k not in fixed):
            return c
    return None


@functools.partial(jax.jit, static_argnames=("width", "n"))
def _trimmed(idx, overflow, *, width: int, n: int):
    """``idx`` (int32 ``(N, M)`` Dense or ``(2, M)`` Sparse, padded with
    ``n``, valid entries first) cut to ``width`` along its last axis, and
    ``overflow`` set if a valid entry was cut: the list built with
    ``width`` itself."""
    return idx[..., :width], overflow | jnp.any(idx[..., width:] < n)


# ``"auto"`` on a CPU searches lists of up to this many particles with
# ``"brute"`` (`jaxrt.backends.BySize`): its program compiles in a fraction
# of the cell list's time (most of a first ``allocate``), and up to about
# this N it rebuilds as fast (all pairs grow as N**2: 8x slower at N = 1000).
_BRUTE_MAX_N_CPU = 256


def _auto_backend(*, has_radii: bool = False) -> str:
    """``backend="auto"`` here: `choose_backend` for JAX's default device.
    Whether Warp loads is asked (which imports it) only where the rule
    could pick a ray-traced backend."""
    platform = jax.default_backend()
    warp = has_radii and platform == "cpu" and "bvh" in backends.available()
    return choose_backend(platform=platform, has_radii=has_radii, warp=warp)


def choose_backend(*, platform: str, has_radii: bool = False,
                   warp: bool = True) -> str:
    """The backend ``backend="auto"`` picks, from the measured tables
    (docs/benchmarks.md; the reasons in docs/guide.md, "Which backend
    auto picks").

    The rule:

    * per-particle radii given to `neighbor_list` (``radii=``), on a CPU,
      with Warp installed: ``"bvh"``, much faster there than the cell
      list's radius classes on seed 003's radii;
    * everything else: ``"cell"``. On the GPU `cell`'s kernel is the
      fastest in every table (rebuilds, the sphere surface, the LJ step,
      radii). On the CPU without radii, `cell` is close to `bvh` for an
      LJ step and faster for an SPH step, and it needs no Warp.
      `delaunay` (2D) was slower than `cell` in every case measured, and
      `spheres` / `squares` slower than `bvh` in every seed-study
      configuration, so neither is ever chosen; nor is ``"brute"`` here
      (small lists on a CPU reach it through `BySize`, below).

    Dimension does not enter: no table shows a different winner for 2D.
    On a CPU the caller wraps a ``"cell"`` choice in `jaxrt.backends.BySize`,
    which searches lists of at most ``_BRUTE_MAX_N_CPU`` particles with
    ``"brute"`` (all pairs: a smaller program to compile at ``allocate``).
    Args: ``platform``: ``jax.default_backend()`` (``"cpu"``,
    ``"gpu"``/``"cuda"``, ``"tpu"``); ``has_radii``: radii given at
    construction; ``warp``: Warp's backends are installed.
    """
    if has_radii and platform == "cpu" and warp:
        return "bvh"
    return "cell"


# ---------------------------------------------------------------------------
# The front's reading of the caller's space, by public-internal names, for
# the list-free energies (`jaxrt.energy.listfree`), which take the same
# arguments.

grid_space = _grid_space
probe_axes = _probe_axes
infer_periodic = _infer_periodic
undetermined_error = _undetermined_error
metric_sq_fn = _metric_sq_fn
normalise_periodic = _normalise_periodic
