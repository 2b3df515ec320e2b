"""Pairs with lattice shifts: ``jaxrt.pairs``, for graphs of machine-learned
potentials in any cell, under ``jit``, ``vmap`` and ``grad``.

jax-md's lists (and `jaxrt.neighbor_list`) carry indices only, so they can
hold one image of each pair: a cutoff past half the cell's height must be
refused. Here every pair is ``(i, j, S)`` with the integer lattice shift
``S`` (ASE's convention)::

    d_ij = R[j] - R[i] + S @ cell          (cell: lattice vectors as rows)

so a two-atom silicon cell with a 5 Å cutoff lists every image of every atom
within the cutoff. The list is full, ``(i, j, S)`` and ``(j, i, -S)``, or
half (``half=True``: each unordered pair once, as ``i < j``, or ``i == j``
with ``S`` lexicographically positive). Self pairs ``(i, i, 0)`` are left
out unless ``self_interaction=True``; ``(i, i, S != 0)`` are pairs. Each
pair is decided as ASE decides it, ``|d_ij| < cutoff`` in the positions'
dtype, so in float64 the sets are ASE's. The search itself (one jitted
program, a cell grid in fractional coordinates or a brute force over every
image) is `jaxrt.pairs.program`'s.

What is static: ``pbc``, ``capacity``, ``max_shift`` (the reach) and the
cutoff's largest value as a Python float (it sets the reach; inside the
program it is traced, so one compiled program serves every cutoff).
Outside ``jit`` (a concrete cell) ``max_shift`` is computed from the cell,
and ``capacity=None`` sizes the list exactly. Eager calls round the atom
count and the capacity up to shared buckets (1, 2, 3, 4, 6, 8, 12, 16, 24,
...), padding with masked atoms, so that a data set of many sizes compiles a
few programs, and each call is one compiled program and one transfer back
(a second when the estimated capacity was short); a system of a few atoms
is searched on the host, in numpy, with no program at all. Under ``jit`` /
``vmap`` pass ``capacity`` and ``max_shift`` (`pairs_sizes` measures them
on a data set); anything that leaves the list incomplete (more pairs than
``capacity``, a cell that needs more shifts than ``max_shift``, a
non-finite position, a singular cell) sets ``overflow`` and a bit of
``error``; `Pairs.check` raises on it, and an eager call raises at once.
"""
from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxrt.layouts.edges import materialized
from jaxrt.pairs import checks
from jaxrt.pairs.bits import ErrorBit, PairsError, raise_if
from jaxrt.pairs.checks import BRUTE_CANDIDATES, Float32Warning
from jaxrt.pairs.cells import safe_norm as _safe_norm, shift_vectors
from jaxrt.pairs.host import search_small_host
from jaxrt.pairs.program import search

__all__ = ["BRUTE_CANDIDATES", "ErrorBit", "Float32Warning", "PairSizes",
           "Pairs", "PairsError", "pairs", "pairs_sizes"]


@functools.partial(jax.tree_util.register_dataclass,
                   data_fields=["i", "j", "shift", "count", "overflow",
                                "error"], meta_fields=[])
@dataclasses.dataclass(frozen=True)
class Pairs:
    """A pair list with lattice shifts (a pytree: jit/vmap-able).

    Attributes (a batch of systems adds leading axes to each):
      i, j: int32 ``(capacity,)``; entries past ``count`` are N (the number
        of atoms, padded atoms included).
      shift: int32 ``(capacity, 3)``, ``S`` with ``d = R[j] - R[i] + S @
        cell`` (zero where padded).
      count: int32 scalar, the exact number of pairs (more than ``capacity``
        when the list overflowed).
      overflow: bool scalar, the list is incomplete (`error` says why).
      error: int32 scalar, `ErrorBit` bits, 0 for a complete list.

    Entries are in the search's order (not specified), or sorted by ``i``
    (``sort="i"``, stable: then ``jax.ops.segment_sum(...,
    indices_are_sorted=True)`` over ``i`` is valid, padding included).
    """

    i: jax.Array
    j: jax.Array
    shift: jax.Array
    count: jax.Array
    overflow: jax.Array
    error: jax.Array

    @property
    def capacity(self) -> int:
        return self.i.shape[-1]

    @property
    def valid(self):
        """bool ``(capacity,)``: which entries are pairs."""
        return jnp.arange(self.capacity) < self.count[..., None]

    def vectors(self, positions, cell=None):
        """float ``(capacity, 3)`` ``R[j] - R[i] + S @ cell`` in the
        positions' dtype, zero where padded; differentiable in ``positions``
        (float ``(N, 3)``) and ``cell`` (stress through the cell). One
        system: call it inside ``vmap`` for a batch. ``cell`` is needed
        wherever the list has shifts (raised outside ``jit``)."""
        return _vectors(self, *_arrays(self, positions, cell))

    def distances(self, positions, cell=None):
        """float ``(capacity,)`` ``|d_ij|``, zero where padded, with a finite
        (zero) gradient where ``d = 0`` (padding, coincident atoms)."""
        return _distances(self, *_arrays(self, positions, cell))

    def shift_vectors(self, cell):
        """float ``(capacity, 3)``: the Cartesian shifts ``S @ cell`` in the
        cell's dtype (zero where padded), differentiable in ``cell``."""
        cell = _cell_array(cell, None)
        return _cartesian(self.shift, checks.as_cell_matrix(cell))

    def check(self) -> "Pairs":
        """Raise `PairsError` if the list (or any list of a batch) is
        incomplete; host-side, so call it outside ``jit``. Returns self."""
        raise_if(ErrorBit.of(self.error), self.count, self.capacity)
        return self


def _cell_array(cell, dtype):
    """A JAX array of a cell given as anything array-like (an ASE ``Cell``
    included: converted by numpy first, whatever the dtype)."""
    if not isinstance(cell, jax.Array):
        cell = checks.plain(cell)
    return jnp.asarray(cell, dtype)


def _arrays(result: Pairs, positions, cell):
    """JAX arrays of the helpers' arguments, the cell in the positions'
    dtype."""
    if not isinstance(positions, jax.Array):
        positions = np.asarray(positions)
    positions = jnp.asarray(positions)
    if cell is None and checks.is_concrete(result.shift) and np.any(
            np.asarray(result.shift)):
        raise ValueError("Pairs.vectors / distances: the list has lattice "
                         "shifts, so pass the cell (cell=) they refer to.")
    return positions, (None if cell is None else
                       _cell_array(cell, positions.dtype))


@jax.jit
def _cartesian(shift, h):
    return shift_vectors(shift.astype(h.dtype), h)


# Jitted: called eagerly, op by op, each small op would compile on its own.
@jax.jit
def _vectors(result: Pairs, positions, cell):
    n = positions.shape[-2]
    valid = result.i < n
    ii = jnp.minimum(result.i, n - 1)
    jj = jnp.minimum(result.j, n - 1)
    # The gathered ends written out, so that reverse mode's scatters do not
    # fuse the gathers (jaxrt.layouts.edges).
    to, start = materialized((positions[jj], positions[ii]))
    d = to - start
    if cell is not None:
        d = d + shift_vectors(result.shift.astype(positions.dtype),
                              checks.as_cell_matrix(cell))
    return jnp.where(valid[..., None], d, 0)


@jax.jit
def _distances(result: Pairs, positions, cell):
    return _safe_norm(_vectors(result, positions, cell))


# ---------------------------------------------------------------------------
# The front: arguments checked, static sizes decided


@dataclasses.dataclass(frozen=True)
class PairSizes:
    """Static sizes for `pairs` under ``jit``: pass as ``**sizes.kwargs``.

    Attributes:
      capacity: the most pairs of any system measured.
      max_shift: per axis, the stencil reach the cells need (0 on free axes).
      max_nodes: flat batches (`jaxrt.pairs_batch_sizes`) only: the most
        atoms of one system, where its systems are small enough to be
        searched as dense blocks; 0 where cells are faster; None (single
        systems): not passed.
    """

    capacity: int
    max_shift: tuple[int, int, int]
    max_nodes: int | None = None

    @property
    def kwargs(self) -> dict:
        out = {"capacity": self.capacity, "max_shift": self.max_shift}
        if self.max_nodes is not None:
            out["max_nodes"] = self.max_nodes
        return out

    def merge(self, other: "PairSizes") -> "PairSizes":
        """Sizes that fit both (the larger of each; dense blocks only where
        both have them and the larger still suits them)."""
        shift = tuple(max(a, b) for a, b in zip(self.max_shift,
                                                 other.max_shift))
        nodes = None
        if self.max_nodes is not None or other.max_nodes is not None:
            a, b = self.max_nodes or 0, other.max_nodes or 0
            nodes = checks.dense_nodes(max(a, b), shift) if a and b else 0
        return PairSizes(max(self.capacity, other.capacity), shift, nodes)


def _inputs(positions, cutoff, cell, pbc, mask, species, traced_ok=False):
    """Checked arguments: positions, (radius, cut, species), pbc, mask.
    ``positions`` may have leading batch axes."""
    positions = checks.positions_array(positions, "jaxrt.pairs")
    pbc = checks.check_pbc(pbc, cell is not None)
    radius, cut, species = checks.cutoffs(
        cutoff, species, positions.shape[-2], traced_ok, "jaxrt.pairs") \
        if positions.ndim == 2 or species is None else _batch_cutoffs(
            cutoff, species, positions.shape[:-1])
    if mask is not None:
        if np.shape(mask) != positions.shape[:-1] or not jnp.issubdtype(
                jnp.asarray(mask).dtype, jnp.bool_):
            raise ValueError(f"jaxrt.pairs: mask must be bool with shape "
                             f"{positions.shape[:-1]} (True for the real "
                             f"atoms), got {jnp.asarray(mask).dtype} "
                             f"{np.shape(mask)}.")
        if checks.is_concrete(mask):
            mask = np.asarray(mask)
    return positions, (radius, cut, species), pbc, mask


def _batch_cutoffs(cutoff, species, shape):
    """`checks.cutoffs` for species of a batch ``(..., N)``."""
    flat = np.asarray(species).reshape(-1)
    radius, cut, flat = checks.cutoffs(cutoff, flat, flat.shape[0], False,
                                       "jaxrt.pairs_sizes")
    return radius, cut, flat.reshape(shape)


def _reach(max_shift, pbc, concrete_cell, radius):
    if max_shift is not None:
        return checks.check_max_shift(max_shift, pbc)
    if not any(pbc):
        return (0, 0, 0)  # free space: no shifts, any cell
    if concrete_cell is None:
        raise ValueError(
            "jaxrt.pairs: the cell is traced, so the lattice shifts the "
            "search must reach are not known: pass max_shift= (an int or "
            "three; jaxrt.pairs_sizes(...) measures it with capacity).")
    return checks.shift_for_cell(concrete_cell, radius, pbc)


def pairs(positions, cutoff, *, cell=None, pbc=None, capacity=None, mask=None,
          max_shift=None, backend: str = "auto", species=None,
          half: bool = False, sort=None,
          self_interaction: bool = False) -> Pairs:
    """Every pair ``(i, j, S)`` with ``|R[j] - R[i] + S @ cell| < cutoff``.

    Args:
      positions: float ``(N, 3)`` Cartesian positions (anywhere: atoms
        outside the cell on periodic axes are found as they are, and their
        shifts refer to the positions given, as ASE's do). The search and
        the decisions run in this dtype (float64 numpy input with JAX's x64
        off is searched in float32, with a `Float32Warning`).
      cutoff: Python float > 0 (strict ``<``, as ASE); or cutoffs by
        species, with ``species=``: ASE's dict ``{(a, b): rc}`` (both
        orders; pairs of species not listed are never neighbours) or a
        symmetric ``(S, S)`` matrix. May be traced (a float scalar or a
        matrix) where ``capacity`` and ``max_shift`` are given.
      cell: ``(3, 3)`` lattice vectors as rows (ASE's convention), ``(3,)``
        sides of an orthorhombic cell, or None for free space. May be traced
        (then pass ``max_shift``). Zero rows on free axes are completed as
        ASE completes them, under ``jit`` too.
      pbc: per axis, or one bool; None: all periodic with a cell, all free
        without. A slab is ``(True, True, False)``.
      capacity: static int, the length of the arrays; None (outside ``jit``
        only): sized exactly, the arrays hold ``count`` pairs.
      mask: bool ``(N,)``, the real atoms of a padded system (``vmap`` over
        a batch); padded atoms have no pairs.
      max_shift: static int or three: per periodic axis, the largest lattice
        shift between wrapped atoms the search reaches, ``ceil(cutoff /
        height)`` (1 for any cell taller than the cutoff; values below 1
        on periodic axes count as 1, free axes are ignored). None: from a
        concrete cell; required with a traced one (`pairs_sizes`). A larger
        value is correct, only slower.
      backend: ``"auto"``, ``"brute"`` or ``"cell"`` (`jaxrt.pairs.program`).
      species: int ``(N,)``, each atom's row of the cutoff matrix (atomic
        numbers for a dict keyed by them); needed by cutoffs by species.
      half: each unordered pair once (module docstring's representative).
      sort: None (search order) or ``"i"`` (sorted by ``i``, stable).
      self_interaction: add ``(i, i, 0)`` for every real atom (ASE's
        option; with cutoffs by species, where the atom's own is > 0).

    Returns:
      `Pairs`: of numpy arrays from an eager call (concrete inputs: the
      host cut them to size), of JAX arrays under ``jit`` / ``vmap``.
      Outside ``jit`` an incomplete list raises `PairsError`; under ``jit``
      its ``overflow`` is set (``check()`` raises).
    """
    traced_ok = capacity is not None and max_shift is not None
    positions, (radius, cut, species), pbc, mask = _inputs(
        positions, cutoff, cell, pbc, mask, species, traced_ok)
    if positions.ndim != 2:
        raise ValueError(f"jaxrt.pairs: positions must be (N, 3) for one "
                         f"system, got {positions.shape}; jax.vmap over a "
                         f"batch (with mask= for padded atoms), or "
                         f"jaxrt.pairs_batch for a flat batch.")
    capacity = checks.check_capacity(capacity)
    options = dict(half=bool(half), sort=checks.check_sort(sort),
                   self_interaction=bool(self_interaction))
    h, concrete_cell = checks.check_cell(cell, pbc, positions.dtype)
    shift = _reach(max_shift, pbc, concrete_cell, radius)
    n = positions.shape[0]
    eager = all(checks.is_concrete(x) for x in (positions, mask, cut,
                                                  species)) and \
        concrete_cell is not None
    if n == 0:
        return _empty(capacity or 0)
    if eager:
        positions = np.asarray(positions)
        return _eager(positions, h, mask, cut, species, radius, pbc, shift,
                      backend, capacity, concrete_cell, options)
    if capacity is None:
        raise ValueError(
            "jaxrt.pairs: capacity=None needs concrete inputs (it counts "
            "the pairs first); under jax.jit or jax.vmap pass capacity= "
            "(a static int, e.g. jaxrt.pairs_sizes(...).capacity).")
    brute, reach, chunk = checks.plan(n, pbc, shift, backend)
    mask = jnp.ones((n,), bool) if mask is None else mask
    out, total, _, error = search(
        positions, jnp.zeros((n,), jnp.int32), mask, h[None],
        np.array(pbc)[None], cut, species, n, periodic=pbc, reach=reach,
        capacity=capacity, brute=brute, chunk=chunk, n_graph=1, **options)
    return _result(out, total, error)


def _empty(capacity: int) -> Pairs:
    zero = jnp.zeros((), jnp.int32)
    return _result(jnp.zeros((capacity, 5), jnp.int32), zero, zero)


def _result(out, total, error) -> Pairs:
    return Pairs(i=out[..., 0], j=out[..., 1], shift=out[..., 2:],
                 count=total, overflow=error != 0, error=error)


def _eager(positions, h, mask, cut, species, radius, pbc, shift, backend,
           capacity, concrete_cell, options) -> Pairs:
    """An eager call: the atoms padded to a bucket (masked), the capacity
    a bucket above an estimate (again with the count's when short), the
    arrays cut to the count on the host."""
    n = positions.shape[0]
    size = checks.bucket(n)
    real = np.ones((n,), bool) if mask is None else mask
    if size > n:
        positions = np.concatenate([positions, np.zeros(
            (size - n, 3), positions.dtype)])
        real = np.concatenate([real, np.zeros((size - n,), bool)])
        if species is not None:
            species = np.concatenate([species, np.zeros((size - n,),
                                                        np.int32)])
    brute, reach, chunk = checks.plan(size, pbc, shift, backend)
    if brute and checks.is_small(size, shift):
        return _eager_small(positions, real, h, concrete_cell, cut, species,
                            pbc, shift, capacity, n, options)
    call = functools.partial(
        search, positions, np.zeros((size,), np.int32), real, h[None],
        np.array(pbc)[None], cut, species, np.int32(n), periodic=pbc,
        reach=reach, brute=brute, chunk=chunk, n_graph=1, completed=True,
        **options)
    if capacity is not None:
        out, total, _, error = jax.device_get(call(capacity=capacity))
        raise_if(int(error), total, capacity)
        return _host_result(out, total, error)
    guess = _guess(positions[:n][real[:n]], concrete_cell, pbc, radius,
                   options, size)
    out, total, _, error = jax.device_get(call(capacity=guess))
    raise_if(int(error) & ~int(ErrorBit.CAPACITY))
    count = int(total)
    if count > guess:
        out, total, _, error = jax.device_get(
            call(capacity=checks.bucket(count)))
    return _host_result(out[:count], total, np.int32(
        int(error) & ~int(ErrorBit.CAPACITY)))


def _eager_small(positions, real, h, concrete_cell, cut, species, pbc,
                 shift, capacity, n, options) -> Pairs:
    """`_eager` for a small system: `search_small_host` (numpy: no
    program to dispatch), on the caller's ``n`` atoms."""
    hinv = checks.inverse3(concrete_cell)[0].astype(positions.dtype)
    rows, error = search_small_host(
        positions[:n], real[:n], np.asarray(h, positions.dtype), hinv,
        np.asarray(cut), None if species is None else species[:n],
        periodic=pbc, reach=shift, half=options["half"],
        self_interaction=options["self_interaction"])
    total = len(rows)
    if capacity is None:
        raise_if(error)
        return _host_result(rows, total, 0)
    if total > capacity:
        error |= int(ErrorBit.CAPACITY)
    raise_if(error, total, capacity)
    out = np.empty((capacity, 5), np.int32)
    out[:total], out[total:] = rows, [n, n, 0, 0, 0]
    return _host_result(out, total, error)


def _guess(r, cell, pbc, radius, options, size: int) -> int:
    """A capacity bucket above the pairs expected of ``size`` atoms at the
    density of ``r`` (so that the systems of one atom bucket and density
    share it)."""
    full = checks.estimate(np.asarray(r, np.float64), cell, pbc, radius)
    expected = (full + 1) // 2 if options["half"] else full
    if options["self_interaction"]:
        expected += len(r)
    return checks.bucket(expected * size / max(len(r), 1))


def _host_result(out, total, error) -> Pairs:
    """`Pairs` of numpy arrays (where the eager call cut them: moving them
    back to the device would cost more than the search of a small
    system; ``jit`` and ``jnp`` take them as they are)."""
    error = np.array(error, np.int32)
    return Pairs(i=np.ascontiguousarray(out[:, 0]),
                 j=np.ascontiguousarray(out[:, 1]),
                 shift=np.ascontiguousarray(out[:, 2:]),
                 count=np.array(total, np.int32), overflow=error != 0,
                 error=error)


def pairs_sizes(positions, cutoff, *, cell=None, pbc=None, mask=None,
                backend: str = "auto", species=None, half: bool = False,
                self_interaction: bool = False) -> PairSizes:
    """Eager: the static sizes `pairs` needs under ``jit`` for every system
    of a batch: the most pairs of one system and the largest stencil reach.

    Args:
      positions: float ``(..., N, 3)``, any leading batch axes.
      cell: None, ``(3,)``, ``(3, 3)``, or one per system ``(..., 3)`` /
        ``(..., 3, 3)``.
      mask: bool ``(..., N)`` or None; species: int ``(..., N)`` or None.
      half, self_interaction: as `pairs` (they change the count).
    Returns:
      `PairSizes` (add a margin to ``capacity`` for systems not measured).
    """
    positions, (radius, cut, species), pbc, mask = _inputs(
        positions, cutoff, cell, pbc, mask, species)
    batch = positions.shape[:-2]
    n = positions.shape[-2]
    r = np.asarray(positions).reshape((-1, n, 3))
    m = np.ones(r.shape[:2], bool) if mask is None else \
        np.asarray(mask).reshape((-1, n))
    sp = None if species is None else species.reshape((-1, n))
    cells = _per_system_cells(cell, batch)
    if cells is None:
        mats, shift = np.broadcast_to(np.eye(3), (len(r), 3, 3)), (0, 0, 0)
    else:
        mats = np.stack([checks.concrete_cell(c, pbc) for c in cells])
        shift = checks.shift_for_cell(mats, radius, pbc) if any(pbc) \
            else (0, 0, 0)
    brute, reach, chunk = checks.plan(n, pbc, shift, backend)
    count = jax.vmap(functools.partial(
        search, periodic=pbc, reach=reach, capacity=0, brute=brute,
        chunk=chunk, half=bool(half), sort=False,
        self_interaction=bool(self_interaction), n_graph=1),
        in_axes=(0, None, 0, 0, None, None, None if sp is None else 0,
                 None))
    _, total, _, error = count(
        r, np.zeros((n,), np.int32), m, mats[:, None].astype(r.dtype),
        np.array(pbc)[None], cut, sp, n)
    raise_if(ErrorBit.of(error) & ~int(ErrorBit.CAPACITY))
    return PairSizes(capacity=int(np.max(np.asarray(total), initial=0)),
                     max_shift=shift)


def _per_system_cells(cell, batch):
    """float64 ``(B, 3, 3)`` from one cell or one per system (matrices or
    sides); None stays None."""
    if cell is None:
        return None
    c = checks.plain(cell).astype(np.float64)
    # Sides, one vector or one per system; a (3, 3) array is one matrix.
    if c.shape != (3, 3) and c.shape in ((3,), batch + (3,)):
        c = checks.as_cell_matrix(c)
    if c.shape not in ((3, 3), batch + (3, 3)):
        raise ValueError(f"jaxrt.pairs_sizes: cell must be one cell ((3, 3) "
                         f"or (3,)) or one per system ({batch + (3, 3)} or "
                         f"{batch + (3,)}), got shape {c.shape}.")
    return np.broadcast_to(c, batch + (3, 3)).reshape(-1, 3, 3)
