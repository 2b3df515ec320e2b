"""The cell search of a flat batch with each system's own reach (the sorted
lists of `jaxrt.pairs.program`, steps 3-5, when a batch holds several
systems).

The static reach ``R`` of a batch is the largest any system needs; a
system whose cell is large against the cutoff needs less. Here system
``g`` searches with its own reach per axis, ``r_gk = ceil(cutoff (1 +
margin) / h_gk)`` on its periodic axes (at most ``R_k``; past it the
error bit is set as with the static reach), 1 on its free axes, and its
cells are cut for that reach (at least ``cutoff / (r_gk h_gk)`` wide). Atom
``i`` then reads ``prod_k (2 r_gk + 1)`` runs (its *lanes*), not
``prod_k (2 R_k + 1)``: the lanes of all atoms are laid end to end,
atom by atom (``i``-major) and offset by offset (lexicographic, as
`jaxrt.pairs.cells.offsets`), and read ``chunk`` lanes at a time in a
loop until every lane is read. In each chunk slot ``t`` of every lane is
decided in step ``t`` of a loop (as many steps as the chunk's longest
run), kept as bit ``t`` of the lane's uint32 word; the kept candidates
are then written at the running count, a window of rows at a time (a
row's lane found by a running maximum, its slot by its bit's rank), so
the rows come out ``i``-major and the count is exact past the capacity.

Each candidate is decided as `jaxrt.pairs.cells` decides it (the same
sums in the positions' dtype, the squared cutoff of
`jaxrt.pairs.cells.square_limit`). A batch with a cell of more than a
word of atoms is searched by ``fallback`` (the static stencil), and so is
one where the static stencil's slots are estimated to cost less (its
finer cells hold fewer atoms).
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxrt.pairs.cells import (CELL_MARGIN, frame, grid, offsets,
                               sort_cells, square_limit, table_size)
from jaxrt.pairs.host import lex_positive
from jaxrt.pairs.placement import cell_coords, short_reach_bit
from jaxrt.pairs.prefix import prefix_sum
from jaxrt.pairs.rows import placed_rows, self_mask
from jaxrt.pairs.words import WORD, popcount, running_max, select_bit

# Lanes read per step of the chunk loop: per atom of the batch (bounded
# below and above), rounded up to a power of two.
LANES_PER_ATOM = 8
LANE_CHUNK = (2 ** 10, 2 ** 13)
# A slot of the lanes read here against one of the static stencil's slot
# loop (`jaxrt.pairs.cells`), which reads its runs in one fused pass: the
# estimate that picks one search or the other (graphs.py's batches).
RAGGED_SLOT_COST = 2.0
# Rows written per step of a chunk's writing loop, per lane of the chunk.
WINDOW_ROWS_PER_LANE = 2


def lane_chunk(n: int) -> int:
    """The static lanes per step for ``n`` atoms."""
    low, high = LANE_CHUNK
    return min(max(1 << (LANES_PER_ATOM * max(n, 1) - 1).bit_length(), low),
               high)


def system_reach(h_height, pbc, radius, reach):
    """int32 ``(G, 3)``: each system's own reach, ``ceil(radius (1 +
    margin) / h)`` on its periodic axes clipped to ``[1, reach_k]``, 1 on
    its free axes (``h_height`` float ``(G, 3)``, ``pbc`` bool ``(G, 3)``,
    ``reach`` the static reach)."""
    need = jnp.ceil(radius * (1 + CELL_MARGIN) / h_height)
    top = np.maximum(np.array(reach), 1)
    # NaN (a NaN cutoff) compares False: the static reach.
    need = jnp.maximum(jnp.where(need <= top, need, top), 1)
    return jnp.where(pbc, need, 1).astype(jnp.int32)


class _Lanes(NamedTuple):
    """The binned atoms and their lanes (by atom, in the caller's order)."""
    error: jax.Array     # int32 bits so far
    real: jax.Array      # bool (N,)
    graph: jax.Array     # int32 (N,) clipped
    # order, rank, runs: None until the own reach's search sorts the atoms
    order: jax.Array     # int32 (N,) sorted slot -> atom
    rank: jax.Array      # int32 (N,) atom -> sorted slot
    runs: jax.Array      # int32 (T, 2) each cell's first slot and length
    coord: jax.Array     # int32 (N, 3) each atom's cell
    cells: jax.Array     # int32 (N, 3) its system's cells per axis
    base: jax.Array      # int32 (N,) its system's first cell
    pbc: jax.Array       # bool (N, 3)
    reach: jax.Array     # int32 (N, 3) its system's reach
    w: jax.Array         # float (N, 3) whole cells each atom was moved by
    h: jax.Array         # (G, 3, 3) completed cells
    lane_end: jax.Array  # int32 (N,) inclusive running count of lanes
    fullest: jax.Array   # int32 (2,) the most atoms in a cell: own grid,
    # static grid


def bin_lanes(positions, graph, mask, cells, pbc, radius, *, reach,
              n_graph, completed) -> _Lanes:
    """Steps 1-3 with each system's own reach (module docstring)."""
    f = frame(positions, graph, mask, cells, pbc, n_graph=n_graph,
              completed=completed)
    # Each system's least reach: finer cells (a larger reach, as the static
    # stencil cuts them) read more lanes, which cost more than the fuller
    # cells they spare (graphs.py's batches).
    r_sys = system_reach(f.h_height, pbc, radius, reach)
    # The grid of reach 1 on heights times the reach: cells at least
    # radius / (r h) wide, as the grid of the static reach cuts them.
    grid_cells, origin, width, base = grid(
        f.fw, f.graph, f.real, pbc, f.h_height * r_sys, radius, (1, 1, 1),
        n_graph, False, f.count)
    error = f.error | short_reach_bit(pbc, grid_cells, f.h_height, radius,
                                      r_sys, f.count, f.bad_cell)
    cells_a, base_a = grid_cells[f.graph], base[f.graph]
    coord = cell_coords(f.fw, f.graph, origin, width, cells_a)
    reach_a = r_sys[f.graph]
    lanes = jnp.where(f.real, jnp.prod(2 * reach_a + 1, axis=-1), 0)
    # The static grid's cells, for its fullest cell (its slot loop's steps).
    s_cells, s_origin, s_width, s_base = grid(
        f.fw, f.graph, f.real, pbc, f.h_height, radius, reach, n_graph,
        False, f.count)
    s_cells_a = s_cells[f.graph]
    s_coord = jnp.clip(jnp.floor((f.fw - s_origin[f.graph]) / s_width[
        f.graph]).astype(jnp.int32), 0, s_cells_a - 1)
    table = table_size(positions.shape[0], n_graph, False)
    fullest = jnp.stack([
        _fullest(coord, cells_a, base_a, f.real, table),
        _fullest(s_coord, s_cells_a, s_base[f.graph], f.real, table)])
    # The atoms are sorted by cell (order, rank, runs) only where the
    # own reach's search runs.
    return _Lanes(error, f.real, f.graph, None, None, None, coord, cells_a,
                  base_a, f.pbc_a, reach_a, f.w, f.h,
                  prefix_sum(lanes, jnp.float64, small=True), fullest)


def _fullest(coord, cells_a, base_a, real, table):
    """int32: the most real atoms in one cell."""
    key = jnp.where(real, base_a + (coord[:, 2] * cells_a[:, 1]
                                    + coord[:, 1]) * cells_a[:, 0]
                    + coord[:, 0], table)
    return jnp.max(jnp.zeros((table,), jnp.int32).at[key].add(
        1, mode="drop"), initial=0)


def ragged_full_stencil(positions, graph, mask, cells, pbc, cut, species,
                        radius, *, reach, capacity, half, self_interaction,
                        n_graph, completed, fallback):
    """`jaxrt.pairs.program`'s full-stencil steps 3-6 with each system's
    own reach (module docstring); ``fallback()`` (the static stencil) where
    a cell holds more than a word of atoms. Returns int32 ``(capacity, 5)``
    rows ``(i, j, S)`` padded with ``(N, N, 0)``, the count, the count per
    system and the error bits."""
    lanes = bin_lanes(positions, graph, mask, cells, pbc, radius,
                      reach=reach, n_graph=n_graph, completed=completed)

    def ragged():
        order, rank, runs = sort_cells(lanes.coord, lanes.cells, lanes.base,
                                       lanes.real, n_graph)
        binned = lanes._replace(order=order, rank=rank, runs=runs)
        per_atom, rows = _read_lanes(positions, binned, cut, species,
                                     stored=capacity, half=half)
        selfs = self_mask(lanes.real, cut, species) if self_interaction \
            else None
        rows, total, per_system = placed_rows(
            per_atom, rows, binned, selfs, capacity=capacity,
            n_graph=n_graph)
        return rows, total, per_system, lanes.error

    # Own reach where its slots (lanes times the fullest cell) cost less
    # than the static stencil's (every atom's runs times its fullest cell).
    fullest = lanes.fullest[0]
    own = RAGGED_SLOT_COST * lanes.lane_end[-1].astype(jnp.float32) * \
        fullest < positions.shape[0] * offsets(reach, True).shape[0] * \
        jnp.maximum(lanes.fullest[1], 1).astype(jnp.float32)
    return jax.lax.cond((fullest <= WORD) & own, ragged, fallback)


def _lane_runs(lanes: _Lanes, ell, n):
    """The lanes ``ell`` (int32 ``(L,)``, past the last: empty): atom,
    run start and length, image ``S' + w[i]`` (int32 ``(L, 3)``) and
    whether the offset is zero."""
    valid = ell < lanes.lane_end[-1]
    a = jnp.minimum(jnp.searchsorted(lanes.lane_end, ell, side="right"),
                    n - 1).astype(jnp.int32)
    r = lanes.reach[a]
    dims = 2 * r + 1
    q = ell - (lanes.lane_end[a] - jnp.where(
        lanes.real[a], jnp.prod(dims, axis=-1), 0))
    # Lexicographic, axis 0 the slowest (as `offsets` lists them).
    o2 = q % dims[:, 2]
    q = q // dims[:, 2]
    o = [q // dims[:, 1] - r[:, 0], q % dims[:, 1] - r[:, 1], o2 - r[:, 2]]
    cells_a = lanes.cells[a]
    inside = valid
    target, image = [], []
    for c in range(3):
        t = lanes.coord[a, c] + o[c]
        # floor(t / cells) of small whole numbers in float32 (exact, the
        # 1/2 keeps the quotient off the integers).
        m = jnp.where(lanes.pbc[a, c], jnp.floor(
            (t.astype(jnp.float32) + 0.5)
            / cells_a[:, c].astype(jnp.float32)).astype(jnp.int32), 0)
        t = t - m * cells_a[:, c]
        inside = inside & (t >= 0) & (t < cells_a[:, c])
        target.append(t)
        image.append(m)
    key = jnp.where(inside, lanes.base[a] + (
        target[2] * cells_a[:, 1] + target[1]) * cells_a[:, 0] + target[0], 0)
    run = lanes.runs[key]
    image = jnp.stack(image, axis=-1) + lanes.w[a].astype(jnp.int32)
    own = (o[0] == 0) & (o[1] == 0) & (o[2] == 0)
    return a, run[:, 0], jnp.where(inside, run[:, 1], 0), image, own


def _read_lanes(positions, lanes: _Lanes, cut, species, *, stored, half):
    """Step 5 over the lanes, ``chunk`` at a time: int32 ``(N,)`` pairs per
    atom (exact) and int32 ``(stored, 5)`` rows ``i``-major."""
    n, dtype = positions.shape[0], positions.dtype
    chunk = lane_chunk(n)
    columns = [positions[lanes.order, c] for c in range(3)] + [
        lanes.w[lanes.order, c].astype(jnp.int32) for c in range(3)]
    limit = square_limit(cut)
    if species is not None:
        species_j = species[lanes.order]
    pad = jnp.array([n, n, 0, 0, 0], jnp.int32)
    window = WINDOW_ROWS_PER_LANE * chunk
    total_lanes = lanes.lane_end[-1]
    ell0 = jnp.arange(chunk, dtype=jnp.int32)

    def step(carry):
        first, total, per_atom, out = carry
        a, start, length, image, own = _lane_runs(lanes, first + ell0, n)
        h = lanes.h[lanes.graph[a]]
        # The atom side of every lane, an array per column, written out
        # once before the slot loop (its readers would gather it again in
        # every step).
        side = jax.lax.optimization_barrier((
            a, start, length, own, lanes.rank[a],
            [positions[a, c] for c in range(3)],
            [image[:, c] for c in range(3)],
            [[h[:, u, c] for c in range(3)] for u in range(3)]))
        a, start, length, own, rank_i, r_i, image_c, h_i = side
        lim = limit if species is None else limit[species[a]]

        def slot(t):
            p = jnp.minimum(start + t, n - 1)
            s = [image_c[c] - columns[3 + c][p] for c in range(3)]
            sf = [x.astype(dtype) for x in s]
            d = [(columns[c][p] - r_i[c]) + (
                sf[0] * h_i[0][c] + sf[1] * h_i[1][c]
                + sf[2] * h_i[2][c]) for c in range(3)]
            return p, s, d[0] * d[0] + d[1] * d[1] + d[2] * d[2]

        def decide(t, bits):
            p, s, d2 = slot(t)
            if species is None:
                ok = d2 <= lim
            else:
                ok = d2 <= jnp.take_along_axis(
                    lim, species_j[p][:, None], axis=1)[:, 0]
            once = ~(own & (p == rank_i))
            if half:
                j = lanes.order[p]
                once = once & ((a < j) | ((a == j) & lex_positive(
                    jnp.stack(s, axis=-1))))
            keep = (t < length) & ok & once
            return bits | jnp.where(keep, jnp.uint32(1) << t.astype(
                jnp.uint32), jnp.uint32(0))

        steps = jnp.max(length, initial=0)
        bits = jax.lax.fori_loop(0, steps, decide,
                                 jnp.zeros((chunk,), jnp.uint32))
        counts = popcount(bits)
        ends = prefix_sum(counts, small=True)
        if stored > 0:
            out = _write_rows(out, total, bits, counts, ends, start, image,
                              a, columns, lanes.order, n=n, window=window)
        per_atom = per_atom.at[a].add(counts)
        return first + chunk, total + ends[-1], per_atom, out

    zero = jnp.zeros((), jnp.int32)
    # ``window`` rows past the capacity: a window is written whole.
    _, _, per_atom, out = jax.lax.while_loop(
        lambda carry: carry[0] < total_lanes, step,
        (zero, zero, jnp.zeros((n,), jnp.int32),
         jnp.broadcast_to(pad, (stored + window if stored else 0, 5))))
    return per_atom, out[:stored]


def _write_rows(out, total, bits, counts, ends, start, image, a, columns,
                order, *, n, window):
    """A chunk's kept candidates (``bits`` of its lanes, ``counts`` and
    inclusive running ``ends`` of them) written as rows at ``total`` on,
    ``window`` rows at a time: a row's lane is the last lane starting at or
    before it (a running maximum of the lanes' first rows), its slot the
    rank of its bit."""
    stored = out.shape[0] - window
    lanes = counts.shape[0]
    first = ends - counts
    r = jnp.arange(window, dtype=jnp.int32)

    def one(carry):
        w0, out = carry
        at = first - w0
        marks = jnp.full((window,), -1, jnp.int32).at[jnp.where(
            (counts > 0) & (at >= 0), at, window)].max(
                jnp.arange(lanes, dtype=jnp.int32), mode="drop")
        # The lane holding the window's first row (it may start before).
        lane0 = jnp.searchsorted(ends, w0, side="right").astype(jnp.int32)
        marks = marks.at[0].max(lane0)
        wid = jnp.minimum(running_max(marks), lanes - 1)
        kept = w0 + r < ends[-1]
        slot = jnp.minimum(start[wid] + select_bit(bits[wid], w0 + r
                                                   - first[wid]), n - 1)
        j = order[slot]
        shift = image[wid] - jnp.stack([columns[3 + c][slot]
                                        for c in range(3)], axis=-1)
        rows = jnp.where(kept[:, None], jnp.concatenate(
            [a[wid][:, None], j[:, None], shift], axis=1),
            jnp.array([n, n, 0, 0, 0], jnp.int32))
        start_row = jnp.minimum(total + w0, stored)
        old = jax.lax.dynamic_slice(out, (start_row, jnp.int32(0)),
                                    (window, 5))
        rows = jnp.where(kept[:, None], rows, old)
        return w0 + window, jax.lax.dynamic_update_slice(
            out, rows, (start_row, jnp.int32(0)))

    # Past the capacity nothing is written.
    _, out = jax.lax.while_loop(
        lambda c: (c[0] < ends[-1]) & (total + c[0] < stored), one,
        (jnp.zeros((), jnp.int32), out))
    return out
