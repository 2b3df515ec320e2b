"""Step 6 of `jaxrt.pairs.program`: the pairs `jaxrt.pairs.cells` found,
as the list's rows: both directions or the representative of each pair
from the half stencil, each atom's self pair, padding."""
from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxrt.pairs.host import lex_positive
from jaxrt.pairs.prefix import exclusive_prefix, prefix_sum


def placed_rows(per_atom, rows, binned, selfs, *, capacity, n_graph):
    """The full stencil's rows (int32 ``(capacity, 5)`` from `candidates`),
    found ``i``-major (so stored at their place when there are no self
    pairs), with atom ``i``'s self pair (``selfs``) placed before its
    pairs. Returns int32 ``(capacity, 5)`` rows padded with ``(N, N, 0)``,
    their count and the count per system."""
    n = binned.order.shape[0]
    i = rows[:, 0]
    if selfs is None:
        return rows, jnp.sum(per_atom, dtype=jnp.int32), \
            jax.ops.segment_sum(per_atom, binned.graph, n_graph)
    kept = i < n
    at_i = jnp.where(kept, i, 0)
    own = selfs.astype(jnp.int32)
    # Each pair moves down by the self pairs of the atoms up to its own.
    before = prefix_sum(own, jnp.float64)
    at = jnp.where(kept, jnp.arange(capacity, dtype=jnp.int32)
                   + before[at_i], capacity)
    placed = jnp.broadcast_to(jnp.array([n, n, 0, 0, 0], jnp.int32),
                              (capacity, 5)).at[at].set(rows, mode="drop")
    degree = per_atom + own
    first = exclusive_prefix(degree)
    atoms = jnp.arange(n, dtype=jnp.int32)
    placed = placed.at[jnp.where(selfs, first, capacity)].set(
        jnp.stack([atoms, atoms] + [jnp.zeros_like(atoms)] * 3, axis=1),
        mode="drop")
    return placed, jnp.sum(degree, dtype=jnp.int32), jax.ops.segment_sum(
        degree, binned.graph, n_graph)


def pair_rows(found, per_atom, pairs, binned, *, half, n_graph):
    """The stored pairs ``(i, j, S)`` (int32 ``(R,)``, ``(R,)``, ``(R, 3)``,
    ``i = N`` where padded) as rows: both directions of each (a full list)
    or its representative (a half list). Returns the rows as five int32
    columns (``i``, ``j``, ``S``; a list: XLA reads the output's ``i``,
    ``j`` and ``S`` straight from them, no array of rows in between), their
    count and the count per system (exact past the capacity)."""
    i, j, s = pairs
    s = [s[:, c] for c in range(3)]
    per_system = jax.ops.segment_sum(per_atom, binned.graph, n_graph)
    if half:
        # The representative: i < j, or i == j and S > 0.
        swap = (j < i) | ((j == i) & ~lex_positive(jnp.stack(s, axis=-1)))
        return ([jnp.where(swap, j, i), jnp.where(swap, i, j)]
                + [jnp.where(swap, -x, x) for x in s]), found, per_system

    # Each pair next to its reverse (j, i, -S).
    def interleave(a, b):
        return jnp.stack([a, b], axis=1).reshape(-1)

    return ([interleave(i, j), interleave(j, i)]
            + [interleave(x, -x) for x in s]), 2 * found, 2 * per_system


def self_mask(real, cut, species):
    """bool ``(N,)``: the atoms with a self pair ``(i, i, 0)``, the real
    ones whose own cutoff is positive (ASE keeps ``0 < rc``)."""
    if species is None:
        return real & (cut > 0)
    return real & (cut.at[species, species].get(mode="fill",
                                                 fill_value=0) > 0)


def self_pair_rows(selfs, graph, n_graph):
    """Step 6's self pairs ``(i, i, 0)`` of ``selfs``, packed first: int32
    ``(N, 5)``, their count and count per system."""
    n = selfs.shape[0]
    atoms = jnp.arange(n, dtype=jnp.int32)
    at = exclusive_prefix(selfs.astype(jnp.int32))
    pad = jnp.array([n, n, 0, 0, 0], jnp.int32)
    rows = jnp.broadcast_to(pad, (n, 5)).at[jnp.where(selfs, at, n)].set(
        jnp.stack([atoms, atoms] + [jnp.zeros_like(atoms)] * 3, axis=1),
        mode="drop")
    return rows, jnp.sum(selfs, dtype=jnp.int32), jax.ops.segment_sum(
        selfs.astype(jnp.int32), graph, n_graph)
