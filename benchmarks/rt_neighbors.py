"""Benchmark: the ray-traced backend "bvh" against jax-md and Warp's HashGrid.

Scenes (seed 001 §5; the results in benchmarks/RESULTS.md):
  uniform  N particles uniform in a periodic cube of side N^(1/3) (rho = 1),
           cutoff 2.5 (k ~ 65 neighbours); three independent draws.
  sphere   N points uniform on the unit sphere's surface, free space, cutoff
           C = 12 / sqrt(N) (k ~ 36), shifted by 1 + C into the box that
           just holds them, of side 2 + 2C (seed 001), for every method.

Rows (float32, Dense unless named), one worker process each (`_harness`);
every time is the median (and min / max) of ``--repeats`` timed calls after
``--warmup`` untimed ones, rotating between 3 input sets so that no call
repeats the previous one:
  bvh jit Dense (rebuild)       jaxrt.neighbor_list(backend="bvh").update
                                under jax.jit, unrelated inputs: every call
                                rebuilds the BVH (``bvh_updates`` counts
                                what it did: `jaxrt.backends.rt.ffi.update_counts`)
  bvh jit Dense (refit)         the same on inputs jittered by 1 % of the
                                cutoff: the kept BVH is refit
  bvh[always-rebuild] jit Dense
                                ``Bvh(policy="rebuild")``: never
                                refits, so never reads the drift back
  bvh jit OrderedSparse (rebuild)
                                count, scan, fill path
  bvh[cluster_size=g] jit Dense (rebuild)
                                one BVH box per g sorted particles
                                (``--jit-clusters``)
  bvh update (rebuild) / (refit), bvh BVH rebuild only, bvh query Dense,
  bvh[unsorted] ...             the Warp pieces (`jaxrt.backends.rt.aabb.AabbSearch`,
                                built from the `jaxrt.backends.Bvh` options)
                                timed directly, synchronised
  bvh[leaf_size=l,cluster_size=g] update (rebuild) / query Dense
                                the same pieces with other options
                                (``--builders`` adds other BVH builders)
  jax-md Dense update           jax_md.partition.neighbor_list(...).update
  jaxrt cell Dense update       the pure-JAX backend
  warp HashGrid build / query Dense
                                wp.HashGrid and a hand-written query kernel
                                writing the same Dense rows (periodic images
                                by the same gamma rays as "bvh",
                                `_warp_hashgrid`)
``k``: mean neighbours of the row's own list where it builds one, else the
scene's nominal k. Every query row's counts on the first input set are
compared with "bvh query Dense"'s: ``counts_differ`` particles differ.

Usage:
  python benchmarks/rt_neighbors.py            # N = 1e5 and 1e6 (GPU)
  python benchmarks/rt_neighbors.py --quick    # N = 2000 (CPU smoke run)
  python benchmarks/rt_neighbors.py --sizes 1000000 --scenes uniform \\
      --only "bvh jit Dense (rebuild)" "warp HashGrid query Dense"
  python benchmarks/rt_neighbors.py --list     # the row labels
"""
from __future__ import annotations

import hashlib
import math
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

if __package__:  # run as -m, or imported: the package's modules
    from benchmarks import _harness
else:  # run as a file: its folder is sys.path[0]
    import _harness

INPUT_SETS = 3
NOMINAL_K = {"uniform": 4 / 3 * math.pi * 2.5 ** 3, "sphere": 36.0}
VARIANTS = [(4, 1), (1, 4), (1, 8), (1, 16), (1, 32), (4, 16)]
"""(leaf_size, cluster_size) of the swept Warp pieces (Warp's default
builder unless ``--builders``)."""


# ---------------------------------------------------------------------------
# Scenes


def make_scene(scene: str, n: int):
    """3 float32 (n, 3) input sets, box side, cutoff, periodic."""
    import numpy as np
    rng = np.random.default_rng({"uniform": 0, "sphere": 1}[scene] + 10 * n)
    if scene == "uniform":
        side = n ** (1.0 / 3.0)
        sets = [(rng.random((n, 3)) * side).astype(np.float32)
                for _ in range(INPUT_SETS)]
        return sets, side, 2.5, True
    cutoff = 12.0 / math.sqrt(n)
    sets = []
    for _ in range(INPUT_SETS):
        v = rng.normal(size=(n, 3))
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        sets.append((v + 1.0 + cutoff).astype(np.float32))
    return sets, 2.0 + 2.0 * cutoff, cutoff, False


def jittered(points, cutoff, seed):
    """3 sets within 1 % of the cutoff of ``points`` (a refit's worth of
    motion)."""
    import numpy as np
    rng = np.random.default_rng(seed)
    return [(points + rng.normal(scale=0.01 * cutoff, size=points.shape)
             ).astype(np.float32) for _ in range(INPUT_SETS)]


# ---------------------------------------------------------------------------
# The plan: one job per row


def plan_rows(jit_clusters, builders) -> list[dict]:
    """Every row's label and what it measures (``kind`` and options)."""
    rows = [dict(method="bvh jit Dense (rebuild)", kind="jit", backend="bvh",
                 format="Dense", inputs="independent", expect="rebuild")]
    rows += [dict(method=f"bvh[cluster_size={g}] jit Dense (rebuild)",
                  kind="jit", backend=f"bvh[cluster_size={g}]", format="Dense",
                  inputs="independent", expect="rebuild") for g in jit_clusters]
    rows += [dict(method="bvh jit Dense (refit)", kind="jit", backend="bvh",
                  format="Dense", inputs="jittered", expect="refit"),
             dict(method="bvh[always-rebuild] jit Dense", kind="jit",
                  backend="bvh[always-rebuild]", format="Dense",
                  inputs="independent", expect="rebuild"),
             dict(method="bvh jit OrderedSparse (rebuild)", kind="jit",
                  backend="bvh", format="OrderedSparse", inputs="independent",
                  expect="rebuild")]
    for label in ("bvh", "bvh[unsorted]"):
        rows.append(dict(method=f"{label} update (rebuild)", kind="update",
                         backend=label, inputs="independent"))
        if label == "bvh":
            rows += [dict(method="bvh BVH rebuild only", kind="bvh-rebuild",
                          backend=label, inputs="independent"),
                     dict(method="bvh update (refit)", kind="update",
                          backend=label, inputs="jittered")]
        rows.append(dict(method=f"{label} query Dense", kind="query",
                         backend=label, inputs="independent"))
    for builder in [None] + list(builders):
        for leaf, cluster in VARIANTS + ([(1, 1)] if builder else []):
            opts = ([f"builder={builder}"] if builder else []) + \
                ([f"leaf_size={leaf}"] if leaf != 1 else []) + \
                ([f"cluster_size={cluster}"] if cluster != 1 else [])
            label = f"bvh[{','.join(opts)}]"
            rows += [dict(method=f"{label} update (rebuild)", kind="update",
                          backend=label, inputs="independent"),
                     dict(method=f"{label} query Dense", kind="query",
                          backend=label, inputs="independent")]
    rows += [dict(method="jax-md Dense update", kind="jax-md",
                  inputs="independent"),
             dict(method="jaxrt cell Dense update", kind="cell",
                  inputs="independent"),
             dict(method="warp HashGrid build", kind="hashgrid-build",
                  inputs="independent"),
             dict(method="warp HashGrid query Dense", kind="hashgrid-query",
                  inputs="independent")]
    return rows


def _bvh_options(label: str):
    """`jaxrt.backends.Bvh` of a row label (a plain ``bvh`` too: the Warp
    rows need its `search_structure`)."""
    import jaxrt
    return jaxrt.backends.Bvh(**_harness.parse_backend(label)[1])


# ---------------------------------------------------------------------------
# One row (in a worker)


def run_row(job: dict) -> dict:
    """Measure one row: ``job`` = a `plan_rows` entry plus scene, N,
    repeats, warmup and the scratch folder for counts."""
    import jax
    import numpy as np
    import warp as wp

    wp.config.quiet = True
    warp_device = "cuda:0" if jax.default_backend() == "gpu" else "cpu"
    if warp_device.startswith("cuda") and not wp.is_cuda_available():
        raise RuntimeError("JAX runs on a GPU but Warp sees no CUDA device; "
                           "the Warp rows would not be comparable.")
    scene, n = job["scene"], job["N"]
    sets, side, cutoff, periodic = make_scene(scene, n)
    if job["inputs"] == "jittered":
        sets = jittered(sets[0], cutoff, seed=2)
    row = {"N": n, "k": NOMINAL_K[scene], "cutoff": cutoff, "box": side}
    reps = dict(repeats=job["repeats"], warmup=job["warmup"])
    kind = job["kind"]
    if kind in ("jit", "jax-md", "cell"):
        timing, k, updates = _jax_row(job, kind, sets, side, cutoff,
                                      periodic, reps)
        row["bvh_updates"] = updates
        if k == k:  # a Dense list's own k (NaN: not Dense, keep the nominal)
            row["k"] = k
    else:
        timing, counts = _warp_row(job, kind, sets, side, cutoff, periodic,
                                   reps, warp_device)
        if counts is not None:
            row["k"] = float(np.mean(counts))
            tag = hashlib.sha1(job["method"].encode()).hexdigest()[:12]
            path = Path(job["_scratch"]) / f"{scene}_{n}_{tag}.npy"
            np.save(path, counts)
            row["counts_file"] = str(path)
    row.update(timing.columns())
    return row


def _jax_row(job, kind, sets, side, cutoff, periodic, reps):
    """Timing of a jitted ``update`` (jaxrt's bvh or cell, or jax-md's),
    the mean k of its allocate'd list and what the BVH did."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax_md import partition, space

    import jaxrt
    disp = (space.periodic(side) if periodic else space.free())[0]
    fmt = getattr(partition, job.get("format", "Dense"))
    if kind == "jax-md":
        fns = partition.neighbor_list(disp, side, cutoff, format=fmt)
    else:
        backend = _bvh_options(job["backend"]) if kind == "jit" else "cell"
        fns = jaxrt.neighbor_list(disp, side, cutoff, format=fmt,
                                  backend=backend)
    inputs = [jnp.asarray(x) for x in sets]
    nbrs = fns.allocate(inputs[0])
    n = inputs[0].shape[0]
    k = float("nan")
    if fmt is partition.Dense:
        k = float(np.mean(np.sum(np.asarray(nbrs.idx) < n, axis=1)))
    update = jax.jit(fns.update)
    updates = None
    if kind == "jit":
        from jaxrt.backends.rt import ffi
        before = ffi.update_counts.copy()
    timing = _harness.time_calls(lambda x: update(x, nbrs), inputs, **reps)
    if kind == "jit":
        done = ffi.update_counts - before
        updates = " ".join(f"{a}:{b}" for a, b in sorted(done.items()))
        if done[job["expect"]] < reps["repeats"]:
            print(f"note: expected {job['expect']}s, BVH did {dict(done)}",
                  file=sys.stderr)
    return timing, k, updates


def _warp_row(job, kind, sets, side, cutoff, periodic, reps, warp_device):
    """Timing of a Warp piece (BVH update, rebuild, query; HashGrid build,
    query) and, for queries, the counts on the first input set."""
    import warp as wp

    from jaxrt.backends.rt import aabb
    n = sets[0].shape[0]
    width = int(1.3 * NOMINAL_K[job["scene"]]) + 16
    warp_sets = [wp.array(x, dtype=wp.vec3, device=warp_device) for x in sets]
    side_array = wp.array([[side] * 3], dtype=wp.vec3, device=warp_device)
    axes = (periodic,) * 3
    rows = wp.empty((n, width), dtype=wp.int32, device=warp_device)
    count = wp.empty(n, dtype=wp.int32, device=warp_device)

    def sync(_=None):
        wp.synchronize_device(warp_device)

    def self_timed(part, before):
        """``run(x)``: ``before(x)`` untimed, then ``part()`` timed (ms)."""
        def run(x):
            before(x)
            sync()
            start = time.perf_counter()
            part()
            sync()
            return (time.perf_counter() - start) * 1e3
        return run

    if kind.startswith("hashgrid"):
        if __package__:
            from benchmarks import _warp_hashgrid
        else:  # run as a file
            import _warp_hashgrid
        _warp_hashgrid.load(warp_device)
        dim = 128 if n > 10_000 else 32
        grid = wp.HashGrid(dim, dim, dim, device=warp_device)
        if kind == "hashgrid-build":
            return _harness.time_calls(lambda x: grid.build(x, cutoff),
                                       warp_sets, sync=sync, **reps), None
        flags = wp.vec3i(*(int(p) for p in axes))
        current = []

        def query():
            wp.launch(_warp_hashgrid.hash_grid_dense, n, device=warp_device,
                      inputs=[wp.uint64(grid.id), current[-1], side_array,
                              flags, float(cutoff), rows, count])

        def build(x):
            current.append(x)
            grid.build(x, cutoff)
        timing = _harness.time_self_timed(self_timed(query, build),
                                          warp_sets, **reps)
        build(warp_sets[0])
        query()
        sync()
        return timing, count.numpy()

    aabb.load(warp_device)
    tree = _bvh_options(job["backend"]).search_structure(n, wp.vec3,
                                                         warp_device)

    def update(x):
        tree.update(x, side_array, axes, cutoff)
    if kind == "update":
        if job["inputs"] == "jittered":
            update(warp_sets[0])  # built once: the timed calls refit
        return _harness.time_calls(update, warp_sets, sync=sync, **reps), None
    if kind == "bvh-rebuild":
        update(warp_sets[0])
        return _harness.time_calls(lambda x: tree.bvh.rebuild(tree.constructor),
                                   warp_sets, sync=sync, **reps), None

    def query():
        tree.query_dense(side_array, mask_self=True, rows=rows, count=count)
    timing = _harness.time_self_timed(self_timed(query, update), warp_sets,
                                      **reps)
    update(warp_sets[0])
    query()
    sync()
    return timing, count.numpy()


def compare_counts(rows: list[dict]) -> None:
    """``counts_differ``: particles whose count differs from "bvh query
    Dense"'s on the same scene and N (a tie at the cutoff, or a bug)."""
    import numpy as np
    for r in rows:
        ref = next((x for x in rows if x["scene"] == r["scene"]
                    and x["N"] == r["N"] and x["method"] == "bvh query Dense"
                    and x.get("counts_file")), None)
        if r.get("counts_file") and ref is not None:
            got, want = np.load(r["counts_file"]), np.load(ref["counts_file"])
            r["counts_differ"] = int(np.sum(got != want))
    for r in rows:
        r.pop("counts_file", None)


COLUMNS = ["scene", "N", "k", "method", "median_ms", "min_ms", "max_ms",
           "repeats", "bvh_updates", "counts_differ"]


def main(argv=None) -> None:
    parser = _harness.make_parser(__doc__)
    parser.add_argument("--quick", "--small", dest="quick", action="store_true",
                        help="N = 2000 only, 3 repeats (CPU smoke run)")
    parser.add_argument("--sizes", type=int, nargs="+",
                        help="particle counts (default 1e5 1e6, or 2000 with --quick)")
    parser.add_argument("--scenes", nargs="+", default=["uniform", "sphere"],
                        choices=["uniform", "sphere"])
    parser.add_argument("--jit-clusters", type=int, nargs="*", default=[8, 16],
                        help="cluster sizes to time through jax.jit besides "
                             "the default of 1 (the seed's box per particle)")
    parser.add_argument("--builders", nargs="*", default=[],
                        help="other Warp BVH builders to sweep (e.g. cubql)")
    parser.add_argument("--only", nargs="+", default=None, metavar="LABEL",
                        help="run only these rows (labels: --list)")
    parser.add_argument("--list", action="store_true",
                        help="print the row labels and exit")
    _harness.add_common_args(parser, name="rt_neighbors.csv", repeats=10,
                             warmup=3, timeout=300)
    args = parser.parse_args(argv)
    rows = plan_rows(args.jit_clusters, args.builders)
    if args.list:
        print("\n".join(r["method"] for r in rows))
        return
    if args.only:
        unknown = set(args.only) - {r["method"] for r in rows}
        if unknown:
            parser.error(f"--only: unknown rows {sorted(unknown)} (see --list)")
        rows = [r for r in rows if r["method"] in args.only]
    if args.quick:
        args.repeats = min(args.repeats, 3)
    sizes = args.sizes or ([2000] if args.quick else [100_000, 1_000_000])
    scratch = tempfile.mkdtemp(prefix="rt_neighbors-")
    jobs = [{"scene": s, "N": n, **r, "repeats": args.repeats,
             "warmup": args.warmup, "_scratch": scratch}
            for s in args.scenes for n in sizes for r in rows]
    try:
        _harness.run_jobs("rt_neighbors:run_row", jobs, columns=COLUMNS,
                          finish=compare_counts, **_harness.run_options(args))
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


if __name__ == "__main__":
    main()
