"""All pairs: the backend ``"brute"`` (jax-md's ``disable_cell_list=True``).

O(N²) time and memory; exact for any metric jax-md accepts, triclinic boxes
and periodic boxes of any size included (each pair as the caller's metric
measures it, through the image it picks), and for per-particle radii
(``d < max(r_i, r_j)``). Meant for small systems and as a reference.
"""
from __future__ import annotations

import dataclasses
import functools
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from jaxrt.backends import contract as _backend
from jaxrt.backends.contract import Capacity, MetricSq, Query


@functools.partial(jax.jit, static_argnames=("width", "query"))
def _rows(position, reach, metric_sq: MetricSq, *, width: int, query: Query):
    """Rows of neighbours of ``position`` (float ``(N, dim)``); ``reach``:
    None or float ``(N,)`` per-particle radii (`Geometry.reach`).

    Returns int32 ``(N, width)`` rows, exact counts and ``j < i`` counts,
    both int32 ``(N,)``.
    """
    n = position.shape[0]
    d2 = jax.vmap(jax.vmap(metric_sq, (None, 0)), (0, None))(position, position)
    if reach is None:
        keep = d2 < jnp.asarray(query.cutoff ** 2, position.dtype)
    else:
        reach = reach.astype(position.dtype)
        keep = d2 < jnp.maximum(reach[:, None], reach[None, :]) ** 2
    j = jnp.broadcast_to(jnp.arange(n, dtype=jnp.int32), (n, n))
    i = j.T
    if query.mask_self:
        keep &= i != j
    rows, count = _backend.pack_rows(j, keep, width)
    return rows, count, jnp.sum(keep & (j < i), axis=1, dtype=jnp.int32)


@dataclasses.dataclass(frozen=True)
class Brute:
    """All pairs as a `jaxrt.backends.Backend` (``"brute"``); no options."""

    name: ClassVar[str] = "brute"
    decides_by_metric: ClassVar[bool] = True
    exact_for_any_metric: ClassVar[bool] = True
    supports_radii: ClassVar[bool] = True
    small_boxes: ClassVar[bool] = True

    def measure(self, position, geometry, query, metric_sq):
        _, count, lower = _rows(position, geometry.reach, metric_sq, width=0,
                                query=query)
        ordered = query.format.name == "OrderedSparse"
        # On the host: NumPy's reductions of a jax.Array compile JAX's.
        count, lower = np.asarray(count), np.asarray(lower)
        return {"row": int(np.max(count, initial=0)),
                "edges": int(np.sum(lower if ordered else count))}

    def search(self, position, geometry, query, capacity: Capacity, metric_sq):
        rows, count, _ = _rows(position, geometry.reach, metric_sq,
                               width=capacity["row"], query=query)
        return _backend.format_dense_rows(rows, count, query, capacity)

