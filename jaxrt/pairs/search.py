"""Pairs with lattice shifts: ``jaxrt.pairs``, for graphs of machine-learned
potentials in any cell, under ``jit``, ``vmap`` and ``grad``.

jax-md's lists (and `jaxrt.neighbor_list`) carry indices only, so they can
hold one image of each pair: a cutoff past half the cell's height must be
refused. Here every pair is ``(i, j, S)`` with the integer lattice shift
``S`` (ASE's convention)::

    d_ij = R[j] - R[i] + S @ cell          (cell: lattice vectors as rows)

so a two-atom silicon cell with a 5 Å cutoff lists every image of every atom
within the cutoff, and the list is full: ``(i, j, S)`` and ``(j, i, -S)``.
Self pairs ``(i, i, 0)`` are left out; ``(i, i, S != 0)`` are pairs.

How it searches (`_search`, one jitted program):

1. **Fractional coordinates.** ``f = R @ inv(cell)``, wrapped into
   ``[0, 1)`` on periodic axes (``w = floor(f)``: the whole cells each atom
   was moved by; shifts found on wrapped atoms are turned back into shifts
   of the caller's positions, ``S = S' - w[j] + w[i]``).
2. **Grid.** Each axis ``k`` is cut into ``c_k`` cells at least
   ``cutoff / (r_k h_k)`` wide (fractional), with ``h_k`` the cell's height
   across axis ``k`` (``1 / |column k of inv(cell)|``) and ``r_k`` the
   static stencil reach. On a periodic axis ``r_k = ceil(cutoff / h_k)``
   (the largest lattice shift a pair of wrapped atoms can need, 1 for any
   cell taller than the cutoff) and ``c_k = max(floor(r_k h_k / cutoff),
   1)``; on a free axis ``r_k = 1`` and the cells span the atoms' extent.
   Cells are coarsened where there would be more than ``4 N`` of them.
   Atoms are sorted by cell, so each cell is one run of the sorted order.
3. **Stencil.** Atom ``i`` in cell ``a`` reads the cells ``a + o`` for
   every offset ``|o_k| <= r_k``; on a periodic axis ``a + o`` is the cell
   ``(a + o) mod c`` in the image ``S'_k = floor((a + o) / c)``. Offsets
   that wrap onto the same cell (a small cell: ``c_k < 2 r_k + 1``) are
   different images, so each candidate ``(j, S)`` is read exactly once.
4. **Decide and store.** Candidates are read ``chunk`` slots of every run at
   a time in a ``while_loop`` until the fullest cell is read (no static
   window: only ``capacity`` and the reach are static). Each is decided as
   ASE decides, on the caller's positions: ``|R[j] - R[i] + S @ cell| <
   cutoff`` (strict), in the positions' dtype, and kept pairs are written at
   the running count (a scatter), so ``count`` is exact even past
   ``capacity``. Only half the stencil is read (offsets ``o >= 0``,
   lexicographic; ``j > i`` within the atom's own cell): each pair kept is
   written as ``(i, j, S)`` and ``(j, i, -S)``, and the two are one
   decision (``|-d| = |d|`` bit for bit), so the list is full and
   symmetric with half the candidates. A candidate costs one gather (its
   position and wrap from a table in sorted order); the scatter stores
   ``(i, p, S)`` once per pair and the loop's end turns sorted indices
   ``p`` into atoms and adds the reverses.

``backend="brute"`` is the same program with one cell per axis (every atom
is a candidate of every atom, in every image): ``N² · Π(2 r_k + 1)``
candidates, in one vectorised step for small systems. ``"auto"`` takes it
while that is at most `BRUTE_CANDIDATES` (about 200 atoms in a cell taller
than the cutoff), and the cell grid above it.

What is static: ``pbc``, ``capacity``, ``max_shift`` (the reach ``r``)
and ``cutoff`` as a Python float (it sets the reach; inside the program it
is traced, so one compiled program serves every cutoff). Outside ``jit`` (a
concrete cell) ``max_shift`` is computed from the cell, and
``capacity=None`` sizes the list exactly: it searches with a power-of-two
capacity above an estimate of the count (again with the count's power of
two when that was short: the count is exact either way) and cuts the
arrays to the count, so most calls compile and run one program. Under ``jit`` / ``vmap`` pass both (`pairs_sizes` measures
them on a data set); anything that leaves the list incomplete (more pairs
than ``capacity``, a cell that needs more shifts than ``max_shift``, a
non-finite position, a singular cell) sets ``overflow`` and a bit of
``error``; `Pairs.check` raises on it, and an eager call raises at once.

One module past 800 lines on purpose: one search and its front (checks,
static sizes).
"""
from __future__ import annotations

import dataclasses
import enum
import functools
import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxrt.errors import Bits, Error, raise_for
from jaxrt.layouts.edges import materialized

# Cells are this much (relatively) wider than their minimum, so that an atom
# binned one cell off by rounding still has all its neighbours in reach.
_CELL_MARGIN = 2.0 ** -10
# The grid has at most this many cells per atom (plus a constant).
_CELLS_PER_ATOM = 4
# "auto" takes the brute force up to this many candidates (N² · images).
BRUTE_CANDIDATES = 2 ** 20
# Candidates read per step of the loop, at most (slots of every run at once).
_CHUNK_CANDIDATES = 2 ** 22
# Slots of each run read per step on the cell grid (the fullest cell of a
# dense solid at a 5 Å cutoff holds ~12 atoms; 4 measured as fast as 2
# and faster than 8 on the CPU).
_CELL_CHUNK = 4
BACKENDS = ("auto", "brute", "cell")


class PairsError(Error, RuntimeError):
    """Raised by `Pairs.check` (and by an eager `pairs`) for an incomplete
    list."""


@enum.unique
class ErrorBit(Bits):
    """Bits of `Pairs.error`."""
    CAPACITY = 1
    MAX_SHIFT = 2
    NONFINITE_POSITION = 4
    SINGULAR_CELL = 8


_MESSAGES = {
    ErrorBit.CAPACITY: "more pairs than capacity (count is the exact number "
                       "needed): pass a larger capacity=",
    ErrorBit.MAX_SHIFT: "the cell needs larger lattice shifts than max_shift "
                        "(a cell shorter than cutoff / max_shift across a "
                        "periodic axis): pass a larger max_shift= (e.g. "
                        "from jaxrt.pairs_sizes)",
    ErrorBit.NONFINITE_POSITION: "a real atom's position is NaN or infinite: "
                                 "its pairs are missing",
    ErrorBit.SINGULAR_CELL: "the cell is singular or not finite",
}


@functools.partial(jax.tree_util.register_dataclass,
                   data_fields=["i", "j", "shift", "count", "overflow",
                                "error"], meta_fields=[])
@dataclasses.dataclass(frozen=True)
class Pairs:
    """A full pair list with lattice shifts (a pytree: jit/vmap-able).

    Attributes (a batch of systems adds leading axes to each):
      i, j: int32 ``(capacity,)``; entries past ``count`` are N (the number
        of atoms, padded atoms included).
      shift: int32 ``(capacity, 3)``, ``S`` with ``d = R[j] - R[i] + S @
        cell`` (zero where padded).
      count: int32 scalar, the exact number of pairs (more than ``capacity``
        when the list overflowed).
      overflow: bool scalar, the list is incomplete (`error` says why).
      error: int32 scalar, `ErrorBit` bits, 0 for a complete list.

    Entries are in search order, each pair next to its reverse ``(j, i,
    -S)``; `pairs_to_ase` sorts.
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

    def check(self) -> "Pairs":
        """Raise `PairsError` if the list (or any list of a batch) is
        incomplete; host-side, so call it outside ``jit``. Returns self."""
        _raise_if(ErrorBit.of(self.error), self)
        return self


def _raise_if(code: int, result=None) -> None:
    """Raise `PairsError` naming each bit set in ``code`` (and, with
    ``result``, the count that overflowed)."""
    messages = dict(_MESSAGES)
    if result is not None and code & ErrorBit.CAPACITY:
        messages[ErrorBit.CAPACITY] += (
            f" (count {int(np.max(np.asarray(result.count)))}, "
            f"capacity {result.capacity})")
    raise_for(code, messages, PairsError,
              "jaxrt.pairs: the list is incomplete: ")


def _arrays(result: Pairs, positions, cell):
    """JAX arrays of the helpers' arguments (an ASE ``Cell`` included)."""
    positions = jnp.asarray(positions)
    if cell is None and _is_concrete(result.shift) and np.any(
            np.asarray(result.shift)):
        raise ValueError("Pairs.vectors / distances: the list has lattice "
                         "shifts, so pass the cell (cell=) they refer to.")
    return positions, (None if cell is None else
                       jnp.asarray(np.asarray(cell) if not hasattr(
                           cell, "dtype") else cell, positions.dtype))


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
        d = d + _shift_vectors(result.shift.astype(positions.dtype),
                               _as_cell_matrix(cell))
    return jnp.where(valid[..., None], d, 0)


@jax.jit
def _distances(result: Pairs, positions, cell):
    return _safe_norm(_vectors(result, positions, cell))


def _safe_norm(d):
    d2 = jnp.sum(d * d, axis=-1)
    positive = d2 > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, d2, 1)), 0)


def _shift_vectors(s, h):
    """``s @ h`` written out (``s`` float ``(..., 3)``, ``h`` ``(3, 3)``):
    elementwise in the dtype, as ASE's sum of three products (a GPU matrix
    product may round float32 to TF32)."""
    return s[..., 0:1] * h[0] + s[..., 1:2] * h[1] + s[..., 2:3] * h[2]


def _as_cell_matrix(cell):
    """A ``(3,)`` vector of sides -> the diagonal matrix; ``(3, 3)`` as is."""
    return jnp.diag(cell) if cell.ndim == 1 else cell


# ---------------------------------------------------------------------------
# The search


def _heights(hinv):
    """float ``(3,)``: the cell's height across each axis, ``1 / |b_k|``
    with ``b_k`` column ``k`` of ``inv(cell)``."""
    return 1 / jnp.sqrt(jnp.sum(hinv * hinv, axis=0))


def _inverse(h):
    """``inv(h)`` and ``det(h)`` of a ``(3, 3)`` matrix, written out by
    cofactors: no solver call (LAPACK on CPUs, cuSOLVER on GPUs) for a 3x3,
    and a fifth of the compile time of `jnp.linalg.inv`."""
    a, b, c = h[0], h[1], h[2]
    adj = jnp.stack([jnp.cross(b, c), jnp.cross(c, a), jnp.cross(a, b)],
                    axis=1)  # columns: inv(h) = adj / det
    det = jnp.sum(a * adj[:, 0])  # elementwise: no TF32 dot on GPUs
    return adj / det, det


def _offsets(reach: tuple[int, ...]) -> np.ndarray:
    """int32 ``(K, 3)``: the stencil, every offset with ``|o_k| <= r_k``."""
    return np.array(list(itertools.product(*(range(-r, r + 1)
                                              for r in reach))), np.int32)


@functools.partial(jax.jit, static_argnames=(
    "pbc", "reach", "capacity", "brute", "chunk"))
def _search(positions, cell, mask, cutoff, *, pbc: tuple[bool, ...],
            reach: tuple[int, ...], capacity: int, brute: bool, chunk: int):
    """The pairs of one system (module docstring).

    Args:
      positions: float ``(N, 3)``; cell: ``(3, 3)`` rows (same dtype);
      mask: bool ``(N,)`` real atoms.
      cutoff: float scalar (traced: one program serves every cutoff).
      reach: static ``r_k`` per axis (0 on free axes of the brute force).
      capacity: static; 0 counts only.
    Returns:
      int32 ``(capacity, 5)`` rows ``(i, j, S)`` padded with ``(N, N, 0)``,
      int32 count, int32 error bits.
    """
    n = positions.shape[0]
    dtype = positions.dtype
    cutoff = jnp.asarray(cutoff, dtype)
    periodic = np.array(pbc)
    # Binning needs no gradient; the decisions use the caller's arrays.
    r = jax.lax.stop_gradient(positions)
    h = jax.lax.stop_gradient(cell)
    hinv, det = _inverse(h)
    bad_cell = ~(jnp.isfinite(det) & (jnp.abs(det) > 0)
                 & jnp.all(jnp.isfinite(hinv)))
    finite = jnp.all(jnp.isfinite(r), axis=1)
    error = jnp.where(jnp.any(mask & ~finite),
                      int(ErrorBit.NONFINITE_POSITION), 0)
    error = error | jnp.where(bad_cell, int(ErrorBit.SINGULAR_CELL), 0)
    real = mask & finite
    hinv = jnp.where(bad_cell, jnp.eye(3, dtype=dtype), hinv)
    f = jnp.sum(jnp.where(real[:, None], r, 0)[:, :, None] * hinv[None],
                axis=1)
    w = jnp.where(periodic, jnp.floor(f), 0)
    fw = f - w
    height = _heights(hinv)

    # The grid (module docstring, 2.).
    cells, origin, width = _grid(fw, real, periodic, reach, cutoff, height,
                                 brute)
    # The reach covers the cutoff unless the cell is too short for it.
    reach_needed = cutoff * cells / height
    short = jnp.any(periodic & (reach_needed > np.array(reach)))
    error = error | jnp.where(short & ~bad_cell, int(ErrorBit.MAX_SHIFT), 0)

    coord = jnp.clip(jnp.floor((fw - origin) / width).astype(jnp.int32), 0,
                     cells - 1)
    order, starts = _cell_table(coord, cells, real, brute)

    # The stencil (module docstring, 3.): per atom and offset, the run of
    # its target cell and the image it lies in.
    # Half the stencil: pair (i, j, S) found from i through offset o is
    # (j, i, -S) from j through -o, so only offsets o >= 0 (lexicographic)
    # are read and each kept pair is stored both ways (bit for bit the same
    # decision: |-d| is |d| in floating point); within o = 0, j > i.
    half = _half(_offsets(reach))
    offsets = jnp.asarray(half)  # (K, 3)
    own = jnp.asarray(~half.any(axis=1))  # (K,): the offset 0
    target = coord[:, None, :] + offsets[None]  # (N, K, 3)
    image = jnp.where(periodic, jnp.floor_divide(target, cells), 0)
    target = jnp.where(periodic, target - image * cells, target)
    inside = jnp.all((target >= 0) & (target < cells), axis=2) & real[:, None]
    tkey = jnp.where(inside, (target[..., 2] * cells[1] + target[..., 1])
                     * cells[0] + target[..., 0], 0)
    start = starts[tkey]
    length = jnp.where(inside, starts[tkey + 1] - start, 0)
    wi = w.astype(jnp.int32)
    # Shifts of the caller's positions: S = S' + w[i] - w[j].
    image = image + wi[:, None, :]
    atoms = jnp.arange(n, dtype=jnp.int32)
    half_capacity = (capacity + 1) // 2
    # One gather per candidate: the sorted atoms' positions and wraps side
    # by side (w holds small whole numbers: exact in the dtype). Candidates
    # are named by their sorted index p until the loop ends (j = order[p]
    # then, on the stored pairs only); within the atom's own cell a pair is
    # kept from the atom that sorts first.
    table = jnp.concatenate([positions[order], w[order]], axis=1)
    rank = jnp.zeros((n,), jnp.int32).at[order].set(atoms)

    def step(t, carry):
        total, out = carry
        slot = t * chunk + jnp.arange(chunk, dtype=jnp.int32)
        valid = slot[None, None, :] < length[:, :, None]  # (N, K, B)
        p = jnp.clip(start[:, :, None] + slot, 0, n - 1)
        row = table[p]
        s = image[:, :, None, :] - row[..., 3:].astype(jnp.int32)
        d = (row[..., :3] - positions[:, None, None, :]) + _shift_vectors(
            s.astype(dtype), cell)
        dist = jnp.sqrt(d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1]
                        + d[..., 2] * d[..., 2])
        once = ~own[None, :, None] | (p > rank[:, None, None])
        keep = valid & (dist < cutoff) & once
        if capacity > 0:
            flat = keep.reshape(-1)
            at = total + jnp.cumsum(flat, dtype=jnp.int32) - 1
            i = jnp.broadcast_to(atoms[:, None, None], p.shape)[..., None]
            rows = jnp.concatenate([i, p[..., None], s], axis=-1)
            out = out.at[jnp.where(flat, at, half_capacity)].set(
                rows.reshape(-1, 5), mode="drop")
        return total + jnp.sum(keep, dtype=jnp.int32), out

    steps = (jnp.max(length, initial=0) + chunk - 1) // chunk
    pad = jnp.array([n, n, 0, 0, 0], jnp.int32)
    out = jnp.broadcast_to(pad, (half_capacity, 5))
    total, out = jax.lax.fori_loop(0, steps, step,
                                   (jnp.zeros((), jnp.int32), out))
    total = 2 * total
    error = error | jnp.where(total > capacity, int(ErrorBit.CAPACITY), 0)
    stored = out[:, 0] < n
    out = out.at[:, 1].set(jnp.where(stored, order[jnp.where(
        stored, out[:, 1], 0)], n))
    # Each pair next to its reverse (j, i, -S): built after the loop, so the
    # scatter moves half the data.
    reverse = jnp.concatenate([out[:, 1:2], out[:, 0:1], -out[:, 2:]], axis=1)
    out = jnp.stack([out, reverse], axis=1).reshape(2 * half_capacity, 5)
    return out[:capacity], total, error.astype(jnp.int32)


def _grid(fw, real, periodic: np.ndarray, reach: tuple[int, ...], cutoff,
          height, brute: bool):
    """The cell grid in fractional coordinates (module docstring, 2.).

    Args:
      fw: float ``(N, 3)`` wrapped fractional positions; real: bool
        ``(N,)``; periodic: bool ``(3,)``; height: float ``(3,)`` the cell's
        heights over its fractional axes.
    Returns:
      int32 ``(3,)`` cells per axis, float ``(3,)`` origin and cell width.
    """
    n, dtype = fw.shape[0], fw.dtype
    reach_arr = np.maximum(np.array(reach), 1)
    if brute:
        return (jnp.ones((3,), jnp.int32), jnp.zeros((3,), dtype),
                jnp.ones((3,), dtype))
    big = jnp.asarray(jnp.finfo(dtype).max, dtype)
    lo = jnp.min(jnp.where(real[:, None], fw, big), axis=0)
    hi = jnp.max(jnp.where(real[:, None], fw, -big), axis=0)
    origin = jnp.where(periodic, 0, jnp.where(jnp.any(real), lo, 0))
    extent = jnp.where(periodic, 1, jnp.maximum(hi - origin, 0))
    least = cutoff * (1 + _CELL_MARGIN) / (reach_arr * height)
    budget = _CELLS_PER_ATOM * n + 64

    def count_cells(coarsen):
        size = least * coarsen
        return jnp.where(periodic, jnp.maximum(jnp.floor(1 / size), 1),
                         jnp.floor(extent / size) + 1)

    coarsen = jax.lax.while_loop(
        lambda c: jnp.prod(count_cells(c)) > budget, lambda c: c * 1.25,
        jnp.ones((), dtype))
    cells_f = count_cells(coarsen)
    width = jnp.where(periodic, 1 / cells_f, least * coarsen)
    return cells_f.astype(jnp.int32), origin, width


def _cell_table(coord, cells, real, brute: bool):
    """The atoms sorted by cell: int32 ``(N,)`` ``order`` (sorted position
    -> atom) and int32 ``(table + 2,)`` where each cell's run starts."""
    n = coord.shape[0]
    table = _CELLS_PER_ATOM * n + 64 if not brute else 1
    key = jnp.where(real, (coord[:, 2] * cells[1] + coord[:, 1]) * cells[0]
                    + coord[:, 0], table)
    sorted_key, order = jax.lax.sort(
        (key, jnp.arange(n, dtype=jnp.int32)), num_keys=1, is_stable=False)
    counts = jnp.zeros((table + 1,), jnp.int32).at[sorted_key].add(
        1, mode="drop")
    starts = jnp.concatenate([jnp.zeros((1,), jnp.int32),
                              jnp.cumsum(counts, dtype=jnp.int32)])
    return order, starts


def _half(offsets: np.ndarray) -> np.ndarray:
    """The offsets that are zero or lexicographically positive."""
    first = np.array([next((v for v in o if v != 0), 0) for o in offsets])
    return offsets[first >= 0]


# ---------------------------------------------------------------------------
# The front: arguments checked, static sizes decided


@dataclasses.dataclass(frozen=True)
class PairSizes:
    """Static sizes for `pairs` under ``jit``: pass as ``**sizes.kwargs``.

    Attributes:
      capacity: the most pairs of any system measured.
      max_shift: per axis, the stencil reach the cells need (0 on free axes).
    """

    capacity: int
    max_shift: tuple[int, int, int]

    @property
    def kwargs(self) -> dict:
        return {"capacity": self.capacity, "max_shift": self.max_shift}


def _is_concrete(x) -> bool:
    return x is None or not isinstance(x, jax.core.Tracer)


def _check_cutoff(cutoff, traced_ok: bool = False):
    """A Python float > 0; or, with ``traced_ok`` (capacity and max_shift
    given: nothing static depends on it), a traced float scalar as is."""
    if isinstance(cutoff, jax.core.Tracer):
        if traced_ok and cutoff.shape == () and jnp.issubdtype(
                cutoff.dtype, jnp.floating):
            return cutoff
        raise TypeError("jaxrt.pairs: cutoff must be a Python float (it "
                        "sets the stencil's reach and the capacity); got a "
                        "traced value. Close over a float, or pass "
                        "max_shift= and capacity= as well (then a traced "
                        "float scalar is fine).")
    try:
        value = float(cutoff)
    except (TypeError, ValueError):
        raise TypeError(f"jaxrt.pairs: cutoff must be a number, got "
                        f"{cutoff!r}.") from None
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"jaxrt.pairs: cutoff must be finite and > 0, got "
                         f"{cutoff!r}.")
    return value


def _check_pbc(pbc, has_cell: bool) -> tuple[bool, bool, bool]:
    if pbc is None:
        return (has_cell,) * 3
    if isinstance(pbc, (bool, np.bool_)):
        pbc = (bool(pbc),) * 3
    values = tuple(np.asarray(pbc).reshape(-1).tolist())
    if len(values) != 3 or not all(isinstance(v, bool) for v in values):
        raise ValueError(f"jaxrt.pairs: pbc must be a bool or three bools "
                         f"(one per axis; a slab is (True, True, False)), got "
                         f"{pbc!r}.")
    if any(values) and not has_cell:
        raise ValueError(f"jaxrt.pairs: pbc={pbc!r} has periodic axes but "
                         f"cell=None (free space): pass cell=, or pbc=False.")
    return values


def _complete(cell: np.ndarray, pbc) -> np.ndarray:
    """ASE's `complete_cell` for zero rows on free axes (a molecule's or a
    slab's cell in ASE often has them): missing vectors orthogonal to the
    others, unit length."""
    missing = np.nonzero(~cell.any(axis=1))[0]
    if any(pbc[k] for k in missing):
        raise ValueError(f"jaxrt.pairs: cell row(s) {missing.tolist()} are "
                         f"zero on a periodic axis (pbc={pbc}): give every "
                         f"periodic axis its lattice vector.")
    cell = cell.copy()
    if len(missing) == 3:
        return np.eye(3)
    if len(missing) == 2:
        u, s, vt = np.linalg.svd(cell.T)
        cell = (u @ np.diag([s[0], 1, 1]) @ vt).T
        if np.linalg.det(cell) < 0:
            cell[missing[0]] = -cell[missing[0]]
    elif len(missing) == 1:
        k = missing[0]
        cell[k] = np.cross(cell[k - 2], cell[k - 1])
        cell[k] /= np.linalg.norm(cell[k])
    return cell


def _check_cell(cell, pbc, dtype):
    """float ``(3, 3)`` in ``dtype`` (traced or not), and the concrete
    float64 matrix or None."""
    if cell is None:
        return jnp.eye(3, dtype=dtype), np.eye(3)
    shape = np.shape(cell)
    if shape not in ((3,), (3, 3)):
        raise ValueError(f"jaxrt.pairs: cell must be a (3, 3) matrix of "
                         f"lattice vectors as rows (ASE's convention), a (3,) "
                         f"vector of sides, or None; got shape {shape}.")
    if not _is_concrete(cell):
        return _as_cell_matrix(jnp.asarray(cell, dtype)), None
    h = np.asarray(cell, np.float64)
    h = np.diag(h) if h.ndim == 1 else h
    if not np.all(np.isfinite(h)):
        raise ValueError("jaxrt.pairs: cell has NaN or infinite entries.")
    h = _complete(h, pbc)
    scale = max(float(np.max(np.abs(h))), 1e-300)
    if abs(np.linalg.det(h)) <= 1e-12 * scale ** 3:
        raise ValueError(f"jaxrt.pairs: cell is singular (det = "
                         f"{np.linalg.det(h):.3g}): its rows must be three "
                         f"independent lattice vectors.")
    return jnp.asarray(h, dtype), h


def _shift_for_cell(h: np.ndarray, cutoff: float, pbc) -> tuple[int, ...]:
    """The reach a concrete cell needs: ``ceil(cutoff / h_k)`` per periodic
    axis (with a margin over the program's own rounding of the heights)."""
    heights = 1 / np.linalg.norm(np.linalg.inv(h), axis=0)
    need = np.ceil(cutoff / heights * (1 + _CELL_MARGIN)).astype(int)
    return tuple(int(max(n, 1)) if p else 0 for n, p in zip(need, pbc))


def _check_max_shift(max_shift, pbc) -> tuple[int, int, int]:
    values = (max_shift,) * 3 if isinstance(max_shift, (int, np.integer)) \
        else tuple(max_shift)
    if len(values) != 3 or not all(
            isinstance(v, (int, np.integer)) and not isinstance(v, bool)
            and v >= 0 for v in values):
        raise ValueError(f"jaxrt.pairs: max_shift must be an int >= 0 or "
                         f"three of them, got {max_shift!r}.")
    return tuple(int(max(v, 1)) if p else 0 for v, p in zip(values, pbc))


def _check_capacity(capacity):
    if capacity is None:
        return None
    if isinstance(capacity, bool) or not isinstance(capacity,
                                                    (int, np.integer)):
        raise TypeError(f"jaxrt.pairs: capacity must be an int (static) or "
                        f"None, got {capacity!r}.")
    if capacity < 0:
        raise ValueError(f"jaxrt.pairs: capacity must be >= 0, got "
                         f"{capacity}.")
    return int(capacity)


def _plan(n: int, pbc, max_shift, backend: str):
    """``(brute, reach, chunk)`` static options of `_search`."""
    if backend not in BACKENDS:
        raise ValueError(f"jaxrt.pairs: backend={backend!r}: choose one of "
                         f"{BACKENDS}.")
    images = math.prod(2 * r + 1 for r in max_shift)
    brute = backend == "brute" or (
        backend == "auto" and n * n * images <= BRUTE_CANDIDATES)
    if brute:
        reach = max_shift
        chunk = max(1, min(n, _CHUNK_CANDIDATES // max(n * images, 1)))
    else:
        reach = tuple(r if p else 1 for r, p in zip(max_shift, pbc))
        k = math.prod(2 * r + 1 for r in reach)
        chunk = max(1, min(_CELL_CHUNK, _CHUNK_CANDIDATES // max(n * k, 1)))
    return brute, reach, chunk


def _inputs(positions, cutoff, cell, pbc, mask, traced_cutoff=False):
    """Checked arguments: positions, cutoff, pbc, mask. ``positions`` may
    have leading batch axes."""
    if not hasattr(positions, "dtype"):
        positions = np.asarray(positions)
    if not jnp.issubdtype(positions.dtype, jnp.floating):
        raise TypeError(f"jaxrt.pairs: positions must be floating point, got "
                        f"{positions.dtype}.")
    positions = jnp.asarray(positions)
    if positions.ndim < 2 or positions.shape[-1] != 3:
        raise ValueError(f"jaxrt.pairs: positions must be (N, 3), got shape "
                         f"{positions.shape}.")
    cutoff = _check_cutoff(cutoff, traced_cutoff)
    pbc = _check_pbc(pbc, cell is not None)
    if mask is None:
        mask = jnp.ones(positions.shape[:-1], bool)
    else:
        if np.shape(mask) != positions.shape[:-1] or not jnp.issubdtype(
                jnp.asarray(mask).dtype, jnp.bool_):
            raise ValueError(f"jaxrt.pairs: mask must be bool with shape "
                             f"{positions.shape[:-1]} (True for the real "
                             f"atoms), got {jnp.asarray(mask).dtype} "
                             f"{np.shape(mask)}.")
        mask = jnp.asarray(mask)
    return positions, cutoff, pbc, mask


def _result(out, total, error) -> Pairs:
    return Pairs(i=out[..., 0], j=out[..., 1], shift=out[..., 2:],
                 count=total, overflow=error != 0, error=error)


def pairs(positions, cutoff, *, cell=None, pbc=None, capacity=None, mask=None,
          max_shift=None, backend: str = "auto") -> Pairs:
    """Every pair ``(i, j, S)`` with ``|R[j] - R[i] + S @ cell| < cutoff``.

    Args:
      positions: float ``(N, 3)`` Cartesian positions (anywhere: atoms
        outside the cell on periodic axes are found as they are, and their
        shifts refer to the positions given, as ASE's do). The search and
        the decisions run in this dtype.
      cutoff: Python float > 0. Strict ``<``, as ASE. May be a traced
        float scalar where ``capacity`` and ``max_shift`` are given.
      cell: ``(3, 3)`` lattice vectors as rows (ASE's convention), ``(3,)``
        sides of an orthorhombic cell, or None for free space. May be traced
        (then pass ``max_shift``). Zero rows on free axes are completed as
        ASE completes them.
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
      backend: ``"auto"``, ``"brute"`` or ``"cell"`` (module docstring).

    Returns:
      `Pairs`. Outside ``jit`` an incomplete list raises `PairsError`;
      under ``jit`` its ``overflow`` is set (``check()`` raises).
    """
    positions, cutoff, pbc, mask = _inputs(
        positions, cutoff, cell, pbc, mask,
        traced_cutoff=capacity is not None and max_shift is not None)
    if positions.ndim != 2:
        raise ValueError(f"jaxrt.pairs: positions must be (N, 3) for one "
                         f"system, got {positions.shape}; jax.vmap over a "
                         f"batch (with mask= for padded atoms).")
    capacity = _check_capacity(capacity)
    h, concrete_cell = _check_cell(cell, pbc, positions.dtype)
    if max_shift is None and not any(pbc):
        shift = (0, 0, 0)  # free space: no shifts, any cell
    elif max_shift is None:
        if concrete_cell is None:
            raise ValueError(
                "jaxrt.pairs: the cell is traced, so the lattice shifts the "
                "search must reach are not known: pass max_shift= (an int or "
                "three; jaxrt.pairs_sizes(...) measures it with capacity).")
        shift = _shift_for_cell(concrete_cell, cutoff, pbc)
    else:
        shift = _check_max_shift(max_shift, pbc)
    n = positions.shape[0]
    brute, reach, chunk = _plan(n, pbc, shift, backend)
    eager = all(_is_concrete(x) for x in (positions, mask)) and \
        concrete_cell is not None
    options = dict(pbc=pbc, reach=reach, brute=brute, chunk=chunk)
    if n == 0:
        out = jnp.zeros((capacity or 0, 5), jnp.int32)
        zero = jnp.zeros((), jnp.int32)
        return _result(out, zero, zero)
    if capacity is not None:
        result = _result(*_search(positions, h, mask, cutoff,
                                  capacity=capacity, **options))
        return result.check() if eager else result
    if not eager:
        raise ValueError(
            "jaxrt.pairs: capacity=None needs concrete inputs (it counts "
            "the pairs first); under jax.jit or jax.vmap pass capacity= "
            "(a static int, e.g. jaxrt.pairs_sizes(...).capacity).")
    # Exact sizing without a second program for most calls: search with a
    # power-of-two capacity above an estimate (programs are shared between
    # calls), again with the count's power of two if that was short, and
    # cut the arrays to the count.
    guess = _bucket(_estimate(np.asarray(positions, np.float64),
                              np.asarray(mask), concrete_cell, pbc, cutoff))
    out, total, error = _search(positions, h, mask, cutoff, capacity=guess,
                                **options)
    _raise_if(int(error) & ~int(ErrorBit.CAPACITY))
    count = int(total)
    if count > guess:
        out, total, error = _search(positions, h, mask, cutoff,
                                    capacity=_bucket(count), **options)
    return _result(out[:count], total,
                   error & ~int(ErrorBit.CAPACITY)).check()


def _bucket(n: int) -> int:
    """The power of two at or above ``n``, at least 16."""
    return max(16, 1 << (max(int(n), 1) - 1).bit_length())


def _estimate(r: np.ndarray, mask: np.ndarray, cell: np.ndarray, pbc,
              cutoff: float) -> int:
    """Pairs expected of a uniform density: N k with k the atoms in a
    sphere of the cutoff (the atoms' fractional extent plus the cutoff on
    free axes, the whole cell on periodic ones), plus a quarter."""
    n = int(np.sum(mask))
    if n < 2:
        return 1
    hinv = np.linalg.inv(cell)
    f = r[mask] @ hinv
    heights = 1 / np.linalg.norm(hinv, axis=0)
    span = [1.0 if p else np.ptp(f[:, k]) + 2 * cutoff / heights[k]
            for k, p in enumerate(pbc)]
    volume = abs(np.linalg.det(cell)) * np.prod(span)
    k = n / volume * 4 / 3 * np.pi * cutoff ** 3
    return int(1.25 * n * k) + 16


def _per_system_cells(cell, batch):
    """float64 ``(B, 3, 3)`` from one cell or one per system (matrices or
    sides); None stays None."""
    if cell is None:
        return None
    c = np.asarray(cell, np.float64)
    # Sides, one vector or one per system; a (3, 3) array is one matrix.
    if c.shape != (3, 3) and c.shape in ((3,), batch + (3,)):
        c = np.vectorize(np.diag, signature="(k)->(k,k)")(c)
    if c.shape not in ((3, 3), batch + (3, 3)):
        raise ValueError(f"jaxrt.pairs_sizes: cell must be one cell ((3, 3) "
                         f"or (3,)) or one per system ({batch + (3, 3)} or "
                         f"{batch + (3,)}), got shape {c.shape}.")
    return np.broadcast_to(c, batch + (3, 3)).reshape(-1, 3, 3)


def pairs_sizes(positions, cutoff, *, cell=None, pbc=None, mask=None,
                backend: str = "auto") -> PairSizes:
    """Eager: the static sizes `pairs` needs under ``jit`` for every system
    of a batch: the most pairs of one system and the largest stencil reach.

    Args:
      positions: float ``(..., N, 3)``, any leading batch axes.
      cell: None, ``(3,)``, ``(3, 3)``, or one per system ``(..., 3)`` /
        ``(..., 3, 3)``.
      mask: bool ``(..., N)`` or None.
    Returns:
      `PairSizes` (add a margin to ``capacity`` for systems not measured).
    """
    positions, cutoff, pbc, mask = _inputs(positions, cutoff, cell, pbc,
                                           mask)
    batch = positions.shape[:-2]
    n = positions.shape[-2]
    r = positions.reshape((-1, n, 3))
    m = mask.reshape((-1, n))
    cells = _per_system_cells(cell, batch)
    mats = []
    shift = [0, 0, 0]
    for c in cells if cell is not None else [None] * len(r):
        h, concrete = _check_cell(c, pbc, positions.dtype)
        mats.append(h)
        need = _shift_for_cell(concrete, cutoff, pbc)
        shift = [max(a, b) for a, b in zip(shift, need)]
    shift = tuple(shift)
    brute, reach, chunk = _plan(n, pbc, shift, backend)
    count = jax.vmap(functools.partial(
        _search, pbc=pbc, reach=reach, capacity=0, brute=brute,
        chunk=chunk), in_axes=(0, 0, 0, None))
    _, total, error = count(r, jnp.stack(mats), m, cutoff)
    _raise_if(ErrorBit.of(error) & ~int(ErrorBit.CAPACITY))
    return PairSizes(capacity=int(np.max(np.asarray(total), initial=0)),
                     max_shift=shift)
