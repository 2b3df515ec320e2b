"""Neighbour-list rebuild time and memory: jaxrt backends against jax-md.

Scenes (DESIGN.md, issue 2):
  uniform   random particles in a periodic cube, density 1, rc = 2.5
  sphere    points on a unit sphere surface with ~30 neighbours, free space;
            jax-md gets a box of side 30 (it needs one), jaxrt none.

Each row runs in its own subprocess, so peak RSS is that row's alone. Times
are the jitted ``update`` (dr_threshold = 0: every call rebuilds), warm,
median of repeats over three rotating input sets. ``xla_temp_mb`` is XLA's
own temp-buffer size for the compiled update; ``peak_mb`` is the device's
peak bytes in use (GPU) or the process's peak RSS (CPU);
``peak_above_baseline_mb`` (CPU) is that peak minus the peak reached after
imports and input creation, before any list is built.

    python benchmarks/neighbors.py                 # CPU sizes
    python benchmarks/neighbors.py --sizes 100000 1000000 --backends cell bvh

A method ``cell:xla`` is the backend ``cell`` with its candidate pass forced
to the portable array programs (on a GPU, ``cell`` runs `_cell_kernel`);
rows of ``cell`` then say whether its list equals that path's
(``same_as_xla``: sorted rows compared entry by entry).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")


def scene(name: str, n: int, seed: int):
    import numpy as np
    rng = np.random.default_rng(seed)
    if name == "uniform":
        side = n ** (1 / 3)
        return rng.uniform(0, side, (n, 3)).astype(np.float32), side, 2.5, True
    # sphere surface: k = N * pi r^2 / (4 pi)  =>  r = sqrt(4 k / N)
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return (v + 15.0).astype(np.float32), 30.0, float(np.sqrt(4 * 30 / n)), False


def _rss_mb() -> float:
    """Peak resident set size of this process so far (Linux: KiB -> MiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def one_row(method: str, scene_name: str, n: int, repeats: int) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax_md import partition, space

    sys.path.insert(0, os.path.dirname(__file__))
    from _provenance import median_ms

    R, side, cutoff, periodic = scene(scene_name, n, 0)
    disp, _ = space.periodic(side) if periodic else space.free()
    backend, _, kernel = method.partition(":")
    if method != "jax-md":
        import jaxrt  # noqa: F401  (before the baseline: its imports are not the list's)
        if kernel:
            jaxrt.backends.get(backend).kernel = kernel
    jitter = np.random.default_rng(1)
    inputs = []
    for _ in range(3):
        moved = R + jitter.normal(0, 1e-3, R.shape).astype(np.float32)
        if periodic:
            moved = np.mod(moved, side).astype(np.float32)
        inputs.append(jnp.asarray(moved))
    first = jnp.asarray(R)
    jax.block_until_ready((first, inputs))
    baseline_mb = _rss_mb()
    if method == "jax-md":
        fns = partition.neighbor_list(disp, side, cutoff)
    else:
        fns = jaxrt.neighbor_list(disp, side if periodic else None, cutoff,
                                  backend=backend)
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
    ms = median_ms(lambda x: update(x, nbrs).idx, inputs, repeats)
    overflow = bool(update(inputs[0], nbrs).did_buffer_overflow)
    dev = jax.devices()[0]
    same_as_xla = None
    if dev.platform == "cpu":
        peak_mb = _rss_mb()
        # the process's peak minus its peak before any list was built
        # (Python, JAX, imports, inputs): what building and updating cost.
        above_mb = peak_mb - baseline_mb
    else:
        peak_mb = dev.memory_stats().get("peak_bytes_in_use", 0) / 2**20
        above_mb = float("nan")
    if method == "cell" and dev.platform != "cpu":
        got = np.sort(np.asarray(update(inputs[0], nbrs).idx), axis=1)
        # A new list: each traces its search once, with the kernel then set.
        jaxrt.backends.get("cell").kernel = "xla"
        portable = jaxrt.neighbor_list(disp, side if periodic else None,
                                       cutoff, backend="cell")
        want = np.asarray(jax.jit(portable.update)(inputs[0], nbrs).idx)
        same_as_xla = bool(np.array_equal(got, np.sort(want, axis=1)))
        jaxrt.backends.get("cell").kernel = "auto"
    return {"scene": scene_name, "method": method, "N": n, "k": round(k, 1),
            "capacity": int(idx.shape[-1]), "allocate_s": allocate_s,
            "update_ms": ms, "repeats": repeats, "xla_temp_mb": temp_mb,
            "peak_mb": peak_mb, "peak_above_baseline_mb": above_mb,
            "overflow": overflow, "same_as_xla": same_as_xla}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+",
                        default=[1_000, 10_000, 100_000])
    parser.add_argument("--sphere-n", type=int, default=10_000)
    parser.add_argument("--backends", nargs="+", default=["cell"])
    parser.add_argument("--no-jax-md", action="store_true")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--timeout", type=int, default=600)
    parser.add_argument("--out", default=None)
    parser.add_argument("--one", nargs=3, metavar=("METHOD", "SCENE", "N"),
                        help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.one:
        method, scene_name, n = args.one
        print(json.dumps(one_row(method, scene_name, int(n), args.repeats)))
        return

    sys.path.insert(0, os.path.dirname(__file__))
    from _provenance import print_table, write_csv
    methods = args.backends + ([] if args.no_jax_md else ["jax-md"])
    plan = [("uniform", n) for n in args.sizes] + [("sphere", args.sphere_n)]
    rows = []
    for scene_name, n in plan:
        for method in methods:
            cmd = [sys.executable, __file__, "--one", method, scene_name,
                   str(n), "--repeats", str(args.repeats)]
            try:
                done = subprocess.run(cmd, capture_output=True, text=True,
                                      timeout=args.timeout)
                row = json.loads(done.stdout.strip().splitlines()[-1])
            except subprocess.TimeoutExpired:
                row = {"scene": scene_name, "method": method, "N": n,
                       "failed": f"timeout {args.timeout}s"}
            except (json.JSONDecodeError, IndexError):
                tail = (done.stderr.strip().splitlines() or ["?"])[-1]
                row = {"scene": scene_name, "method": method, "N": n,
                       "failed": tail[:120]}
            rows.append(row)
            print(json.dumps(row), flush=True)
    for scene_name, n in plan:  # speed-up and memory ratio over jax-md
        ref = next((r for r in rows if r["scene"] == scene_name and r["N"] == n
                    and r["method"] == "jax-md" and "update_ms" in r), None)
        for r in rows:
            if ref and r is not ref and r["scene"] == scene_name and r["N"] == n \
                    and "update_ms" in r:
                r["speedup"] = ref["update_ms"] / r["update_ms"]
                r["temp_ratio"] = ref["xla_temp_mb"] / max(r["xla_temp_mb"], 1e-9)
    print_table(rows, ["scene", "method", "N", "k", "update_ms", "speedup",
                       "xla_temp_mb", "temp_ratio", "peak_mb",
                       "peak_above_baseline_mb", "allocate_s",
                       "failed"])
    print("wrote", write_csv(rows, "neighbors.csv", args.out))


if __name__ == "__main__":
    main()
