"""The arguments of `jaxrt.pairs` and `jaxrt.pairs_batch` checked, and the
static sizes of their programs decided (reach, brute force or grid, size
buckets), on the host."""
from __future__ import annotations

import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np

# "auto" takes the brute force up to this many candidates (N² · images):
# on 2 CPU cores (benchmarks/pairs.py) it and the grid cost the same near
# 16 atoms in a cell taller than the cutoff (27 images), the grid 3x less
# at 64.
BRUTE_CANDIDATES = 2 ** 13
# An eager call of one system up to this many candidates (N² · images)
# searches on the host (`host.search_small_host`).
SMALL_CANDIDATES = 2 ** 14
# Candidates read per step of the loop: a power of two near this many per
# atom, within these bounds (on 2 CPU cores smaller blocks ran faster on
# batches of a few hundred atoms; larger ones save steps on large systems).
BLOCK_PER_ATOM = 16
BLOCK_CANDIDATES = (2 ** 12, 2 ** 16)
BACKENDS = ("auto", "brute", "cell")
# Reach beyond the cell's own rounding of the heights (program.CELL_MARGIN).
_REACH_MARGIN = 2.0 ** -10


class Float32Warning(UserWarning):
    """float64 input searched in float32 (JAX's x64 is off)."""


def is_concrete(x) -> bool:
    return x is None or not isinstance(x, jax.core.Tracer)


def bucket(n: int) -> int:
    """``n`` rounded up to a shared size (1, 2, 3, 4, 6, 8, 12, 16, 24, ...:
    two an octave, at most 1.5x; the ladder of the lists' ``allocate``,
    `jaxrt.backends.contract.compile_size`, which imports jax-md), so that
    many sizes share a few compiled programs."""
    size = max(int(n), 1)
    if size <= 4:
        return size
    power = 1 << (size - 1).bit_length()
    return 3 * power // 4 if 3 * power // 4 >= size else power


def positions_array(positions, who: str, stacklevel: int = 4):
    """float ``(..., 3)`` positions as a JAX array or, concrete, a numpy
    array in the dtype the search will use; warns when float64 numpy input
    will be searched in float32."""
    if not hasattr(positions, "dtype"):
        positions = np.asarray(positions)
    if not jnp.issubdtype(positions.dtype, jnp.floating):
        raise TypeError(f"{who}: positions must be floating point, got "
                        f"{positions.dtype}.")
    if positions.ndim < 2 or positions.shape[-1] != 3:
        raise ValueError(f"{who}: positions must be (N, 3), got shape "
                         f"{positions.shape}.")
    if isinstance(positions, np.ndarray):
        dtype = jax.dtypes.canonicalize_dtype(positions.dtype)
        if dtype != positions.dtype and positions.dtype == np.float64:
            warnings.warn(
                f"{who}: float64 positions are searched in float32 because "
                f"JAX's x64 mode is off, so pairs within float32 rounding of "
                f"the cutoff may differ from a float64 search (ASE's). "
                f"Enable it (jax.config.update('jax_enable_x64', True), or "
                f"`with jax.enable_x64(True):`), or pass float32 positions "
                f"to search in float32 on purpose.", Float32Warning,
                stacklevel=stacklevel)
        return np.asarray(positions, dtype)
    return positions


def check_cutoff(cutoff, traced_ok: bool = False):
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
        raise TypeError(f"jaxrt.pairs: cutoff must be a number, a dict "
                        f"{{(species_a, species_b): cutoff}} or a square "
                        f"matrix by species, got {cutoff!r}.") from None
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"jaxrt.pairs: cutoff must be finite and > 0, got "
                         f"{cutoff!r}.")
    return value


def cutoff_matrix(cutoff) -> np.ndarray:
    """float64 ``(S, S)`` from ASE's dict ``{(a, b): rc}`` (integer species,
    both orders, 0 where absent, the last of repeated keys) or a square
    symmetric matrix."""
    if isinstance(cutoff, dict):
        keys = list(cutoff)
        if not keys or not all(
                isinstance(k, tuple) and len(k) == 2 and all(
                    isinstance(v, (int, np.integer)) and not isinstance(
                        v, bool) and v >= 0 for v in k) for k in keys):
            raise ValueError(
                f"jaxrt.pairs: a cutoff dict maps pairs of species (ints "
                f">= 0, e.g. atomic numbers) to cutoffs, {{(1, 8): 1.2}}; "
                f"got keys {keys[:4]!r}. Chemical symbols: "
                f"jaxrt.ase_neighbor_list converts them.")
        size = 1 + max(max(k) for k in keys)
        table = np.zeros((size, size))
        for (a, b), value in cutoff.items():
            table[a, b] = table[b, a] = float(value)
    else:
        table = np.asarray(cutoff, np.float64)
        if table.ndim != 2 or table.shape[0] != table.shape[1] or \
                not np.array_equal(table, table.T):
            raise ValueError(f"jaxrt.pairs: a cutoff matrix must be square "
                             f"and symmetric (species by species), got "
                             f"shape {table.shape}.")
    if not (np.all(np.isfinite(table)) and np.all(table >= 0)
            and np.max(table, initial=0) > 0):
        raise ValueError("jaxrt.pairs: cutoffs by species must be finite, "
                         ">= 0 (0: no pairs), and one of them > 0.")
    return table


def cutoffs(cutoff, species, n_atoms: int, traced_ok: bool, who: str):
    """``(radius, cut, species)``: the search radius (a float, or traced),
    the cutoff the program decides with (a scalar, or an ``(S, S)``
    matrix) and int32 species ``(N,)`` or None."""
    matrix = isinstance(cutoff, dict) or (
        not isinstance(cutoff, jax.core.Tracer) and np.ndim(cutoff) == 2) or (
        isinstance(cutoff, jax.core.Tracer) and cutoff.ndim == 2)
    if not matrix:
        if np.ndim(cutoff) != 0:
            raise ValueError(
                f"{who}: cutoff must be a number, a dict {{(a, b): rc}} or "
                f"an (S, S) matrix by species; got shape "
                f"{np.shape(cutoff)} (ASE's per-atom radii are not "
                f"supported).")
        value = check_cutoff(cutoff, traced_ok)
        return value, value, None
    if species is None:
        raise ValueError(f"{who}: cutoffs by species need species= (int "
                         f"(N,), each atom's row of the cutoff matrix, e.g. "
                         f"atomic numbers for a dict).")
    if isinstance(cutoff, jax.core.Tracer):
        if not traced_ok:
            raise TypeError(f"{who}: a traced cutoff matrix needs capacity= "
                            f"and max_shift= (its largest value sets the "
                            f"reach).")
        table, radius = cutoff, None
    else:
        table = cutoff_matrix(cutoff)
        radius = float(np.max(table))
    if np.shape(species) != (n_atoms,):
        raise ValueError(f"{who}: species must be int ({n_atoms},), one per "
                         f"atom, got shape {np.shape(species)}.")
    if is_concrete(species):
        s = np.asarray(species)
        if not np.issubdtype(s.dtype, np.integer):
            raise TypeError(f"{who}: species must be integers, got "
                            f"{s.dtype}.")
        if s.size and (s.min() < 0 or s.max() >= np.shape(table)[0]):
            raise ValueError(
                f"{who}: species must index the cutoff matrix (0 <= s < "
                f"{np.shape(table)[0]}), got values in [{s.min()}, "
                f"{s.max()}]; add the missing species to the cutoffs.")
        species = s.astype(np.int32)
    else:
        species = species.astype(jnp.int32)
    return radius, table, species


def check_pbc(pbc, has_cell: bool) -> tuple[bool, bool, bool]:
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


def complete(cell: np.ndarray, pbc) -> np.ndarray:
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


def as_cell_matrix(cell):
    """A ``(..., 3)`` vector of sides -> diagonal matrices; ``(..., 3, 3)``
    as is (numpy or JAX)."""
    if np.shape(cell)[-2:] == (3, 3):
        return cell
    xp = np if isinstance(cell, np.ndarray) else jnp
    return cell[..., :, None] * xp.eye(3, dtype=cell.dtype)


def plain(array):
    """A concrete array-like as numpy, an ASE ``Cell`` included (its
    ``__array__`` refuses numpy 2's dtype conversions without a copy)."""
    return np.asarray(getattr(array, "array", array))


# Eager calls of one structure (a training set's frames) repeat its cell:
# the checked cell, its inverse and its reach are kept by the cell's bytes.
_CACHE_SIZE = 256
_cells: dict = {}
_inverses: dict = {}
_reaches: dict = {}


def _remember(cache: dict, key, value):
    if len(cache) >= _CACHE_SIZE:
        cache.clear()
    cache[key] = value
    return value


def inverse3(h: np.ndarray):
    """``(inv(h), det(h))`` of one float ``(3, 3)`` by cofactors in Python
    floats (a numpy call costs more than the arithmetic); float64, read
    only (kept for the next call with the same ``h``)."""
    key = (h.dtype.str, h.tobytes())
    found = _inverses.get(key)
    if found is not None:
        return found
    (a, b, c), (d, e, f), (g, i, k) = h.tolist()
    co = [e * k - f * i, f * g - d * k, d * i - e * g]
    det = a * co[0] + b * co[1] + c * co[2]
    if det == 0 or not math.isfinite(det):
        return _remember(_inverses, key, (None, det))
    inv = np.array([[co[0], c * i - b * k, b * f - c * e],
                    [co[1], a * k - c * g, c * d - a * f],
                    [co[2], b * g - a * i, a * e - b * d]]) / det
    inv.flags.writeable = False
    return _remember(_inverses, key, (inv, det))


def concrete_cell(cell, pbc, who: str = "jaxrt.pairs") -> np.ndarray:
    """A concrete cell (matrix or sides) checked and completed: float64
    ``(3, 3)``, read only."""
    c = plain(cell)
    key = (c.dtype.str, c.shape, c.tobytes(), tuple(bool(p) for p in pbc))
    found = _cells.get(key)
    if found is not None:
        return found
    h = as_cell_matrix(c.astype(np.float64))
    if not np.isfinite(h).all():
        raise ValueError(f"{who}: cell has NaN or infinite entries.")
    if not h.any(axis=1).all():
        h = complete(h, pbc)
    scale = max(float(np.abs(h).max()), 1e-300)
    det = inverse3(h)[1]
    if not abs(det) > 1e-12 * scale ** 3:
        raise ValueError(f"{who}: cell is singular (det = {det:.3g}): its "
                         f"rows must be three independent lattice vectors.")
    h = np.array(h)
    h.flags.writeable = False
    return _remember(_cells, key, h)


def check_cell(cell, pbc, dtype):
    """float ``(3, 3)`` (traced, or numpy in ``dtype``), and the concrete
    float64 matrix or None."""
    if cell is None:
        return np.eye(3, dtype=dtype), np.eye(3)
    shape = np.shape(cell)
    if shape not in ((3,), (3, 3)):
        raise ValueError(f"jaxrt.pairs: cell must be a (3, 3) matrix of "
                         f"lattice vectors as rows (ASE's convention), a (3,) "
                         f"vector of sides, or None; got shape {shape}.")
    if not is_concrete(cell):
        return as_cell_matrix(jnp.asarray(cell, dtype)), None
    h = concrete_cell(cell, pbc)
    return h.astype(dtype), h


def shift_for_cell(h: np.ndarray, cutoff: float, pbc) -> tuple[int, ...]:
    """The reach concrete cells need: ``ceil(cutoff / h_k)`` per periodic
    axis (with a margin over the program's own rounding of the heights);
    ``h`` ``(3, 3)`` or ``(B, 3, 3)`` (the largest of each axis)."""
    if h.ndim == 2:  # one cell: Python floats (numpy calls cost more)
        key = (h.dtype.str, h.tobytes(), cutoff, tuple(pbc))
        found = _reaches.get(key)
        if found is not None:
            return found
        columns = zip(*inverse3(h)[0].tolist())
        need = [math.ceil(cutoff * math.sqrt(sum(v * v for v in c))
                          * (1 + _REACH_MARGIN)) for c in columns]
        return _remember(_reaches, key, tuple(
            int(max(n, 1)) if p else 0 for n, p in zip(need, pbc)))
    else:
        hinv = np.linalg.inv(h)
        heights = 1 / np.sqrt(np.sum(hinv * hinv, axis=-2))
        need = np.ceil(cutoff / heights * (1 + _REACH_MARGIN)).astype(
            int).reshape(-1, 3).max(axis=0).tolist()
    return tuple(int(max(n, 1)) if p else 0 for n, p in zip(need, pbc))


def check_max_shift(max_shift, pbc) -> tuple[int, int, int]:
    values = (max_shift,) * 3 if isinstance(max_shift, (int, np.integer)) \
        else tuple(max_shift)
    if len(values) != 3 or not all(
            isinstance(v, (int, np.integer)) and not isinstance(v, bool)
            and v >= 0 for v in values):
        raise ValueError(f"jaxrt.pairs: max_shift must be an int >= 0 or "
                         f"three of them, got {max_shift!r}.")
    return tuple(int(max(v, 1)) if p else 0 for v, p in zip(values, pbc))


def check_capacity(capacity):
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


def check_sort(sort):
    if sort not in (None, "i"):
        raise ValueError(f"jaxrt.pairs: sort must be None (search order) or "
                         f"'i' (by i, stable), got {sort!r}.")
    return sort == "i"


def is_small(n: int, max_shift) -> bool:
    """Whether an eager call of one system takes
    `host.search_small_host` (every candidate at once, in numpy: no
    program to dispatch)."""
    return n * n * math.prod(2 * r + 1 for r in max_shift) <= SMALL_CANDIDATES


# A flat batch's systems are searched as dense blocks (every atom against
# every atom of its system, in every image of the reach) while each atom
# has at most DENSE_CANDIDATES candidates; past them the cells read fewer
# (on a CPU the two cross between 128 and 256 atoms of fcc at reach 1). A
# system of more than one word (32 atoms) is read by tiles of 32, each atom
# deciding only the tiles near it: they stay faster than the cells up to
# DENSE_TILE_CANDIDATES candidates and DENSE_LARGEST atoms (fcc at reach 1:
# the tiles win at a thousand atoms, the cells at two thousand; the tiles'
# own test grows as the square of the atoms).
DENSE_CANDIDATES = 2 ** 12
DENSE_TILE_CANDIDATES = 2 ** 15
DENSE_LARGEST = 1024
# Every system's block has ``max_nodes`` slots (padding systems too) and
# the blocks pay for every slot, the cells only for real atoms: dense
# blocks only where the real atoms fill more than 1/DENSE_SLOTS_PER_ATOM of
# the slots. Calibrated on a CPU (benchmarks/results/cpu-2core/
# graphs_dense_cells_1495944.csv, jaxrt[dense] against jaxrt[cells]):
# batches of 16 fcc Cu cells of 4-256 atoms (24 systems with padding: 2/3
# of the slots filled) and of 16 primitive Si cells were faster as blocks
# (up to 2.3x) but for 8 and 16 atoms (cells 1.1x, 1.2x); 16 cells of 72
# atoms in 96 slots (half filled) and the mixed batches (a third or less)
# faster by cells (1.1x-6x).
DENSE_SLOTS_PER_ATOM = 2
# Atoms per word (and per tile) of a dense block (`jaxrt.pairs.blocks`).
DENSE_WORD = 32


def dense_nodes(largest: int, max_shift, atoms: int | None = None,
                systems: int | None = None) -> int:
    """The static ``max_nodes`` of dense blocks for systems of at most
    ``largest`` atoms (rounded up by `bucket`), or 0 where cells are the
    better search; ``atoms`` real atoms in ``systems`` systems (padding
    ones included) when known: blocks they fill too little go to cells."""
    m = bucket(largest)
    if atoms is not None and systems is not None and \
            systems * m >= DENSE_SLOTS_PER_ATOM * atoms:
        return 0
    candidates = m * math.prod(2 * r + 1 for r in max_shift)
    if m <= DENSE_WORD:
        return m if candidates <= DENSE_CANDIDATES else 0
    return m if candidates <= DENSE_TILE_CANDIDATES and m <= DENSE_LARGEST \
        else 0


def plan(n: int, pbc, max_shift, backend: str, candidates=None):
    """``(brute, reach, chunk)`` static options of the program (``chunk``:
    candidates per step). ``candidates``: the brute force's atom pairs
    (``N²`` for one system, ``sum n_g²`` for a batch)."""
    if backend not in BACKENDS:
        raise ValueError(f"jaxrt.pairs: backend={backend!r}: choose one of "
                         f"{BACKENDS}.")
    images = math.prod(2 * r + 1 for r in max_shift)
    candidates = n * n if candidates is None else candidates
    brute = backend == "brute" or (
        backend == "auto" and candidates * images <= BRUTE_CANDIDATES)
    if brute:
        reach = max_shift
    else:
        reach = tuple(r if p else 1 for r, p in zip(max_shift, pbc))
    low, high = BLOCK_CANDIDATES
    chunk = min(max(1 << (BLOCK_PER_ATOM * n - 1).bit_length(), low), high)
    return brute, reach, chunk


def estimate(r: np.ndarray, cell: np.ndarray, pbc, cutoff: float) -> int:
    """Pairs (full list) expected of a uniform density: N k with k the atoms
    in a sphere of the cutoff (the atoms' fractional extent plus the cutoff
    on free axes, the whole cell on periodic ones), plus a quarter."""
    n = len(r)
    if n < 2:
        return 1
    hinv, det = inverse3(cell)
    volume = abs(det)
    if not all(pbc):
        f = r @ hinv
        heights = 1 / np.sqrt(np.sum(hinv * hinv, axis=0))
        for k, p in enumerate(pbc):
            if not p:
                volume *= np.ptp(f[:, k]) + 2 * cutoff / heights[k]
    k = n / volume * 4 / 3 * math.pi * cutoff ** 3
    return int(1.25 * n * k) + 16
