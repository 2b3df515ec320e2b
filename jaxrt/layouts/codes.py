"""A list's pairs read on the host, whatever its layout: for comparing two
lists (the ``jaxrt`` command's checks, the accuracy sweep, tests)."""
from __future__ import annotations

import numpy as np


def pair_codes(nbrs, n: int) -> np.ndarray:
    """Sorted unique ``i * n + j`` (i < j) of a list in any layout.

    Args:
      nbrs: a jax-md ``NeighborList`` (Dense, Sparse or OrderedSparse) of
        ``n`` particles.
    Returns:
      int64 ``(pairs,)``.
    """
    from jax_md import partition
    idx = np.asarray(nbrs.idx)
    if partition.is_sparse(nbrs.format):
        i, j = idx[0], idx[1]
    else:
        i = np.broadcast_to(np.arange(n)[:, None], idx.shape).ravel()
        j = idx.ravel()
    keep = (i < n) & (j < n) & (i != j)
    i, j = i[keep].astype(np.int64), j[keep].astype(np.int64)
    return np.unique(np.minimum(i, j) * n + np.maximum(i, j))
