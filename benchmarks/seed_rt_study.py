"""Seed 001 §5 reproduced: ray-tracing-style neighbour search against grids.

Scenes (float32, free space with walls as in the seed; `jaxrt.scenes`):
  uniform  §5.2: ``N = p·β³`` particles uniform in the unit box, cutoff
           ``C = 1/β``; β ∈ {2, 4, 8, 16, 32}, p ∈ {1, 2, 4, 8, 16, 32}.
  sphere   §5.3 / Code 2: ``N = p·α³`` particles uniform on the unit sphere,
           cutoff for ≈ 9·p neighbours (`jaxrt.scenes.sphere_surface_cutoff`);
           α ∈ {8, 16, 32, 64, 128}, p ∈ {1, …, 32}. Points shifted by
           ``1 + C`` into ``[0, 2 + 2C)³``.

Methods (every one through jax-md's ``neighbor_list`` interface, Dense
layout, ``dr_threshold = 0`` so every ``update`` rebuilds from scratch,
``capacity_multiplier = 1.25``, ``mask_self = True``):
  aabb-unsorted  jaxrt backend "bvh-unsorted" (Warp custom-AABB BVH, input order)
  aabb-sorted    jaxrt backend "bvh"          (the same, Morton-sorted)
  spheres        jaxrt backend "spheres"      (seed's sphere + ray method)
  squares        jaxrt backend "squares"      (seed's double-squares method)
  cell           jaxrt backend "cell"         (pure-JAX cell list)
  jax-md         ``jax_md.partition.neighbor_list`` (its cell list), with
                 ``space.free()`` and box 1.0 (uniform) or ``2 + 2C``
                 (sphere: the box enclosing the shifted sphere). jaxrt gets
                 the same ``space.free()`` displacement and ``box=None``.
  Speed-ups in the table and on the plots are over "jax-md", the grid
  method (the seed's CUDA grid of cells), by total time.

Columns (three rotating input sets: the scene plus two copies jittered by
1e-3·C, clipped to the unit box for "uniform"; each timed call is warm and
reads the next set, so no call repeats the previous input):
  init_ms     median wall time of ``allocate(R)`` over ``--init-repeats``
              calls after one untimed call (compile / warm-up). allocate
              builds the search structure (BVH / cell grid) on the host
              path, measures the exact capacity and allocates the Dense
              ``(N, capacity)`` buffer: the seed's "initialization step".
  compute_ms  median wall time of one jitted call
              ``f(R, nbrs) = (update(R, nbrs), lj_forces(R, idx))`` over
              ``--repeats`` calls after one warm call per input: the list
              search itself (for these methods it rebuilds the BVH / grid
              inside update, as nothing is kept between calls) plus an
              LJ-like force accumulation over the pairs found (σ = C/2,
              ε = 1, r² clamped at (σ/10)², summed over each Dense row:
              a gather + reduction in JAX, the same code for every method).
              The seed's "computation step".
  search_ms   the same with ``update`` alone (no forces), for reference.
  total_ms    init_ms + compute_ms (what the bars stack).
  k_mean      mean neighbours per particle (from the allocate'd list).
  capacity    Dense row width; overflow: did any timed list overflow.
  failed      reason a row has no times: the exception (e.g. XLA
              RESOURCE_EXHAUSTED, a Warp error), "timeout", "crashed", or
              "skipped: ..." (``--max-n``, ``--time-budget``).
  speedup_vs_jaxmd / speedup_vs_cell   total_ms ratios, same configuration.

Each (configuration, method) runs as one job in a worker subprocess that
runs jobs in order and prints one JSON row per job; a job that crashes the
worker (OOM abort, segfault) or passes ``--timeout`` is recorded as failed
and a fresh worker takes the remaining jobs (a job's timeout includes the
worker's imports and the first compile of each kernel). Errors inside a job
are caught and recorded (``failed=...``). After ``--time-budget`` seconds no
new configuration is started; the rest are recorded as skipped. At
``--hard-stop`` seconds the running job is killed ("killed at --hard-stop")
and the rest skipped. Finished rows are also appended to
``seed_rt_study.partial.jsonl`` as they come, in case the whole run is killed.
Configurations run in order of N, both scenes interleaved, so a budget cuts
the largest.

Usage:
  python benchmarks/seed_rt_study.py --small --out /tmp/seedstudy   # CPU smoke
  python benchmarks/seed_rt_study.py --time-budget 330 --hard-stop 450 \
      --timeout 150                                                # GPU, < 8 min
  python benchmarks/seed_rt_study.py --plot-only results.csv [--out DIR]
Writes seed_rt_study.csv (with provenance columns), seed_rt_uniform.png and
seed_rt_sphere.png to --out, else $OUT, else benchmarks/results/<device>/.
"""
from __future__ import annotations

import os

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import argparse  # noqa: E402
import csv  # noqa: E402
import gc  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import queue  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402
from pathlib import Path  # noqa: E402

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))

METHODS = {  # column name -> jaxrt backend (None: jax-md itself)
    "aabb-unsorted": "bvh-unsorted",
    "aabb-sorted": "bvh",
    "spheres": "spheres",
    "squares": "squares",
    "cell": "cell",
    "jax-md": None,
}
SCENES = {"uniform": ("beta", [2, 4, 8, 16, 32]),
          "sphere": ("alpha", [8, 16, 32, 64, 128])}
P_FULL = [1, 2, 4, 8, 16, 32]
SMALL = {"uniform": [2, 4, 8], "sphere": [8, 16]}
P_SMALL = [1, 4]
INPUT_SETS = 3
COLORS = {"aabb-unsorted": "#ff7f0e", "aabb-sorted": "#d62728",
          "spheres": "#2ca02c", "squares": "#1f77b4", "cell": "#9467bd",
          "jax-md": "#7f7f7f"}


# ---------------------------------------------------------------------------
# Scenes


def make_scene(scene: str, param: int, p: int):
    """float32 input sets (3 of (N, 3)), cutoff, jax-md box side."""
    import numpy as np
    from jaxrt import scenes
    if scene == "uniform":
        pos, cutoff = scenes.uniform(param, p, seed=0)
        box = 1.0
    else:
        pos, cutoff = scenes.sphere_surface(param, p, seed=0)
        pos = pos + (1.0 + cutoff)
        box = 2.0 + 2.0 * cutoff
    rng = np.random.default_rng(1)
    sets = [pos]
    for _ in range(INPUT_SETS - 1):
        moved = pos + rng.normal(0.0, 1e-3 * cutoff, pos.shape)
        sets.append(np.clip(moved, 0.0, np.nextafter(box, 0.0)))
    return [s.astype(np.float32) for s in sets], float(cutoff), float(box)


def n_of(param: int, p: int) -> int:
    return p * param ** 3


# ---------------------------------------------------------------------------
# One job (runs in the worker)


def lj_forces(R, idx, sigma):
    """LJ-like pair forces summed over each Dense row (padding idx = N)."""
    import jax.numpy as jnp
    n = R.shape[0]
    mask = idx < n
    dr = R[:, None, :] - R[jnp.minimum(idx, n - 1)]
    r2 = jnp.maximum(jnp.sum(dr * dr, axis=-1), (0.1 * sigma) ** 2)
    s6 = (sigma * sigma / r2) ** 3
    fmag = jnp.where(mask, 24.0 * (2.0 * s6 * s6 - s6) / r2, 0.0)
    return jnp.sum(fmag[..., None] * dr, axis=1)


def run_job(scene: str, param: int, p: int, method: str, repeats: int,
            init_repeats: int) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax_md import partition, space
    from _provenance import median_ms

    sets, cutoff, box = make_scene(scene, param, p)
    n = sets[0].shape[0]
    row = {"scene": scene, "param": param, "p": p, "N": n, "cutoff": cutoff,
           "method": method}
    disp, _ = space.free()
    if METHODS[method] is None:
        fns = partition.neighbor_list(disp, box, cutoff, dr_threshold=0.0,
                                      format=partition.Dense)
    else:
        import jaxrt
        fns = jaxrt.neighbor_list(disp, None, cutoff, dr_threshold=0.0,
                                  format=partition.Dense,
                                  backend=METHODS[method])
    inputs = [jnp.asarray(s) for s in sets]
    del sets

    # init: allocate, first call untimed
    for x in inputs[::-1]:  # warm-up: compile for every input's shapes
        nbrs = fns.allocate(x)
        jax.block_until_ready(nbrs.idx)
    times = []
    for k in range(init_repeats):
        x = inputs[(k + 1) % INPUT_SETS]
        t = time.perf_counter()
        fresh = fns.allocate(x)
        jax.block_until_ready(fresh.idx)
        times.append((time.perf_counter() - t) * 1e3)
        del fresh
    row["init_ms"] = float(np.median(times))
    idx = np.asarray(nbrs.idx)
    row["k_mean"] = round(float(np.mean(np.sum(idx < n, axis=1))), 2)
    row["capacity"] = int(idx.shape[1])
    del idx

    sigma = 0.5 * cutoff

    @jax.jit
    def compute(x, nb):
        nb = fns.update(x, nb)
        return nb.idx, nb.did_buffer_overflow, lj_forces(x, nb.idx, sigma)

    search = jax.jit(lambda x, nb: fns.update(x, nb).idx)
    row["compute_ms"] = median_ms(lambda x: compute(x, nbrs), inputs, repeats)
    row["search_ms"] = median_ms(lambda x: search(x, nbrs), inputs, repeats)
    row["total_ms"] = row["init_ms"] + row["compute_ms"]
    row["overflow"] = any(bool(compute(x, nbrs)[1]) for x in inputs)
    row["repeats"] = repeats
    return row


def worker(jobs_file: str, deadline: float) -> None:
    """Run jobs in order; print 'START i' then 'ROW {json}' per job. Stops
    (exit 0) at a configuration boundary once past ``deadline``."""
    import jax
    with open(jobs_file) as f:
        spec = json.load(f)
    last_config = None
    for i, job in enumerate(spec["jobs"]):
        config = (job["scene"], job["param"], job["p"])
        if config != last_config and time.time() > deadline:
            return
        last_config = config
        print(f"START {i}", flush=True)
        try:
            row = run_job(job["scene"], job["param"], job["p"], job["method"],
                          spec["repeats"], spec["init_repeats"])
        except Exception as exc:  # noqa: BLE001 - recorded as a failed row
            traceback.print_exc(file=sys.stderr)
            msg = f"{type(exc).__name__}: {exc}".replace("\n", " ")
            row = {**job, "N": n_of(job["param"], job["p"]),
                   "failed": msg[:200]}
        print("ROW " + json.dumps(row), flush=True)
        gc.collect()
        try:
            jax.clear_caches()
        except Exception:  # noqa: BLE001
            pass


# ---------------------------------------------------------------------------
# Driver


def _reader(stream, q):
    for line in stream:
        q.put(line)
    q.put(None)


def run_jobs(jobs: list[dict], args, deadline: float, hard: float, tmp: Path,
             log: Path) -> list[dict]:
    rows: list[dict | None] = [None] * len(jobs)
    start = 0
    while start < len(jobs) and time.time() <= deadline:
        jobs_file = tmp / "seed_rt_jobs.json"
        jobs_file.write_text(json.dumps({"jobs": jobs[start:],
                                         "repeats": args.repeats,
                                         "init_repeats": args.init_repeats}))
        err_path = tmp / "seed_rt_worker.err"
        with open(err_path, "w") as err:
            proc = subprocess.Popen(
                [sys.executable, __file__, "--worker", str(jobs_file),
                 "--deadline", str(deadline)],
                stdout=subprocess.PIPE, stderr=err, text=True)
            q: queue.Queue = queue.Queue()
            threading.Thread(target=_reader, args=(proc.stdout, q),
                             daemon=True).start()
            current = None
            started_at = time.time()
            broke = None
            while True:
                wait = args.timeout + 120 if current is None else \
                    max(1.0, args.timeout - (time.time() - started_at))
                wait = min(wait, max(0.1, hard - time.time()))
                try:
                    line = q.get(timeout=wait)
                except queue.Empty:
                    broke = "killed at --hard-stop" if time.time() >= hard \
                        else f"timeout {args.timeout:g}s"
                    proc.kill()
                    break
                if line is None:
                    proc.wait()
                    if current is not None:
                        broke = f"crashed (rc {proc.returncode})"
                    break
                if line.startswith("START "):
                    current = start + int(line.split()[1])
                    started_at = time.time()
                    j = jobs[current]
                    print(f"  {j['scene']:7s} {SCENES[j['scene']][0]}="
                          f"{j['param']:<3d} p={j['p']:<2d} N={n_of(j['param'], j['p']):<9d}"
                          f" {j['method']:13s}", end=" ", flush=True)
                elif line.startswith("ROW ") and current is not None:
                    row = json.loads(line[4:])
                    rows[current] = row
                    with open(log, "a") as f:
                        f.write(json.dumps(row) + "\n")
                    print(f"init {row.get('init_ms', float('nan')):9.3f} ms  "
                          f"compute {row.get('compute_ms', float('nan')):9.3f} ms"
                          + (f"  FAILED {row['failed'][:80]}" if "failed" in row else ""),
                          flush=True)
                    current = None
            proc.wait()
        if broke is None or current is None:
            break  # worker finished (or stopped at the deadline / hard stop)
        tail = [ln for ln in err_path.read_text().strip().splitlines() if ln.strip()]
        reason = broke + (f": {tail[-1][:150]}" if tail and "crash" in broke else "")
        j = jobs[current]
        rows[current] = {**j, "N": n_of(j["param"], j["p"]), "failed": reason}
        print(f"FAILED {reason}", flush=True)
        with open(log, "a") as f:
            f.write(json.dumps(rows[current]) + "\n")
        start = current + 1
        if time.time() >= hard:
            break
    for i, j in enumerate(jobs):
        if rows[i] is None:
            rows[i] = {**j, "N": n_of(j["param"], j["p"]),
                       "failed": "skipped: time budget or hard stop"}
    return rows


def add_speedups(rows: list[dict]) -> None:
    by_config: dict = {}
    for r in rows:
        by_config.setdefault((r["scene"], int(r["param"]), int(r["p"])), {})[r["method"]] = r
    for group in by_config.values():
        for ref_name, col in (("jax-md", "speedup_vs_jaxmd"), ("cell", "speedup_vs_cell")):
            ref = group.get(ref_name)
            for r in group.values():
                if ref and _ok(ref) and _ok(r):
                    r[col] = float(ref["total_ms"]) / float(r["total_ms"])


def _ok(row) -> bool:
    v = row.get("total_ms")
    return v not in (None, "") and not row.get("failed") and math.isfinite(float(v))


def headline(rows: list[dict]) -> list[dict]:
    out = []
    configs = sorted({(r["scene"], int(r["param"]), int(r["p"]), int(r["N"])) for r in rows},
                     key=lambda c: (c[0] != "uniform", c[3], c[1]))
    for scene, param, p, n in configs:
        group = [r for r in rows if r["scene"] == scene and int(r["param"]) == param
                 and int(r["p"]) == p]
        good = [r for r in group if _ok(r)]
        if not good:
            reason = group[0].get("failed", "") if group else ""
            out.append({"scene": scene, SCENES[scene][0]: param, "p": p, "N": n,
                        "fastest": "-", "note": reason[:40]})
            continue
        best = min(good, key=lambda r: float(r["total_ms"]))
        ref = {r["method"]: r for r in group}

        def ratio(name):
            r = ref.get(name)
            if r is None:
                return "-"
            if not _ok(r):
                return "skip" if str(r.get("failed", "")).startswith("skipped") else "fail"
            return round(float(r["total_ms"]) / float(best["total_ms"]), 2)
        out.append({"scene": scene, SCENES[scene][0]: param, "p": p, "N": n,
                    "fastest": best["method"], "total_ms": float(best["total_ms"]),
                    "x_vs_jaxmd": ratio("jax-md"), "x_vs_cell": ratio("cell"),
                    "note": ""})
    return out


# ---------------------------------------------------------------------------
# Plots (seed's Figures 9 and 10 style)


def _lighten(color: str, amount: float = 0.55):
    from matplotlib.colors import to_rgb
    r, g, b = to_rgb(color)
    return (r + (1 - r) * amount, g + (1 - g) * amount, b + (1 - b) * amount)


def plot(rows: list[dict], folder: Path) -> list[Path]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    paths = []
    for scene, fname in (("uniform", "seed_rt_uniform.png"), ("sphere", "seed_rt_sphere.png")):
        srows = [r for r in rows if r["scene"] == scene]
        if not srows:
            continue
        pname = SCENES[scene][0]
        params = sorted({int(r["param"]) for r in srows})
        methods = [m for m in METHODS if any(r["method"] == m for r in srows)]
        fig, axes = plt.subplots(len(params), 1, squeeze=False, layout="constrained",
                                 figsize=(10, 1.2 + 2.8 * len(params)))
        for ax, param in zip(axes[:, 0], params):
            prow = [r for r in srows if int(r["param"]) == param]
            ps = sorted({int(r["p"]) for r in prow})
            width = 0.8 / len(methods)
            tops = []
            for mi, m in enumerate(methods):
                for pi, p in enumerate(ps):
                    r = next((r for r in prow if r["method"] == m and int(r["p"]) == p), None)
                    x = pi + (mi - (len(methods) - 1) / 2) * width
                    if r is None:
                        continue
                    if not _ok(r):
                        label = "skip" if str(r.get("failed", "")).startswith("skipped") else "fail"
                        ax.text(x, 0, label, rotation=90, ha="center", va="bottom",
                                fontsize=6, color="red", transform=ax.get_xaxis_transform())
                        continue
                    init, comp = float(r["init_ms"]), float(r["compute_ms"])
                    ax.bar(x, init, width, color=_lighten(COLORS[m]), edgecolor="none")
                    ax.bar(x, comp, width, bottom=init, color=COLORS[m], edgecolor="none")
                    sp = r.get("speedup_vs_jaxmd")
                    if sp not in (None, "") and m != "jax-md":
                        tops.append((x, init + comp, f"{float(sp):.2g}"))
            if scene == "sphere":
                ax.set_yscale("log")
            ymax = ax.get_ylim()[1]
            for x, top, txt in tops:
                ax.text(x, top, txt, ha="center", va="bottom", fontsize=6, rotation=90)
            if scene != "sphere":
                ax.set_ylim(0, ymax * 1.25)
            else:
                ax.set_ylim(top=ymax * 4)
            ax.set_xticks(range(len(ps)))
            ax.set_xticklabels([f"p={p}\nN={n_of(param, p):,}" for p in ps], fontsize=7)
            ax.set_ylabel("time (ms)")
            ax.set_title(f"{scene}: {pname}={param}", fontsize=9)
        handles = [Patch(color=COLORS[m], label=f"{m} compute") for m in methods] + \
                  [Patch(color=_lighten(COLORS[m]), label=f"{m} init") for m in methods]
        fig.legend(handles=handles, ncol=len(methods), fontsize=7,
                   loc="outside lower center")
        dev = next((r.get("device") for r in srows if r.get("device")), "")
        fig.suptitle(f"Seed 001 §5 {scene} ({dev}); number on bar = total speed-up "
                     "over jax-md; light = init (allocate), dark = compute "
                     "(update + forces)", fontsize=8)
        path = folder / fname
        fig.savefig(path, dpi=130)
        plt.close(fig)
        paths.append(path)
    return paths


def read_csv(path: str) -> list[dict]:
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    for r in rows:
        for k in ("init_ms", "compute_ms", "search_ms", "total_ms",
                  "speedup_vs_jaxmd", "speedup_vs_cell"):
            if r.get(k) not in (None, ""):
                r[k] = float(r[k])
    return rows


# ---------------------------------------------------------------------------


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--small", action="store_true",
                        help="CPU smoke: beta<=8, alpha<=16, p in {1,4}, 3 repeats")
    parser.add_argument("--max-n", type=float, default=2e7)
    parser.add_argument("--methods", nargs="+", default=list(METHODS),
                        choices=list(METHODS))
    parser.add_argument("--scenes", nargs="+", default=list(SCENES),
                        choices=list(SCENES))
    parser.add_argument("--p", type=int, nargs="+", default=None,
                        help="particles per cell (default 1..32, or 1 4 with --small)")
    parser.add_argument("--repeats", type=int, default=None, help="default 10 (3 --small)")
    parser.add_argument("--init-repeats", type=int, default=None, help="default 5 (2 --small)")
    parser.add_argument("--time-budget", type=float, default=float("inf"),
                        help="seconds; no new configuration starts after it")
    parser.add_argument("--hard-stop", type=float, default=float("inf"),
                        help="seconds; kill the running job then, skip the rest")
    parser.add_argument("--timeout", type=float, default=300,
                        help="seconds per (configuration, method) job")
    parser.add_argument("--out", default=None)
    parser.add_argument("--plot-only", metavar="CSV", default=None)
    parser.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--deadline", type=float, default=float("inf"),
                        help=argparse.SUPPRESS)
    args = parser.parse_args(argv)

    if args.worker:
        worker(args.worker, args.deadline)
        return

    from _provenance import print_table

    if args.plot_only:
        rows = read_csv(args.plot_only)
        folder = Path(args.out) if args.out else Path(args.plot_only).parent
        folder.mkdir(parents=True, exist_ok=True)
        for path in plot(rows, folder):
            print("wrote", path)
        print_table(headline(rows), ["scene", "beta", "alpha", "p", "N", "fastest",
                                     "total_ms", "x_vs_jaxmd", "x_vs_cell", "note"])
        return

    t0 = time.time()
    deadline = t0 + args.time_budget
    args.repeats = args.repeats or (3 if args.small else 10)
    args.init_repeats = args.init_repeats or (2 if args.small else 5)
    ps = args.p or (P_SMALL if args.small else P_FULL)
    # plan: configurations in order of N (both scenes interleaved), so a
    # time budget cuts the largest ones
    configs = []
    for scene in args.scenes:
        params = SMALL[scene] if args.small else SCENES[scene][1]
        configs += [(scene, param, p) for param in params for p in ps]
    configs.sort(key=lambda c: (n_of(c[1], c[2]), c[0] != "uniform"))
    jobs, rows_skipped = [], []
    for scene, param, p in configs:
        for m in args.methods:
            job = {"scene": scene, "param": param, "p": p, "method": m}
            if n_of(param, p) > args.max_n:
                rows_skipped.append({**job, "N": n_of(param, p),
                                     "failed": f"skipped: N > max-n {args.max_n:g}"})
            else:
                jobs.append(job)
    folder_hint = Path(args.out or os.environ.get("OUT") or "/tmp")
    folder_hint.mkdir(parents=True, exist_ok=True)
    print(f"{len(jobs)} jobs ({len(configs)} configurations x {len(args.methods)} "
          f"methods), {len(rows_skipped)} skipped by --max-n", flush=True)
    log = folder_hint / "seed_rt_study.partial.jsonl"
    log.unlink(missing_ok=True)
    print(f"rows also appended to {log} as they finish", flush=True)
    rows = run_jobs(jobs, args, deadline, t0 + args.hard_stop, folder_hint,
                    log) + rows_skipped
    (folder_hint / "seed_rt_jobs.json").unlink(missing_ok=True)
    add_speedups(rows)

    from _provenance import write_csv
    cols = ["scene", "param", "p", "N", "cutoff", "method", "init_ms", "compute_ms",
            "search_ms", "total_ms", "speedup_vs_jaxmd", "speedup_vs_cell", "k_mean",
            "capacity", "overflow", "repeats", "failed"]
    rows = [{c: r.get(c) for c in cols} for r in rows]
    for r in rows:
        r["param_name"] = SCENES[r["scene"]][0]
    path = write_csv(rows, "seed_rt_study.csv", args.out)
    print("wrote", path)
    rows = read_csv(str(path))
    for p in plot(rows, path.parent):
        print("wrote", p)
    print_table(rows, ["scene", "param", "p", "N", "method", "init_ms", "compute_ms",
                       "search_ms", "speedup_vs_jaxmd", "k_mean", "overflow", "failed"])
    print("\nHeadline: fastest method per configuration (total = init + compute); "
          "x_vs_* = that method's total / fastest total")
    print_table(headline(rows), ["scene", "beta", "alpha", "p", "N", "fastest", "total_ms",
                                 "x_vs_jaxmd", "x_vs_cell", "note"])
    print(f"elapsed {time.time() - t0:.0f} s")


if __name__ == "__main__":
    main()
