"""The Warp engine of the list-free sums (``backend=
jaxrt.backends.Cell(kernel="warp")``): the grid chosen in JAX; for
`jaxrt.energy.listfree.lj`, the walk in one call of
`jaxrt.backends.rt.ffi.cell_lj_sums` (`jaxrt.backends.cell.warp_kernels`);
for `jaxrt.energy.listfree.sph`, the sort in one call (`sort`) and each
pass in one more (`sph_density`, `sph_forces`;
`jaxrt.backends.cell.warp_sph`).

The grid (`jaxrt.backends.cell.warp_grid.build`): cells at least
``params.bound / reach`` wide. A periodic axis of side ``L`` has
``floor(L reach / bound)`` cells (fixed by the box, the table sized for
them); a free axis spans the particles' extent, its cells coarsened so that
all the free axes' cells together fit the rest of the static table
(`table_size`); padding axes (`Params.dim`) have one cell.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxrt.backends.cell import warp_grid, warp_kernels
from jaxrt.backends.rt import ffi
from jaxrt.energy.listfree.lj import Params

Array = jax.Array


def _flat(params: Params) -> tuple[bool, ...]:
    dim = len(params.side) if params.dim is None else params.dim
    return tuple(a >= dim for a in range(3))


def _min_size(params: Params, reach) -> tuple[float, ...]:
    return tuple(params.bound / r for r in reach)


def table_size(n: int, params: Params, reach=(1, 1, 1)
               ) -> tuple[int, tuple[int, ...]]:
    """Static: ``(table, periodic cells)``: the cell-start table's size
    (the periodic axes' cells times a budget for the free axes' cells
    together) and the cells of each periodic axis (0 elsewhere), cells
    ``bound / reach`` wide."""
    flat = _flat(params)
    counted = warp_grid.periodic_cells(params.side, _min_size(params, reach))
    fixed = tuple(c if p and not f else 0
                  for c, p, f in zip(counted, params.periodic, flat))
    product = math.prod(c for c in fixed if c)
    free = sum(1 for c, f in zip(fixed, flat) if not c and not f)
    budget = max(27, -(-2 * n // product)) if free else 1
    return product * budget, fixed


def grid(R3: Array, params: Params, reach=(1, 1, 1)
         ) -> tuple[Array, Array, int]:
    """``(grid (3, 3), cells int32 (6,), table)`` of
    `jaxrt.backends.rt.ffi.cell_lj_sums` for positions ``R3`` (finite),
    cells ``bound / reach`` wide (static ints per axis):
    `jaxrt.backends.cell.warp_grid.build` on the periodic axes' static
    sides, with a table that holds their cells times the free axes'
    budget."""
    table, fixed = table_size(R3.shape[0], params, reach)
    g, cells = warp_grid.build(
        R3, params.side, periodic=tuple(bool(c) for c in fixed),
        padding=_flat(params), min_size=_min_size(params, reach),
        reach=reach, table=table)
    return g, cells, table


def stencil_reach(params: Params, reach=(1, 1)) -> tuple[int, int, int]:
    """Static: the stencil's reach in cells per axis from ``(along x,
    across)``, 1 on padding axes."""
    reach = (reach[0], reach[1], reach[1])
    return tuple(1 if f else r for r, f in zip(reach, _flat(params)))


def periodic_flags(n: int, params: Params, reach) -> int:
    """Static: the ``PERIODIC << axis`` bits of the grid's periodic axes
    (``reach`` per axis, `stencil_reach`)."""
    flags = 0
    for a, c in enumerate(table_size(n, params, reach)[1]):
        flags |= (warp_kernels.PERIODIC << a) if c else 0
    return flags


def finite(R3: Array) -> Array:
    """``R3``, or zeros if any entry is not finite: garbage sums (which
    the callers poison) rather than cells out of range."""
    return jnp.where(jnp.all(jnp.isfinite(R3)), R3, 0)


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
    reach = stencil_reach(params, reach)
    dtype = R3.dtype
    R3 = finite(R3)
    g, cells, table = grid(R3, params, reach)
    flags = warp_kernels.COUNT if count else 0
    flags |= warp_kernels.DERIVATIVES if derivatives else 0
    flags |= warp_kernels.HAS_RADII if radii is not None else 0
    flags |= periodic_flags(R3.shape[0], params, reach)
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


# ---------------------------------------------------------------------------
# The SPH walks (`jaxrt.energy.listfree.sph`'s ``Cell(kernel="warp")``):
# one sort, then a walk per pass on it.


class Sorted(NamedTuple):
    """One configuration binned and sorted by `sort`: ``order`` int32
    ``(N,)`` (the caller's index of each sorted particle), ``keys``,
    ``start``, ``position`` (wrapped, sorted), ``grid`` and ``cells``, as
    `jaxrt.backends.rt.ffi.cell_sort` and `grid` return them."""

    order: Array
    keys: Array
    start: Array
    position: Array
    grid: Array
    cells: Array


def sort(R3: Array, params: Params, reach=(1, 1)) -> Sorted:
    """Bin and sort ``R3`` (float ``(N, 3)``) on the grid of `grid`, cells
    ``bound / reach`` wide (``reach``: static, along x and across)."""
    n = R3.shape[0]
    reach = stencil_reach(params, reach)
    R3 = finite(jax.lax.stop_gradient(R3))
    g, cells, table = grid(R3, params, reach)
    keys, values, start, position = ffi.cell_sort(
        R3, g, cells, flags=periodic_flags(n, params, reach), table=table)
    return Sorted(values[:n], keys, start, position, g, cells)


def sph_density(state: Sorted, params: Params, reach, kind: str,
                constants: Array, mass: Array) -> Array:
    """``sum_{j != i} m_j W(r_ij)`` per sorted particle, float ``(N,)``.

    ``params``, ``reach``: `sort`'s; ``kind``: the kernel (one of
    `jaxrt.backends.cell.warp_sph.KINDS`); ``constants``:
    ``(warp_sph.N_PARAMS,)`` in the positions' dtype; ``mass`` ``(N,)``
    sorted."""
    flags = periodic_flags(state.order.shape[0], params,
                           stencil_reach(params, reach))
    return ffi.cell_sph_density(state.position, state.keys, state.start,
                                state.grid, state.cells, constants, mass,
                                flags=flags, kind=kind)


def sph_forces(state: Sorted, params: Params, reach, kind: str,
               constants: Array, V3: Array, mass: Array, rho: Array,
               q: Array, sound: Array) -> tuple[Array, Array]:
    """``(pressure, viscosity)`` accelerations per sorted particle, float
    ``(N, 3)``: as `sph_density`, with ``V3`` ``(N, 3)`` and ``mass``,
    ``rho``, ``q = P / rho^2``, ``sound`` ``(N,)``, all sorted."""
    flags = periodic_flags(state.order.shape[0], params,
                           stencil_reach(params, reach))
    return ffi.cell_sph_forces(state.position, state.keys, state.start,
                               state.grid, state.cells, constants, V3, mass,
                               rho, q, sound, flags=flags, kind=kind)


def sph_step(R3: Array, V3: Array, mass: Array, params: Params, reach,
             kind: str, constants: Array, graph: str = "none"
             ) -> tuple[Array, Array, Array]:
    """A whole SPH step's sums in one call
    (`jaxrt.backends.rt.ffi.cell_sph_step`): ``(pressure (N, 3),
    viscosity (N, 3), density (N,))`` accelerations and summation
    densities, the caller's order. ``R3``, ``V3`` float ``(N, 3)``,
    ``mass`` ``(N,)``; ``constants``: every row of
    `jaxrt.backends.cell.warp_sph`'s params; the rest as `sort`'s and
    `sph_density`'s."""
    n = R3.shape[0]
    reach = stencil_reach(params, reach)
    R3 = finite(jax.lax.stop_gradient(R3))
    g, cells, table = grid(R3, params, reach)
    return ffi.cell_sph_step(R3, V3, mass, g, cells, constants,
                             flags=periodic_flags(n, params, reach),
                             table=table, kind=kind, graph=graph)
