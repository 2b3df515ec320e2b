"""The cell list's candidate pass as one GPU kernel (Pallas, lowered to Triton).

`jaxrt.backends.cell.search` finds, for each particle, the runs of the cell-sorted order
that hold its candidates. On CPUs it tests them as fixed windows of whole
32-slot words and left-packs the hits with array programs; on a GPU that
formulation is at XLA's floor (docs/benchmarks-notes.md): every particle
reads windows sized by the longest run, two thirds of them past its own
run, and the left-packing is a search per output slot. A kernel does neither: each
thread walks its particle's runs to their real ends and appends hits to its
row as it finds them.

The kernel makes the same three-way split as the XLA path, with the same
thresholds: pairs surely within the cutoff go to the row, pairs within
``tol`` of it (a few per hundred particles) to a small shell buffer that the
caller's metric decides afterwards in JAX, and the rest are dropped. So both
paths return the same sets, which `tests/lists/test_neighbors.py` checks by running
this kernel in Pallas' interpreter on the CPU.

Threads of a block take consecutive particles of the sorted order: they
mostly share a cell, so they walk the same runs and read the same
candidates at the same time.
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
try:
    from jax.experimental import pallas as pl
    from jax.experimental.pallas import triton as plgpu
    _COMPILER_PARAMS = (getattr(plgpu, "CompilerParams", None)
                        or plgpu.TritonCompilerParams)
except (ImportError, AttributeError):  # an older JAX: the portable path
    pl = plgpu = None

# Bits per axis of the run image codes (`jaxrt.backends.cell.grid.run_images`).
IMAGE_BITS = 2


class CellGrid(NamedTuple):
    """The sorted cell grid, for a kernel that finds each particle's runs
    itself (`pair_sums`' ``grid``).

    Attributes:
      starts: int32 ``(T + 1 + 2 reach[0] + 2,)``: how many sorted particles
        lie in cells with smaller keys, padded at the end
        (`jaxrt.backends.cell.grid.cell_starts`).
      cell: int32 ``(N, dim)``: the sorted particles' cell coordinates.
      cells: int32 ``(dim,)``: cells per axis (keys: x fastest).
      reach: static ``(along x, across)``: the stencil's reach in cells.
    """

    starts: jax.Array
    cell: jax.Array
    cells: jax.Array
    reach: tuple[int, int]

# Particles per program (one per thread) and warps per program: one warp
# per program was the fastest of 32-256 particles and 1-8 warps on the GPU
# (`benchmarks/results/h100/neighbors_cell_kernel.csv`).
_BLOCK = 32
_WARPS = 1


def fits(n: int, row_width: int, shell: int) -> bool:
    """Whether this JAX has Pallas' Triton backend, there are particles,
    and the kernel's int32 flat offsets can address the outputs."""
    return (plgpu is not None and 0 < n
            and n * max(row_width, shell, 1) < 2 ** 31 - 1)


def _grid_inputs(grid: CellGrid, pad) -> list:
    """The kernel inputs `_run_reader` reads of ``grid``: the cell-start
    table, one int32 ``(padded,)`` array of cell coordinates per axis
    (``pad``: `_padding`'s), the cells per axis."""
    return [grid.starts.astype(jnp.int32),
            *[pad(grid.cell[:, a].astype(jnp.int32))
              for a in range(grid.cell.shape[1])],
            grid.cells.astype(jnp.int32)]


def _padding(n: int, block: int):
    """``(padded, pad)``: N rounded up to whole blocks, and a function that
    pads axis 0 to it. The last block's spare threads repeat the last
    particle: they write what it writes (a masked-off store is no write on
    a GPU, but the interpreter writes back the old value, which would
    race)."""
    padded = -(-n // block) * block

    def pad(x):
        return jnp.pad(x, [(0, padded - x.shape[0])]
                       + [(0, 0)] * (x.ndim - 1), mode="edge")
    return padded, pad


def candidate_rows(sorted_cart, order, grid: CellGrid, inner_sq, outer_sq,
                   side, *, periodic: tuple[bool, ...], mask_self: bool,
                   row_width: int, shell: int, lower_only: bool = False,
                   interpret: bool = False):
    """Walk every particle's runs; append sure hits to its row, shell hits
    to its shell buffer.

    Args:
      sorted_cart: float ``(N, dim)`` wrapped Cartesian positions, sorted
        by cell.
      order: int32 ``(N,)``: sorted position -> caller's index.
      grid: the sorted grid (`CellGrid`): each thread finds its particle's
        runs in the cell-start table (`_run_reader`).
      inner_sq, outer_sq: float scalars: squared distances below which a
        pair is sure, and below which it is in the shell.
      side: float ``(dim,)`` box sides (used on periodic axes only).
      row_width, shell: static widths of the two outputs.
      lower_only: keep only candidates whose caller's index is below the
        particle's own (OrderedSparse's edges, written as half rows: half
        the entries, and no rank along full rows to convert them).
      interpret: run in Pallas' interpreter (any backend; for tests).
    Returns:
      In the caller's order: int32 ``(N, row_width)`` rows, left-packed with
      caller's indices of the sure neighbours and padded with ``N``; int32
      ``(N,)`` their exact counts (which may exceed ``row_width``); int32
      ``(N, shell)`` the shell candidates (valid up to the count) and int32
      ``(N,)`` their exact counts.
    """
    # Indices only: no tangents may reach the kernel (a pallas_call with
    # aliased outputs has no JVP, and grad through a list update in a scan
    # would differentiate it).
    sorted_cart, inner_sq, outer_sq, side = jax.lax.stop_gradient(
        (sorted_cart, inner_sq, outer_sq, side))
    n, dim = sorted_cart.shape
    dtype = sorted_cart.dtype
    padded, pad = _padding(n, _BLOCK)

    # One array per axis: the kernel gathers scalars by index.
    coords = [pad(sorted_cart[:, a]) for a in range(dim)]
    n_runs = (2 * grid.reach[1] + 1) ** (dim - 1) * (2 if periodic[0] else 1)
    run_inputs = _grid_inputs(grid, pad)
    params = jnp.zeros((8,), dtype)
    params = params.at[0].set(inner_sq).at[1].set(outer_sq)
    params = params.at[2:2 + dim].set(side.astype(dtype))
    params = params.at[5:5 + dim].set((1.0 / side).astype(dtype))
    row_width = max(row_width, 1)
    shell = max(shell, 1)
    kernel = functools.partial(_walk, n=n, dim=dim, periodic=periodic,
                               mask_self=mask_self, lower_only=lower_only,
                               row_width=row_width, shell=shell, runs=n_runs,
                               reach=grid.reach)
    outputs = (
        jax.ShapeDtypeStruct((n * row_width,), jnp.int32),
        jax.ShapeDtypeStruct((n,), jnp.int32),
        jax.ShapeDtypeStruct((n * shell,), jnp.int32),
        jax.ShapeDtypeStruct((n,), jnp.int32),
    )
    rows, count, shell_rows, shell_count = pl.pallas_call(
        kernel, out_shape=outputs, grid=(padded // _BLOCK,),
        input_output_aliases={len(coords) + 2 + len(run_inputs): 0},
        compiler_params=_COMPILER_PARAMS(num_warps=_WARPS),
        interpret=interpret, name="jaxrt_cell_walk",
    )(params, *coords, pad(order), *run_inputs,
      jnp.full((n * row_width,), n, jnp.int32))
    return (rows.reshape(n, row_width), count,
            shell_rows.reshape(n, shell), shell_count)


def _walk(params_ref, *refs, n, dim, periodic, mask_self, lower_only,
          row_width, shell, runs, reach):
    """One program: ``_BLOCK`` consecutive sorted particles, one per thread.

    Refs: float ``(8,)`` params (inner_sq, outer_sq, then ``dim`` box
    sides from slot 2 and their inverses from slot 5); ``dim`` float
    ``(padded,)`` sorted coordinates; int32 ``(padded,)`` order; the grid
    (`_run_reader`: cell-start table, ``dim`` int32 ``(padded,)`` cell
    coordinates, int32 ``(dim,)`` cells per axis); the row fill (aliased
    to the rows); then the four outputs of `candidate_rows`, flat.
    """
    coord_refs = refs[:dim]
    order_ref = refs[dim]
    run_refs = refs[dim + 1:dim + 1 + _n_run_refs(dim, (), reach)]
    rows_ref, count_ref, shell_ref, shell_count_ref = refs[-4:]
    first = pl.program_id(0) * _BLOCK
    block = pl.ds(first, _BLOCK)
    # sorted index (spare threads of the last block: the last particle)
    me = jnp.minimum(first + jnp.arange(_BLOCK, dtype=jnp.int32), n - 1)
    mine = [ref[block] for ref in coord_refs]
    dest = order_ref[block]  # caller's index
    inner_sq, outer_sq = params_ref[0], params_ref[1]
    side = [params_ref[2 + a] for a in range(dim)]
    inverse_side = [params_ref[5 + a] for a in range(dim)]
    zero = jnp.zeros((_BLOCK,), jnp.int32)

    # Spare threads walk the last particle's runs (``me`` is clamped): they
    # write what it writes.
    run_at = _run_reader(run_refs, block, me, n, mine, side, dim=dim,
                         periodic=periodic, image_axes=(False,) * dim,
                         reach=reach)

    # One loop over runs, not one per run: a fifth of the interpreter's
    # compile time, and the same speed on the GPU.
    def walk_run(r, counts):
        start, length, _ = run_at(r)

        def step(s, counts):
            count, shell_count = counts
            inside = s < length
            j = jnp.where(inside, start + s, 0)
            d2 = jnp.zeros((_BLOCK,), mine[0].dtype)
            for a in range(dim):
                d = plgpu.load(coord_refs[a].at[j]) - mine[a]
                if periodic[a]:
                    # Pallas' Triton lowering has no round; a half-way tie
                    # picks either image of the same length, and the 1-ulp
                    # slip of adding 0.5 is within tol.
                    d = d - side[a] * jnp.floor(d * inverse_side[a] + 0.5)
                d2 = d2 + d * d
            if mask_self:
                inside = inside & (j != me)
            caller_j = plgpu.load(order_ref.at[j])
            if lower_only:
                inside = inside & (caller_j < dest)
            sure = inside & (d2 < inner_sq)
            maybe = inside & ~sure & (d2 < outer_sq)
            plgpu.store(rows_ref.at[dest * row_width
                                    + jnp.minimum(count, row_width - 1)],
                        caller_j, mask=sure & (count < row_width))
            plgpu.store(shell_ref.at[dest * shell
                                     + jnp.minimum(shell_count, shell - 1)],
                        caller_j, mask=maybe & (shell_count < shell))
            return (count + sure.astype(jnp.int32),
                    shell_count + maybe.astype(jnp.int32))

        return jax.lax.fori_loop(0, jnp.max(length), step, counts)

    count, shell_count = jax.lax.fori_loop(0, runs, walk_run, (zero, zero))
    plgpu.store(count_ref.at[dest], count)
    plgpu.store(shell_count_ref.at[dest], shell_count)


# ---------------------------------------------------------------------------
# Pair sums with no list: the same walk, but each thread folds
# every candidate into its own particle's sums instead of writing it down.


def _power_of_two(value: int) -> bool:
    return value > 0 and not value & (value - 1)


def pair_sums(sorted_cart, sorted_runs, side, scalars, per_particle=(), *,
              periodic: tuple[bool, ...], pair_terms, n_sums: int,
              images=None, image_axes: tuple[bool, ...] | None = None,
              grid: CellGrid | None = None, newton: bool = False,
              block: int = _BLOCK, warps: int = _WARPS, tile: int = 0,
              unroll: int = 1, interpret: bool = False):
    """Each sorted particle's sums over all its candidates, in one kernel.

    Every pair is met from both of its particles (no atomics, no list;
    ``newton`` meets it once); the particle's sums stay in registers while
    its runs are walked, and are stored once. Two layouts of the walk (``tile``):

    - ``tile=0``, a thread per particle: each thread walks its own runs,
      one candidate per step (loads of single values, shared by the
      threads of a cell);
    - ``tile=T``, clusters (GROMACS' nbnxm idea on the sorted order): a
      program of ``block`` consecutive particles walks the union of their
      runs in contiguous tiles of ``T`` candidates, each a coalesced load,
      and decides all ``block x T`` pairs of the tile at once, every
      particle keeping only the candidates of its own runs. It tests more
      pairs than it keeps (the union is wider than each run), but with
      vector loads and no divergence; gaps in the union that no particle
      of the program needs (a program spanning two rows of cells) are
      jumped.

    Minimum images: on a periodic axis each candidate's difference is
    rounded to its nearest image (3 instructions per axis per candidate,
    and the walk is bound by instruction issue), except on the
    ``image_axes``, where each run's image (``images``) is subtracted from
    the particle's own position once per run instead. That is exact where
    every run lies in one image of the box (`jaxrt.backends.cell.grid.run_images`;
    `jaxrt.backends.cell.grid.image_axes` says where, statically).

    Args:
      sorted_cart: float ``(N, dim)`` wrapped Cartesian positions, sorted
        by cell; with ``image_axes``, exactly those the cells were binned
        from (`jaxrt.backends.cell.grid.grid`'s): a run's image is right only for
        a position in its cell.
      sorted_runs: ``(start1, len1, start2, len2)``, int32 ``(N, R)`` in
        sorted order (`jaxrt.backends.cell.grid.runs`).
      side: float ``(dim,)`` box sides (used on periodic axes only).
      scalars: float ``(S,)`` values handed to ``pair_terms`` (traced
        parameters such as sigma and epsilon).
      per_particle: float ``(N,)`` arrays in sorted order, handed to
        ``pair_terms`` for both particles of a pair (radii, densities).
      images: None, or ``(first, wrapped)``, int32 ``(N, R)`` in sorted
        order as ``sorted_runs``: the image codes of each run's first and
        wrapped parts (`jaxrt.backends.cell.grid.run_images`: ``s_a + 1`` in bits
        ``2 a`` and up, the run's candidates standing for their images at
        ``x_a + s_a side_a``).
      image_axes: static ``dim`` bools, periodic axes on which the
        ``images`` are used instead of per-candidate minimum images; None:
        none.
      pair_terms: ``(d2, valid, scalars, mine, theirs, d) -> (g, sums)``:
        traced in the kernel on arrays of candidates (one value per thread,
        or a tile of them); ``d2`` the squared minimum-image distance,
        ``valid`` whether the candidate is another particle, ``mine`` /
        ``theirs`` tuples of the ``per_particle`` values, ``d`` the ``dim``
        components of the minimum-image ``x_i - x_j``; returns ``g`` (the
        particle's vector sum gains ``g (x_i - x_j)``) and a tuple of
        ``n_sums`` scalar terms, all zero where ``valid`` is false. (On
        the ``image_axes`` a candidate beyond the grid's cutoff may be
        seen through another image than its nearest, never closer: the
        terms must vanish beyond the cutoff, as the walk's do anyway.)
      grid: None, or the sorted grid itself (`CellGrid`): then each thread
        finds its particle's runs and their images from the cell-start
        table (two loads per run) instead of reading ``sorted_runs`` and
        ``images`` (which may be None): the grid needs no pass over every
        particle's runs in memory.
      newton: meet every pair once, not from both particles (Newton's
        third law, LAMMPS' ``newton on``): a thread walks only the upper
        half of its stencil (the rows after the centre row in
        `jaxrt.backends.cell.search._stencil_rows`' order, and in the centre row the
        sorted particles after its own), adds ``g (x_i - x_j)`` to its own
        vector sum and ``-g (x_i - x_j)`` to the partner's with an atomic
        add, and keeps the scalar terms of the pairs it meets: the scalar
        sums' total is then the pairs' total once (not twice), and their
        per-particle split is not the symmetric one. ``pair_terms`` must be
        symmetric in the two particles. Needs the thread walk (``tile=0``)
        and no repeated stencil cell across: every periodic axis but x
        among the ``image_axes`` (which proves at least ``2 across + 1``
        cells there). The vector sums' rounding then depends on the order
        of the atomics (not bitwise reproducible on a GPU).
      block, warps: particles per program and warps per program.
      tile: 0, or the candidates per tile of the cluster layout (a power
        of two, as ``block``).
      unroll: candidates per loop step of the thread walk (>= 1).
      interpret: run in Pallas' interpreter (any backend; for tests).
    Returns:
      float ``(N, dim)`` vector sums and float ``(n_sums, N)`` scalar sums,
      in sorted order and ``sorted_cart``'s dtype.
    """
    n, dim = sorted_cart.shape
    dtype = sorted_cart.dtype
    if not _power_of_two(block):
        raise ValueError(f"pair_sums: block={block} must be a power of two "
                         "(Triton's blocks are).")
    if tile and not _power_of_two(tile):
        raise ValueError(f"pair_sums: tile={tile} must be 0 or a power of "
                         "two (Triton's blocks are).")
    if unroll < 1:
        raise ValueError(f"pair_sums: unroll={unroll} must be >= 1.")
    image_axes = tuple(bool(x) for x in image_axes or (False,) * dim)
    if len(image_axes) != dim or any(
            x and not p for x, p in zip(image_axes, periodic)):
        raise ValueError(f"pair_sums: image_axes={image_axes} must be {dim} "
                         f"bools, true only on periodic axes ({periodic}).")
    if any(image_axes) and images is None and grid is None:
        raise ValueError("pair_sums: image_axes needs the runs' images "
                         "(images=(first, wrapped)).")
    if newton and tile:
        raise ValueError(f"pair_sums: newton=True needs the thread walk "
                         f"(tile=0, not {tile}).")
    if newton and not all(x or not p for x, p in zip(image_axes[1:],
                                                     periodic[1:])):
        raise ValueError(
            f"pair_sums: newton=True needs every periodic axis but x among "
            f"image_axes ({image_axes}, periodic {periodic}): elsewhere a "
            "stencil cell across may repeat, and a pair seen only through a "
            "lower row would be lost.")
    padded, pad = _padding(n, block)
    extra = padded - n
    # Candidates' arrays: a tile from any run's start stays in them (a
    # dynamic slice past the end would be clamped back onto other
    # particles); without tiles, the particles' own padding.
    pad_j = _padding(n + tile, block)[1]

    coords = [pad_j(sorted_cart[:, a]) for a in range(dim)]
    if grid is not None:
        rows = (2 * grid.reach[1] + 1) ** (dim - 1)
        n_runs = rows * (2 if periodic[0] else 1)
        # Spare lanes repeat the last particle's cell; `live` empties them.
        run_inputs = _grid_inputs(grid, pad)
    else:
        start1, len1, start2, len2 = sorted_runs
        rows = start1.shape[1]
        starts = jnp.concatenate([start1, start2], axis=1)
        lengths = jnp.concatenate([len1, len2], axis=1)
        if not any(periodic):
            starts, lengths = start1, len1
        # The spare threads of the last block walk nothing.
        lengths = jnp.pad(lengths, [(0, extra), (0, 0)]).T
        starts = jnp.clip(pad(starts), 0, n).T
        n_runs = starts.shape[0]
        run_inputs = [starts, lengths]
        if any(image_axes):  # the runs' images, laid out as their starts
            codes = jnp.concatenate(images, axis=1)[:, :n_runs]
            run_inputs.append(pad(codes).T)
    geometry = jnp.concatenate([side.astype(dtype),
                                (1.0 / side).astype(dtype)])
    scalars = jnp.asarray(scalars, dtype).reshape(-1)
    extras = [pad_j(jnp.asarray(p, dtype)) for p in per_particle]
    kernel = functools.partial(
        _tile_walk if tile else _sum_walk, n=n, dim=dim, periodic=periodic,
        image_axes=image_axes, block=block, runs=n_runs,
        n_extras=len(extras), n_sums=n_sums, n_scalars=scalars.shape[0],
        pair_terms=pair_terms, reach=None if grid is None else grid.reach,
        **({"tile": tile} if tile else {"unroll": unroll, "newton": newton,
                                        "rows": rows,
                                        "interpret": interpret}))
    outputs = ([jax.ShapeDtypeStruct((padded,), dtype)] * dim
               + [jax.ShapeDtypeStruct((padded,), dtype)] * n_sums)
    # With newton, the vector sums gather atomic adds from other programs:
    # they start as zeros aliased to those outputs.
    inputs = [geometry, scalars, *coords, *run_inputs, *extras]
    zeros = [jnp.zeros((padded,), dtype)] * (dim if newton else 0)
    sums = pl.pallas_call(
        kernel, out_shape=outputs, grid=(padded // block,),
        input_output_aliases={len(inputs) + a: a for a in range(len(zeros))},
        compiler_params=_COMPILER_PARAMS(num_warps=warps),
        interpret=interpret, name="jaxrt_cell_pair_sums",
    )(*inputs, *zeros)
    vector = jnp.stack([s[:n] for s in sums[:dim]], axis=1)
    scalar = jnp.stack([s[:n] for s in sums[dim:]]) if n_sums else (
        jnp.zeros((0, n), dtype))
    return vector, scalar


def _sum_refs(refs, dim: int, n_extras: int, n_run_refs: int):
    """`pair_sums`' refs after the geometry and scalars: (coordinates, the
    refs the runs are read from, per-particle values, outputs)."""
    coords, runs, refs = (refs[:dim], refs[dim:dim + n_run_refs],
                          refs[dim + n_run_refs:])
    return coords, runs, refs[:n_extras], refs[n_extras:]


def _n_run_refs(dim: int, image_axes, reach) -> int:
    """How many refs `_run_reader` takes: the grid's (cell-start table,
    ``dim`` cell coordinates, cells per axis), or the stored runs' (starts,
    lengths, and image codes where any axis uses them)."""
    if reach is not None:
        return dim + 2
    return 2 + any(image_axes)


def _remainder(x, m: int):
    """``x mod m`` of a non-negative int32 ``x`` by a static ``m``, as a
    division and a multiply: jnp's ``%`` fixes signs with ops that Triton's
    lowering mistypes under x64, and a ``rem`` in a program reads as
    periodic wrapping to the checks that a wall box does none
    (tests/sim/test_scene.py)."""
    return x - jax.lax.div(x, jnp.int32(m)) * jnp.int32(m)


def _run_reader(run_refs, lanes, me, n, mine, side, *, dim, periodic,
                image_axes, reach):
    """``run_at(r) -> (start, length, origin)`` for the lanes of a program:
    int32 ``(block,)`` the sorted position where run ``r`` begins and its
    length, and the lanes' own positions as the run sees them (``mine``
    minus the run's periodic image, ``dim`` arrays shaped as ``mine``).

    Stored runs (``reach`` None) are read from the ``(runs, padded)``
    tables. With the grid (``reach``: the stencil's reach in cells, along
    x and across), each lane computes its runs as `jaxrt.backends.cell.grid.runs`
    and `_run_images` do, in their order (the first parts of the ``R``
    stencil rows, then, on a periodic x, their wrapped parts), and two
    loads from the cell-start table give a run's ends as
    `jaxrt.backends.cell.search._run_ends` does: the same runs and images, so the
    same sums. (Axes that `jaxrt.backends.cell.grid.grid` compacted need nothing
    of their own: their wrapped cells are empty.) ``me``: the lanes'
    sorted indices (``>= n`` is a spare lane, which walks nothing).
    """
    def moved(shift):  # mine - s side on the axes that use the images
        out = []
        for a, x in enumerate(mine):
            if image_axes[a]:
                s = shift[a].reshape(x.shape).astype(x.dtype)
                x = x - s * side[a]
            out.append(x)
        return out

    if reach is None:
        starts_ref, lengths_ref = run_refs[:2]
        codes_ref = run_refs[2] if len(run_refs) > 2 else None

        def run_at(r):
            shift = [None] * dim
            if codes_ref is not None:
                code = codes_ref[r, lanes]
                shift = [((code >> (IMAGE_BITS * a))
                          & ((1 << IMAGE_BITS) - 1)) - 1 for a in range(dim)]
            return starts_ref[r, lanes], lengths_ref[r, lanes], moved(shift)
        return run_at

    table_ref, cell_refs, cells_ref = (run_refs[0], run_refs[1:1 + dim],
                                       run_refs[1 + dim])
    along, across = reach
    width = 2 * across + 1
    rows = width ** (dim - 1)
    span = 2 * along + 2  # `jaxrt.backends.cell.search._RUN_SPAN`
    size = table_ref.shape[0] - span
    cell = [ref[lanes] for ref in cell_refs]
    cells = [cells_ref[a] for a in range(dim)]
    live = me < n

    def run_at(r):
        r = jnp.asarray(r, jnp.int32)
        row = _remainder(r, rows) if periodic[0] else r
        valid = live
        shift = [None] * dim
        base = jnp.zeros_like(cell[0])
        stride = cells[0]
        for a in range(1, dim):
            # `_stencil_rows`' order: the last axis fastest.
            k = _remainder(jax.lax.div(row, jnp.int32(
                width ** (dim - 1 - a))), width)
            c = cell[a] + k - across
            if periodic[a]:
                # One wrap; a box of fewer than 2 across + 1 cells names a
                # cell more than once, and only the first offset to name
                # it counts (offset k repeats an earlier one iff a
                # multiple of the cells fits in k).
                s = (c >= cells[a]).astype(jnp.int32) - (c < 0).astype(
                    jnp.int32)
                c = c - s * cells[a]
                shift[a] = s
                valid = valid & (k < cells[a])
            else:
                valid = valid & (c >= 0) & (c < cells[a])
            base = base + c * stride
            stride = stride * cells[a]
        lo, hi = cell[0] - along, cell[0] + along
        first_lo = jnp.maximum(lo, 0)
        first_hi = jnp.minimum(hi, cells[0] - 1)
        if periodic[0]:
            # The stencil pokes out of one end of the row: its cells wrap
            # to a second run at the other end, seen through the image
            # one box below (from the top end) or above. A row of at most
            # 2 along + 1 cells is one run, whole.
            whole = cells[0] <= 2 * along + 1
            first_lo = jnp.where(whole, 0, first_lo)
            first_hi = jnp.where(whole, cells[0] - 1, first_hi)
            wrapped = r >= rows
            below = lo < 0
            valid = valid & (~wrapped | (~whole & (below | (hi >= cells[0]))))
            lo = jnp.where(wrapped, jnp.where(below, cells[0] + lo, 0),
                           first_lo)
            hi = jnp.where(wrapped, jnp.where(below, cells[0] - 1,
                                              hi - cells[0]), first_hi)
            shift[0] = jnp.where(wrapped, jnp.where(below, -1, 1), 0)
        else:
            lo, hi = first_lo, first_hi
        begin = jnp.clip(base + lo, 0, size)
        start = plgpu.load(table_ref.at[begin])
        end = plgpu.load(table_ref.at[begin + jnp.clip(hi - lo + 1, 0,
                                                       span - 1)])
        return start, jnp.where(valid, end - start, 0), moved(shift)
    return run_at


def _scatter_add(ref, index, value, mask, interpret: bool):
    """``ref[index] += value`` where ``mask``, lanes colliding on an index
    summed: an atomic add on the GPU. Pallas' interpreter has no masked
    atomic and drops all but one of colliding lanes, so it gets a scatter-add
    of the whole array instead (its programs run one after another)."""
    if interpret:
        ref[...] = ref[...].at[index].add(jnp.where(mask, value, 0))
    else:
        plgpu.atomic_add(ref, index, value, mask=mask)


def _sum_walk(geometry_ref, scalars_ref, *refs, n, dim, periodic, image_axes,
              block, runs, n_extras, n_sums, n_scalars, pair_terms,
              reach=None, unroll=1, newton=False, rows=1, interpret=False):
    """One program of `pair_sums`: ``block`` consecutive sorted particles.

    Refs: float ``(2 dim,)`` sides then inverse sides; float ``(S,)``
    scalars; ``dim`` float ``(padded,)`` coordinates; int32 ``(runs,
    padded)`` run starts and lengths; where any ``image_axes``, int32
    ``(runs, padded)`` run image codes (or, with ``reach``, the grid:
    `_run_reader`); ``n_extras`` float ``(padded,)``
    per-particle values; with ``newton``, ``dim`` float ``(padded,)`` zeros
    (aliased to the vector outputs); then ``dim + n_sums`` float
    ``(padded,)`` outputs. ``rows``: stencil rows (runs ``r`` and ``r +
    rows`` are one row's first and wrapped parts).
    """
    coord_refs, run_refs, extra_refs, out_refs = _sum_refs(
        refs, dim, n_extras, _n_run_refs(dim, image_axes, reach))
    out_refs = out_refs[dim:] if newton else out_refs  # past the zeros
    # Per-candidate minimum images only where the runs' images are not used.
    rounded = [p and not x for p, x in zip(periodic, image_axes)]
    first = pl.program_id(0) * block
    lanes = pl.ds(first, block)
    me = first + jnp.arange(block, dtype=jnp.int32)
    mine = [ref[lanes] for ref in coord_refs]
    mine_extra = tuple(ref[lanes] for ref in extra_refs)
    side = [geometry_ref[a] for a in range(dim)]
    inverse_side = [geometry_ref[dim + a] for a in range(dim)]
    # One load per scalar: Triton's lowering has no slice of a loaded vector.
    scalars = tuple(scalars_ref[k] for k in range(n_scalars))
    dtype = mine[0].dtype
    zero = jnp.zeros((block,), dtype)

    run_at = _run_reader(run_refs, lanes, me, n, mine, side, dim=dim,
                         periodic=periodic, image_axes=image_axes,
                         reach=reach)

    def walk_run(r, acc):
        start, length, origin = run_at(r)
        if newton:  # the upper half of the stencil (`pair_sums`)
            row = _remainder(jnp.asarray(r, jnp.int32), rows)
            centre = rows // 2
            begin = jnp.where(row == centre, jnp.maximum(start, me + 1),
                              start)
            length = jnp.where(row < centre, 0,
                               jnp.maximum(start + length - begin, 0))
            start = begin

        def one(s, acc):
            inside = s < length
            j = jnp.where(inside, start + s, 0)
            d2 = zero
            d = []
            for a in range(dim):
                da = origin[a] - plgpu.load(coord_refs[a].at[j])
                if rounded[a]:
                    da = da - side[a] * jnp.floor(da * inverse_side[a] + 0.5)
                d.append(da)
                d2 = d2 + da * da
            valid = inside & (j != me)
            theirs = tuple(plgpu.load(ref.at[j]) for ref in extra_refs)
            g, terms = pair_terms(jnp.where(valid, d2, 0), valid, scalars,
                                  mine_extra, theirs, tuple(d))
            if newton:
                for ref, da in zip(out_refs, d):
                    _scatter_add(ref, j, -g * da, valid, interpret)
            vector = tuple(v + g * da for v, da in zip(acc[:dim], d))
            return vector + tuple(t + u for t, u in zip(acc[dim:], terms))

        def step(s, acc):
            for u in range(unroll):
                acc = one(s * unroll + u, acc)
            return acc

        steps = (jnp.max(length) + unroll - 1) // unroll
        return jax.lax.fori_loop(0, steps, step, acc)

    acc = jax.lax.fori_loop(0, runs, walk_run, (zero,) * (dim + n_sums))
    for a, (ref, value) in enumerate(zip(out_refs, acc)):
        if newton and a < dim:  # other programs add to these too
            _scatter_add(ref, me, value, me < n, interpret)
        else:
            ref[lanes] = value


def _tile_walk(geometry_ref, scalars_ref, *refs, n, dim, periodic,
               image_axes, block, runs, n_extras, n_sums, n_scalars,
               pair_terms, tile, reach=None):
    """One program of `pair_sums`' cluster layout: ``block`` consecutive
    sorted particles against tiles of ``tile`` consecutive candidates.

    Refs as `_sum_walk`'s; the coordinates and per-particle values are
    padded to hold a whole tile from any run's start. Each particle keeps
    only the candidates of its own run, so its own image serves the whole
    tile.
    """
    coord_refs, run_refs, extra_refs, out_refs = _sum_refs(
        refs, dim, n_extras, _n_run_refs(dim, image_axes, reach))
    rounded = [p and not x for p, x in zip(periodic, image_axes)]
    first = pl.program_id(0) * block
    lanes = pl.ds(first, block)
    me = (first + jnp.arange(block, dtype=jnp.int32))[:, None]
    mine = [ref[lanes][:, None] for ref in coord_refs]
    mine_extra = tuple(ref[lanes][:, None] for ref in extra_refs)
    side = [geometry_ref[a] for a in range(dim)]
    inverse_side = [geometry_ref[dim + a] for a in range(dim)]
    scalars = tuple(scalars_ref[k] for k in range(n_scalars))
    dtype = mine[0].dtype
    zero = jnp.zeros((block,), dtype)
    offsets = jnp.arange(tile, dtype=jnp.int32)[None, :]
    big = jnp.int32(2 ** 30)

    run_at = _run_reader(run_refs, lanes, me[:, 0], n, mine, side, dim=dim,
                         periodic=periodic, image_axes=image_axes,
                         reach=reach)

    def walk_run(r, acc):
        start, length, origin = run_at(r)
        end = start + length
        empty = end <= start
        start_flat = jnp.where(empty, big, start)
        end_flat = jnp.where(empty, 0, end)
        lo, hi = jnp.min(start_flat), jnp.max(end_flat)
        start, end = start[:, None], end[:, None]

        def visit(base, acc):
            j = base + offsets
            valid = (j >= start) & (j < end) & (j != me)
            d2 = jnp.zeros((block, tile), dtype)
            d = []
            for a in range(dim):
                da = origin[a] - coord_refs[a][pl.ds(base, tile)][None, :]
                if rounded[a]:
                    da = da - side[a] * jnp.floor(da * inverse_side[a] + 0.5)
                d.append(da)
                d2 = d2 + da * da
            theirs = tuple(ref[pl.ds(base, tile)][None, :]
                           for ref in extra_refs)
            g, terms = pair_terms(jnp.where(valid, d2, 0), valid, scalars,
                                  mine_extra, theirs, tuple(d))
            vector = tuple(v + jnp.sum(g * da, axis=1)
                           for v, da in zip(acc[:dim], d))
            return vector + tuple(s + jnp.sum(t, axis=1)
                                  for s, t in zip(acc[dim:], terms))

        def next_tile(carry):
            base, acc = carry
            acc = visit(base, acc)
            # The next candidate that a run of the program still needs: a
            # program whose particles lie in two rows of cells jumps the
            # gap between their runs instead of walking it.
            after = base + tile
            wanted = jnp.where(end_flat > after,
                               jnp.maximum(start_flat, after), big)
            return jnp.min(wanted), acc

        return jax.lax.while_loop(lambda carry: carry[0] < hi, next_tile,
                                  (lo, acc))[1]

    acc = jax.lax.fori_loop(0, runs, walk_run, (zero,) * (dim + n_sums))
    for ref, value in zip(out_refs, acc):
        ref[lanes] = value
