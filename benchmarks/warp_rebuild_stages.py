"""Where a ``cell[warp]`` Dense list rebuild's time goes: each stage of
the list's update (`jaxrt.backends.cell.search`'s Warp walk: the grid in
JAX, then one Warp call that bins, sorts, fills the cell table, gathers and
walks the rows, then the shell's decision in JAX) timed alone, on
neighbors.py's uniform scene (float32, density 1, cutoff 2.5, periodic).

Stages (one line and one CSV row each; a stage that fails is reported with
its error and the rest still run):

* ``allocate``: the list's first allocate (compiles), wall time.
* ``update jit first`` / ``update jit``: the jitted ``update`` (as
  neighbors.py times it), its first call (compiles) and the later ones;
  ``update eager``: the same without an outer jit.
* ``grid build (jit)``: `jaxrt.backends.cell.warp_grid.build` with the
  list's cell sizes and table.
* ``rows call (jit, graph G)``: `jaxrt.backends.rt.ffi.cell_candidate_rows`
  jitted alone, Warp's launches enqueued by the callback at every call
  (``none``) or replayed from Warp's graph (``warp``, CUDA only).
* ``warp bin`` ... ``warp rows walk``: the Warp pipeline's launches from
  Python on Warp's own arrays, each synchronised (wall time, launch
  included); ``warp table (serial tail)``: the cell table as it was
  built before, one thread writing every entry past the last key;
  ``warp pipeline``: all launches, one synchronise; ``warp host enqueue``:
  the host's time to launch them.

Timing: median, min and max over ``--repeats`` calls after ``--warmup``
untimed ones (the ``first`` rows: one call).

    python benchmarks/warp_rebuild_stages.py --n 1000000 --out $OUT
    python benchmarks/warp_rebuild_stages.py --n 4000 --repeats 2  # CPU
"""
from __future__ import annotations

import argparse
import os
import sys
import time
import traceback

if __package__:
    from benchmarks import _harness
else:
    import _harness

CUTOFF = 2.5
# The list's Warp grid: cells cutoff (1 + margin) / reach wide, reach 4
# along x and 2 across, a table of 4 cells per particle (the cell search's
# own constants).
REACH = (4, 2, 2)
MARGIN = 2.0 ** -10
CELLS_PER_PARTICLE = 4
SHELL = 8


def _legacy_table():
    import warp as wp

    @wp.kernel
    def serial_tail_table(keys: wp.array(dtype=wp.int32), n: int,
                          table: int, start: wp.array(dtype=wp.int32)):
        i = wp.tid()
        previous = int(-1)
        if i > 0:
            previous = keys[i - 1]
        current = table
        if i < n:
            current = keys[i]
        for c in range(previous + 1, current + 1):
            start[c] = i

    return serial_tail_table


class Recorder:
    """Times stages, prints a line per stage, keeps the CSV rows."""

    def __init__(self, args, common):
        self.args, self.common, self.rows = args, common, []

    def add(self, stage, samples_ms=None, error=None, **extra):
        row = {"stage": stage, **extra}
        if samples_ms:
            t = _harness.summarize(samples_ms, extra.pop("warmup", 0))
            row.update(t.columns())
            line = (f"{stage:34s} {t.median_ms:10.3f} ms  (min {t.min_ms:.3f}"
                    f", max {t.max_ms:.3f}, n={t.repeats})")
        else:
            line = f"{stage:34s} FAILED: {error}"
        row["status"] = "ok" if samples_ms else f"error: {error}"[:300]
        row.update(self.common)
        self.rows.append(row)
        extras = " ".join(f"{k}={v}" for k, v in extra.items())
        print(line + (f"  {extras}" if extras else ""), flush=True)

    def time(self, stage, fn, *, sync, repeats=None, warmup=None, **extra):
        repeats = self.args.repeats if repeats is None else repeats
        warmup = self.args.warmup if warmup is None else warmup
        try:
            for _ in range(warmup):
                sync(fn())
            samples = []
            for _ in range(repeats):
                t = time.perf_counter()
                sync(fn())
                samples.append((time.perf_counter() - t) * 1e3)
            self.add(stage, samples, warmup=warmup, **extra)
        except Exception as e:  # noqa: BLE001 - report and go on
            traceback.print_exc(limit=3)
            self.add(stage, error=f"{type(e).__name__}: {e}", **extra)


def list_stages(rec, R, side, n):
    """The list's own calls: allocate, jitted and eager update."""
    import jax
    import jaxrt
    from jax_md import space
    disp, _ = space.periodic(side)
    fns = jaxrt.neighbor_list(disp, side, CUTOFF,
                              backend=_harness.backend("cell[warp]"))
    nbrs = None

    def allocate():
        nonlocal nbrs
        nbrs = fns.allocate(R[0])
        return nbrs.idx

    rec.time("allocate (first, compiles)", allocate,
             sync=jax.block_until_ready, repeats=1, warmup=0)
    if nbrs is None:
        return None
    width = int(nbrs.idx.shape[1])
    update = jax.jit(fns.update)
    calls = iter(range(10 ** 6))
    pick = lambda: R[next(calls) % len(R)]  # noqa: E731
    rec.time("update jit first (compiles)", lambda: update(pick(), nbrs).idx,
             sync=jax.block_until_ready, repeats=1, warmup=0,
             row_width=width)
    rec.time("update jit", lambda: update(pick(), nbrs).idx,
             sync=jax.block_until_ready, row_width=width)
    rec.time("update eager (no outer jit)",
             lambda: fns.update(pick(), nbrs).idx,
             sync=jax.block_until_ready, repeats=max(2, rec.args.repeats // 3),
             warmup=1, row_width=width)
    return width


def jax_stages(rec, R, side, n, width, cuda):
    """The update's JAX pieces jitted alone: the grid, the Warp call."""
    import jax
    import jax.numpy as jnp
    from jaxrt.backends.cell import warp_grid, warp_rows
    from jaxrt.backends.rt import ffi
    table = CELLS_PER_PARTICLE * n + 64
    sizes = tuple(CUTOFF * (1 + MARGIN) / r for r in REACH)
    side3 = jnp.full((3,), side, jnp.float32)

    @jax.jit
    def grid_of(points):
        return warp_grid.build(points, side3, periodic=(True,) * 3,
                               padding=(False,) * 3, reach=REACH,
                               table=table, min_size=sizes)

    rec.time("grid build (jit)", lambda: grid_of(R[0]),
             sync=jax.block_until_ready)
    grid, cells = grid_of(R[0])
    thresholds = jnp.asarray([(CUTOFF - 1e-4) ** 2, (CUTOFF + 1e-4) ** 2],
                             jnp.float32)
    flags = warp_rows.MASK_SELF | sum(warp_rows.PERIODIC << a
                                      for a in range(3))
    for graph in ("none", "warp") if cuda else ("none",):
        call = jax.jit(lambda p, g, c, t, graph=graph: ffi.cell_candidate_rows(
            p, g, c, t, flags=flags, table=table, row_width=width,
            shell=SHELL, graph=graph))
        rec.time(f"rows call (jit, graph {graph})",
                 lambda: call(R[0], grid, cells, thresholds),
                 sync=jax.block_until_ready, row_width=width)
    return grid, cells, table, thresholds, flags


def warp_stages(rec, R, grid, cells, table, thresholds, flags, width):
    """The Warp pipeline's launches from Python, one stage at a time."""
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
    rows, count = empty(n * width, wp.int32), empty(n, wp.int32)
    shells, shell_count = empty(n * SHELL, wp.int32), empty(n, wp.int32)
    k = wk.KERNELS[wp.float32]
    end_bit = max(1, int(table).bit_length())
    sort_flags = flags & (7 * wk.PERIODIC)
    walk = wr.rows_kernel(wp.float32)
    legacy = _legacy_table()
    stages = {
        "warp bin": lambda: wp.launch(
            k["bin_particles"], dim=n, device=device,
            inputs=[points, grid_w, cells_w, sort_flags, wrapped, keys,
                    values]),
        "warp radix sort": lambda: wp.utils.radix_sort_pairs(
            keys, values, n, end_bit=end_bit),
        "warp table": lambda: wp.launch(
            wk.cell_table, dim=wk.table_threads(n, table), device=device,
            inputs=[keys, n, table, start]),
        "warp table (serial tail)": lambda: wp.launch(
            legacy, dim=n + 1, device=device, inputs=[keys, n, table, start]),
        "warp gather": lambda: wp.launch(
            k["gather"], dim=n, device=device,
            inputs=[values, wrapped, radius, 0, position, radius]),
        "warp rows walk": lambda: wp.launch(
            walk, dim=n, device=device, block_dim=wr.WALK_BLOCK,
            inputs=[position, keys, values, start, grid_w, cells_w, thr,
                    flags, width, SHELL, rows, count, shells, shell_count]),
    }
    sync = lambda _: wp.synchronize_device(device)  # noqa: E731
    # In pipeline order, so that each stage reads what the one before wrote.
    for name, fn in stages.items():
        rec.time(name, fn, sync=sync, device_warp=device)
    order = ("warp bin", "warp radix sort", "warp table", "warp gather",
             "warp rows walk")

    def pipeline():
        for name in order:
            stages[name]()

    rec.time("warp pipeline", pipeline, sync=sync, device_warp=device)
    rec.time("warp host enqueue", pipeline, sync=lambda _: None,
             device_warp=device)
    wp.synchronize_device(device)
    try:
        hits = count.numpy()
        rec.add("warp rows walk hits per particle (value)",
                [float(hits.mean())], row_width=width,
                overflowing=int((hits > width).sum()))
    except Exception as e:  # noqa: BLE001
        rec.add("warp rows walk hits per particle (value)", error=str(e))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--skip-list", action="store_true",
                        help="skip the list's allocate and update")
    parser.add_argument("--out", default=None, help="CSV path or folder")
    args = parser.parse_args(argv)
    # Leave room for Warp's own arrays next to JAX's pool.
    os.environ.setdefault("XLA_PYTHON_CLIENT_MEM_FRACTION", "0.5")
    import jax
    import jax.numpy as jnp
    import numpy as np
    device_columns = _harness.device_provenance()
    path = _harness.out_path(args.out, "warp_rebuild_stages.csv",
                             device_columns["device_slug"])
    import warp as wp
    common = {"N": args.n, "dtype": "float32", **device_columns,
              **_harness.host_provenance(), "git_sha": _harness.git_sha(),
              "warp": wp.__version__}
    rec = Recorder(args, common)
    n = args.n
    side = n ** (1 / 3)
    base = np.random.default_rng(0).uniform(0, side, (n, 3))
    jitter = np.random.default_rng(1)
    R = [jnp.asarray(np.mod(base + jitter.normal(0, 1e-3, base.shape), side)
                     .astype(np.float32)) for _ in range(3)]
    cuda = jax.default_backend() in ("gpu", "cuda")
    width = None
    if not args.skip_list:
        width = list_stages(rec, R, side, n)
    width = width or 128
    prepared = None
    try:
        prepared = jax_stages(rec, R, side, n, width, cuda)
    except Exception as e:  # noqa: BLE001
        traceback.print_exc(limit=3)
        rec.add("jax stages", error=f"{type(e).__name__}: {e}")
    if prepared is not None:
        try:
            warp_stages(rec, R[0], *prepared, width)
        except Exception as e:  # noqa: BLE001
            traceback.print_exc(limit=3)
            rec.add("warp stages", error=f"{type(e).__name__}: {e}")
    _harness.write_csv(rec.rows, path)
    print(f"wrote {path}")


if __name__ == "__main__":
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    main()
