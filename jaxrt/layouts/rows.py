"""jax-md's layouts from Dense rows: left-packing rows (`pack_rows`) and
rows to edges (`dense_to_sparse`, one Pallas kernel on CUDA:
`jaxrt.layouts.edge_kernel`).

Layouts (``N`` particles, padding index ``N`` everywhere):

* Dense: ``idx`` int32 ``(N, capacity)``, row ``i`` left-packed with the
  neighbours of ``i``.
* Sparse: ``idx`` int32 ``(2, capacity)`` = (receivers ``j``, senders ``i``),
  valid edges a prefix, both directions present.
* OrderedSparse: as Sparse, only edges with ``j < i``.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxrt import platforms
from jaxrt.layouts import edge_kernel as _edge_kernel

Array = jax.Array


def pack_rows(idx: Array, keep: Array, capacity: int) -> tuple[Array, Array]:
    """Left-pack the kept entries of each row into ``capacity`` columns.

    Args:
      idx: int32 ``(N, M)`` candidate neighbour indices.
      keep: bool ``(N, M)``, which candidates are neighbours.
      capacity: output width.
    Returns:
      int32 ``(N, capacity)`` padded with ``N``, and int32 ``(N,)`` exact
      counts (which may exceed ``capacity``).
    """
    n = idx.shape[0]
    slot = jnp.cumsum(keep, axis=1, dtype=jnp.int32) - 1
    slot = jnp.where(keep, slot, capacity)  # out of range: dropped
    rows = jnp.broadcast_to(jnp.arange(n, dtype=jnp.int32)[:, None], idx.shape)
    out = jnp.full((n, capacity), n, jnp.int32)
    out = out.at[rows, slot].set(idx.astype(jnp.int32), mode="drop")
    return out, jnp.sum(keep, axis=1, dtype=jnp.int32)


_ENGINES = ("auto", "xla", "interpret")


def dense_to_sparse(dense: Array, capacity: int, ordered: bool, *,
                    counts: Array | None = None, engine: str = "auto"
                    ) -> tuple[Array, Array]:
    """Convert a left-packed Dense list to jax-md's Sparse layout.

    Args:
      dense: int32 ``(N, M)`` padded with ``N``, each row's entries first.
      capacity: number of edge slots in the output.
      ordered: keep only edges with ``j < i`` (OrderedSparse).
      counts: None, or int32 ``(N,)`` the rows' entries (each at most
        ``M``), known already; else counted from ``dense``. Only for rows
        that are edges as they stand (``ordered`` false): ordered rows'
        counts are those of their ``j < i`` entries, counted here.
      engine: ``"auto"``: rows that are edges as they stand (``ordered``
        false) are copied by one kernel on CUDA GPUs
        (`jaxrt.layouts.edge_kernel`), by XLA's scatters elsewhere; ``"xla"``:
        the scatters everywhere; ``"interpret"``: the kernel in Pallas'
        interpreter (tests). All write the same array.
    Returns:
      int32 ``(2, capacity)`` = (receivers j, senders i), valid edges first
      in row order, padded with ``N``; and the exact int32 number of edges.
    """
    if engine not in _ENGINES:
        raise ValueError(f"dense_to_sparse: engine={engine!r}; choose one "
                         f"of {_ENGINES}.")
    if ordered and counts is not None:
        raise ValueError("dense_to_sparse: counts= is for rows that are "
                         "edges as they stand; with ordered=True the j < i "
                         "entries are counted here (pass counts=None).")
    n, width = dense.shape
    senders = jnp.arange(n, dtype=jnp.int32)[:, None]
    keep = dense < n
    if ordered:
        keep = keep & (dense < senders)
        # The kept entries are spread along each row: rank them in it.
        rank = jnp.cumsum(keep, axis=1, dtype=jnp.int32) - 1
    else:
        # Left-packed: entry c of a row is its c-th edge.
        rank = jnp.arange(width, dtype=jnp.int32)[None, :]
    # Each row's first slot from N row counts, not a scan over all N x M
    # entries (the conversion's cost at 10^6: benchmarks/RESULTS.md).
    if counts is None:
        counts = jnp.sum(keep, axis=1, dtype=jnp.int32)
    counts = counts.astype(jnp.int32)
    starts = jnp.cumsum(counts, dtype=jnp.int32) - counts
    total = jnp.sum(counts, dtype=jnp.int32)

    def scatters():
        slot = jnp.where(keep, starts[:, None] + rank, capacity).reshape(-1)
        # Written out, not fused into the scatters (jaxrt.layouts.edges).
        slot = jax.lax.optimization_barrier(slot)
        out = jnp.full((2, capacity), n, jnp.int32)
        out = out.at[0, slot].set(dense.reshape(-1), mode="drop")
        return out.at[1, slot].set(
            jnp.broadcast_to(senders, dense.shape).reshape(-1), mode="drop")

    def kernel(interpret=False):
        return _edge_kernel.rows_to_edges(dense, counts, starts, capacity,
                                          interpret=interpret)

    if (ordered or engine == "xla" or capacity == 0
            or not _edge_kernel.fits(n, width, capacity)):
        return scatters(), total
    if engine == "interpret":
        return kernel(interpret=True), total
    return platforms.cuda_or_default(kernel, scatters), total
