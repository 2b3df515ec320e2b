"""Where the Warp rows walk's time goes, and what its stores cost: the
walk of `jaxrt.backends.cell.warp_rows` next to variants that differ only
in how the rows are written, on warp_rebuild_stages.py's scene (uniform,
density 1, cutoff 2.5, periodic, float32), one GPU run, each variant timed
after the same sort (Warp launches from Python, each synchronised).

Variants (``--variants``):

* ``current``: the library's walk (one 4-byte store per sure pair, at the
  caller's row, then the padding one entry at a time).
* ``trimmed`` / ``untrimmed``: the library's walk with each stencil row
  cut to the sphere it covers (``trim=True``) / read whole
  (``trim=False``); ``current`` is one of them (`warp_rows.TRIM`).
* ``counts``: the same walk with no row stores (counts only): the walk's
  own cost.
* ``vec4`` / ``vec8``: sure pairs buffered in registers and stored 16 (32)
  bytes at a time at the caller's row (row width rounded up to 4 / 8),
  padding likewise.
* ``vec4 sorted``: ``vec4`` at the sorted particle's row (rows in the
  walk's order: what locality of the stores alone is worth).
* ``lanesG``: ``G`` threads per particle (4, 8, 32): each stencil range
  read ``G`` candidates at a time, the sure pairs compacted by a ballot
  over the group and stored side by side (one lane on a CPU).
* ``transposed``: entry ``k`` of sorted particle ``i`` at ``k * N + i``
  (a warp's stores of one ``k`` coalesce), with ``transpose (XLA)``: the
  jitted ``(W, N) -> (N, W)`` transpose and reorder to the caller's rows
  that this layout would need.

Also the cost of writing the output at all: ``fill (XLA)``, a jitted
``jnp.full((N, W), N)``; ``rows call W=8``: the library's jitted FFI call
with 8-wide rows (the output's size against the call's fixed cost).

    python benchmarks/warp_rows_variants.py --n 1000000 --out $OUT
    python benchmarks/warp_rows_variants.py --n 4000 --repeats 2  # CPU
"""

import argparse
import os
import sys
import traceback

if __package__:
    from benchmarks import _harness, warp_rebuild_stages as stages_bench
else:
    import _harness
    import warp_rebuild_stages as stages_bench

VARIANTS = ("current", "trimmed", "untrimmed", "counts", "vec4", "vec8", "vec4 sorted", "transposed",
            "lanes4", "lanes8", "lanes32")


import warp as wp  # noqa: E402 - a native snippet is parsed from source


# 16 bytes at once where the compiler can see the alignment (CUDA's int4);
# the CPU build stores the four entries one by one.
@wp.func_native("""
#if defined(__CUDA_ARCH__)
reinterpret_cast<int4*>(rows.data)[at] = make_int4(a, b, c, d);
#else
int* q = reinterpret_cast<int*>(rows.data) + 4 * at;
q[0] = a; q[1] = b; q[2] = c; q[3] = d;
#endif
""")
def store4(rows: wp.array(dtype=wp.int32), at: int, a: int, b: int, c: int,
           d: int):
    ...


# A ballot over the ``width`` lanes of a lane group (bits from the group's
# first lane), and a population count; one lane on the CPU.
@wp.func_native("""
#if defined(__CUDA_ARCH__)
unsigned bits = width == 32 ? 0xffffffffu : ((1u << width) - 1u);
return (int)((__ballot_sync(bits << shift, pred != 0) >> shift) & bits);
#else
return pred != 0 ? 1 : 0;
#endif
""")
def group_ballot(pred: int, shift: int, width: int) -> int:
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
return __popc((unsigned)x);
#else
return __builtin_popcount((unsigned)x);
#endif
""")
def popcount(x: int) -> int:
    ...


def _group_kernel(lanes: int):
    """The rows walk with ``lanes`` threads per particle: each stencil
    range read ``lanes`` candidates at a time, the group's sure pairs
    compacted by a ballot and stored side by side (one lane on a CPU)."""
    import warp as wp
    from jaxrt.backends.cell import warp_kernels as wk
    from jaxrt.backends.cell import warp_rows as wr
    scalar = wp.float32
    vector = wp.types.vector(3, scalar)
    span, difference = wk.stencil_functions(scalar)
    stencil = wk.stencil
    grid_side = wk.SIDE
    group = lanes

    @wp.kernel(module="unique", module_options=wk.MODULE_OPTIONS)
    def walk(position: wp.array(dtype=vector),
             keys: wp.array(dtype=wp.int32),
             values: wp.array(dtype=wp.int32),
             start: wp.array(dtype=wp.int32),
             grid: wp.array(dtype=vector),
             cells: wp.array(dtype=wp.int32),
             thresholds: wp.array(dtype=scalar), flags: int,
             row_width: int, shell: int,
             rows: wp.array(dtype=wp.int32),
             count: wp.array(dtype=wp.int32),
             shells: wp.array(dtype=wp.int32),
             shell_count: wp.array(dtype=wp.int32)):
        t = wp.tid()
        width = wp.static(group)
        i = t / width
        lane = t % width
        shift = (t % 32) / width * width
        below_me = (1 << lane) - 1
        side = grid[grid_side]
        inner_sq = thresholds[wr.INNER_SQ]
        outer_sq = thresholds[wr.OUTER_SQ]
        s = stencil(flags, cells, keys[i])
        p = position[i]
        me = values[i]
        n = position.shape[0]
        hits = int(0)
        near = int(0)
        for dz in range(-s.az, s.az + 1):
            for piece in range(s.pieces):
                first, end, shift3 = span(s, start, side, dz, piece)
                q = p - shift3
                for j0 in range(first, end, width):
                    j = j0 + lane
                    sure = int(0)
                    close = int(0)
                    theirs = int(0)
                    if j < end:
                        d, d2 = difference(q, position[j], side, s)
                        if d2 < outer_sq and j != i:
                            theirs = values[j]
                            if d2 < inner_sq:
                                sure = 1
                            else:
                                close = 1
                    m = group_ballot(sure, shift, width)
                    at = hits + popcount(m & below_me)
                    if sure != 0 and at < row_width:
                        rows[me * row_width + at] = theirs
                    hits = hits + popcount(m)
                    m2 = group_ballot(close, shift, width)
                    at2 = near + popcount(m2 & below_me)
                    if close != 0 and at2 < shell:
                        shells[me * shell + at2] = theirs
                    near = near + popcount(m2)
        for k in range(wp.min(hits, row_width) + lane, row_width, width):
            rows[me * row_width + k] = n
        if lane == 0:
            count[me] = hits
            shell_count[me] = near

    return walk


def _variant_kernel(variant: str):
    """The rows walk for ``variant`` (float32 positions)."""
    import warp as wp
    from jaxrt.backends.cell import warp_kernels as wk
    from jaxrt.backends.cell import warp_rows as wr
    scalar = wp.float32
    vector = wp.types.vector(3, scalar)
    span, difference = wk.stencil_functions(scalar)
    stencil = wk.stencil
    mode = {"counts": 0, "vec4": 1, "vec8": 2, "vec4 sorted": 3,
            "transposed": 4}[variant]
    grid_side = wk.SIDE

    @wp.kernel(module="unique", module_options=wk.MODULE_OPTIONS)
    def walk(position: wp.array(dtype=vector),
             keys: wp.array(dtype=wp.int32),
             values: wp.array(dtype=wp.int32),
             start: wp.array(dtype=wp.int32),
             grid: wp.array(dtype=vector),
             cells: wp.array(dtype=wp.int32),
             thresholds: wp.array(dtype=scalar), flags: int,
             row_width: int, shell: int,
             rows: wp.array(dtype=wp.int32),
             count: wp.array(dtype=wp.int32),
             shells: wp.array(dtype=wp.int32),
             shell_count: wp.array(dtype=wp.int32)):
        i = wp.tid()
        n = position.shape[0]
        side = grid[grid_side]
        inner_sq = thresholds[wr.INNER_SQ]
        outer_sq = thresholds[wr.OUTER_SQ]
        s = stencil(flags, cells, keys[i])
        p = position[i]
        me = values[i]
        row = me
        if wp.static(mode == 3):
            row = i
        quads = row_width / 4
        hits = int(0)
        near = int(0)
        b0 = int(0)
        b1 = int(0)
        b2 = int(0)
        b3 = int(0)
        b4 = int(0)
        b5 = int(0)
        b6 = int(0)
        b7 = int(0)
        for dz in range(-s.az, s.az + 1):
            for piece in range(s.pieces):
                first, end, shift = span(s, start, side, dz, piece)
                q = p - shift
                for j in range(first, end):
                    d, d2 = difference(q, position[j], side, s)
                    if d2 < outer_sq and j != i:
                        theirs = values[j]
                        if d2 < inner_sq:
                            if wp.static(mode == 1 or mode == 3):
                                slot = hits & 3
                                b0 = wp.where(slot == 0, theirs, b0)
                                b1 = wp.where(slot == 1, theirs, b1)
                                b2 = wp.where(slot == 2, theirs, b2)
                                b3 = wp.where(slot == 3, theirs, b3)
                                if slot == 3 and hits < row_width:
                                    store4(rows, row * quads + hits / 4,
                                           b0, b1, b2, b3)
                            if wp.static(mode == 2):
                                slot = hits & 7
                                b0 = wp.where(slot == 0, theirs, b0)
                                b1 = wp.where(slot == 1, theirs, b1)
                                b2 = wp.where(slot == 2, theirs, b2)
                                b3 = wp.where(slot == 3, theirs, b3)
                                b4 = wp.where(slot == 4, theirs, b4)
                                b5 = wp.where(slot == 5, theirs, b5)
                                b6 = wp.where(slot == 6, theirs, b6)
                                b7 = wp.where(slot == 7, theirs, b7)
                                if slot == 7 and hits < row_width:
                                    at = row * quads + (hits / 8) * 2
                                    store4(rows, at, b0, b1, b2, b3)
                                    store4(rows, at + 1, b4, b5, b6, b7)
                            if wp.static(mode == 4):
                                if hits < row_width:
                                    rows[hits * n + i] = theirs
                            hits = hits + 1
                        else:
                            if near < shell:
                                shells[me * shell + near] = theirs
                            near = near + 1
        kept = wp.min(hits, row_width)
        if wp.static(mode == 1 or mode == 3):
            tail = kept & 3
            if tail != 0:
                store4(rows, row * quads + kept / 4, b0,
                       wp.where(tail > 1, b1, n), wp.where(tail > 2, b2, n),
                       n)
            for k in range((kept + 3) / 4, quads):
                store4(rows, row * quads + k, n, n, n, n)
        if wp.static(mode == 2):
            tail = kept & 7
            at = row * quads + (kept / 8) * 2
            if tail != 0:
                store4(rows, at, b0, wp.where(tail > 1, b1, n),
                       wp.where(tail > 2, b2, n), wp.where(tail > 3, b3, n))
                store4(rows, at + 1, wp.where(tail > 4, b4, n),
                       wp.where(tail > 5, b5, n), wp.where(tail > 6, b6, n),
                       n)
            for k in range(((kept + 7) / 8) * 2, quads):
                store4(rows, row * quads + k, n, n, n, n)
        if wp.static(mode == 4):
            for k in range(kept, row_width):
                rows[k * n + i] = n
        count[me] = hits
        shell_count[me] = near

    return walk


def _check(name, rows_np, count_np, reference, ref_count, width, values, n):
    """Each variant's rows, as sets per caller's row, equal the library's."""
    import numpy as np
    if not np.array_equal(count_np, ref_count):
        return "counts differ"
    if name == "counts":
        return "ok"
    if name == "transposed":
        table = rows_np.reshape(width, n).T
        mine = np.empty_like(table)
        mine[values[:n]] = table
    elif name == "vec4 sorted":
        table = rows_np.reshape(n, width)
        mine = np.empty_like(table)
        mine[values[:n]] = table
    else:
        mine = rows_np.reshape(n, width)
    ref = reference.reshape(n, -1)
    ref_width = ref.shape[1]
    if np.any(mine[:, ref_width:] != n):
        return "padding past the library's width"
    a = np.sort(mine[:, :ref_width], axis=1)
    b = np.sort(ref, axis=1)
    return "ok" if np.array_equal(a, b) else "rows differ"


def variant_stages(rec, R, grid, cells, table, thresholds, flags, width,
                   names):
    import numpy as np
    import warp as wp
    from jaxrt.backends.cell import warp_kernels as wk
    from jaxrt.backends.cell import warp_rows as wr
    device = "cuda:0" if wp.is_cuda_available() else "cpu"
    n = R.shape[0]
    v3 = wp.vec3f
    arr = lambda a, dt: wp.array(np.asarray(a), dtype=dt, device=device)  # noqa: E731,E501
    empty = lambda k, dt: wp.empty(k, dtype=dt, device=device)  # noqa: E731
    points, grid_w = arr(R, v3), arr(grid, v3)
    cells_w, thr = arr(cells, wp.int32), arr(thresholds, wp.float32)
    keys, values = empty(2 * n, wp.int32), empty(2 * n, wp.int32)
    wrapped, position = empty(n, v3), empty(n, v3)
    start, radius = empty(table + 1, wp.int32), empty(1, wp.float32)
    wide = -(-width // 8) * 8
    rows = empty(n * wide, wp.int32)
    count = empty(n, wp.int32)
    shells, shell_count = empty(n * stages_bench.SHELL, wp.int32), empty(
        n, wp.int32)
    wk.sort_cells(points, radius, grid_w, cells_w, flags & (7 * wk.PERIODIC),
                  keys=keys, values=values, wrapped=wrapped, start=start,
                  position=position, radius=radius)
    sync = lambda _: wp.synchronize_device(device)  # noqa: E731
    reference = ref_count = None
    sorted_values = values.numpy()
    for name in names:
        try:
            w = width if name in ("current", "trimmed", "untrimmed") else (
                wide if name == "vec8" else -(-width // 4) * 4)
            lanes = int(name[5:]) if name.startswith("lanes") else 1
            if lanes > 1 and device == "cpu":
                lanes = 1
            if name.startswith("lanes"):
                w = width
                kernel = _group_kernel(lanes)
            else:
                kernel = (wr.rows_kernel(wp.float32) if name == "current"
                          else wr.rows_kernel(wp.float32,
                                              trim=name == "trimmed")
                          if name.endswith("trimmed")
                          else _variant_kernel(name))
            f = flags if name in ("current", "trimmed", "untrimmed") else \
                flags & ~wr.MASK_SELF
            launch = lambda kernel=kernel, w=w, f=f, lanes=lanes: wp.launch(  # noqa: E731,E501
                kernel, dim=n * lanes, device=device, block_dim=wr.WALK_BLOCK,
                inputs=[position, keys, values, start, grid_w, cells_w, thr,
                        f, w, stages_bench.SHELL, rows, count, shells,
                        shell_count])
            rec.time(f"walk {name}", launch, sync=sync, device_warp=device,
                     row_width=w)
            launch()
            wp.synchronize_device(device)
            got = rows.numpy()[:n * w]
            if name == "current":
                reference, ref_count = got.copy(), count.numpy().copy()
                status = "reference"
            else:
                status = _check(name, got, count.numpy(), reference,
                                ref_count, w, sorted_values, n)
            rec.rows[-1]["check"] = status
            print(f"  check {name}: {status}", flush=True)
        except Exception as e:  # noqa: BLE001 - report and go on
            traceback.print_exc(limit=4)
            rec.add(f"walk {name}", error=f"{type(e).__name__}: {e}")


def xla_stages(rec, R, grid, cells, table, thresholds, flags, width, cuda):
    import jax
    import jax.numpy as jnp
    from jaxrt.backends.rt import ffi
    n = R.shape[0]
    fill = jax.jit(lambda x: jnp.full((n, width), n, jnp.int32) + x)
    rec.time("fill (XLA)", lambda: fill(jnp.int32(0)),
             sync=jax.block_until_ready, row_width=width)
    T = jnp.zeros((width, n), jnp.int32)
    order = jnp.asarray(__import__("numpy").random.default_rng(0)
                        .permutation(n).astype("int32"))
    transpose = jax.jit(lambda t, o: jnp.take(t.T, o, axis=0))
    rec.time("transpose (XLA)", lambda: transpose(T, order),
             sync=jax.block_until_ready, row_width=width)
    del T
    graph = "warp" if cuda else "none"
    for w in (8, width):
        call = jax.jit(lambda p, g, c, t, w=w: ffi.cell_candidate_rows(
            p, g, c, t, flags=flags, table=table, row_width=w,
            shell=stages_bench.SHELL, graph=graph))
        rec.time(f"rows call W={w} (jit, graph {graph})",
                 lambda call=call: call(R, grid, cells, thresholds),
                 sync=jax.block_until_ready, row_width=w)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--width", type=int, default=137,
                        help="the rows' width (the list's, at 10^6: 137)")
    parser.add_argument("--variants", nargs="*", default=list(VARIANTS))
    parser.add_argument("--out", default=None, help="CSV path or folder")
    args = parser.parse_args(argv)
    os.environ.setdefault("XLA_PYTHON_CLIENT_MEM_FRACTION", "0.5")
    import jax
    import jax.numpy as jnp
    import numpy as np
    import warp as wp
    device_columns = _harness.device_provenance()
    path = _harness.out_path(args.out, "warp_rows_variants.csv",
                             device_columns["device_slug"])
    common = {"N": args.n, "dtype": "float32", **device_columns,
              **_harness.host_provenance(), "git_sha": _harness.git_sha(),
              "warp": wp.__version__}
    rec = stages_bench.Recorder(args, common)
    n = args.n
    side = n ** (1 / 3)
    R = jnp.asarray(np.random.default_rng(0).uniform(0, side, (n, 3))
                    .astype(np.float32))
    cuda = jax.default_backend() in ("gpu", "cuda")
    try:
        prepared = stages_bench.jax_stages(rec, [R], side, n, args.width,
                                           cuda)
        variant_stages(rec, R, *prepared, args.width, args.variants)
        xla_stages(rec, R, *prepared, args.width, cuda)
    except Exception as e:  # noqa: BLE001
        traceback.print_exc(limit=4)
        rec.add("stages", error=f"{type(e).__name__}: {e}")
    _harness.write_csv(rec.rows, path)
    print(f"wrote {path}")


if __name__ == "__main__":
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    main()
