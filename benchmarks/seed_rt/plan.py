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
    # Seed 001's fused mode (jaxrt.rt.FusedEnergy): the energy summed during
    # the traversal, no list. FUSED[name] is the list method it fuses.
    "aabb-unsorted-fused": "bvh[unsorted]",
    "aabb-sorted-fused": "bvh",
    "spheres-fused": "spheres",
    "squares-fused": "squares",
}
FUSED = {m: m.removesuffix("-fused") for m in METHODS if m.endswith("-fused")}
# Methods with a Warp build / query split (build_ms, query_ms columns).
WARP_METHODS = ("aabb-unsorted", "aabb-sorted", "spheres", "squares", *FUSED)
# Order inside a configuration: the fused methods first (no list: least
# memory), then the Warp list methods, the pure-JAX ones last (JAX's pool
# never shrinks with preallocation off, so a huge jax-md attempt goes last;
# Warp allocates outside JAX's pool).
RUN_ORDER = ["aabb-sorted-fused", "aabb-unsorted-fused", "squares-fused",
             "spheres-fused", "aabb-sorted", "aabb-unsorted", "squares", "spheres",
             "cell", "jax-md"]
# Dense-list entries each list method can index (jaxrt.backends.rt.ffi.MAX_LIST_ENTRIES
# for the Warp kernels' 32-bit byte offsets, int32 indices otherwise): a
# configuration whose mean row alone (times capacity_multiplier 1.25)
# passes it is refused at allocate, so the plan skips it and says why.
LIST_LIMIT = {"aabb-unsorted": 2 ** 29 - 1, "aabb-sorted": 2 ** 29 - 1,
              "spheres": 2 ** 29 - 1, "squares": 2 ** 29 - 1,
              "cell": 2 ** 31 - 1, "jax-md": 2 ** 31 - 1}
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
    # jaxrt.sim.distributions.sphere_surface_cutoff, without importing jaxrt (and JAX,
    # Warp) into the driver just for the plan
    c = math.acos(1.0 - 2.0 * 9.0 * p / n_of(param, p))
    return float(int((2 + 2 * c) / c)) ** 3


# A rough guess per call, in ms: (fixed, per neighbour pair) for the
# compute step. List methods: fitted by eye to H100 runs (RESULTS.md: bvh
# 13.3 ms and jax-md 21 ms at 10⁶ uniform k = 65; cell 28.7 ms; unsorted
# 3.5x sorted; allocate 28-46 ms for the Warp methods); spheres/squares
# are guesses. Fused: the H200's sphere α = 128, p = 32 (N = 67M, k = 288,
# 1.9e10 pairs; results/h200/seed_rt_study/part1_65309c3): aabb-sorted
# 1.21 s and aabb-unsorted 5.24 s per call; spheres timed out at 150 s
# with 8 calls to make (> 19 s a call, > 1e-6 ms a pair: guessed 1.5x
# that); squares: 0.7 of its list's rays. Only for --plan, the parts and
# the per-job timeouts.
_GUESS = {"aabb-sorted": (1.0, 2e-7), "aabb-unsorted": (1.0, 6e-7),
          "spheres": (1.5, 1e-6), "squares": (1.5, 4e-7),
          "cell": (2.0, 4e-7), "jax-md": (0.15, 3e-7),
          "aabb-sorted-fused": (1.0, 6.5e-8),
          "aabb-unsorted-fused": (1.0, 2.8e-7),
          "spheres-fused": (1.5, 1.5e-6),
          "squares-fused": (1.5, 2.8e-7)}
# compiles etc. per job (partial run: ~2.4 s per job on average, with a
# cache clear per job; on CPU the cell list compiles ~3x longer than the
# rest); a fresh worker per configuration adds GUESS_WORKER_S (from
# --large-n particles up; below, the configurations share one worker and
# pay GUESS_SHARED_S each: on the 2-core CPU, --small took 289 s with a
# worker per configuration and 186 s with one shared, the same rows), and
# its scene (made on the host: three jittered sets, then copied to the
# device) GUESS_SCENE_S per particle: the H200's part 1 spent ~50 s of
# its 257 s on neither start-up nor the 67M configuration's three jobs.
GUESS_WORKER_S = 8.0
GUESS_SHARED_S = 1.0
GUESS_SCENE_S = 4e-7
_GUESS_JOB_OVERHEAD_S = {"cell": 4.0, "jax-md": 2.0}
GUESS_STARTUP_S = 60.0       # first worker: imports, Warp kernel compiles
# A job's timeout: this many times its guess, and at least --timeout.
TIMEOUT_FACTOR = 3.0


def config_overhead_s(n: int, large_n: float) -> float:
    """Guessed seconds a configuration costs besides its jobs: a fresh
    worker from ``large_n`` particles up (below, its share of a shared
    one), and the scene."""
    worker = GUESS_WORKER_S if n >= large_n else GUESS_SHARED_S
    return worker + GUESS_SCENE_S * n


def min_repeats(n: int, args) -> int:
    """Timed calls per measurement at least: ``--min-repeats``, but one
    from ``--large-n`` particles up, where a call takes seconds and
    repeats barely differ (H200, 67M: 1209.8-1210.0 ms over three) while
    three of each of a job's measurements cost minutes of a part."""
    return 1 if n >= args.large_n else args.min_repeats


def list_entries(scene: str, param: int, p: int) -> int:
    """Dense-list entries at the mean row, N * ceil(1.25 k) (a lower bound
    of what allocate asks for)."""
    return n_of(param, p) * math.ceil(1.25 * k_expected(scene, param, p))


def guess_job_s(scene: str, param: int, p: int, method: str, args) -> float:
    n = n_of(param, p)
    pairs = n * k_expected(scene, param, p)
    fixed, per_pair = _GUESS[method]
    compute = fixed + per_pair * pairs
    build = 0.5 + 1e-6 * n * (4 if method.startswith("squares") else 1)
    if method == "jax-md":
        compute += 1.5e-7 * scene_cells(scene, param, p)
        init = 15.0 + compute
    elif method == "cell":
        init = 10.0 + 1.5 * compute
    else:
        init = 35.0 + 2.0 * compute
    total = _GUESS_JOB_OVERHEAD_S.get(method, 1.3)
    # A fused method's init is its build-only time (seed_rt's docstring),
    # measured by the split below.
    steps = [compute] if method in FUSED else [init, compute]
    if args.search and compute <= args.search_limit_ms and method not in FUSED:
        steps.append(0.85 * compute)
    if method not in FUSED:
        steps.append(0.3 + 1e-7 * pairs)  # interaction_ms: the JAX sum alone
    if method in WARP_METHODS and getattr(args, "split", True):
        steps += [build, compute - build if method in FUSED else 0.85 * compute]
    least = min_repeats(n, args)
    for t_ms in steps:
        t = t_ms / 1e3
        reps = min(max(math.ceil(args.target_s / t), least), args.max_repeats)
        total += (1 + reps) * t
    return total


def timeout_s(scene: str, param: int, p: int, method: str, args) -> float:
    """A job's timeout: `TIMEOUT_FACTOR` times its guess, at least
    ``--timeout`` (so it grows with N and k where the guess does)."""
    return max(args.timeout,
               TIMEOUT_FACTOR * guess_job_s(scene, param, p, method, args))


def is_heavy(c: dict, method: str, args) -> bool:
    """A job guessed over ``--heavy-s``: it runs after all the others, in
    a part of its own (`build_plan`), so that it can take no other job's
    place in a part (the guesses are roughest there, and a timeout costs
    a part its time)."""
    return guess_job_s(c["scene"], c["param"], c["p"], method, args) > args.heavy_s


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
    # Jobs certain to be refused (or to break Warp's 32-bit offsets) are not
    # run; the CSV says why.
    for c in planned:
        doomed = {m: why for m in c["methods"]
                  if (why := refusal(c["scene"], c["param"], c["p"], m))}
        for m, why in doomed.items():
            skip(c["scene"], c["param"], c["p"], c["tier"], why, [m])
        c["methods"] = [m for m in c["methods"] if m not in doomed]
    planned = [c for c in planned if c["methods"]]
    if explicit is None:
        # Heavy jobs last, each its own entry (so its own part), largest first.
        heavy = [{**c, "methods": [m], "heavy": True} for c in planned
                 for m in c["methods"] if is_heavy(c, m, args)]
        heavy.sort(key=lambda c: -guess_job_s(c["scene"], c["param"], c["p"],
                                              c["methods"][0], args))
        light = [{**c, "methods": [m for m in c["methods"]
                                   if not is_heavy(c, m, args)]}
                 for c in planned]
        planned = [c for c in light if c["methods"]] + heavy
    return planned, skipped


# Warp arrays address bytes with 32-bit ints: an array of vec3 (12 bytes)
# must stay below 2**31 bytes.
WARP_VEC3_LIMIT = (2 ** 31 - 1) // 12


def refusal(scene: str, param: int, p: int, method: str) -> str | None:
    """Why ``method`` cannot run this configuration (a "skipped: ..."
    reason), or None."""
    n = n_of(param, p)
    base = FUSED.get(method, method)
    if base == "squares" and 4 * n > WARP_VEC3_LIMIT:
        return (f"skipped: 4N = {4 * n:,} triangle boxes pass Warp's 32-bit "
                f"byte offsets ({WARP_VEC3_LIMIT:,} vec3)")
    if method in LIST_LIMIT and list_entries(scene, param, p) > LIST_LIMIT[method]:
        limit = LIST_LIMIT[method]
        why = ("jaxrt refuses it at allocate" if method != "jax-md" else
               "int32 flat indices; try it with --configs")
        return (f"skipped: Dense list >= N*ceil(1.25k) entries, above "
                f"{'2**29' if limit < 2 ** 30 else '2**31'} ({why}); "
                f"the fused methods need no list")
    return None


def split_parts(planned: list[dict], args) -> list[list[dict]]:
    """The plan cut into consecutive parts, each guessed (`guess_job_s`,
    first-worker start-up included) under ``args.part_budget`` seconds; a
    configuration stays in one part unless it alone exceeds the budget,
    when its methods are spread over parts of their own (in order). Each
    entry is a configuration dict whose ``methods`` are those of the part."""
    budget = args.part_budget
    parts: list[list[dict]] = []
    current: list[dict] = []
    used = GUESS_STARTUP_S

    def close():
        nonlocal current, used
        if current:
            parts.append(current)
        current, used = [], GUESS_STARTUP_S

    for c in planned:
        est = {m: guess_job_s(c["scene"], c["param"], c["p"], m, args)
               for m in c["methods"]}
        overhead = config_overhead_s(c["N"], args.large_n)
        whole = overhead + sum(est.values())
        if c.get("heavy"):  # a part of its own (`is_heavy`)
            close()
            current.append(c)
            used += whole
            close()
            continue
        if used + whole <= budget:
            current.append(c)
            used += whole
            continue
        close()
        if used + whole <= budget:
            current.append(c)
            used += whole
            continue
        take: list[str] = []
        cost = overhead
        for m in c["methods"]:
            if take and used + cost + est[m] > budget:
                current.append({**c, "methods": take})
                close()
                take, cost = [], overhead
            take.append(m)
            cost += est[m]
        current.append({**c, "methods": take})
        used += cost
    close()
    return parts


def select_part(planned: list[dict], skipped: list[dict], args
                ) -> tuple[list[dict], list[dict]]:
    """``--part K``: the K-th part of `split_parts` (1-based); the other
    parts' jobs become skipped rows ("not in --part K/M")."""
    parts = split_parts(planned, args)
    k, m = args.part
    if m is not None and m != len(parts):
        raise SystemExit(f"--part {k}/{m}: the plan has {len(parts)} parts with "
                         f"--part-budget {args.part_budget:g} (see --plan); use "
                         f"--part K/{len(parts)} or the same other options as --plan.")
    if not 1 <= k <= len(parts):
        raise SystemExit(f"--part {k}: choose 1..{len(parts)} (see --plan).")
    chosen = parts[k - 1]
    keep = {(c["scene"], c["param"], c["p"], meth) for c in chosen for meth in c["methods"]}
    reason = f"skipped: not in --part {k}/{len(parts)}"
    skipped = list(skipped)
    for c in planned:
        for meth in c["methods"]:
            if (c["scene"], c["param"], c["p"], meth) not in keep:
                skipped.append({"scene": c["scene"], "param": c["param"], "p": c["p"],
                                "N": c["N"], "method": meth, "tier": c["tier"],
                                "status": "skipped", "failed": reason})
    return chosen, skipped


def parse_part(text: str) -> tuple[int, int | None]:
    """``K`` or ``K/M`` -> (K, M or None)."""
    try:
        k, _, m = text.partition("/")
        return int(k), (int(m) if m else None)
    except ValueError:
        raise SystemExit(f"--part {text!r}: give K or K/M (e.g. --part 3/12)")


def print_plan(planned: list[dict], skipped: list[dict], args,
               first_part: int = 1) -> None:
    """The job order, one line per configuration (or per piece of one that
    parts split), with its part (numbered from ``first_part``) when
    ``args.part_budget`` is set."""
    parts = split_parts(planned, args) if args.part_budget else [planned]
    n_configs = len({(c["scene"], c["param"], c["p"]) for c in planned})
    n_jobs = sum(len(c["methods"]) for c in planned)
    grid = len(universe(args.small))
    print(f"{grid} configurations in the seed's grid x {len(METHODS)} methods = "
          f"{grid * len(METHODS)} rows; planned: {n_configs} configurations, "
          f"{n_jobs} jobs, in this order (reps = timed calls per measurement "
          f"at least; est = rough H100/H200 guess incl. compiles and the scene; "
          f"tmo = the longest job timeout; a worker start-up "
          f"~{GUESS_STARTUP_S:.0f} s more per part):")
    print(f"{'part':>4} {'#':>3} {'tier':>4} {'scene':7s} {'param':>9s} {'p':>3} "
          f"{'N':>10} {'k~':>5} {'jobs':>4} {'reps':>4} {'est s':>6} "
          f"{'cum s':>6} {'tmo s':>6}")
    i = 0
    totals = []
    for k, part in enumerate(parts, first_part):
        cum = GUESS_STARTUP_S
        for c in part:
            est = config_overhead_s(c["N"], args.large_n) + sum(
                guess_job_s(c["scene"], c["param"], c["p"], m, args)
                for m in c["methods"])
            longest = max(timeout_s(c["scene"], c["param"], c["p"], m, args)
                          for m in c["methods"])
            mark = f"  (heavy: {c['methods'][0]})" if c.get("heavy") else ""
            if cum > args.time_budget:  # it would start after the budget
                mark += "  (after --time-budget: would be skipped)"
            cum += est
            i += 1
            pname = SCENES[c["scene"]][0]
            print(f"{k:>4} {i:>3} {c['tier']:>4} {c['scene']:7s} "
                  f"{pname + '=' + str(c['param']):>9s} {c['p']:>3} {c['N']:>10,} "
                  f"{k_expected(c['scene'], c['param'], c['p']):>5.0f} "
                  f"{len(c['methods']):>4} {min_repeats(c['N'], args):>4} "
                  f"{est:>6.1f} {cum:>6.0f} {longest:>6.0f}{mark}")
        totals.append(cum)
    print(f"methods: {' '.join(m for m in RUN_ORDER if m in args.methods)}")
    if args.part_budget:
        print(f"{len(parts)} parts under --part-budget {args.part_budget:g} s "
              f"(guessed): " + ", ".join(f"{k}: {t:.0f} s" for k, t in
                                         enumerate(totals, first_part))
              + f"; total {sum(totals):.0f} s")
    reasons: dict = {}
    for r in skipped:
        cfgs, methods = reasons.setdefault(r["failed"], (set(), set()))
        cfgs.add((r["scene"], r["param"], r["p"]))
        methods.add(r["method"])
    for reason, (cfgs, methods) in sorted(reasons.items()):
        names = ", ".join(f"{s[0]}{SCENES[s][0][0]}{a}p{p}" for s, a, p in sorted(cfgs))
        which = ("all methods" if len(methods) == len(METHODS)
                 else " ".join(m for m in METHODS if m in methods))
        print(f"{reason}: {len(cfgs)} configurations ({names}); {which}")
