"""Where the list-free cell step's grid time goes (#18): each stage of
`jaxrt.energy.listfree.lj.cell_runs` jitted and timed alone on roofline.py's LJ
system (jittered simple-cubic lattice, rho = 0.8, cutoff 2.5, float32),
beside the alternatives that would replace a stage.

Rows: ``grid+key`` (`jaxrt.backends.cell.grid.grid`, its coarsening while_loop, and the
cell keys), ``grid+key static`` (the same with the cells per axis known
when tracing), the sort as `fused.sort_by_key` does it and three others,
``cell_starts`` (a scatter-add and a cumsum over the 4 N + 64 table) with
its two pieces, ``runs`` (`jaxrt.backends.cell.grid.runs`: starts and both parts' run
ends), the run ends of 9 runs per particle as one slice each (before
2026-12-02) or two gathers, ``cell_runs`` whole, and only what the kernel
reads of it now that it finds its runs in the cell-start table (order,
positions, table, cells); the table as long as the cells, and built by
binary searches (`jnp.searchsorted`) instead of a scatter and a cumsum. Stages timed apart pay their own
launches and outputs, so they add up to more than the whole.

    GIT_SHA=$(git rev-parse --short HEAD) python benchmarks/grid_stages.py --n 1000000
    python benchmarks/grid_stages.py --n 27000          # CPU smoke
"""
from __future__ import annotations

import argparse
import os
import sys

if __package__:  # run as -m, or imported: the package's modules
    from benchmarks import _harness
else:  # run as a file: its folder is sys.path[0]
    import _harness


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--out", default=None, help="CSV path or folder")
    args = parser.parse_args(argv)

    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax_md.partition import NeighborListFormat
    import roofline
    from jaxrt.backends.cell import grid as cell_grid
    from jaxrt.backends.cell import search as cell_list
    from jaxrt.backends.contract import Geometry, Query
    from jaxrt.energy.listfree import lj as fused

    R, box, _ = roofline._system(args.n, jnp.float32)
    n = R.shape[0]
    params = roofline._grid(box)
    inputs = [R, (R + 1e-3) % box]
    geometry = Geometry(side=jnp.asarray(params.side, R.dtype),
                        scale=jnp.ones((3,), R.dtype))
    query = Query(cutoff=params.bound, periodic=(True,) * 3, mask_self=True,
                  format=NeighborListFormat.Dense)
    reach, table = cell_grid.REACH, cell_grid.table_size(n)
    device = _harness.device_provenance()
    rows = []

    def stage(name, f, xs):
        t = _harness.time_calls(jax.jit(f), xs, repeats=args.repeats,
                                warmup=args.warmup)
        rows.append({"stage": name, "N": n, **t.columns(), "dtype": "float32",
                     **device, **_harness.host_provenance(),
                     "git_sha": _harness.git_sha()})
        print(f"{name:30s} {t.median_ms:8.3f} ms", flush=True)

    def grid(R):
        _, cell, cells = cell_grid.grid(geometry.grid_coordinates(R),
                                         geometry, query, reach)
        return cell, cells, cell_grid.key(cell, cells)

    stage("grid+key", grid, inputs)
    outs = [jax.jit(grid)(x) for x in inputs]
    cells = np.asarray(outs[0][1])

    def grid_static(R):
        side = jnp.asarray(params.side, R.dtype)
        wrapped = jnp.mod(R, side)
        cell = jnp.clip(jnp.floor(wrapped / (side / cells)).astype(jnp.int32),
                        0, cells - 1)
        return cell, cell_grid.key(cell, jnp.asarray(cells))

    stage("grid+key static", grid_static, inputs)
    keys = [o[2] for o in outs]
    stage("sort: sort_by_key", lambda k: fused.sort_by_key(k, table), keys)
    stage("sort: argsort", jnp.argsort, keys)
    stage("sort: uint32 keys only", lambda k: jnp.sort(k.astype(jnp.uint32)), keys)
    stage("sort: uint32 packed (lossy)", lambda k: jnp.sort(
        (k.astype(jnp.uint32) << 11) | (jnp.arange(n, dtype=jnp.uint32) & 2047)),
        keys)
    srt = [jax.jit(lambda k: fused.sort_by_key(k, table))(k) for k in keys]
    stage("cell_starts", cell_grid.cell_starts, [s[1] for s in srt])
    stage("cell_starts: cumsum", lambda x: jnp.cumsum(x, dtype=jnp.int32),
          [jnp.ones((table,), jnp.int32)] * 2)
    stage("cell_starts: scatter-add", lambda k: jnp.zeros(
        (table,), jnp.int32).at[k].add(1, mode="drop"), [s[1] for s in srt])
    # The table as long as the cells (the fused grid's static table), and
    # the same table by binary searches instead of a scatter and a scan.
    static = int(np.prod(cells)) + 1
    stage("cell_starts static table", lambda k: cell_grid.cell_starts(
        k, static), [s[1] for s in srt])
    for method in ("scan_unrolled", "sort"):
        stage(f"cell_starts static: searchsorted {method}",
              lambda k, m=method: jnp.searchsorted(
                  k, jnp.arange(static + 1, dtype=jnp.int32), side="left",
                  method=m).astype(jnp.int32), [s[1] for s in srt])

    def runs(a):
        (order, sorted_key), (cell, n_cells, _) = a
        return cell_grid.runs(sorted_key, cell[order], n_cells, query, reach)

    stage("runs", runs, list(zip(srt, outs)))
    starts = [jax.jit(cell_grid.cell_starts)(s[1]) for s in srt]
    firsts = [jnp.asarray(np.random.default_rng(k).integers(0, table - 20, (n, 9)),
                          jnp.int32) for k in range(2)]
    extra = jnp.full((n, 9), 8, jnp.int32)

    def run_ends_slice(start, first):
        # The run ends as one slice of the table per run (before 2026-12-02).
        span_len = cell_list._RUN_SPAN
        first = jnp.clip(first, 0, start.shape[0] - span_len)
        span = jax.vmap(lambda f: jax.lax.dynamic_slice(start, (f,), (span_len,)))(
            first.reshape(-1)).reshape(first.shape + (span_len,))
        at = jnp.arange(span_len, dtype=jnp.int32)
        return span[..., 0], jnp.sum(jnp.where(at == 9, span, 0), axis=-1)

    stage("run ends x9: slices", lambda a: run_ends_slice(*a),
          list(zip(starts, firsts)))
    stage("run ends x9: two gathers (now)",
          lambda a: cell_list._run_ends(a[0], a[1], extra),
          list(zip(starts, firsts)))
    stage("cell_runs", lambda R: fused.cell_runs(R, params), inputs)

    def kernel_grid(R):  # what the kernel that finds its runs reads
        order, _, images = fused.cell_runs(R, params)
        return (order, images.position, images.cell_starts, images.cell,
                images.cells)

    stage("cell_runs: the kernel's grid", kernel_grid, inputs)
    path = _harness.write_csv(rows, _harness.out_path(
        args.out, "grid_stages.csv", device.get("device_slug", "unknown")))
    print(f"cells per axis {cells.tolist()}; wrote {path}")


if __name__ == "__main__":
    main()
