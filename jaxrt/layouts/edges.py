"""Per-edge arrays (jax-md's Sparse and OrderedSparse layouts, `jaxrt.pairs`)
kept out of XLA's scatter fusions.

A sum over edges ends in a scatter-add onto particles: `segment_sum` in the
forward pass, and the transpose of every gather ``R[idx]`` in reverse mode.
XLA fuses the computation of the values being scattered (the gathers and the
pair arithmetic) into that scatter, and on the GPU the fused scatter ran an
order of magnitude or more slower than the same values written to memory
and then scattered, for jax-md's own energies as for ours
(`benchmarks/list_forces.py`; docs/benchmarks-notes.md, "Layouts"). An
optimization barrier on the per-edge arrays makes
XLA write them out; its transpose puts a barrier on their cotangents too, so
reverse mode's scatters read plain arrays. The values are unchanged: the
barrier is the identity. Work that runs forward alone (an SPH step) takes
`materialized_in_reverse`, whose barrier falls on the tangents only: there
the forward barrier was memory traffic for nothing.
"""
from __future__ import annotations

from typing import Callable

import jax
from jax.ops import segment_sum

Array = jax.Array


def materialized(tree):
    """``tree`` unchanged, written to memory before its consumers (and, in
    reverse mode, its cotangents before theirs)."""
    return jax.lax.optimization_barrier(tree)


@jax.custom_jvp
def materialized_in_reverse(tree):
    """``tree`` unchanged, and fused as XLA likes where nothing is
    differentiated; its tangents are written to memory, so that in reverse
    mode its cotangents are written out before the scatters that consume
    them (the transposes of its gathers).

    For per-edge work that runs forward alone (an SPH step), where the
    forward barrier of `materialized` is memory traffic for nothing
    (measured slower on the GPU: docs/benchmarks.md, the SPH step).
    A custom JVP, not a custom VJP: forward mode (``jax.jvp``, Hessians)
    keeps working.
    """
    return tree


@materialized_in_reverse.defjvp
def _tangents_materialized(primals, tangents):
    (tree,), (tangent,) = primals, tangents
    return tree, jax.lax.optimization_barrier(tangent)


def edge_sum(values: Array, segment_ids: Array, n: int, *,
             forward_barrier: bool = True) -> Array:
    """`jax.ops.segment_sum` of per-edge ``values`` (float ``(E, ...)``) onto
    ``n`` particles by int ``(E,)`` ``segment_ids``; ids ``>= n`` (padding)
    are dropped. Returns float ``(n, ...)``.

    ``forward_barrier``: the values are written out before the forward
    scatter too (`materialized`); False: in reverse mode only
    (`materialized_in_reverse`)."""
    barrier = materialized if forward_barrier else materialized_in_reverse
    return segment_sum(barrier(values), segment_ids, n)


def materialized_metric(metric: Callable) -> Callable:
    """``metric(Ra, Rb, **kw)`` on materialized inputs: given to jax-md's
    ``smap.pair_neighbor_list``, which vmaps it over the gathered ends of an
    edge list, the barrier falls on the whole ``(E, dim)`` gathers."""

    def metric_of_materialized(Ra, Rb, **kwargs):
        Ra, Rb = materialized((Ra, Rb))
        return metric(Ra, Rb, **kwargs)

    return metric_of_materialized
