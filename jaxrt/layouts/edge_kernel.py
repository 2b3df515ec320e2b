"""Left-packed Dense rows to jax-md's edge layouts as one GPU kernel (Pallas,
lowered to Triton).

Row ``i``'s ``count_i`` entries become the edges in slots ``start_i ..
start_i + count_i - 1``, where ``start`` is the rows' counts' exclusive
prefix sum. XLA writes them with two scatters of all ``N x M`` entries (the
invalid ones dropped), far slower on the GPU than the bytes they move
(docs/benchmarks-notes.md, "Layouts"). Here a
program takes ``_ROWS`` consecutive rows
and copies them ``_COLUMNS`` columns at a time: each row's step is one
contiguous load and two contiguous stores (the entries, and the row's index
as their senders), and nothing past a row's count is read or written but
the padding.
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
try:
    from jax.experimental import pallas as pl
    from jax.experimental.pallas import triton as plgpu
    _COMPILER_PARAMS = (getattr(plgpu, "CompilerParams", None)
                        or plgpu.TritonCompilerParams)
except (ImportError, AttributeError):  # an older JAX: XLA's scatters
    pl = plgpu = None

# Rows per program and columns per step: one lane per (row, column), a
# 128-byte run of a row per 32 lanes.
_ROWS = 32
_COLUMNS = 32
_WARPS = 4


def fits(n: int, width: int, capacity: int) -> bool:
    """Whether this JAX has Pallas' Triton backend, and the kernel's int32
    flat offsets address the rows (``n x width``) and both halves of the
    output (``2 x capacity`` slots, a parking slot, and the padding's
    offsets, which run up to a program's worth of lanes per row block
    past ``capacity``)."""
    past = -(-n // _ROWS) * _ROWS * _COLUMNS + _ROWS * _COLUMNS
    return (plgpu is not None and n > 0 and width > 0 and capacity > 0
            and n * width < 2 ** 31 - 1
            and 2 * capacity + past + 1 < 2 ** 31 - 1)


def rows_to_edges(dense, counts, starts, capacity: int, *,
                  interpret: bool = False):
    """Write each row's leading entries as edges from its first slot.

    Args:
      dense: int32 ``(N, M)`` rows, each row's ``counts`` entries first
        (the rest is not read).
      counts: int32 ``(N,)`` entries per row, each at most ``M``.
      starts: int32 ``(N,)`` each row's first slot: the exclusive prefix
        sum of ``counts``.
      capacity: static number of edge slots; edges past it are dropped.
      interpret: run in Pallas' interpreter (any backend; for tests).
    Returns:
      int32 ``(2, capacity)``: row 0 the entries, row 1 the index of the
      row each came from, slots past the last edge padded with ``N``.
    """
    n, width = dense.shape
    programs = -(-n // _ROWS)
    lanes = _ROWS * _COLUMNS
    # Each program also pads its share of the slots (those past the last
    # edge): no fill of the whole output beforehand, which writes every
    # slot once more.
    chunk = -(-capacity // (programs * lanes)) * lanes
    # A masked-off store is no write on a GPU, but Pallas' interpreter
    # writes the old value back, which may land after another lane's write
    # to the same slot: there masked lanes are parked on a spare slot.
    spare = 1 if interpret else 0
    counts = counts.astype(jnp.int32)
    total = jnp.sum(counts, dtype=jnp.int32).reshape(1)
    kernel = functools.partial(_copy_rows, n=n, width=width,
                               capacity=capacity, chunk=chunk,
                               park=spare > 0)
    edges = pl.pallas_call(
        kernel, out_shape=jax.ShapeDtypeStruct((2 * capacity + spare,),
                                               jnp.int32),
        grid=(programs,),
        compiler_params=_COMPILER_PARAMS(num_warps=_WARPS),
        interpret=interpret, name="jaxrt_rows_to_edges",
    )(dense.reshape(-1), counts, starts.astype(jnp.int32), total)
    if spare:
        edges = edges[:2 * capacity]
    return edges.reshape(2, capacity)


def _copy_rows(dense_ref, counts_ref, starts_ref, total_ref, edges_ref, *,
               n, width, capacity, chunk, park):
    """One program: rows ``_ROWS p ..``, lane ``l`` on row ``l // _COLUMNS``
    and column ``l % _COLUMNS`` of each step; then slots ``chunk p ..``
    past the last edge (``total_ref``), padded with ``n``."""
    # Divisions as `jax.lax.div` of non-negative ints: jnp's ``//`` fixes
    # signs with a ``rem``, which reads as periodic wrapping to the checks
    # that a wall box does none (tests/sim/test_scene.py).
    lane = jnp.arange(_ROWS * _COLUMNS, dtype=jnp.int32)
    program = pl.program_id(0)
    lane_row = jax.lax.div(lane, jnp.int32(_COLUMNS))
    row = program * _ROWS + lane_row
    column = lane - lane_row * _COLUMNS
    live = row < n
    row = jnp.minimum(row, n - 1)
    count = jnp.where(live, plgpu.load(counts_ref.at[row]), 0)
    start = plgpu.load(starts_ref.at[row])
    steps = jax.lax.div(jnp.max(count) + _COLUMNS - 1, jnp.int32(_COLUMNS))

    def write(slot, receiver, sender, keep):
        """Both halves of edge ``slot`` where ``keep``."""
        other = capacity + slot
        if park:
            slot = jnp.where(keep, slot, 2 * capacity)
            other = jnp.where(keep, other, 2 * capacity)
        plgpu.store(edges_ref.at[slot], receiver, mask=keep)
        plgpu.store(edges_ref.at[other], sender, mask=keep)

    def copy(t, carry):
        col = t * _COLUMNS + column
        slot = start + col
        keep = (col < count) & (slot < capacity)
        entry = plgpu.load(dense_ref.at[row * width
                                        + jnp.minimum(col, width - 1)],
                           mask=keep, other=n)
        write(slot, entry, row, keep)
        return carry

    jax.lax.fori_loop(0, steps, copy, 0)

    total = total_ref[0]
    first = program * chunk
    padding = jnp.full(lane.shape, n, jnp.int32)

    def pad(t, carry):
        slot = first + t * lane.shape[0] + lane
        write(slot, padding, padding, (slot >= total) & (slot < capacity))
        return carry

    jax.lax.fori_loop(0, chunk // lane.shape[0], pad, 0)
