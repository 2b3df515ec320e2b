"""Steps 3-6 of `jaxrt.pairs.program` on a GPU: the cells found and sorted
as the program finds them (`jaxrt.pairs.cells`), the stencil walked by
one Warp kernel per atom (`jaxrt.pairs.warp_kernels`, through
`jaxrt.backends.rt.ffi.pair_walk`) instead of the program's arrays of runs
per atom and offset.

The rows are the full stencil's, row for row: ``i``-major, each atom's self
pair (when asked for) first, then its pairs offset by offset and, within a
cell, in the cell's sorted order; every candidate is decided as the program
decides it (`jaxrt.pairs.cells.square_limit`), in the positions' dtype.
The count and the count per system are exact past the capacity.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxrt.pairs.cells import frame, grid, sort_cells, square_limit
from jaxrt.pairs.placement import cell_coords, short_reach_bit
from jaxrt.pairs.rows import self_mask

# How the walk's call runs on CUDA (`jaxrt.backends.rt.ffi.pair_walk`):
# "none" launches its kernels from the callback every call, "warp" replays
# a CUDA graph of them.
GRAPH = "none"
# The scratch row of each atom during the count holds this many times the
# pairs per atom the capacity allows (at least WIDTH_LEAST, at most
# WIDTH_MOST, a multiple of four); atoms with more are walked again. 0: no
# scratch, the walk runs twice (count, write), which measured faster than
# the scratch rows' first copy kernel (benchmarks/results/h100/pairs_gpu_*).
WIDTH_SLACK = 0.0
WIDTH_LEAST, WIDTH_MOST = 8, 512


class WalkInputs(NamedTuple):
    """What the walk reads (`jaxrt.pairs.warp_kernels`), in its order."""
    position: jax.Array         # float (N, 3) the caller's positions
    sorted_position: jax.Array  # float (N, 3) by sorted slot
    sorted_wrap: jax.Array      # int32 (N, 3) whole cells moved, by slot
    sorted_species: jax.Array   # int32 (N,) by slot
    order: jax.Array            # int32 (N,) sorted slot -> atom
    coord: jax.Array            # int32 (N, 3) each atom's cell
    wrap: jax.Array             # int32 (N, 3) whole cells moved
    graph: jax.Array            # int32 (N,)
    real: jax.Array             # int32 (N,) 1 for atoms with pairs
    selfs: jax.Array            # int32 (N,) 1 for atoms with a self pair
    species: jax.Array          # int32 (N,)
    cells: jax.Array            # int32 (G, 3) cells per axis
    base: jax.Array             # int32 (G,) first cell in the table
    pbc: jax.Array              # int32 (G, 3)
    lattice: jax.Array          # float (G, 3, 3) completed cells (rows)
    runs: jax.Array             # int32 (T, 2) first slot, length per cell
    limit: jax.Array            # float (S * S,) squared cutoffs


def walk_inputs(positions, graph, mask, cells, pbc, cut, species, radius, *,
                reach, n_graph, completed, self_interaction):
    """Steps 1-4 of `jaxrt.pairs.program` (the cells, the sort) as the
    walk reads them. Returns `WalkInputs`, the number of species of
    ``limit`` and int32 error bits."""
    (error, real, graph, _, h, bad_cell, h_height, count, pbc_a, w,
     fw) = frame(positions, graph, mask, cells, pbc, n_graph=n_graph,
                 completed=completed)
    grid_cells, origin, width, base = grid(
        fw, graph, real, pbc, h_height, radius, reach, n_graph, False, count)
    error = error | short_reach_bit(pbc, grid_cells, h_height, radius,
                                    np.array(reach), count, bad_cell)
    cells_a = grid_cells[graph]
    coord = cell_coords(fw, graph, origin, width, cells_a)
    order, _, runs = sort_cells(coord, cells_a, base[graph], real, n_graph)
    n = positions.shape[0]
    if species is None:
        kinds = jnp.zeros((n,), jnp.int32)
        limit, n_species = square_limit(cut).reshape(1), 1
    else:
        # A species outside the matrix reads a row and column of -inf: no
        # pairs, as the program's reads filled past the matrix.
        n_species = cut.shape[0] + 1
        kinds = jnp.asarray(species, jnp.int32)
        kinds = jnp.where((kinds >= 0) & (kinds < cut.shape[0]), kinds,
                          cut.shape[0])
        limit = jnp.pad(square_limit(cut), (0, 1),
                        constant_values=-jnp.inf).reshape(-1)
    wrap = w.astype(jnp.int32)
    selfs = self_mask(real, cut, species) if self_interaction \
        else jnp.zeros((n,), bool)
    r = jax.lax.stop_gradient(positions)
    i32 = [jnp.asarray(x).astype(jnp.int32) for x in (
        order, coord, grid_cells, base, runs)]
    order, coord, grid_cells, base, runs = i32
    inputs = WalkInputs(
        position=r, sorted_position=r[order], sorted_wrap=wrap[order],
        sorted_species=kinds[order], order=order, coord=coord, wrap=wrap,
        graph=graph.astype(jnp.int32), real=real.astype(jnp.int32),
        selfs=selfs.astype(jnp.int32), species=kinds, cells=grid_cells,
        base=base, pbc=pbc.astype(jnp.int32), lattice=h.astype(r.dtype),
        runs=runs, limit=limit.astype(r.dtype))
    return inputs, n_species, error


def warp_stencil(positions, graph, mask, cells, pbc, cut, species, radius, *,
                 reach, capacity, half, self_interaction, n_graph,
                 completed):
    """`jaxrt.pairs.program`'s full stencil (``_full_stencil``'s returns)
    by the Warp walk: int32 ``(capacity, 5)`` rows padded with ``(N, N,
    0)``, int32 count, int32 ``(G,)`` count per system, int32 error bits
    (before the capacity's)."""
    from jaxrt.backends.rt import ffi
    n = positions.shape[0]
    inputs, n_species, error = walk_inputs(
        positions, graph, mask, cells, pbc, cut, species, radius,
        reach=reach, n_graph=n_graph, completed=completed,
        self_interaction=self_interaction)
    degree, total, rows = ffi.pair_walk(
        inputs, n_species=n_species, reach=tuple(int(r) for r in reach),
        half=half, capacity=capacity, width=scratch_width(capacity, n),
        graph=GRAPH)
    per_system = jax.ops.segment_sum(degree, inputs.graph, n_graph)
    return rows[:capacity], total[0], per_system, error


def scratch_width(capacity: int, n: int) -> int:
    """Pairs per atom kept in scratch during the count (static)."""
    if WIDTH_SLACK <= 0:
        return 0
    per_atom = int(np.ceil(WIDTH_SLACK * capacity / max(n, 1)))
    return int(min(max(-(-per_atom // 4) * 4, WIDTH_LEAST), WIDTH_MOST))
