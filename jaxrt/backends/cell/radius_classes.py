"""Per-particle radii on the cell list: cells by radius class (seed 003 §3).

With radii the pair rule is ``d(i, j) < max(r_i, r_j)`` (`jaxrt.backends.contract`).
A grid of cells of the largest radius finds every pair, but for the paper's
log-normal radii (one particle in a hundred 330 times the smallest) it makes
every small particle test the crowd of a 27-cell block sized for the
largest: nearly all pairs of the system. Here instead:

1. **Classes.** Particle ``i`` is in class ``c`` when its reach lies in
   ``(R_c / 2, R_c]``, ``R_c = cutoff · 2**-c``, ``c = 0 .. K - 1``; the
   last class also holds everything smaller. ``K`` is fixed at ``allocate``
   from the smallest radius (`classes_for`); the classes are a static
   function of the radius, so a later radius in any class is still right.
2. **One grid per class**, of the class's particles only, with cells of
   ``R_c`` (a 3**dim stencil; coarsened as the cell list's are, so that the
   table of cell starts stays O(N)).
3. **Each pair is found by its smaller particle.** For ``class(j) <=
   class(i)`` (``j`` the larger or equal), ``d < max(r_i, r_j) <= R_class(j)``,
   so ``i`` finds ``j`` in the stencil of class ``class(j)``'s grid. Each
   particle searches its own class and the larger ones: a small particle
   tests few large ones, and the large ones test nobody smaller.
4. **Both rows.** Pairs of equal classes are found from both ends; a pair of
   unequal classes only by the smaller particle, so it is also written,
   reversed, into the larger one's row (a compacted buffer, sorted by
   row).

Every candidate is decided by the caller's metric, ``metric_sq(R_i, R_j) <
max(reach_i, reach_j)**2``, so the lists are the brute-force ones for any
metric the grid's distance bounds from below (triclinic boxes included).
``Cell(radius_classes=1)`` is the plain scheme (cells of the largest radius),
kept for comparison (`benchmarks/radii.py`).
"""
from __future__ import annotations

import dataclasses
import functools
import itertools
import math
import os

import jax
import jax.numpy as jnp
import numpy as np

from jaxrt.backends import contract as _backend
from jaxrt.backends.contract import Capacity, Geometry, MetricSq, Query
from jaxrt.errors import ListTooLargeError

# More classes than this would only split the tiny radii further (each
# class costs a sort and a stencil pass over N particles).
MAX_CLASSES = 10


def classes_for(reach: np.ndarray, cutoff: float) -> int:
    """Classes enough to give the smallest positive reach a class of its
    own size: ``1 + ceil(log2(cutoff / min reach))``, at most `MAX_CLASSES`."""
    positive = reach[reach > 0]
    if positive.size == 0:
        return 1
    ratio = cutoff / float(positive.min())
    return int(min(max(1 + math.ceil(math.log2(max(ratio, 1.0))), 1),
                   MAX_CLASSES))


def class_of(reach: jax.Array, cutoff: float, classes: int) -> jax.Array:
    """int32 ``(N,)``: each particle's class (0 holds the largest)."""
    c = jnp.zeros(reach.shape, jnp.int32)
    for k in range(1, classes):
        c = c + (reach <= cutoff * 2.0 ** -k).astype(jnp.int32)
    return c


def _class_query(query: Query, c: int) -> Query:
    return dataclasses.replace(query, cutoff=query.cutoff * 2.0 ** -c)


def _stencil(coord, n, query: Query):
    """Cells of the 3**dim stencil around each particle's cell.

    Args:
      coord: int32 ``(N, dim)`` cell coordinates; n: int32 ``(dim,)``.
    Returns:
      int32 ``(N, S)`` cell keys and bool ``(N, S)`` valid (inside the grid
      on free axes; on periodic axes of fewer than 3 cells, the offsets that
      alias an earlier one are dropped, so no cell is visited twice).
    """
    from jaxrt.backends.cell import grid  # which imports the search, ours
    dim = query.dim
    offsets = np.array(list(itertools.product((-1, 0, 1), repeat=dim)),
                       np.int32)  # (S, dim)
    cells = coord[:, None, :] + offsets[None, :, :]
    valid = jnp.ones(cells.shape[:2], bool)
    wrapped = []
    for a in range(dim):
        c = cells[..., a]
        if query.periodic[a]:
            c = jnp.where(c < 0, c + n[a], jnp.where(c >= n[a], c - n[a], c))
            # Offset x aliases an earlier e when n divides the gap x - e.
            first = jnp.stack([
                jnp.all(jnp.stack([jnp.mod(g, n[a]) != 0
                                   for g in range(1, x + 2)]))
                if x > -1 else jnp.asarray(True) for x in offsets[:, a]])
            valid &= first[None, :]
        else:
            valid &= (c >= 0) & (c < n[a])
        wrapped.append(c)
    return grid.key(jnp.stack(wrapped, axis=-1), n), valid


def _class_grid(cart, members, geometry: Geometry, query: Query):
    """One class's grid: cells of the class bound ``query.cutoff``.

    Args:
      cart: float ``(N, dim)`` grid coordinates of every particle.
      members: bool ``(N,)``, the class's particles.
    Returns:
      ``order`` int32 ``(N,)`` (sorted position -> particle; members first),
      ``start`` int32 ``(table + 1,)`` sorted positions where each cell
      begins, and the stencil (`_stencil`) of every particle, int32 and
      bool ``(N, S)``.
    """
    from jaxrt.backends.cell import grid  # which imports the search, ours
    n_particles = cart.shape[0]
    _, coord, n = grid.grid(cart, geometry, query, reach=(1, 1))
    size = grid.table_size(n_particles)
    key = jnp.where(members, grid.key(coord, n), size)  # others past the table
    sorted_key, order = jax.lax.sort(
        (key, jnp.arange(n_particles, dtype=jnp.int32)), num_keys=1,
        is_stable=False)
    del sorted_key
    count = jnp.zeros((size,), jnp.int32).at[key].add(1, mode="drop")
    start = jnp.concatenate([jnp.zeros((1,), jnp.int32),
                             jnp.cumsum(count, dtype=jnp.int32)])
    cells, valid = _stencil(coord, n, query)
    return order, start, count, cells, valid


@functools.partial(jax.jit, static_argnames=("query", "classes"))
def _fullest(position, geometry: Geometry, *, query: Query, classes: int):
    """int32 ``(classes,)``: the most particles in one cell of each class's
    grid (the windows `_candidates` needs)."""
    reach = geometry.reach.astype(position.dtype)
    cls = class_of(reach, query.cutoff, classes)
    cart = geometry.grid_coordinates(position)
    cart = jnp.where(jnp.isfinite(cart), cart, 0.0)
    return jnp.stack([
        jnp.max(_class_grid(cart, cls == c, geometry,
                            _class_query(query, c))[2], initial=0)
        for c in range(classes)])


@functools.partial(jax.jit, static_argnames=("query", "windows"))
def _candidates(position, geometry: Geometry, metric_sq: MetricSq, *,
                query: Query, windows: tuple[int, ...]):
    """Each particle's neighbours of its own class and the larger ones.

    Args:
      windows: static, one per class: the most particles of one cell.
    Returns:
      ``j`` int32 ``(N, M)`` candidates, ``own`` bool ``(N, M)`` (``j`` is a
      neighbour of ``i``), ``reverse`` bool ``(N, M)`` (also write ``i``
      into ``j``'s row: ``j``'s class is larger), the fullest cell of each
      class int32 ``(K,)``.
    """
    n = position.shape[0]
    reach = geometry.reach.astype(position.dtype)
    cls = class_of(reach, query.cutoff, len(windows))
    cart = geometry.grid_coordinates(position)
    cart = jnp.where(jnp.isfinite(cart), cart, 0.0)
    i = jnp.arange(n, dtype=jnp.int32)[:, None]
    js, owns, reverses, fullest = [], [], [], []
    for c, window in enumerate(windows):
        members = cls == c
        order, start, count, cells, valid = _class_grid(
            cart, members, geometry, _class_query(query, c))
        fullest.append(jnp.max(count, initial=0))
        first = start[cells]  # (N, S)
        size = jnp.where(valid, start[cells + 1] - first, 0)
        slot = jnp.arange(window, dtype=jnp.int32)
        at = first[..., None] + slot  # (N, S, W)
        inside = slot < size[..., None]
        j = order[jnp.clip(at, 0, n - 1)].reshape(n, -1)
        inside = inside.reshape(n, -1) & (cls[:, None] >= c)
        if query.mask_self:
            inside &= j != i
        d2 = jax.vmap(jax.vmap(metric_sq, (None, 0)), (0, 0))(position,
                                                               position[j])
        radius = jnp.maximum(reach[:, None], reach[j])
        own = inside & (d2 < radius * radius)
        js.append(j)
        owns.append(own)
        reverses.append(own & (cls[:, None] > c))
    return (jnp.concatenate(js, axis=1), jnp.concatenate(owns, axis=1),
            jnp.concatenate(reverses, axis=1), jnp.stack(fullest))


def _packed(j, mask, width: int):
    """Left-pack ``j`` where ``mask``, a row at a time, by the cell list's
    bit selection (`jaxrt.backends.cell.grid.select`): the output is written, not
    scattered from every candidate (a scatter over N x M candidates was
    most of the update on CPUs).

    Args:
      j: int32 ``(N, M)``; mask: bool ``(N, M)``; width: static columns.
    Returns:
      int32 ``(N, width)`` padded with N, int32 ``(N,)`` exact counts.
    """
    from jaxrt.backends.cell import grid  # which imports the search, ours
    n, m = j.shape
    words = -(-m // 32)
    # About as many groups as words per group: the selection compares
    # each output against every group's last prefix, then within one group.
    group = max(1, math.isqrt(words))
    words = group * -(-words // group)
    mask = jnp.pad(mask, ((0, 0), (0, 32 * words - m)))
    bits = mask.reshape(n, words, 32).astype(jnp.uint32) << jnp.arange(
        32, dtype=jnp.uint32)
    packed = jnp.sum(bits, axis=2, dtype=jnp.uint32)  # distinct bits: an or
    payload = jnp.broadcast_to(
        jnp.arange(words, dtype=jnp.int32)[None, :, None], (n, words, 1))
    bit, got, valid, count = grid.select(packed, width, payload, group)
    column = jnp.clip(32 * got[..., 0] + bit, 0, m - 1)
    picked = jnp.take_along_axis(j, column, axis=1)
    return jnp.where(valid, picked, n), count


def _rows(j, own, reverse, *, width: int, own_row: int, reverse_row: int,
          reverse_capacity: int):
    """Dense rows from `_candidates`' output.

    Args:
      width: static columns of the rows.
      own_row: static, the most neighbours one particle finds itself (the
        selection's cost grows with it: a large particle's row is mostly
        reversed entries, written by the buffer below).
      reverse_row: static, the most reversed entries one particle finds.
      reverse_capacity: static, the most reversed entries in all.
    Returns:
      int32 ``(N, width)`` rows padded with N, int32 ``(N,)`` counts (exact
      unless a buffer overflowed), bool scalar: ``own_row``,
      ``reverse_row`` or ``reverse_capacity`` was too small.
    """
    n = j.shape[0]
    rows, count = _packed(j, own, min(own_row, width))
    rows = jnp.pad(rows, ((0, 0), (0, width - rows.shape[1])),
                   constant_values=n)
    own_overflow = jnp.any(count > own_row)
    # Each particle's larger partners, then all of them in one buffer.
    larger, per_row = _packed(j, reverse, reverse_row)
    flat = larger.reshape(-1)
    real = flat < n
    total = jnp.sum(per_row, dtype=jnp.int32)
    slot = jnp.where(real, jnp.cumsum(real, dtype=jnp.int32) - 1,
                     reverse_capacity)
    senders = jnp.broadcast_to(jnp.arange(n, dtype=jnp.int32)[:, None],
                               larger.shape).reshape(-1)
    row = jnp.full((reverse_capacity,), n, jnp.int32).at[slot].set(
        flat, mode="drop")
    value = jnp.full((reverse_capacity,), n, jnp.int32).at[slot].set(
        senders, mode="drop")
    row, value = jax.lax.sort((row, value), num_keys=1)
    # Rank within the row: distance to the row's first entry.
    rank = jnp.arange(reverse_capacity, dtype=jnp.int32) - jnp.searchsorted(
        row, row, side="left").astype(jnp.int32)
    real = row < n
    place = jnp.where(real, count[jnp.minimum(row, n - 1)] + rank, width)
    rows = rows.at[row, place].set(value, mode="drop")
    count = count + jnp.zeros((n,), jnp.int32).at[row].add(
        real.astype(jnp.int32), mode="drop")
    overflow = ((total > reverse_capacity) | jnp.any(per_row > reverse_row)
                | own_overflow)
    return rows, count, overflow


# int32 flat indices over the candidates (`_rows`' cumsum, the reshapes)
# address at most this many.
MAX_CANDIDATES = 2 ** 31 - 1
# What the update holds per candidate at the least: its index (int32) and
# two flags (`_candidates`' outputs), besides any temporaries.
_CANDIDATE_BYTES = 6


def _memory_bytes(position) -> int | None:
    """The memory of the device ``position`` lives on (its allocator's limit
    where JAX reports one, else the host's RAM), or None if unknown."""
    devices = getattr(position, "devices", None)
    device = next(iter(devices())) if callable(devices) else jax.devices()[0]
    try:
        stats = device.memory_stats() or {}
    except Exception:  # some platforms do not implement it
        stats = {}
    if stats.get("bytes_limit"):
        return int(stats["bytes_limit"])
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def _check_candidates(n: int, windows: tuple[int, ...], query: Query,
                      memory: int | None) -> None:
    """Refuse, before building them, candidate arrays that int32 cannot
    index or that cannot fit in memory (never a wrapped index, never the
    process killed for memory)."""
    per_particle = 3 ** query.dim * sum(windows)
    total = n * per_particle
    needed = total * _CANDIDATE_BYTES
    if total <= MAX_CANDIDATES and (memory is None or needed <= memory):
        return
    why = (f"more than int32 indices address ({MAX_CANDIDATES:,})"
           if total > MAX_CANDIDATES else
           f"at least {needed / 2 ** 30:,.1f} GiB, more than the device's "
           f"{memory / 2 ** 30:,.1f} GiB")
    raise ListTooLargeError(
        f"radii=: the cell list's radius classes would test {total:,} "
        f"candidate pairs (N = {n:,} x {per_particle:,}: the fullest cells "
        f"of the classes hold {list(windows)} particles), {why}. The radii "
        "put most of the system within one particle's reach (a dense "
        "cluster with large radii), so any list is of order N**2. Use the "
        "list-free jaxrt.energy.lennard_jones_fused(..., radii=..., "
        "backend='cell'), which never stores a pair, or fewer particles or "
        "smaller radii.")


@jax.jit
def _sizes(j, own, reverse):
    """Counts of `_candidates`' output, on the device (the candidates never
    travel to the host): int32 ``(N,)`` row lengths, and int32 scalars the
    OrderedSparse edges, the reversed entries, the most of them in one
    row, and the most neighbours one particle finds itself."""
    n = j.shape[0]
    i = jnp.arange(n, dtype=jnp.int32)[:, None]
    own_count = jnp.sum(own, axis=1, dtype=jnp.int32)
    count = own_count + jnp.zeros((n,), jnp.int32).at[
        jnp.where(reverse, j, n)].add(1, mode="drop")
    ordered = (jnp.sum(own & (j < i), dtype=jnp.int32)
               + jnp.sum(reverse & (i < j), dtype=jnp.int32))
    per_row = jnp.sum(reverse, axis=1, dtype=jnp.int32)
    return (count, ordered, jnp.sum(per_row), jnp.max(per_row, initial=0),
            jnp.max(own_count, initial=0))


def measure(position, geometry: Geometry, query: Query, metric_sq: MetricSq,
            classes: int | None) -> dict[str, int]:
    """Exact sizes (see `jaxrt.backends.cell.search.Cell.measure`): ``row``, ``edges``,
    ``classes``, ``window<c>`` per class, ``reverse``, ``reverse_row`` and
    ``own_row``. Eager.

    Raises:
      ValueError: the candidates cannot be indexed or held
        (`_check_candidates`).
    """
    reach = np.asarray(geometry.reach, np.float64)
    k = classes_for(reach, query.cutoff) if classes is None else classes
    windows = tuple(max(int(f), 1) for f in np.asarray(
        _fullest(position, geometry, query=query, classes=k)))
    _check_candidates(position.shape[0], windows, query,
                      _memory_bytes(position))
    j, own, reverse, _ = _candidates(position, geometry, metric_sq,
                                     query=query, windows=windows)
    count, ordered, reversed_, reverse_row, own_row = _sizes(j, own, reverse)
    del j, own, reverse
    count = np.asarray(count)
    if query.format.name == "OrderedSparse":
        edges = int(ordered)
    else:
        edges = int(count.sum(dtype=np.int64))
    sizes = {"row": int(count.max(initial=0)), "edges": edges,
             "classes": k, "reverse": int(reversed_),
             "reverse_row": int(reverse_row), "own_row": int(own_row)}
    sizes.update({f"window{c}": w for c, w in enumerate(windows)})
    return sizes


def search(position, geometry: Geometry, query: Query, capacity: Capacity,
           metric_sq: MetricSq) -> _backend.SearchResult:
    """The list in ``query.format``; jit-able."""
    k = capacity["classes"]
    windows = tuple(capacity[f"window{c}"] for c in range(k))
    j, own, reverse, fullest = _candidates(position, geometry, metric_sq,
                                           query=query, windows=windows)
    rows, count, buffer_overflow = _rows(
        j, own, reverse, width=max(capacity["row"], 1),
        own_row=max(capacity["own_row"], 1),
        reverse_row=max(capacity["reverse_row"], 1),
        reverse_capacity=max(capacity["reverse"], 1))
    result = _backend.format_dense_rows(rows, count, query, capacity)
    overflow = buffer_overflow | jnp.any(fullest > jnp.asarray(windows))
    return result._replace(overflow=result.overflow | overflow)
