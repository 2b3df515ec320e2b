"""Neighbour-list rebuild time and memory: jaxrt backends against jax-md.

Scenes (the project's measured anchors; seed 001 §5.3 for the sphere):
  uniform   random particles in a periodic cube, density 1, rc = 2.5
  sphere    N points on a unit sphere surface, free space, cutoff C for
            ~30 neighbours (C = sqrt(4·30 / N)); as in seed 001, the points
            are shifted by 1 + C into the box that just holds them, of side
            2 + 2C, and every method (jax-md included) gets that box.

Each row runs in its own worker process (`_harness`), so peak RSS is that
row's alone and a row that runs out of memory or time is written as such.
Times are the jitted ``update`` (dr_threshold = 0: every call searches
again), warm-up excluded, median / min / max of the repeats over three
rotating input sets (the scene and two copies jittered by 1e-3).
``allocate_s`` is the first (cold) ``allocate``; ``reallocate_ms`` the
median of three more on new structures of the same scene and N (seeds
1-3), compiles included: what each structure of a training set costs.
``xla_temp_mb`` is XLA's temp-buffer size for the compiled update;
``peak_mb`` is the device's peak bytes in use (GPU) or the process's peak
RSS (CPU); ``peak_above_baseline_mb`` (CPU) is that peak minus the peak
reached after imports and input creation, before any list is built. For the
ray-traced backends ``bvh_updates`` counts what the kept BVH did during the
timed calls (`jaxrt.backends.rt.ffi.update_counts`: build / rebuild / refit).

Methods are backend labels (`_harness.parse_backend`): ``cell``,
``cell[xla]`` (the portable array programs), ``cell[pallas]`` (the GPU
kernel, `jaxrt.backends.cell.kernel`), ``cell[interpret]`` (that kernel in Pallas'
interpreter), ``cell[warp]`` (the Warp walk, `jaxrt.backends.cell.warp_rows`;
CPU or CUDA), ``bvh``, ``bvh[unsorted]``, ... passed as
``backend=jaxrt.backends.Cell(kernel="xla")`` etc.; ``jax-md`` is
``jax_md.partition.neighbor_list``. Rows of ``cell`` that run a kernel
(on a GPU, ``cell[interpret]`` or ``cell[warp]``) say whether their list
equals the ``cell[xla]`` list (``same_as_xla``: sorted rows compared entry
by entry).

    python benchmarks/neighbors.py                 # CPU sizes
    python benchmarks/neighbors.py --sizes 1000000 --sphere-n 1000000 \\
        --backends "cell[pallas]" "cell[xla]" bvh  # the H200 rows
    python benchmarks/neighbors.py --sizes 1000000 --scenes uniform \\
        --backends "cell[warp]" "cell[pallas]"     # Warp walk vs Pallas
    python benchmarks/neighbors.py --quick         # CPU smoke, N = 2000
"""
from __future__ import annotations

import importlib
import os
import resource
import sys
import time

if __package__:  # run as -m, or imported: the package's modules
    from benchmarks import _harness
else:  # run as a file: its folder is sys.path[0]
    import _harness

SPHERE_K = 30


def scene(name: str, n: int, seed: int):
    """float32 positions (N, 3), box side, cutoff, periodic."""
    import numpy as np
    rng = np.random.default_rng(seed)
    if name == "uniform":
        side = n ** (1 / 3)
        return rng.uniform(0, side, (n, 3)).astype(np.float32), side, 2.5, True
    # sphere surface: k = N * pi C^2 / (4 pi)  =>  C = sqrt(4 k / N)
    cutoff = float(np.sqrt(4 * SPHERE_K / n))
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return (v + 1.0 + cutoff).astype(np.float32), 2.0 + 2.0 * cutoff, cutoff, False


def _rss_mb() -> float:
    """Peak resident set size of this process so far (Linux: KiB -> MiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _list_fns(method: str, disp, side: float, cutoff: float):
    from jax_md import partition
    if method == "jax-md":
        return partition.neighbor_list(disp, side, cutoff)
    import jaxrt
    return jaxrt.neighbor_list(disp, side, cutoff,
                               backend=_harness.backend(method))


def run_row(job: dict) -> dict:
    """One (scene, method, N) row, in a worker."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax_md import space

    method, scene_name, n = job["method"], job["scene"], job["N"]
    R, side, cutoff, periodic = scene(scene_name, n, 0)
    disp, _ = space.periodic(side) if periodic else space.free()
    name, opts = _harness.parse_backend(method)
    if method != "jax-md":  # before the baseline: its imports are not the list's
        importlib.import_module("jaxrt")
    jitter = np.random.default_rng(1)
    inputs = []
    for _ in range(3):
        moved = R + jitter.normal(0, 1e-3, R.shape).astype(np.float32)
        moved = (np.mod(moved, side) if periodic else
                 np.clip(moved, 0, np.nextafter(np.float32(side), 0)))
        inputs.append(jnp.asarray(moved.astype(np.float32)))
    first = jnp.asarray(R)
    jax.block_until_ready((first, inputs))
    baseline_mb = _rss_mb()
    fns = _list_fns(method, disp, side, cutoff)
    t = time.perf_counter()
    nbrs = fns.allocate(first)
    jax.block_until_ready(nbrs.idx)
    allocate_s = time.perf_counter() - t
    idx = np.asarray(nbrs.idx)
    k = float(np.mean(np.sum(idx < n, axis=1)))
    update = jax.jit(fns.update)
    try:
        temp = update.lower(inputs[0], nbrs).compile().memory_analysis()
        temp_mb = temp.temp_size_in_bytes / 2**20
    except Exception:  # noqa: BLE001 - not every backend reports it
        temp_mb = float("nan")
    counts = None
    if name.startswith("bvh"):
        from jaxrt.backends.rt import ffi
        before = ffi.update_counts.copy()
    timing = _harness.time_calls(lambda x: update(x, nbrs).idx, inputs,
                                 repeats=job["repeats"], warmup=job["warmup"])
    if name.startswith("bvh"):
        counts = dict(ffi.update_counts - before)
    last = update(inputs[0], nbrs)  # untimed: overflow, same_as_xla
    overflow = bool(last.did_buffer_overflow)
    dev = jax.devices()[0]
    if dev.platform == "cpu":
        peak_mb = _rss_mb()
        # the process's peak minus its peak before any list was built
        # (Python, JAX, imports, inputs): what building and updating cost.
        above_mb = peak_mb - baseline_mb
    else:
        peak_mb = dev.memory_stats().get("peak_bytes_in_use", 0) / 2**20
        above_mb = float("nan")
    # allocate on new structures of the same scene and N (a training set's
    # next ones): each measures its own sizes, which differ a little; what
    # it compiles for them is reused (`jaxrt.lists.neighbors._compiled_capacity`)
    # or not (jax-md runs allocate op by op).
    reallocate_ms = []
    for seed in (1, 2, 3):
        other = jnp.asarray(scene(scene_name, n, seed)[0])
        t = time.perf_counter()
        jax.block_until_ready(fns.allocate(other).idx)
        reallocate_ms.append((time.perf_counter() - t) * 1e3)
        del other
    same_as_xla = None
    kernel = opts.get("kernel", "auto")
    if name == "cell" and kernel != "xla" and (
            dev.platform != "cpu" or kernel in ("interpret", "warp")):
        got = np.sort(np.asarray(last.idx), axis=1)
        portable = _list_fns("cell[xla]", disp, side, cutoff)
        want = np.asarray(jax.jit(portable.update)(inputs[0], nbrs).idx)
        same_as_xla = bool(np.array_equal(got, np.sort(want, axis=1)))
    return {"N": n, "k": round(k, 1), "cutoff": cutoff, "box": side,
            "capacity": int(idx.shape[-1]), "allocate_s": allocate_s,
            "reallocate_ms": float(np.median(reallocate_ms)),
            "reallocate_max_ms": max(reallocate_ms),
            "update_ms": timing.median_ms, **timing.columns(),
            "xla_temp_mb": temp_mb, "peak_mb": peak_mb,
            "peak_above_baseline_mb": above_mb, "overflow": overflow,
            "same_as_xla": same_as_xla,
            "bvh_updates": " ".join(f"{k}:{v}" for k, v in sorted(counts.items()))
            if counts is not None else None}


def add_ratios(rows: list[dict]) -> None:
    """Speed-up and XLA temp ratio of every row over jax-md's, same scene
    and N."""
    for r in rows:
        ref = next((x for x in rows if x["scene"] == r["scene"]
                    and x["N"] == r["N"] and x["method"] == "jax-md"
                    and x["status"] == "ok"), None)
        if ref is None or r is ref or r["status"] != "ok":
            continue
        r["speedup"] = ref["update_ms"] / r["update_ms"]
        r["temp_ratio"] = ref["xla_temp_mb"] / max(r["xla_temp_mb"], 1e-9)


COLUMNS = ["scene", "method", "N", "k", "update_ms", "min_ms", "max_ms",
           "speedup", "xla_temp_mb", "temp_ratio", "peak_mb",
           "peak_above_baseline_mb", "allocate_s", "reallocate_ms",
           "same_as_xla"]


def main(argv=None) -> None:
    parser = _harness.make_parser(__doc__)
    parser.add_argument("--sizes", type=int, nargs="+",
                        default=[1_000, 10_000, 100_000],
                        help="N of the uniform scene")
    parser.add_argument("--sphere-n", type=int, default=10_000)
    parser.add_argument("--scenes", nargs="+", default=["uniform", "sphere"],
                        choices=["uniform", "sphere"])
    parser.add_argument("--backends", nargs="+", default=["cell"],
                        help="backend labels: cell, cell[xla], cell[pallas], "
                        "cell[warp], bvh, bvh[unsorted], ...")
    parser.add_argument("--no-jax-md", action="store_true")
    parser.add_argument("--quick", action="store_true",
                        help="CPU smoke: N = 2000, cell and jax-md, 3 repeats")
    _harness.add_common_args(parser, name="neighbors.csv", repeats=10,
                             warmup=3, timeout=600)
    args = parser.parse_args(argv)
    if args.quick:
        args.sizes, args.sphere_n, args.repeats = [2000], 2000, 3
    for label in args.backends:
        _harness.parse_backend(label)  # a typo fails here, not in a worker
    methods = args.backends + ([] if args.no_jax_md else ["jax-md"])
    plan = [("uniform", n) for n in args.sizes if "uniform" in args.scenes]
    plan += [("sphere", args.sphere_n)] if "sphere" in args.scenes else []
    jobs = [{"scene": s, "method": m, "N": n, "repeats": args.repeats,
             "warmup": args.warmup} for s, n in plan for m in methods]
    _harness.run_jobs("neighbors:run_row", jobs, columns=COLUMNS,
                      finish=add_ratios, **_harness.run_options(args))


if __name__ == "__main__":
    main()
