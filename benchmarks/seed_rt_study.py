"""Seed 001 §5 reproduced: ray-tracing-style neighbour search against grids.

Scenes (float32, free space with walls as in the seed; `jaxrt.scenes`):
  uniform  §5.2: ``N = p·β³`` particles uniform in the unit box, cutoff
           ``C = 1/β``; β ∈ {2, 4, 8, 16, 32}, p ∈ {1, 2, 4, 8, 16, 32}.
  sphere   §5.3 / Code 2: ``N = p·α³`` particles uniform on the unit sphere,
           cutoff for ≈ 9·p neighbours (`jaxrt.scenes.sphere_surface_cutoff`);
           α ∈ {8, 16, 32, 64, 128}, p ∈ {1, …, 32}. Points shifted by
           ``1 + C`` into ``[0, 2 + 2C)³``.

Methods (every one through jax-md's ``neighbor_list`` interface, Dense
layout, ``dr_threshold = 0`` so every ``update`` searches again,
``capacity_multiplier = 1.25``, ``mask_self = True``):
  aabb-unsorted  jaxrt backend "bvh-unsorted" (Warp custom-AABB BVH, input order)
  aabb-sorted    jaxrt backend "bvh"          (the same, Morton-sorted)
  spheres        jaxrt backend "spheres"      (seed's sphere + ray method)
  squares        jaxrt backend "squares"      (seed's double-squares method)
  cell           jaxrt backend "cell"         (pure-JAX cell list)
  jax-md         ``jax_md.partition.neighbor_list`` (its dense cell list), with
                 ``space.free()`` and box 1.0 (uniform) or ``2 + 2C``
                 (sphere: the box enclosing the shifted sphere). jaxrt gets
                 the same ``space.free()`` displacement and ``box=None``.
  Speed-ups in the tables and on the plots are over "jax-md", the grid
  method (the seed's CUDA grid of cells), by total time.

What ``update`` redoes in the compute step: spheres, squares, cell and
jax-md rebuild their structure (BVH / grid) on every call. The two aabb
methods keep one BVH per compiled call site (`jaxrt.rt.ffi`) and *refit* it,
because the inputs differ by 1e-3·C, below the rebuild threshold (0.2·C);
their compute step is refit + rays, closer to the seed's compute step (which
excludes the build) than the grid methods' update is.

Columns (three rotating input sets: the scene plus two copies jittered by
1e-3·C, clipped to the box; each timed call reads the next set, so no call
repeats the previous input):
  init_ms     median wall time of ``allocate(R)``: builds the search
              structure on the host path, measures the exact capacity and
              allocates the Dense ``(N, capacity)`` buffer (the seed's
              "initialization step").
  compute_ms  median wall time of one jitted call
              ``f(R, nbrs) = (update(R, nbrs), lj_forces(R, idx))``: the
              list search plus an LJ-like force accumulation over the pairs
              found (σ = C/2, ε = 1, r² clamped at (σ/10)², summed over each
              Dense row: a gather + reduction in JAX, the same code for
              every method). The seed's "computation step".
  search_ms   the same with ``update`` alone (no forces), for reference
              (empty with ``--no-search``, or when compute_ms is above
              ``--search-limit-ms``; search_reps is then 0).
  total_ms    init_ms + compute_ms (what the bars stack).
  init_reps, compute_reps, search_reps
              timed calls behind each median. Every measurement makes one
              untimed warm-up call (compilation, first BVH build, lazy
              loads), then timed calls; the first timed call's time t sets
              their number, ``clamp(ceil(--target-s / t), --min-repeats,
              --max-repeats)``, so large N gets few repeats and small N
              many. compute and search are compiled together, in two
              threads, before either is timed.
  k_mean      mean neighbours per particle (from the allocate'd list).
  capacity    Dense row width; overflow: did any timed compute call's list
              overflow.
  tier        the configuration's priority (below); 0 for --configs.
  failed      why a row has no times: "out of memory: ..." (XLA
              RESOURCE_EXHAUSTED, a failed Warp/CUDA allocation), another
              exception, "timeout ...", "crashed (rc ...)", or
              "skipped: ..." (not selected, --max-n, --time-budget,
              --hard-stop).
  speedup_vs_jaxmd / speedup_vs_cell   total_ms ratios, same configuration.

Plan. The seed's Figures 9 and 10 have one panel per β (α), bars for each
p. Configurations run by priority tier, largest N first inside a tier, all
methods of a configuration back to back:
  tier 1  every panel's largest p with N <= --max-n (32; 8 for α = 128:
          many particles per cell, where sorting and the interactions
          decide), and p = 1 on the large panels β ∈ {16, 32},
          α ∈ {32, 64, 128} (few per cell: where the seed finds the grid's
          empty cells cost most, and α = 128 is its out-of-memory case).
  tier 2  p = 8 (α = 128: p = 4) everywhere; p = 1 on the small panels.
  tier 3  p ∈ {2, 16} (α = 128: p = 2).
  tier 4  p = 4 (the rest).
The smallest configurations (N <= 2048) are dominated by fixed per-call
overheads whatever the method; they come last inside each tier.
Every row of the seed's grid is written to the CSV; rows not run say why.
``--plan`` prints the order with N and a rough H100 time guess and exits.

Isolation. Jobs run in one long-lived worker subprocess (imports, Warp
kernel loads and JAX's per-shape executables are paid once, not per job;
one worker at a time, since on one GPU concurrent workers would disturb the
timings and each would pin its own memory pool). The driver sends one job
at a time. A job that crashes the worker (segfault, host OOM kill) or passes
``--timeout`` is recorded as failed and a fresh worker takes the next job.
An exception inside a job is caught and recorded; after any exception other
than out-of-memory the worker also exits (its CUDA state may be poisoned)
and a fresh one starts. After ``--time-budget`` seconds no new
configuration starts; at ``--hard-stop`` seconds the running job is killed.
Finished rows are also appended to ``seed_rt_study.partial.jsonl`` as they
come, in case the whole run is killed.

Usage:
  python benchmarks/seed_rt_study.py --plan                         # dry run
  python benchmarks/seed_rt_study.py --small --out /tmp/seedstudy   # CPU smoke
  python benchmarks/seed_rt_study.py --time-budget 470 --hard-stop 505 \
      --timeout 100                                                 # GPU, < 9 min
  python benchmarks/seed_rt_study.py --configs uniform:32:1 sphere:128:8
  python benchmarks/seed_rt_study.py --plot-only results.csv [--out DIR]
Writes seed_rt_study.csv (with provenance columns), seed_rt_uniform.png,
seed_rt_sphere.png and seed_rt_headline.md to --out, else $OUT, else
benchmarks/results/<device>/.
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
import signal  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402
from concurrent.futures import ThreadPoolExecutor  # noqa: E402
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
# Order inside a configuration: the Warp methods first, the pure-JAX ones
# last (JAX's pool never shrinks with preallocation off, so a huge jax-md
# attempt goes last; Warp allocates outside JAX's pool).
RUN_ORDER = ["aabb-sorted", "aabb-unsorted", "squares", "spheres", "cell", "jax-md"]
SCENES = {"uniform": ("beta", [2, 4, 8, 16, 32]),
          "sphere": ("alpha", [8, 16, 32, 64, 128])}
P_FULL = [1, 2, 4, 8, 16, 32]
SMALL = {"uniform": [4, 8], "sphere": [8, 16]}
P_SMALL = [1, 4]
INPUT_SETS = 3
COLORS = {"aabb-unsorted": "#ff7f0e", "aabb-sorted": "#d62728",
          "spheres": "#2ca02c", "squares": "#1f77b4", "cell": "#9467bd",
          "jax-md": "#7f7f7f"}
OOM_MARKERS = ("RESOURCE_EXHAUSTED", "out of memory", "Out of memory",
               "OUT_OF_MEMORY", "Failed to allocate", "failed to allocate",
               "MemoryAllocation", "Unable to allocate", "MemoryError")


def n_of(param: int, p: int) -> int:
    return p * param ** 3


# ---------------------------------------------------------------------------
# Plan


def p_max(param: int, ps: list[int], max_n: float) -> int | None:
    fit = [p for p in ps if n_of(param, p) <= max_n]
    return max(fit) if fit else None


def tier_of(scene: str, param: int, p: int, ps: list[int], max_n: float) -> int:
    """Priority of a configuration (module docstring): 1 first."""
    top = p_max(param, ps, max_n)
    large_panel = param >= (16 if scene == "uniform" else 32)
    middle = 8 if top is None or top > 8 else 4
    if p == top or (p == 1 and large_panel):
        return 1
    if p == middle or p == 1:
        return 2
    if p in (2, 16):
        return 3
    return 4


def k_expected(scene: str, param: int, p: int) -> float:
    """Mean neighbours per particle, roughly (walls ignored)."""
    return 4.18879 * p if scene == "uniform" else 9.0 * p


def scene_cells(scene: str, param: int, p: int) -> float:
    """Cells of jax-md's dense grid (cell side = cutoff)."""
    if scene == "uniform":
        return float(param) ** 3
    # jaxrt.scenes.sphere_surface_cutoff, without importing jaxrt (and JAX,
    # Warp) into the driver just for the plan
    c = math.acos(1.0 - 2.0 * 9.0 * p / n_of(param, p))
    return float(int((2 + 2 * c) / c)) ** 3


# A rough H100 guess per call, in ms: (fixed, per neighbour pair) for the
# compute step, fitted by eye to RESULTS.md (bvh 13.3 ms and jax-md 21 ms at
# 10⁶ uniform k = 65; cell 28.7 ms; unsorted 3.5x sorted) and the partial
# H100 CSV (allocate 28-46 ms for the Warp methods). spheres/squares are
# guesses. Only for --plan and the time estimate; nothing depends on it.
_GUESS = {"aabb-sorted": (1.0, 2e-7), "aabb-unsorted": (1.0, 6e-7),
          "spheres": (1.5, 1e-6), "squares": (1.5, 4e-7),
          "cell": (2.0, 4e-7), "jax-md": (0.15, 3e-7)}
# compiles etc. per job (partial run: ~2.4 s per job on average, with a
# cache clear per job; on CPU the cell list compiles ~3x longer than the rest)
_GUESS_JOB_OVERHEAD_S = {"cell": 4.0, "jax-md": 2.0}
GUESS_STARTUP_S = 60.0       # first worker: imports, Warp kernel compiles, warm-up


def guess_job_s(scene: str, param: int, p: int, method: str, args) -> float:
    n = n_of(param, p)
    pairs = n * k_expected(scene, param, p)
    fixed, per_pair = _GUESS[method]
    compute = fixed + per_pair * pairs
    if method == "jax-md":
        compute += 1.5e-7 * scene_cells(scene, param, p)
        init = 15.0 + compute
    elif method == "cell":
        init = 10.0 + 1.5 * compute
    else:
        init = 35.0 + 2.0 * compute
    total = _GUESS_JOB_OVERHEAD_S.get(method, 1.3)
    steps = [init, compute]
    if args.search and compute <= args.search_limit_ms:
        steps.append(0.85 * compute)
    for t_ms in steps:
        t = t_ms / 1e3
        reps = min(max(math.ceil(args.target_s / t), args.min_repeats), args.max_repeats)
        total += (1 + reps) * t
    return total


def universe(small: bool) -> list[tuple[str, int, int]]:
    grid = SMALL if small else {s: v[1] for s, v in SCENES.items()}
    ps = P_SMALL if small else P_FULL
    return [(s, param, p) for s in SCENES for param in grid[s] for p in ps]


def parse_configs(specs: list[str]) -> list[tuple[str, int, int]]:
    out = []
    for spec in specs:
        try:
            scene, param, p = spec.split(":")
            if scene not in SCENES:
                raise ValueError
            out.append((scene, int(param), int(p)))
        except ValueError:
            raise SystemExit(f"--configs: '{spec}' is not scene:param:p with scene "
                             f"in {list(SCENES)} (e.g. uniform:32:1, sphere:128:8)")
    return out


def build_plan(args) -> tuple[list[dict], list[dict]]:
    """(configurations to run, in order; skipped rows). A configuration is
    a dict with scene, param, p, N, tier, methods."""
    ps = P_SMALL if args.small else P_FULL
    methods = [m for m in RUN_ORDER if m in args.methods]
    planned, skipped = [], []

    def skip(scene, param, p, tier, reason, which=None):
        for m in (which or list(METHODS)):
            skipped.append({"scene": scene, "param": param, "p": p,
                            "N": n_of(param, p), "method": m, "tier": tier,
                            "failed": reason})

    explicit = parse_configs(args.configs) if args.configs else None
    for scene, param, p in universe(args.small):
        tier = tier_of(scene, param, p, ps, args.max_n)
        n = n_of(param, p)
        if explicit is not None and (scene, param, p) in explicit:
            continue  # planned below, in the order given
        if n > args.max_n:
            skip(scene, param, p, tier, f"skipped: N > --max-n {args.max_n:g}")
        elif explicit is not None:
            skip(scene, param, p, tier, "skipped: not selected (--configs)")
        elif (scene not in args.scenes or (args.params and param not in args.params)
              or (args.p and p not in args.p)):
            skip(scene, param, p, tier,
                 "skipped: not selected (--scenes/--params/--p)")
        elif tier not in args.tiers:
            skip(scene, param, p, tier, f"skipped: not selected (tier {tier}; "
                 f"--tiers {' '.join(map(str, args.tiers))})")
        else:
            planned.append({"scene": scene, "param": param, "p": p, "N": n,
                            "tier": tier, "methods": methods})
    if explicit is None:
        planned.sort(key=lambda c: (c["tier"], -c["N"], c["scene"] != "uniform",
                                    c["param"]))
    else:
        for scene, param, p in explicit:
            n = n_of(param, p)
            if n > args.max_n:
                skip(scene, param, p, 0, f"skipped: N > --max-n {args.max_n:g}")
            else:
                planned.append({"scene": scene, "param": param, "p": p, "N": n,
                                "tier": 0, "methods": methods})
    unselected = [m for m in METHODS if m not in methods]
    if unselected:
        for c in planned:
            skip(c["scene"], c["param"], c["p"], c["tier"],
                 "skipped: not selected (--methods)", unselected)
    return planned, skipped


def print_plan(planned: list[dict], skipped: list[dict], args) -> None:
    print(f"{len(planned)} configurations, {sum(len(c['methods']) for c in planned)} "
          f"jobs, in this order (est = rough H100 guess incl. compiles; "
          f"first worker start-up ~{GUESS_STARTUP_S:.0f} s more):")
    print(f"{'#':>3} {'tier':>4} {'scene':7s} {'param':>9s} {'p':>3} {'N':>10} "
          f"{'k~':>5} {'est s':>6} {'cum s':>6}")
    cum = GUESS_STARTUP_S
    for i, c in enumerate(planned):
        est = sum(guess_job_s(c["scene"], c["param"], c["p"], m, args) for m in c["methods"])
        mark = ""
        if cum > args.time_budget:  # it would start after the budget
            mark = "  (after --time-budget: would be skipped)"
        cum += est
        pname = SCENES[c["scene"]][0]
        print(f"{i + 1:>3} {c['tier']:>4} {c['scene']:7s} {pname + '=' + str(c['param']):>9s} "
              f"{c['p']:>3} {c['N']:>10,} {k_expected(c['scene'], c['param'], c['p']):>5.0f} "
              f"{est:>6.1f} {cum:>6.0f}{mark}")
    print(f"methods per configuration: {' '.join(planned[0]['methods']) if planned else '-'}")
    reasons: dict = {}
    for r in skipped:
        reasons.setdefault(r["failed"], set()).add((r["scene"], r["param"], r["p"]))
    for reason, cfgs in sorted(reasons.items()):
        names = ", ".join(f"{s[0]}{SCENES[s][0][0]}{a}p{p}" for s, a, p in sorted(cfgs))
        print(f"{reason}: {len(cfgs)} configurations ({names})")


# ---------------------------------------------------------------------------
# Worker side


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
    sets = [pos.astype(np.float32)]
    for _ in range(INPUT_SETS - 1):
        moved = pos + rng.normal(0.0, 1e-3 * cutoff, pos.shape)
        sets.append(np.clip(moved, 0.0, np.nextafter(box, 0.0)).astype(np.float32))
    return sets, float(cutoff), float(box)


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


def measure(fn, inputs, target_s: float, min_r: int, max_r: int, keep=None):
    """(median ms, timed calls, first output). One untimed call (compile,
    first build, lazy loads), then timed calls rotating over ``inputs``:
    the first one's time t sets their number,
    ``clamp(ceil(target_s / t), min_r, max_r)``. ``keep(out)`` sees every
    timed output."""
    import jax
    import numpy as np
    first = jax.block_until_ready(fn(inputs[0]))
    times: list[float] = []
    reps = max_r
    k = 0
    while len(times) < reps:
        k += 1
        x = inputs[k % len(inputs)]
        t = time.perf_counter()
        out = jax.block_until_ready(fn(x))
        times.append((time.perf_counter() - t) * 1e3)
        if len(times) == 1:
            reps = min(max(math.ceil(target_s * 1e3 / max(times[0], 1e-3)), min_r), max_r)
        if keep is not None:
            keep(out)
        del out
    return float(np.median(times)), reps, first


class SceneCache:
    """The current configuration's inputs on the device (methods of one
    configuration run back to back); switching configuration frees them."""

    def __init__(self):
        self.key = None
        self.value = None

    def get(self, scene: str, param: int, p: int):
        import jax
        import jax.numpy as jnp
        key = (scene, param, p)
        if key != self.key:
            self.key = self.value = None
            release_memory(clear_caches=True)
            sets, cutoff, box = make_scene(scene, param, p)
            inputs = [jnp.asarray(s) for s in sets]
            del sets
            jax.block_until_ready(inputs)
            self.key, self.value = key, (inputs, cutoff, box)
        return self.value

    def clear(self):
        self.key = self.value = None


def release_memory(clear_caches: bool = False) -> None:
    """Drop what jaxrt keeps between calls (kept BVHs, the last scene of the
    spheres / squares methods), then collect."""
    try:
        from jaxrt import backends
        from jaxrt.rt import ffi
        ffi.forget_trees()
        for inst in list(getattr(backends, "_INSTANCES", {}).values()):
            method = getattr(inst, "method", None)
            if method is not None and hasattr(method, "_scene"):
                method._scene = None
    except Exception:  # noqa: BLE001 - Warp absent: nothing kept
        pass
    gc.collect()
    if clear_caches:
        import jax
        jax.clear_caches()
        gc.collect()


def run_job(job: dict, cache: SceneCache) -> dict:
    import jax
    import jax.numpy as jnp
    from jax_md import partition, space

    scene, param, p, method = job["scene"], job["param"], job["p"], job["method"]
    target, lo, hi = job["target_s"], job["min_repeats"], job["max_repeats"]
    fault = job.get("inject")
    if fault == "crash":
        os.abort()  # as a segfault or a CUDA abort would
    elif fault == "hang":
        time.sleep(1e6)
    elif fault == "oom":
        raise RuntimeError("RESOURCE_EXHAUSTED: injected out of memory (--inject)")
    elif fault == "error":
        raise RuntimeError("injected error (--inject)")
    inputs, cutoff, box = cache.get(scene, param, p)
    n = inputs[0].shape[0]
    row = {"scene": scene, "param": param, "p": p, "N": n, "cutoff": cutoff,
           "method": method, "tier": job.get("tier")}
    disp, _ = space.free()
    if METHODS[method] is None:
        fns = partition.neighbor_list(disp, box, cutoff, dr_threshold=0.0,
                                      format=partition.Dense)
    else:
        import jaxrt
        fns = jaxrt.neighbor_list(disp, None, cutoff, dr_threshold=0.0,
                                  format=partition.Dense,
                                  backend=METHODS[method])

    # init: allocate (eager). The first (untimed) call's list is kept.
    row["init_ms"], row["init_reps"], nbrs = measure(
        fns.allocate, inputs, target, lo, hi)
    row["k_mean"] = round(float(jnp.mean(jnp.sum(nbrs.idx < n, axis=1))), 2)
    row["capacity"] = int(nbrs.idx.shape[1])

    sigma = 0.5 * cutoff

    @jax.jit
    def compute(x, nb):
        nb = fns.update(x, nb)
        return nb.did_buffer_overflow, lj_forces(x, nb.idx, sigma)

    search = jax.jit(lambda x, nb: fns.update(x, nb).idx)
    # Trace here, compile both programs at once (XLA releases the GIL).
    lowered = [compute.lower(inputs[0], nbrs)]
    if job.get("search", True):
        lowered.append(search.lower(inputs[0], nbrs))
    with ThreadPoolExecutor(len(lowered)) as pool:
        compiled = [f.result() for f in [pool.submit(lw.compile) for lw in lowered]]
    del lowered, compute, search

    flags = []
    row["compute_ms"], row["compute_reps"], _ = measure(
        lambda x: compiled[0](x, nbrs), inputs, target, lo, hi,
        keep=lambda out: flags.append(out[0]))
    row["overflow"] = bool(any(bool(f) for f in flags))
    del flags, _
    if len(compiled) > 1:
        if row["compute_ms"] <= job.get("search_limit_ms", float("inf")):
            row["search_ms"], row["search_reps"], _ = measure(
                lambda x: compiled[1](x, nbrs), inputs, target, lo, hi)
            del _
        else:
            row["search_reps"] = 0  # compute too slow: not worth the budget
    del compiled
    row["total_ms"] = row["init_ms"] + row["compute_ms"]
    return row


def is_oom(msg: str) -> bool:
    return any(s in msg for s in OOM_MARKERS)


def is_harmless(exc: BaseException, msg: str) -> bool:
    """An error raised by Python-level checks (bad argument, particles too
    close for the sphere method), after which the worker can go on; any
    other error (XLA / CUDA / Warp runtime) restarts the worker."""
    if "CUDA" in msg or "cuda" in msg or "illegal" in msg:
        return False
    return isinstance(exc, (ValueError, TypeError, KeyError, IndexError)) or \
        "ParticlesTooCloseError" in msg or "closer than" in msg


def worker_main(methods: list[str]) -> None:
    """Jobs as JSON lines on stdin; 'START' then 'ROW {json}' per job on
    stdout. Exits after a job failed with anything but out-of-memory."""
    t0 = time.time()
    proto = sys.stdout
    sys.stdout = sys.stderr  # library chatter must not mix with the protocol

    def say(msg: str) -> None:
        proto.write(msg + "\n")
        proto.flush()

    import jax
    import jax_md  # noqa: F401
    import jaxrt  # noqa: F401
    device = str(jax.devices()[0])
    try:  # load the Warp kernels now, not inside the first timed job
        import warp as wp
        wp.config.quiet = True
        from jaxrt import backends
        import jaxrt.rt  # noqa: F401 - registers the RT backends
        wdev = "cuda" if jax.default_backend() in ("gpu", "cuda") else "cpu"
        for name in ("bvh", "bvh-unsorted", "spheres", "squares"):
            backends.get(name)
        for mod in ("jaxrt.rt.aabb", "jaxrt.rt.spheres", "jaxrt.rt.squares",
                    "jaxrt.rt.epsilon"):
            wp.load_module(module=mod, device=wdev)
    except Exception as exc:  # noqa: BLE001 - RT jobs will fail and say why
        print(f"warp preload failed: {exc!r}", file=sys.stderr)
    # One tiny run per Warp method: compiles the kernel overloads actually
    # launched (Warp rebuilds a module for a new generic overload), so that
    # no timed job's warm-up pays a Warp module compile.
    tiny = SceneCache()
    for m in methods:
        if METHODS[m] is None or METHODS[m] == "cell":
            continue
        try:
            run_job({"scene": "uniform", "param": 2, "p": 4, "method": m, "tier": 0,
                     "target_s": 0.0, "min_repeats": 1, "max_repeats": 1,
                     "search": False}, tiny)
        except Exception as exc:  # noqa: BLE001 - the real job will say why
            print(f"warm-up of {m} failed: {exc!r}", file=sys.stderr)
    tiny.clear()
    release_memory(clear_caches=True)
    say("READY " + json.dumps({"device": device, "startup_s": time.time() - t0}))
    cache = SceneCache()
    for line in sys.stdin:
        if not line.strip():
            continue
        job = json.loads(line)
        say("START")
        fatal = None
        try:
            row = run_job(job, cache)
        except Exception as exc:  # noqa: BLE001 - recorded as a failed row
            traceback.print_exc(file=sys.stderr)
            msg = f"{type(exc).__name__}: {exc}".replace("\n", " ")
            if is_oom(msg):
                msg = "out of memory: " + msg
            elif not is_harmless(exc, msg):
                fatal = msg
            row = {k: job[k] for k in ("scene", "param", "p", "method", "tier")}
            row.update(N=n_of(job["param"], job["p"]), failed=msg[:300])
        say("ROW " + json.dumps(row))
        release_memory()
        if fatal:
            say("EXIT restarting after an error that may leave CUDA state broken")
            return
        if row.get("failed"):
            release_memory(clear_caches=True)


# ---------------------------------------------------------------------------
# Driver


def _reader(stream, q):
    for line in stream:
        q.put(line.rstrip("\n"))
    q.put(None)


class Worker:
    def __init__(self, err_path: Path, methods: list[str]):
        self.err_path = err_path
        self.err = open(err_path, "a")
        self.proc = subprocess.Popen(
            [sys.executable, __file__, "--worker", "--methods", *methods],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, stderr=self.err, text=True, bufsize=1)
        self.err_pos = 0
        self.q: queue.Queue = queue.Queue()
        threading.Thread(target=_reader, args=(self.proc.stdout, self.q),
                         daemon=True).start()
        self.alive = True

    def expect(self, prefix: str, timeout: float) -> str | None:
        """The next protocol line starting with ``prefix``; None on timeout,
        "" when the worker exited."""
        end = time.time() + timeout
        while True:
            try:
                line = self.q.get(timeout=max(0.05, end - time.time()))
            except queue.Empty:
                return None
            if line is None:
                self.alive = False
                self.proc.wait()
                return ""
            if line.startswith(prefix):
                return line
            print(f"    | {line}", flush=True)

    def send(self, job: dict) -> None:
        self.err.flush()
        self.err_pos = self.err_path.stat().st_size  # the job's stderr starts here
        self.proc.stdin.write(json.dumps(job) + "\n")
        self.proc.stdin.flush()

    def stderr_tail(self) -> str:
        """The worker's last stderr line that is not Warp's module chatter."""
        self.err.flush()
        with open(self.err_path, errors="replace") as f:
            f.seek(self.err_pos)
            text = f.read()
        lines = [ln for ln in text.splitlines()
                 if ln.strip() and not ln.startswith("Module ")]
        return lines[-1][:200] if lines else ""

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait()
        self.alive = False
        self.err.close()

    def close(self) -> None:
        try:
            self.proc.stdin.close()
            self.proc.wait(timeout=30)
        except Exception:  # noqa: BLE001
            pass
        self.kill()


def _fmt_ms(row: dict, key: str) -> str:
    v = row.get(key)
    return "        -" if v is None else f"{v:9.3f}"


def run_plan(planned: list[dict], args, t0: float, folder: Path, log: Path) -> list[dict]:
    deadline, hard = t0 + args.time_budget, t0 + args.hard_stop
    err_path = folder / "seed_rt_worker.err"
    err_path.write_text("")
    rows: list[dict] = []
    worker: Worker | None = None
    start_failures = 0

    def record(row: dict) -> None:
        rows.append(row)
        with open(log, "a") as f:
            f.write(json.dumps(row) + "\n")

    for ci, c in enumerate(planned):
        base = {"scene": c["scene"], "param": c["param"], "p": c["p"], "N": c["N"],
                "tier": c["tier"]}
        pname = SCENES[c["scene"]][0]
        now = time.time()
        if now > deadline or now >= hard or start_failures >= 2:
            why = ("skipped: workers failed to start" if start_failures >= 2 else
                   f"skipped: --time-budget {args.time_budget:g}s reached"
                   if now < hard else f"skipped: --hard-stop {args.hard_stop:g}s reached")
            for m in c["methods"]:
                rows.append({**base, "method": m, "failed": why})
            continue
        print(f"[{now - t0:5.0f}s] config {ci + 1}/{len(planned)} tier {c['tier']}: "
              f"{c['scene']} {pname}={c['param']} p={c['p']} N={c['N']:,}", flush=True)
        for m in c["methods"]:
            job = {**base, "method": m, "target_s": args.target_s,
                   "min_repeats": args.min_repeats, "max_repeats": args.max_repeats,
                   "search": args.search, "search_limit_ms": args.search_limit_ms}
            for spec in args.inject or ():
                kind, _, target = spec.partition("@")
                if target == f"{c['scene']}:{c['param']}:{c['p']}:{m}":
                    job["inject"] = kind
            if time.time() >= hard or start_failures >= 2:
                rows.append({**base, "method": m, "failed":
                             "skipped: workers failed to start" if start_failures >= 2
                             else f"skipped: --hard-stop {args.hard_stop:g}s reached"})
                continue
            if worker is None or not worker.alive or worker.proc.poll() is not None:
                if worker is not None:
                    worker.kill()
                worker = Worker(err_path, c["methods"])
                ready = worker.expect("READY", min(args.startup_timeout,
                                                   max(1.0, hard - time.time())))
                if not ready:
                    tail = worker.stderr_tail()
                    worker.kill()
                    worker = None
                    start_failures += 1
                    record({**base, "method": m, "failed":
                            f"worker failed to start: {tail}" if ready == "" else
                            "worker start-up timed out"})
                    print(f"    worker failed to start: {tail}", flush=True)
                    continue
                start_failures = 0
                info = json.loads(ready[len("READY "):])
                print(f"    worker ready on {info['device']} in {info['startup_s']:.1f} s",
                      flush=True)
            print(f"    {m:13s}", end=" ", flush=True)
            try:
                worker.send(job)
            except (BrokenPipeError, OSError):
                worker.kill()  # it had exited after the previous job
                worker = None
                rows.append({**base, "method": m,
                             "failed": "skipped: worker gone before the job (rerun)"})
                print("worker gone", flush=True)
                continue
            started = worker.expect("START", 60)
            limit = min(args.timeout, max(0.1, hard - time.time()))
            line = worker.expect("ROW ", limit) if started else started
            if line:
                row = json.loads(line[4:])
                record(row)
                if row.get("failed"):
                    print(f"FAILED {row['failed'][:110]}", flush=True)
                    if worker.expect("EXIT", 0.5) is not None:
                        worker.close()  # it exits after such a failure
                        worker = None
                else:
                    print(f"init {_fmt_ms(row, 'init_ms')} ms (x{row['init_reps']:<2d})  "
                          f"compute {_fmt_ms(row, 'compute_ms')} ms (x{row['compute_reps']:<2d})"
                          f"  search {_fmt_ms(row, 'search_ms')} ms  k {row['k_mean']}"
                          + ("  OVERFLOW" if row.get("overflow") else ""), flush=True)
                continue
            if line is None:  # timed out
                worker.kill()
                reason = (f"killed at --hard-stop {args.hard_stop:g}s" if time.time() >= hard
                          else f"timeout {args.timeout:g}s")
            else:
                tail = worker.stderr_tail()
                rc = worker.proc.returncode
                how = f"rc {rc}"
                if rc is not None and rc < 0:
                    try:
                        how = signal.Signals(-rc).name
                    except ValueError:
                        pass
                    if -rc == signal.SIGKILL:
                        how += ", host out of memory?"
                reason = f"crashed ({how})" + (f": {tail}" if tail else "")
            record({**base, "method": m, "failed": reason})
            print(f"FAILED {reason[:110]}", flush=True)
    if worker is not None:
        worker.close()
    return rows


# ---------------------------------------------------------------------------
# Results: speed-ups, headline, plots


def _ok(row) -> bool:
    v = row.get("total_ms")
    return v not in (None, "") and not row.get("failed") and math.isfinite(float(v))


# Prefix of a row's ``failed`` text -> its label on the plots, in order;
# out-of-memory texts (any prefix, `is_oom`) rank after the skips.
_SKIPS = (("skipped: not selected", "n/s"), ("skipped: N > --max-n", "N>max"),
          ("skipped", "skip"))
_FAILURES = (("timeout", "timeout"), ("killed", "killed"), ("crashed", "crash"))


def short_reason(row) -> str:
    f = str(row.get("failed") or "")
    if not f:
        return ""
    label = next((lb for prefix, lb in _SKIPS if f.startswith(prefix)), None)
    if label is None and (f.startswith("out of memory") or is_oom(f)):
        label = "OOM"
    if label is None:
        label = next((lb for prefix, lb in _FAILURES if f.startswith(prefix)),
                     "fail")
    return label


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


def _attempted(rows: list[dict]) -> list[dict]:
    """Rows of the configurations that were planned (run or cut by the
    budget), not those never selected."""
    never = ("skipped: not selected", "skipped: N > --max-n")
    keep = {(r["scene"], int(r["param"]), int(r["p"])) for r in rows
            if not str(r.get("failed") or "").startswith(never)}
    return [r for r in rows if (r["scene"], int(r["param"]), int(r["p"])) in keep
            and not str(r.get("failed") or "").startswith("skipped: not selected")]


def headline_markdown(rows: list[dict]) -> str:
    """Per scene and configuration: total ms (init + compute) per method,
    the fastest, and its speed-up over jax-md and over cell."""
    rows = _attempted(rows)
    methods = [m for m in METHODS if any(r["method"] == m for r in rows)]
    lines = []
    for scene in SCENES:
        srows = [r for r in rows if r["scene"] == scene]
        if not srows:
            continue
        pname = SCENES[scene][0]
        sym = {"beta": "β", "alpha": "α"}[pname]
        lines.append(f"\n**{scene}** — total ms = init + compute (median); "
                     "fastest in bold; ×jax-md = jax-md total / fastest total\n")
        lines.append(f"| {sym} | p | N | " + " | ".join(methods) +
                     " | fastest | ×jax-md | ×cell |")
        lines.append("|" + "---|" * (len(methods) + 6))
        configs = sorted({(int(r["param"]), int(r["p"])) for r in srows})
        for param, p in configs:
            group = {r["method"]: r for r in srows
                     if int(r["param"]) == param and int(r["p"]) == p}
            good = [r for r in group.values() if _ok(r)]
            best = min(good, key=lambda r: float(r["total_ms"])) if good else None
            cells = []
            for m in methods:
                r = group.get(m)
                if r is None:
                    cells.append("–")
                elif _ok(r):
                    txt = f"{float(r['total_ms']):.3g}"
                    cells.append(f"**{txt}**" if r is best else txt)
                else:
                    cells.append(short_reason(r))

            def ratio(name):
                r = group.get(name)
                if best is None or r is None:
                    return "–"
                if not _ok(r):
                    return short_reason(r)
                return f"{float(r['total_ms']) / float(best['total_ms']):.2f}"
            lines.append(f"| {param} | {p} | {n_of(param, p):,} | " + " | ".join(cells) +
                         f" | {best['method'] if best else '–'} | {ratio('jax-md')} | "
                         f"{ratio('cell')} |")
    lines.append("\nOOM = out of memory; skip = cut by the time budget; "
                 "timeout / crash / fail: see the CSV's `failed` column.")
    return "\n".join(lines)


def _lighten(color: str, amount: float = 0.55):
    from matplotlib.colors import to_rgb
    r, g, b = to_rgb(color)
    return (r + (1 - r) * amount, g + (1 - g) * amount, b + (1 - b) * amount)


def plot(rows: list[dict], folder: Path) -> list[Path]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    rows = _attempted(rows)
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
            tops, marks = [], []
            for mi, m in enumerate(methods):
                for pi, p in enumerate(ps):
                    r = next((r for r in prow if r["method"] == m and int(r["p"]) == p), None)
                    x = pi + (mi - (len(methods) - 1) / 2) * width
                    if r is None:
                        continue
                    if not _ok(r):
                        marks.append((x, short_reason(r), m))
                        continue
                    init, comp = float(r["init_ms"]), float(r["compute_ms"])
                    ax.bar(x, init, width, color=_lighten(COLORS[m]), edgecolor="none")
                    ax.bar(x, comp, width, bottom=init, color=COLORS[m], edgecolor="none")
                    sp = r.get("speedup_vs_jaxmd")
                    if sp not in (None, "") and m != "jax-md":
                        tops.append((x, init + comp, f"{float(sp):.2g}"))
            ax.set_xlim(-0.5, len(ps) - 0.5)
            lows = [float(r["init_ms"]) for r in prow if _ok(r) and float(r["init_ms"]) > 0]
            if scene == "sphere":
                ax.set_yscale("log")
                if lows:  # show the init part of the lowest bar too
                    ax.set_ylim(bottom=0.5 * min(lows))
            if not any(_ok(r) for r in prow):
                ax.set_ylim(1, 10) if scene == "sphere" else ax.set_ylim(0, 1)
            ymax = ax.get_ylim()[1]
            for x, top, txt in tops:
                ax.text(x, top, txt, ha="center", va="bottom", fontsize=6, rotation=90)
            for x, txt, m in marks:
                ax.text(x, 0.02, txt, rotation=90, ha="center", va="bottom", fontsize=6,
                        color=COLORS[m] if txt == "skip" else "red",
                        transform=ax.get_xaxis_transform())
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
                     "(update + forces)\nOOM = out of memory, skip = cut by the time "
                     "budget, timeout / crash / fail = see CSV", fontsize=8)
        path = folder / fname
        fig.savefig(path, dpi=130)
        plt.close(fig)
        paths.append(path)
    return paths


FLOAT_COLS = ("init_ms", "compute_ms", "search_ms", "total_ms", "speedup_vs_jaxmd",
              "speedup_vs_cell", "k_mean", "cutoff")


def read_csv(path: str) -> list[dict]:
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    for r in rows:
        for k in FLOAT_COLS:
            if r.get(k) not in (None, ""):
                r[k] = float(r[k])
    return rows


def report(rows: list[dict], folder: Path) -> None:
    from _provenance import print_table
    for p in plot(rows, folder):
        print("wrote", p)
    shown = _attempted(rows)
    print_table(shown, ["scene", "param", "p", "N", "method", "init_ms", "compute_ms",
                        "search_ms", "speedup_vs_jaxmd", "k_mean", "init_reps",
                        "compute_reps", "overflow", "failed"])
    md = headline_markdown(rows)
    (folder / "seed_rt_headline.md").write_text(md + "\n")
    print("\nHeadline (also in", folder / "seed_rt_headline.md", "):")
    print(md)


# ---------------------------------------------------------------------------


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--plan", action="store_true",
                        help="print the job order with N and an H100 time guess; run nothing")
    parser.add_argument("--small", action="store_true",
                        help="CPU smoke: beta in {4,8}, alpha in {8,16}, p in {1,4}")
    parser.add_argument("--max-n", type=float, default=2e7)
    parser.add_argument("--methods", nargs="+", default=list(METHODS),
                        choices=list(METHODS))
    parser.add_argument("--scenes", nargs="+", default=list(SCENES),
                        choices=list(SCENES))
    parser.add_argument("--params", type=int, nargs="+", default=None,
                        help="only these beta/alpha values")
    parser.add_argument("--p", type=int, nargs="+", default=None,
                        help="only these particles-per-cell values")
    parser.add_argument("--tiers", type=int, nargs="+", default=[1, 2, 3, 4],
                        help="priority tiers to plan (module docstring)")
    parser.add_argument("--configs", nargs="+", default=None, metavar="SCENE:PARAM:P",
                        help="run exactly these configurations, in this order")
    parser.add_argument("--target-s", type=float, default=0.5,
                        help="aim for this much timed wall time per measurement")
    parser.add_argument("--min-repeats", type=int, default=3)
    parser.add_argument("--max-repeats", type=int, default=10)
    parser.add_argument("--no-search", dest="search", action="store_false",
                        help="skip the search-only measurement (one compile less per job)")
    parser.add_argument("--search-limit-ms", type=float, default=300.0,
                        help="skip the search-only measurement when compute_ms is above")
    parser.add_argument("--time-budget", type=float, default=float("inf"),
                        help="seconds; no new configuration starts after it")
    parser.add_argument("--hard-stop", type=float, default=float("inf"),
                        help="seconds; kill the running job then, skip the rest")
    parser.add_argument("--timeout", type=float, default=300,
                        help="seconds per (configuration, method) job")
    parser.add_argument("--startup-timeout", type=float, default=300,
                        help="seconds for a worker's imports and Warp kernel loads")
    parser.add_argument("--inject", nargs="+", default=None,
                        metavar="KIND@SCENE:PARAM:P:METHOD",
                        help="testing aid: make that job crash (abort), hang, "
                             "raise an error or a fake out-of-memory; KIND in "
                             "crash hang error oom")
    parser.add_argument("--out", default=None)
    parser.add_argument("--plot-only", metavar="CSV", default=None)
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)

    if args.worker:
        worker_main(args.methods)
        return

    if args.plot_only:
        rows = read_csv(args.plot_only)
        folder = Path(args.out) if args.out else Path(args.plot_only).parent
        folder.mkdir(parents=True, exist_ok=True)
        report(rows, folder)
        return

    t0 = time.time()
    planned, skipped = build_plan(args)
    print_plan(planned, skipped, args)
    if args.plan:
        return
    folder_hint = Path(args.out or os.environ.get("OUT") or "/tmp")
    folder_hint.mkdir(parents=True, exist_ok=True)
    log = folder_hint / "seed_rt_study.partial.jsonl"
    log.unlink(missing_ok=True)
    print(f"rows also appended to {log} as they finish", flush=True)
    rows = run_plan(planned, args, t0, folder_hint, log) + skipped
    add_speedups(rows)

    from _provenance import write_csv
    cols = ["scene", "param", "p", "N", "tier", "cutoff", "method", "init_ms",
            "compute_ms", "search_ms", "total_ms", "speedup_vs_jaxmd", "speedup_vs_cell",
            "k_mean", "capacity", "overflow", "init_reps", "compute_reps", "search_reps",
            "failed"]
    order = {(s, a, p): i for i, (s, a, p) in enumerate(universe(args.small))}
    rows.sort(key=lambda r: (order.get((r["scene"], int(r["param"]), int(r["p"])), 1 << 30),
                             list(METHODS).index(r["method"])))
    rows = [{c: r.get(c) for c in cols} for r in rows]
    for r in rows:
        r["param_name"] = SCENES[r["scene"]][0]
        r["target_s"] = args.target_s
    path = write_csv(rows, "seed_rt_study.csv", args.out)
    print("wrote", path)
    report(read_csv(str(path)), path.parent)
    print(f"elapsed {time.time() - t0:.0f} s")


if __name__ == "__main__":
    main()
