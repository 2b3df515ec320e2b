"""Where each atom lands in its system's grid (step 3 of
`jaxrt.pairs.program`), shared by the searches that bin atoms: the static
stencil's (`jaxrt.pairs.cells`), each system's own reach
(`jaxrt.pairs.reach`) and the GPU's walk (`jaxrt.pairs.warp_search`)."""
from __future__ import annotations

import jax.numpy as jnp

from jaxrt.pairs.bits import ErrorBit


def short_reach_bit(pbc, grid_cells, h_height, radius, reach, count,
                    bad_cell):
    """int32 ``MAX_SHIFT`` where a system with atoms and a regular cell
    has a periodic axis whose cells reach less than the cutoff (``reach``:
    per axis, or ``(G, 3)`` per system), else 0."""
    short = jnp.any(pbc & (radius * grid_cells / h_height > reach),
                    axis=-1) & (count > 0) & ~bad_cell
    return jnp.where(jnp.any(short), int(ErrorBit.MAX_SHIFT), 0)


def cell_coords(fw, graph, origin, width, cells_a):
    """int32 ``(N, 3)``: each atom's cell, clamped into its system's grid
    (``fw`` the wrapped fractional positions, ``cells_a`` each atom's
    system's cells per axis)."""
    return jnp.clip(jnp.floor((fw - origin[graph]) / width[graph]).astype(
        jnp.int32), 0, cells_a - 1)
