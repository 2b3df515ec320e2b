"""Words of 32 candidates: the keep bits of up to 32 candidates as one
uint32, counted, packed and read back row by row. The dense blocks
(`jaxrt.pairs.blocks`) and the cell search's short runs
(`jaxrt.pairs.cells`) share them."""
from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxrt.pairs.checks import DENSE_WORD as WORD


def popcount(x):
    """int32 set bits of uint32 ``x`` (elementwise)."""
    return jax.lax.population_count(x).astype(jnp.int32)


def pack(keep):
    """uint32 ``(..., W)`` words of bool ``(..., 32 W)`` (bit ``b`` of word
    ``w``: entry ``32 w + b``)."""
    shape = keep.shape
    keep = keep.reshape(shape[:-1] + (shape[-1] // WORD, WORD))
    bit = jnp.arange(WORD, dtype=jnp.uint32)
    return jnp.sum(jnp.where(keep, jnp.uint32(1) << bit, jnp.uint32(0)),
                   axis=-1, dtype=jnp.uint32)


def select_bit(bits, rank):
    """int32 ``(R,)``: the position of the set bit of rank ``rank`` (int32
    ``(R,)``, from 0) in each uint32 ``bits`` ``(R,)``: the bits whose
    inclusive count is at most ``rank``, counted (one reduction: XLA
    writes it out once rather than computing it again in each reader)."""
    lanes = jnp.arange(WORD, dtype=jnp.uint32)
    # (2 << 31) - 1 wraps to every bit, as wanted.
    upto = (jnp.uint32(2) << lanes) - jnp.uint32(1)
    inclusive = popcount(bits[:, None] & upto)
    return jnp.sum(inclusive <= rank[:, None], axis=1, dtype=jnp.int32)


def running_max(x):
    """int32 ``(n,)`` inclusive running maximum of int32 ``(n,)`` ``x``."""
    return jax.lax.associative_scan(jnp.maximum, x)


def row_words(counts, ends, capacity):
    """Where each of ``capacity`` rows lies among words of int32 ``counts``
    ``(W,)`` rows (inclusive running counts ``ends``): int32 ``(capacity,)``
    word and rank in it, and bool ``(capacity,)`` whether the row is
    stored. Each nonempty word marks its first row; a row's word is the
    last mark at or before it (a running maximum: no search per row)."""
    r = jnp.arange(capacity, dtype=jnp.int32)
    word_start = ends - counts
    marks = jnp.zeros((capacity,), jnp.int32).at[jnp.where(
        counts > 0, word_start, capacity)].set(
            jnp.arange(counts.shape[0], dtype=jnp.int32), mode="drop")
    wid = running_max(marks)
    return wid, r - word_start[wid], r < ends[-1]
