"""The Warp engine of the list-free Lennard-Jones sums (``backend=
jaxrt.backends.Cell(kernel="warp")`` of `jaxrt.energy.listfree.lj`): the
grid chosen in JAX, the walk in one call of
`jaxrt.backends.rt.ffi.cell_lj_sums` (`jaxrt.backends.cell.warp_kernels`).

The grid: cells at least ``params.bound`` wide. A periodic axis of side
``L`` has ``floor(L / bound)`` cells (fixed by the box); a free axis spans
the particles' extent, its cells coarsened so that all the free axes'
cells together fit the static table (``free_cells``); padding axes
(`Params.dim`) have one cell.
"""
from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from jaxrt.backends.cell import warp_kernels
from jaxrt.backends.rt import ffi
from jaxrt.energy.listfree.lj import Params

Array = jax.Array


def _flat(params: Params) -> tuple[bool, ...]:
    dim = len(params.side) if params.dim is None else params.dim
    return tuple(a >= dim for a in range(3))


def table_size(n: int, params: Params, reach=(1, 1, 1)
               ) -> tuple[int, int, tuple[int, ...]]:
    """Static: ``(table, free_cells, periodic cells)``: the cell-start
    table's size, the budget of cells of the free axes together, and the
    cells of each periodic axis (0 elsewhere), cells ``bound / reach``
    wide."""
    flat = _flat(params)
    fixed = tuple(max(1, int(math.floor(s * r / params.bound))) if p and not f
                  else 0 for s, p, f, r in zip(params.side, params.periodic,
                                               flat, reach))
    product = math.prod(c for c in fixed if c)
    free = sum(1 for c, f in zip(fixed, flat) if not c and not f)
    budget = max(27, -(-2 * n // product)) if free else 1
    return product * budget, budget, fixed


def grid(R3: Array, params: Params, reach=(1, 1, 1)
         ) -> tuple[Array, Array, int]:
    """``(grid (3, 3), cells int32 (6,), table)`` of
    `jaxrt.backends.rt.ffi.cell_lj_sums` for positions ``R3`` (finite),
    cells ``bound / reach`` wide (static ints per axis)."""
    dtype = R3.dtype
    table, budget, fixed = table_size(R3.shape[0], params, reach)
    flat = _flat(params)
    free = jnp.asarray([not c and not f for c, f in zip(fixed, flat)])
    bound = jnp.asarray(params.bound, dtype) / jnp.asarray(reach, dtype)
    if R3.shape[0]:
        lo, hi = jnp.min(R3, axis=0), jnp.max(R3, axis=0)
    else:
        lo = hi = jnp.zeros((3,), dtype)
    extent = jnp.where(free, hi - lo, 0)
    ideal = jnp.where(free, jnp.clip(jnp.floor(extent / bound), 1, budget), 1)
    k = sum(1 for c, f in zip(fixed, flat) if not c and not f)
    if k:
        product = jnp.prod(ideal.astype(jnp.float32))
        # Coarsen evenly until the free axes' cells fit the budget (the
        # margin covers the rounding of the root).
        shrink = jnp.maximum(1.0, (product / budget) ** (1.0 / k) * 1.001)
        ideal = jnp.where(free, jnp.maximum(1, jnp.floor(ideal / shrink)), 1)
    fixed_cells = jnp.asarray([max(c, 1) for c in fixed], jnp.int32)
    cells = jnp.where(free, ideal.astype(jnp.int32), fixed_cells)
    side = jnp.asarray(params.side, dtype)
    periodic = jnp.asarray([bool(c) for c in fixed])
    width = jnp.where(periodic, side / cells.astype(dtype),
                      jnp.maximum(extent / cells.astype(dtype), bound))
    origin = jnp.where(free, lo, 0).astype(dtype)
    side = jnp.where(periodic, side, 1).astype(dtype)
    cells = jnp.concatenate([cells, jnp.asarray(reach, jnp.int32)])
    return jnp.stack([origin, width.astype(dtype), side]), cells, table


def walk(R3: Array, sigma, epsilon, radii, params: Params, *,
         derivatives: bool = True, count: bool = True, graph: str = "none",
         reach=(1, 1), walk: str = "thread", cluster_size: int = 8):
    """Per-particle sums ``(forces (N, 3), energy, d_sigma, d_epsilon,
    count)`` as `jaxrt.energy.listfree.lj.CellSums`' walks return them,
    forces in the caller's order, each pair in both of its particles'
    sums (the count zero unless ``count``). Non-finite positions give garbage sums (the caller poisons
    them), never an access out of bounds. ``reach``: static, the
    stencil's reach in cells along x and across (cells ``bound / reach``
    wide); ``graph``, ``walk``, ``cluster_size``:
    `jaxrt.backends.rt.ffi.cell_lj_sums`'."""
    reach = (reach[0], reach[1], reach[1])
    flat = _flat(params)
    reach = tuple(1 if f else r for r, f in zip(reach, flat))
    dtype = R3.dtype
    R3 = jnp.where(jnp.all(jnp.isfinite(R3)), R3, 0)
    g, cells, table = grid(R3, params, reach)
    flags = warp_kernels.COUNT if count else 0
    flags |= warp_kernels.DERIVATIVES if derivatives else 0
    flags |= warp_kernels.HAS_RADII if radii is not None else 0
    for a, c in enumerate(table_size(R3.shape[0], params, reach)[2]):
        flags |= (warp_kernels.PERIODIC << a) if c else 0
    values = [None] * warp_kernels.N_PARAMS
    values[warp_kernels.SIGMA], values[warp_kernels.EPSILON] = sigma, epsilon
    values[warp_kernels.R_ONSET] = params.r_onset
    values[warp_kernels.R_CUTOFF] = params.r_cutoff
    packed = jnp.stack([jnp.asarray(v, dtype) for v in values])
    cuts = jnp.zeros((1,), dtype) if radii is None else radii.astype(dtype)
    forces, e, ds, de, c = ffi.cell_lj_sums(R3, cuts, g, cells, packed,
                                            flags=flags, table=table,
                                            graph=graph, walk=walk,
                                            cluster_size=cluster_size)
    return forces, e, ds, de, c.astype(dtype)
