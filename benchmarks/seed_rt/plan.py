"""The seed study's plan: which configurations (scene, β or α, p) run, in
which order, and a rough guess of their time (`benchmarks/seed_rt`'s
docstring gives the tiers). Nothing here imports JAX."""
from __future__ import annotations

import math

METHODS = {  # column name -> jaxrt backend label (None: jax-md itself)
    "aabb-unsorted": "bvh[unsorted]",
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


def n_of(param: int, p: int) -> int:
    return p * param ** 3


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
    # jaxrt.seed_distributions.sphere_surface_cutoff, without importing jaxrt (and JAX,
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
# cache clear per job; on CPU the cell list compiles ~3x longer than the
# rest); a fresh worker per configuration adds GUESS_WORKER_S
GUESS_WORKER_S = 8.0
_GUESS_JOB_OVERHEAD_S = {"cell": 4.0, "jax-md": 2.0}
GUESS_STARTUP_S = 60.0       # first worker: imports, Warp kernel compiles


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
                            "status": "skipped", "failed": reason})

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
        est = GUESS_WORKER_S + sum(guess_job_s(c["scene"], c["param"], c["p"], m, args)
                                   for m in c["methods"])
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
