"""Where the Warp list-free LJ engine's time goes: each stage of
`jaxrt.backends.cell.warp_kernels.lj_sums` timed alone (bin, radix sort,
cell table, gather, walk), the walk's variants side by side, the
neighbour lists' walk on the same grid (`jaxrt.backends.cell.warp_rows`:
``rows walk``, rows of `ROW_WIDTH`), each whole pipeline and the host's
time to enqueue it, and the jitted JAX call
(`jaxrt.energy.listfree.warp_cell.walk`, grid included), on md_step's LJ
system (roofline.py's jittered simple-cubic lattice, rho 0.8, cutoff 2.5,
float32, periodic), with the MD step's flags (forces and energy only).

Timing: CUDA events around each stage inside one pass of the pipeline,
queued behind an untimed walk so that they time the GPU's work rather
than Python's launches (on the CPU, wall time with a device synchronise
between stages); median, min and max over ``--repeats`` passes after
``--warmup`` untimed ones. ``host enqueue``: the host's time to launch the
whole pipeline, which a step pays where nothing else keeps the GPU busy.

Walk variants (`walk_kernel`): ``generic`` reads the flags at run time,
``static`` compiles them in; ``hoist`` computes the pair terms' constants
once per particle and selects the switch (`lj_forces`); ``bN`` launches N
threads per block. ``same`` says whether the variant's forces equal the
first variant's bit for bit (``max_rel``: else their largest difference
over the largest force).

The cluster walk (`jaxrt.backends.cell.warp_cluster`): ``clusters``
times its table (counts, scan, starts), ``walk clusterK`` a thread per
cluster of up to K particles of one cell (static flags, hoisted terms,
loops over the cluster unrolled on CUDA), ``noprune`` without the
cluster's bounding-box test; its rows give the clusters' number and mean
size. ``walk nativeK`` (CUDA only): a warp per cluster of K, its
candidates compacted by a ballot and shuffled to the lanes
(`warp_cluster_native.native_kernel`; the sums agree to rounding, so ``same`` is
usually False and ``max_rel`` small). Cells are ``bound / reach`` wide (``--reach X Y``: X along x, Y
across): the cluster walk needs several particles per cell (reach 1 1 or
2 1), the thread walk prefers small cells (4 2, the default).

Roofline columns per row: ``bytes`` and ``flops`` counted per stage (the
model below), ``floor_ms`` the larger of bytes over ``--bandwidth`` and
flops over ``--flops``, ``of_floor`` the time over it. The walk's
candidates per particle (``candidates``) are counted on a sample of
particles with the kernel's own stencil; its pairs (``hits``) by the
kernel's count.

    GIT_SHA=$(git rev-parse --short HEAD) python benchmarks/warp_stages.py \\
        --n 1000000 10000000 --out benchmarks/results/h200/warp_stages_SHA
    python benchmarks/warp_stages.py --n 4096 --repeats 3 --warmup 1  # CPU
    python benchmarks/warp_stages.py --reach 1 1 --n 1000000  # clusters
"""
from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time

if __package__:  # run as -m, or imported: the package's modules
    from benchmarks import _harness
else:  # run as a file: its folder is sys.path[0]
    import _harness

# The walk's variants: (label, specialize, hoist, block_dim[, trim]);
# ``trim``: rows skipped and x ranges cut by `warp_kernels.trim_functions`
# (the sphere the stencil covers, not the cutoff). Measured
# before and dropped (slower; results/h200/warp_stages_244e535): each
# stencil row's x range trimmed to the particle's cutoff (171 -> 116
# candidates per particle, but a warp still walks its widest lane's range).
VARIANTS = (("generic", False, False, 256), ("static", True, False, 256),
            ("static+hoist", True, True, 256),
            ("static+hoist b128", True, True, 128),
            ("static+hoist b64", True, True, 64),
            ("static+hoist b64 trim", True, True, 64, True))
# The lists' walk's row and shell widths (rows of the LJ system hold ~52).
ROW_WIDTH, SHELL_WIDTH = 96, 8
# Flops of the walk: a candidate's difference, square and test; a pair's
# Lennard-Jones terms inside the switch (reciprocal, powers, force, sums).
FLOPS_CANDIDATE, FLOPS_PAIR = 9, 35
# The cluster walk's variants: (label, particles per cluster, prune,
# block_dim).
CLUSTER_VARIANTS = (("cluster8", 8, True, 64),
                    ("cluster8 noprune", 8, False, 64),
                    ("cluster8 b128", 8, True, 128), ("cluster4", 4, True, 64),
                    ("cluster16", 16, True, 64))
# The warp-cooperative walk's (CUDA only): (label, size, block_dim).
NATIVE_VARIANTS = (("native8", 8, 128), ("native8 b256", 8, 256),
                   ("native4", 4, 128), ("native16", 16, 128))


def candidates(keys, cells, sample=4096):
    """Mean candidates per particle of the walk's stencil (the kernel's
    rows and x ranges, periodic axes with images) over ``sample`` sorted
    particles, from the cell-start table's counts."""
    import numpy as np
    n = len(keys)
    nx, ny, nz, ax, ay, az = (int(c) for c in cells)
    counts = np.bincount(keys, minlength=nx * ny * nz).reshape(nz, ny, nx)
    rng = np.random.default_rng(0)
    total = 0
    picks = rng.choice(n, min(sample, n), replace=False)
    for i in picks:
        k = int(keys[i])
        cx, cy, cz = k % nx, (k // nx) % ny, k // (nx * ny)
        for dz in range(-az, az + 1):
            for dy in range(-ay, ay + 1):
                for x in range(cx - ax, cx + ax + 1):
                    total += counts[(cz + dz) % nz, (cy + dy) % ny, x % nx]
    return total / len(picks)


def measure(n_target, args, rows, device_columns):
    import jax
    import jax.numpy as jnp
    import numpy as np
    import warp as wp
    import roofline
    from jaxrt.backends.cell import warp_cluster as wc
    from jaxrt.backends.cell import warp_cluster_native as wcn
    from jaxrt.backends.cell import warp_kernels as wk
    from jaxrt.backends.cell import warp_rows as wr
    from jaxrt.energy.listfree import warp_cell

    R, box, _ = roofline._system(n_target, jnp.float32)
    n = R.shape[0]
    params = roofline._grid(box)
    reach = (args.reach[0], args.reach[1], args.reach[1])
    g, cells, table = warp_cell.grid(R, params, reach)
    g, cells = np.asarray(g, np.float32), np.asarray(cells, np.int32)
    device = "cuda:0" if wp.is_cuda_available() else "cpu"
    cuda = device.startswith("cuda")
    v3 = wp.vec3f
    arr = lambda a, dt: wp.array(a, dtype=dt, device=device)  # noqa: E731
    empty = lambda k, dt: wp.empty(k, dtype=dt, device=device)  # noqa: E731
    points = arr(np.asarray(R, np.float32), v3)
    radii = empty(1, wp.float32)
    grid_w, cells_w = arr(g, v3), arr(cells, wp.int32)
    packed = np.zeros(wk.N_PARAMS, np.float32)
    packed[wk.SIGMA], packed[wk.EPSILON] = 1.0, 1.0
    packed[wk.R_ONSET], packed[wk.R_CUTOFF] = params.r_onset, params.r_cutoff
    params_w = arr(packed, wp.float32)
    flags = (wk.PERIODIC << 0) | (wk.PERIODIC << 1) | (wk.PERIODIC << 2)
    forces, energy = empty(n, v3), empty(n, wp.float32)
    d_sigma, d_epsilon = empty(n, wp.float32), empty(n, wp.float32)
    count = empty(n, wp.int32)
    keys, values = empty(2 * n, wp.int32), empty(2 * n, wp.int32)
    wrapped, position = empty(n, v3), empty(n, v3)
    start, radius = empty(table + 1, wp.int32), empty(1, wp.float32)
    k = wk.KERNELS[wp.float32]
    end_bit = max(1, int(table).bit_length())
    # The cluster walk's tables, one set per cluster size.
    natives = NATIVE_VARIANTS if cuda else ()
    sizes = sorted({v[1] for v in CLUSTER_VARIANTS + natives})
    counts = empty(table + 1, wp.int32)
    tables = {size: (empty(table + 1, wp.int32),
                     empty(wc.bound(n, table, size) + 1, wp.int32))
              for size in sizes}

    def build(size):
        offs, clusters = tables[size]
        wc.build_clusters(start, counts, offs, clusters, n=n, size=size)

    def cluster_args(size, walk_flags):
        # The arrays both cluster walks (native and tiled) read and write.
        offs, clusters = tables[size]
        return dict(position=position, keys=keys, values=values,
                    radius=radius, start=start, offsets=offs,
                    clusters=clusters, grid=grid_w, cells=cells_w,
                    params=params_w, flags=walk_flags, forces=forces,
                    energy=energy, d_sigma=d_sigma, d_epsilon=d_epsilon,
                    count=count, size=size)

    def native_walk(variant, walk_flags=flags):
        _, size, block = variant
        kernel = wcn.native_kernel(wp.float32, walk_flags, size=size)
        wcn.launch(kernel, **cluster_args(size, walk_flags), block_dim=block)

    def cluster_walk(variant, walk_flags=flags):
        if len(variant) == 3:
            return native_walk(variant, walk_flags)
        _, size, prune, block = variant
        kernel = wc.cluster_kernel(wp.float32, walk_flags, size=size,
                                   prune=prune, unroll=cuda)
        wc.launch_walk(kernel, **cluster_args(size, walk_flags),
                       block_dim=block)

    def walk(variant, walk_flags=flags):
        _, specialize, hoist, block = variant[:4]
        trim = variant[4] if len(variant) > 4 else False
        kernel = wk.walk_kernel(wp.float32, walk_flags, specialize=specialize,
                                hoist=hoist, trim=trim)
        wp.launch(kernel, dim=n, device=device, block_dim=block,
                  inputs=[position, keys, values, radius, start, grid_w,
                          cells_w, params_w, walk_flags, forces, energy,
                          d_sigma, d_epsilon, count])

    stages = {
        "bin": lambda: wp.launch(k["bin_particles"], dim=n, device=device,
                                 inputs=[points, grid_w, cells_w, flags,
                                         wrapped, keys, values]),
        "sort": lambda: wp.utils.radix_sort_pairs(keys, values, n,
                                                  end_bit=end_bit),
        "table": lambda: wp.launch(wk.cell_table,
                                   dim=wk.table_threads(n, table),
                                   device=device,
                                   inputs=[keys, n, table, start]),
        "gather": lambda: wp.launch(k["gather"], dim=n, device=device,
                                    inputs=[values, wrapped, radii, 0,
                                            position, radius]),
    }
    for v in VARIANTS:
        stages["walk " + v[0]] = (lambda v=v: walk(v))
    stages["clusters"] = lambda: build(wc.CLUSTER_SIZE)
    for size in sizes:
        if size != wc.CLUSTER_SIZE:
            stages[f"clusters{size}"] = (lambda size=size: build(size))
    for v in CLUSTER_VARIANTS + natives:
        stages["walk " + v[0]] = (lambda v=v: cluster_walk(v))

    # The neighbour lists' walk (`warp_rows`) on the same sorted grid: the
    # sums' stencil, writing rows of ROW_WIDTH and shells of SHELL_WIDTH.
    rows_out, row_count = empty(n * ROW_WIDTH, wp.int32), empty(n, wp.int32)
    shells, shell_count = empty(n * SHELL_WIDTH, wp.int32), empty(n, wp.int32)
    rc = float(params.r_cutoff)
    thresholds = arr(np.asarray([(rc * (1 - 2.0 ** -18)) ** 2,
                                 (rc * (1 + 2.0 ** -18)) ** 2], np.float32),
                     wp.float32)
    rows_flags = flags | wr.MASK_SELF
    rows_inputs = [position, keys, values, start, grid_w, cells_w,
                   thresholds, rows_flags, ROW_WIDTH, SHELL_WIDTH, rows_out,
                   row_count, shells, shell_count]
    stages["rows walk (lists)"] = lambda: wp.launch(
        wr.rows_kernel(wp.float32), dim=n, device=device,
        block_dim=wr.WALK_BLOCK, inputs=rows_inputs)

    def timed_pass():
        # One pass of the pipeline, every walk variant after the gather;
        # returns ms per stage.
        out = {}
        if cuda:
            # A walk queued first keeps the GPU busy while the host
            # enqueues the stages: the events then time the GPU's work,
            # not Python's launches (``host enqueue`` times those).
            walk(VARIANTS[0])
            marks = [wp.Event(enable_timing=True) for _ in range(len(stages)
                                                                  + 1)]
            wp.record_event(marks[0])
            for m, (name, f) in zip(marks[1:], stages.items()):
                f()
                wp.record_event(m)
            wp.synchronize_device(device)
            for a, b, name in zip(marks, marks[1:], stages):
                out[name] = wp.get_event_elapsed_time(a, b)
        else:
            for name, f in stages.items():
                t0 = time.perf_counter()
                f()
                wp.synchronize_device(device)
                out[name] = 1e3 * (time.perf_counter() - t0)
        return out

    samples = {name: [] for name in stages}
    reference = None
    same = {}
    for rep in range(args.warmup + args.repeats):
        t = timed_pass()
        if rep >= args.warmup:
            for name, ms in t.items():
                samples[name].append(ms)
        if rep == 0:
            # Each variant's forces against the first's, bit for bit.
            for v in VARIANTS + CLUSTER_VARIANTS + natives:
                (walk if v in VARIANTS else cluster_walk)(v)
                f = forces.numpy()
                if reference is None:
                    reference = f
                same[v[0]] = (bool(np.array_equal(f, reference)),
                              float(np.max(np.abs(f - reference))
                                    / np.max(np.abs(reference))))

    # The pipeline whole (events around it) and the host's enqueue time.
    def pipeline():
        wk.lj_sums(points, radii, grid_w, cells_w, params_w, flags,
                   forces=forces, energy=energy, d_sigma=d_sigma,
                   d_epsilon=d_epsilon, count=count, keys=keys, values=values,
                   wrapped=wrapped, start=start, position=position,
                   radius=radius)
    def rows_pipeline():
        wr.candidate_rows(points, grid_w, cells_w, thresholds, rows_flags,
                          row_width=ROW_WIDTH, shell=SHELL_WIDTH,
                          rows=rows_out, count=row_count, shells=shells,
                          shell_count=shell_count, keys=keys, values=values,
                          wrapped=wrapped, start=start, position=position,
                          radius=radius)

    for label, run in (("lj_sums", pipeline),
                       ("candidate_rows", rows_pipeline)):
        whole, host = [], []
        for rep in range(args.warmup + args.repeats):
            wp.synchronize_device(device)
            if cuda:
                walk(VARIANTS[0])  # busy, as in timed_pass
                a = wp.Event(enable_timing=True)
                b = wp.Event(enable_timing=True)
                wp.record_event(a)
            t0 = time.perf_counter()
            run()
            t1 = time.perf_counter()
            if cuda:
                wp.record_event(b)
            wp.synchronize_device(device)
            if rep >= args.warmup:
                host.append(1e3 * (t1 - t0))
                whole.append(wp.get_event_elapsed_time(a, b) if cuda
                             else 1e3 * (time.perf_counter() - t0))
        samples[f"pipeline ({label})"] = whole
        samples[f"host enqueue ({label})"] = host

    # The cluster walk's pipeline, as ffi.cell_lj_sums(walk="cluster")
    # launches it (clusters of wc.CLUSTER_SIZE).
    def cluster_pipeline():
        offs, clusters = tables[wc.CLUSTER_SIZE]
        wc.lj_sums(points, radii, grid_w, cells_w, params_w, flags,
                   forces=forces, energy=energy, d_sigma=d_sigma,
                   d_epsilon=d_epsilon, count=count, keys=keys, values=values,
                   wrapped=wrapped, start=start, position=position,
                   radius=radius, counts=counts, offsets=offs,
                   clusters=clusters)
    whole = []
    for rep in range(args.warmup + args.repeats):
        wp.synchronize_device(device)
        if cuda:
            walk(VARIANTS[0])  # busy, as in timed_pass
            a, b = wp.Event(enable_timing=True), wp.Event(enable_timing=True)
            wp.record_event(a)
        t0 = time.perf_counter()
        cluster_pipeline()
        if cuda:
            wp.record_event(b)
        wp.synchronize_device(device)
        if rep >= args.warmup:
            whole.append(wp.get_event_elapsed_time(a, b) if cuda
                         else 1e3 * (time.perf_counter() - t0))
    samples["pipeline (cluster lj_sums)"] = whole

    # The JAX call as the MD step makes it (grid in JAX, then the FFI).
    jwalk = jax.jit(lambda R: warp_cell.walk(
        R, 1.0, 1.0, None, params, derivatives=False, count=False,
        reach=tuple(args.reach))[0])
    t = _harness.time_calls(jwalk, [R], repeats=args.repeats,
                            warmup=args.warmup)
    timing_jax = t
    jcluster = jax.jit(lambda R: warp_cell.walk(
        R, 1.0, 1.0, None, params, derivatives=False, count=False,
        reach=tuple(args.reach), walk="cluster")[0])
    timing_cluster = _harness.time_calls(jcluster, [R], repeats=args.repeats,
                                         warmup=args.warmup)

    # Work counts for the roofline.
    walk(VARIANTS[-1], flags | wk.COUNT)
    wp.synchronize_device(device)
    hits = float(np.mean(count.numpy()))
    key = keys.numpy()[:n]
    cand = candidates(key, cells)
    cluster_stats = {}
    for size in sizes:
        build(size)
        total = int(tables[size][0].numpy()[-1])
        cluster_stats[size] = (total, n / max(total, 1))
    passes = math.ceil(end_bit / 8)
    model = {
        "bin": (12 + 20) * n, "sort": (4 + passes * 16) * n,
        "table": 4 * n + 4 * (table + 1), "gather": (4 + 12 + 12) * n,
        # positions, key, index read; force (scattered), three sums and a
        # count written; the table's run bounds mostly from cache.
        "walk": (12 + 8 + 12 + 16) * n,
        # counts written, scanned (read, written), starts read and written.
        "clusters": 4 * 5 * (table + 1) + 4 * n,
    }
    common = {"N": n, "dtype": "float32", "table": table,
              "reach": " ".join(str(r) for r in reach), "cells":
              " ".join(str(int(c)) for c in cells[:3]), "hits": hits,
              **device_columns, **_harness.host_provenance(),
              "git_sha": _harness.git_sha()}
    for name, ms in samples.items():
        row = {"stage": name, "median_ms": statistics.median(ms),
               "min_ms": min(ms), "max_ms": max(ms),
               "repeats": args.repeats, "warmup": args.warmup, **common}
        base = name.split(" ")[0]
        if base == "walk":
            label = name[len("walk "):]
            row["candidates"] = cand
            row["same"], row["max_rel"] = same[label]
            row["bytes"] = model["walk"]
            row["flops"] = n * (cand * FLOPS_CANDIDATE + hits * FLOPS_PAIR)
            size = next((v[1] for v in CLUSTER_VARIANTS + NATIVE_VARIANTS
                         if v[0] == label), None)
            if size is not None:
                row["clusters"], row["per_cluster"] = cluster_stats[size]
        elif base.startswith("clusters"):
            row["bytes"], row["flops"] = model["clusters"], 0
        elif base in model:
            row["bytes"], row["flops"] = model[base], 0
        if "bytes" in row:
            floor = max(row["bytes"] / args.bandwidth,
                        row["flops"] / args.flops) * 1e3
            row["floor_ms"], row["of_floor"] = floor, row["median_ms"] / floor
        rows.append(row)
        print(f"N {n:9d} {name:24s} {row['median_ms']:9.4f} ms"
              + (f"  floor {row['floor_ms']:.4f}" if "floor_ms" in row
                 else "") + (f"  same {row['same']} {row['max_rel']:.1e}"
                             if "same" in row else ""), flush=True)
    rows.append({"stage": "jax walk (jit, grid + ffi)",
                 **timing_jax.columns(), **common})
    rows.append({"stage": "jax cluster walk (jit, grid + ffi)",
                 **timing_cluster.columns(), **common})
    print(f"N {n:9d} {'jax walk':24s} {timing_jax.median_ms:9.4f} ms; "
          f"candidates {cand}, hits {hits:.2f}", flush=True)
    print(f"N {n:9d} {'jax cluster walk':24s} "
          f"{timing_cluster.median_ms:9.4f} ms; clusters (number, mean "
          f"size) {cluster_stats}", flush=True)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, nargs="+", default=[1_000_000])
    parser.add_argument("--reach", type=int, nargs=2, default=[4, 2],
                        metavar=("X", "YZ"),
                        help="the stencil's reach in cells along x and "
                        "across (cells bound / reach wide)")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--bandwidth", type=float, default=4.8e12,
                        help="bytes/s of the floor (H200's HBM3e)")
    parser.add_argument("--flops", type=float, default=60e12,
                        help="FP32 flop/s of the floor (H200)")
    parser.add_argument("--out", default=None, help="CSV path or folder")
    args = parser.parse_args(argv)
    device_columns = _harness.device_provenance()
    path = _harness.out_path(args.out, "warp_stages.csv",
                             device_columns["device_slug"])
    rows = []
    for n in args.n:
        measure(n, args, rows, device_columns)
        _harness.write_csv(rows, path)
    print(f"wrote {path}")


if __name__ == "__main__":
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    main()
