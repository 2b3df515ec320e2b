"""Benchmark: the ray-traced backend "bvh" against jax-md and Warp's HashGrid.

Scenes (seed 001 §5, DESIGN.md "Measured anchors"):
  uniform  N particles uniform in a periodic cube of side N^(1/3) (rho = 1),
           cutoff 2.5 (k ~ 65 neighbours);
  sphere   N points uniform on the unit sphere's surface, free space, cutoff
           12 / sqrt(N) (k ~ 36).

Rows (float32, Dense unless named; median of --repeats timed calls after
warm-up, rotating between 3 input sets so no call repeats the previous one):
  bvh jit Dense (rebuild)       jaxrt.neighbor_list(backend="bvh").update
                                under jax.jit, unrelated inputs: every call
                                rebuilds the BVH
  bvh jit Dense (refit)         the same on inputs jittered by 1 % of the
                                cutoff: the kept BVH is refit
  bvh jit Dense (always rebuild)
                                a BVH policy that never refits, so it never
                                reads the drift back to the host
  bvh jit OrderedSparse         count, scan, fill path
  bvh jit Dense (rebuild) cluster g
                                the same with one BVH box per g sorted
                                particles (--jit-clusters)
  bvh update (rebuild) / (refit), bvh lbvh rebuild only, bvh query Dense,
  bvh-unsorted ...              the Warp pieces timed directly (synchronised)
  bvh <builder> leaf <l> cluster <g> ...
                                the same pieces with another BVH builder,
                                leaf size or cluster size
  jax-md Dense update           jax_md.partition.neighbor_list(...).update
  jaxrt cell Dense update       the pure-JAX backend
  warp HashGrid build / query Dense
                                wp.HashGrid and a hand-written query kernel
                                writing the same Dense rows (periodic images
                                by the same gamma rays as "bvh")

Usage:
  python benchmarks/rt_neighbors.py            # N = 1e5 and 1e6 (GPU)
  python benchmarks/rt_neighbors.py --small    # N = 2000 (CPU smoke run)
Writes a table to stdout and CSV to $OUT/rt_neighbors.csv if $OUT is set,
else benchmarks/results/<device>/rt_neighbors.csv.
"""
import os

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import argparse  # noqa: E402
import csv  # noqa: E402
import importlib.metadata  # noqa: E402
import math  # noqa: E402
import re  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402
from pathlib import Path  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import warp as wp  # noqa: E402
from jax_md import partition, space  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import jaxrt  # noqa: E402
from jaxrt.rt import aabb, ffi  # noqa: E402
from jaxrt.rt import periodic as gamma  # noqa: E402

INPUT_SETS = 3


# ---------------------------------------------------------------------------
# Scenes


def uniform_scene(n, rng):
    """Uniform, rho = 1, periodic. Returns 3 float32 (n, 3) sets, side, cutoff."""
    side = n ** (1.0 / 3.0)
    sets = [(rng.random((n, 3)) * side).astype(np.float32) for _ in range(INPUT_SETS)]
    return sets, side, 2.5, True


def sphere_scene(n, rng):
    """Unit sphere surface centred in a free box of side 3 (jax-md's cell grid)."""
    cutoff = 12.0 / math.sqrt(n)
    sets = []
    for _ in range(INPUT_SETS):
        v = rng.normal(size=(n, 3))
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        sets.append((v + 1.5).astype(np.float32))
    return sets, 3.0, cutoff, False


def jittered(points, cutoff, rng):
    """3 sets within 1 % of the cutoff of ``points`` (a refit's worth of motion)."""
    return [(points + rng.normal(scale=0.01 * cutoff, size=points.shape)
             ).astype(np.float32) for _ in range(INPUT_SETS)]


# ---------------------------------------------------------------------------
# Timing


def time_calls(call, inputs, repeats, sync):
    """Median ms of ``call(inputs[k % 3])`` over ``repeats`` calls, after one
    warm-up call per input set."""
    for x in inputs:
        sync(call(x))
    times = []
    for r in range(repeats):
        x = inputs[r % len(inputs)]
        start = time.perf_counter()
        sync(call(x))
        times.append((time.perf_counter() - start) * 1e3)
    return float(np.median(times))


def jax_sync(out):
    jax.block_until_ready(out)


# ---------------------------------------------------------------------------
# Warp HashGrid baseline (same Dense rows as "bvh")


@wp.kernel
def hash_grid_dense(grid: wp.uint64, points: wp.array(dtype=wp.vec3),
                    side: wp.array(dtype=wp.vec3), periodic: wp.vec3i,
                    cutoff: wp.float32, rows: wp.array2d(dtype=wp.int32),
                    count: wp.array(dtype=wp.int32)):
    """rows[i] = neighbours of i (d² < cutoff², minimum image), padded N."""
    tid = wp.tid()
    i = wp.hash_grid_point_id(grid, tid)
    xi = points[i]
    box = side[0]
    width = rows.shape[1]
    n = int(0)
    for ray in range(gamma.RAYS_PER_PARTICLE):
        shift = gamma.ray_shift(ray)
        if gamma.ray_is_cast(shift, xi, box, periodic, cutoff):
            origin = gamma.shifted(xi, shift, box)
            query = wp.hash_grid_query(grid, origin, cutoff)
            j = int(0)
            while wp.hash_grid_query_next(query, j):
                xj = points[j]
                if j != i and gamma.is_canonical_image(shift, xi, xj, box, periodic):
                    d = origin - xj
                    if wp.dot(d, d) < cutoff * cutoff:
                        if n < width:
                            rows[i, n] = j
                        n += 1
    count[i] = n
    for s in range(wp.min(n, width), width):
        rows[i, s] = points.shape[0]


# ---------------------------------------------------------------------------
# Provenance


def device_name():
    dev = jax.devices()[0]
    return dev.device_kind if dev.platform != "cpu" else "cpu"


def git_sha():
    if os.environ.get("GIT_SHA"):
        return os.environ["GIT_SHA"]
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True, check=True,
                              cwd=Path(__file__).parent).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def provenance():
    return {"device": device_name(), "jax": jax.__version__,
            "jax_md": importlib.metadata.version("jax-md"),
            "warp": wp.__version__, "git_sha": git_sha()}


# ---------------------------------------------------------------------------
# One scene at one size


def bench_scene(scene, n, repeats, rng, warp_device, jit_clusters=()):
    sets, side, cutoff, periodic = {"uniform": uniform_scene,
                                    "sphere": sphere_scene}[scene](n, rng)
    disp = (space.periodic(side) if periodic else space.free())[0]
    rows = []
    k_mean = [float("nan")]

    def record(method, run):
        try:
            ms = run()
        except Exception:  # noqa: BLE001 - the row is printed as failed
            print(f"  {scene} N={n} {method}: FAILED", file=sys.stderr)
            traceback.print_exc()
            ms = float("nan")
        rows.append({"scene": scene, "N": n, "cutoff": cutoff,
                     "method": method, "median_ms": ms, "repeats": repeats})
        print(f"  {scene:8s} N={n:<8d} {method:32s} {ms:10.3f} ms", flush=True)

    device_sets = [jnp.asarray(x) for x in sets]
    refit_sets = [jnp.asarray(x) for x in jittered(sets[0], cutoff, rng)]

    # jaxrt "bvh" through the jax-md interface (dr_threshold 0: every call
    # searches).
    def bvh_jit(fmt, inputs, expect, backend="bvh"):
        def run():
            fns = jaxrt.neighbor_list(disp, side, cutoff, format=fmt,
                                      backend=backend)
            nbrs = fns.allocate(inputs[0])
            if fmt is partition.Dense:
                counts = np.sum(np.asarray(nbrs.idx) < n, axis=1)
                k_mean[0] = float(counts.mean())
            update = jax.jit(fns.update)
            before = ffi.update_counts.copy()
            ms = time_calls(lambda x: update(x, nbrs), inputs, repeats, jax_sync)
            done = ffi.update_counts - before
            if done[expect] < repeats:
                print(f"    note: expected {expect}s, BVH did {dict(done)}",
                      file=sys.stderr)
            return ms
        return run

    record("bvh jit Dense (rebuild)", bvh_jit(partition.Dense, device_sets, "rebuild"))
    # The same call with one BVH box per run of g sorted particles.
    for g in jit_clusters:
        name = f"bvh-cluster{g}"
        if name not in jaxrt.available_backends():
            jaxrt.backends.register(name, lambda g=g, name=name: ffi.AabbBackend(
                name, sort=True, cluster_size=g))
        record(f"bvh jit Dense (rebuild) cluster {g}",
               bvh_jit(partition.Dense, device_sets, "rebuild", backend=name))
    record("bvh jit Dense (refit)", bvh_jit(partition.Dense, refit_sets, "refit"))
    # Rebuilding on every call needs no drift read-back (no host stall).
    record("bvh jit Dense (always rebuild)",
           bvh_jit(partition.Dense, device_sets, "rebuild",
                   backend="bvh-always-rebuild"))
    record("bvh jit OrderedSparse (rebuild)",
           bvh_jit(partition.OrderedSparse, device_sets, "rebuild"))

    # The Warp pieces directly.
    width = int(1.3 * (64 if math.isnan(k_mean[0]) else k_mean[0])) + 16
    warp_sets = [wp.array(x, dtype=wp.vec3, device=warp_device) for x in sets]
    warp_refit = [wp.array(np.asarray(x), dtype=wp.vec3, device=warp_device)
                  for x in refit_sets]
    side_array = wp.array([[side] * 3], dtype=wp.vec3, device=warp_device)
    axes = (periodic,) * 3

    def warp_sync(_):
        wp.synchronize_device(warp_device)

    def timed_query(tree, out_rows, out_count):
        """``run()`` for `record`: the median query time of ``tree``, each
        call after an (untimed) update to the next input set."""
        def query(x):
            tree.update(x, side_array, axes, cutoff)
            wp.synchronize_device(warp_device)
            start = time.perf_counter()
            tree.query_dense(side_array, mask_self=True, rows=out_rows,
                             count=out_count)
            wp.synchronize_device(warp_device)
            return (time.perf_counter() - start) * 1e3
        return lambda: median_of_self_timed(query, warp_sets, repeats)

    for name, sort in (("bvh", True), ("bvh-unsorted", False)):
        tree = aabb.AabbSearch(n, wp.vec3, warp_device, sort=sort)
        out_rows = wp.empty((n, width), dtype=wp.int32, device=warp_device)
        out_count = wp.empty(n, dtype=wp.int32, device=warp_device)
        record(f"{name} update (rebuild)", lambda: time_calls(
            lambda x: tree.update(x, side_array, axes, cutoff), warp_sets,
            repeats, warp_sync))
        if sort:
            record(f"{name} lbvh rebuild only", lambda: time_calls(
                lambda x: tree.bvh.rebuild(tree.constructor), warp_sets,
                repeats, warp_sync))
            tree.update(warp_refit[0], side_array, axes, cutoff)
            record(f"{name} update (refit)", lambda: time_calls(
                lambda x: tree.update(x, side_array, axes, cutoff), warp_refit,
                repeats, warp_sync))

        record(f"{name} query Dense", timed_query(tree, out_rows, out_count))
        if sort:
            bvh_count = out_count.numpy()

    # The BVH's builder and leaf size change only the speed: sweep them.
    cuda = str(warp_device).startswith("cuda")
    variants = ([("lbvh", 4, 1), ("lbvh", 1, 4), ("lbvh", 1, 8),
                 ("lbvh", 1, 16), ("lbvh", 1, 32), ("lbvh", 4, 16)]
                if cuda else [("sah", 4, 1), ("sah", 1, 8)])
    for constructor, leaf, cluster in variants:
        try:
            tree = aabb.AabbSearch(n, wp.vec3, warp_device, sort=True,
                                   constructor=constructor, leaf_size=leaf,
                                   cluster_size=cluster)
        except Exception as e:  # noqa: BLE001 - builder absent on this device
            print(f"  {constructor} leaf {leaf} cluster {cluster}: not "
                  f"available ({e})")
            continue
        out_rows = wp.empty((n, width), dtype=wp.int32, device=warp_device)
        out_count = wp.empty(n, dtype=wp.int32, device=warp_device)
        label = f"bvh {constructor} leaf {leaf} cluster {cluster}"
        record(f"{label} update (rebuild)", lambda: time_calls(
            lambda x: tree.update(x, side_array, axes, cutoff), warp_sets,
            repeats, warp_sync))

        record(f"{label} query Dense", timed_query(tree, out_rows, out_count))
        if not np.array_equal(out_count.numpy(), bvh_count):
            print(f"  WARNING: {label} counts differ from the default BVH's",
                  file=sys.stderr)
        del tree, out_rows, out_count

    # Baselines.
    def jax_md_update():
        fns = partition.neighbor_list(disp, side, cutoff, format=partition.Dense)
        nbrs = fns.allocate(device_sets[0])
        update = jax.jit(fns.update)
        return time_calls(lambda x: update(x, nbrs), device_sets, repeats, jax_sync)

    record("jax-md Dense update", jax_md_update)

    def cell_update():
        fns = jaxrt.neighbor_list(disp, side, cutoff, format=partition.Dense,
                                  backend="cell")
        nbrs = fns.allocate(device_sets[0])
        update = jax.jit(fns.update)
        return time_calls(lambda x: update(x, nbrs), device_sets, repeats, jax_sync)

    record("jaxrt cell Dense update", cell_update)

    grid_dim = 128 if n > 10_000 else 32
    grid = wp.HashGrid(grid_dim, grid_dim, grid_dim, device=warp_device)
    grid_rows = wp.empty((n, width), dtype=wp.int32, device=warp_device)
    grid_count = wp.empty(n, dtype=wp.int32, device=warp_device)
    flags = wp.vec3i(*(int(p) for p in axes))

    record("warp HashGrid build", lambda: time_calls(
        lambda x: grid.build(x, cutoff), warp_sets, repeats, warp_sync))

    def grid_query(x):
        grid.build(x, cutoff)
        wp.synchronize_device(warp_device)
        start = time.perf_counter()
        wp.launch(hash_grid_dense, n, device=warp_device,
                  inputs=[wp.uint64(grid.id), x, side_array, flags,
                          float(cutoff), grid_rows, grid_count])
        wp.synchronize_device(warp_device)
        return (time.perf_counter() - start) * 1e3

    record("warp HashGrid query Dense", lambda: median_of_self_timed(
        grid_query, warp_sets, repeats))

    # Both Warp queries ran last on warp_sets[(repeats - 1) % 3].
    mismatch = int(np.sum(grid_count.numpy() != bvh_count))
    if mismatch:
        print(f"  WARNING: {scene} N={n}: HashGrid and bvh counts differ for "
              f"{mismatch} particles (ties at the cutoff, or a bug)",
              file=sys.stderr)
    for row in rows:
        row["k"] = k_mean[0]
    return rows


def median_of_self_timed(run, inputs, repeats):
    """Median of ``run(x)``'s own timing (ms), after a warm-up per input."""
    for x in inputs:
        run(x)
    return float(np.median([run(inputs[r % len(inputs)]) for r in range(repeats)]))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--small", action="store_true",
                        help="N = 2000 only (CPU smoke run)")
    parser.add_argument("--sizes", type=int, nargs="+",
                        help="particle counts (default 1e5 1e6, or 2000 with --small)")
    parser.add_argument("--scenes", nargs="+", default=["uniform", "sphere"],
                        choices=["uniform", "sphere"])
    parser.add_argument("--repeats", type=int, default=10,
                        help="timed calls per row (>= 10 for reported numbers)")
    parser.add_argument("--jit-clusters", type=int, nargs="*", default=[8, 16],
                        help="cluster sizes to time through jax.jit besides "
                             "the default of 1 (the seed's box per particle)")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be >= 1")
    sizes = args.sizes or ([2000] if args.small else [100_000, 1_000_000])

    wp.config.quiet = True
    warp_device = "cuda:0" if jax.default_backend() == "gpu" else "cpu"
    if warp_device.startswith("cuda") and not wp.is_cuda_available():
        sys.exit("JAX runs on a GPU but Warp sees no CUDA device; the Warp "
                 "rows would not be comparable.")
    aabb.load(warp_device)
    jaxrt.backends.register("bvh-always-rebuild", lambda: ffi.AabbBackend(
        "bvh-always-rebuild", sort=True, policy=aabb.RebuildPolicy(0.0)))
    wp.load_module(module=__name__, device=warp_device)
    meta = provenance()
    print(f"device {meta['device']}  jax {meta['jax']}  jax-md {meta['jax_md']}"
          f"  warp {meta['warp']}  git {meta['git_sha']}  warp device {warp_device}")

    rng = np.random.default_rng(0)
    rows = []
    for scene in args.scenes:
        for n in sizes:
            rows += bench_scene(scene, n, args.repeats, rng, warp_device,
                                args.jit_clusters)
            ffi.forget_trees()  # free the previous size's BVHs

    print(f"\n{'scene':8s} {'N':>8s} {'k':>6s}  {'method':32s} {'median ms':>10s}")
    for r in rows:
        print(f"{r['scene']:8s} {r['N']:8d} {r['k']:6.1f}  {r['method']:32s} "
              f"{r['median_ms']:10.3f}")

    out_dir = os.environ.get("OUT")
    if out_dir:
        path = Path(out_dir) / "rt_neighbors.csv"
    else:
        folder = re.sub(r"[^A-Za-z0-9._-]+", "_", meta["device"]).strip("_")
        path = Path(__file__).parent / "results" / folder / "rt_neighbors.csv"
    path.parent.mkdir(parents=True, exist_ok=True)
    fields = ["scene", "N", "k", "cutoff", "method", "median_ms", "repeats",
              "device", "jax", "jax_md", "warp", "git_sha"]
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        for r in rows:
            writer.writerow({**r, **meta})
    print(f"\nwrote {path}")


if __name__ == "__main__":
    main()
