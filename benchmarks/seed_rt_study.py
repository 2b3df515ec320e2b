"""Seed 001 §5 reproduced: ray-tracing-style neighbour search against grids.

The entry point of `benchmarks/seed_rt` (its docstring, printed by
``--help``, describes scenes, methods, columns, plan and isolation):
`seed_rt.plan` chooses the configurations, `seed_rt.worker` measures one
(configuration, method) job in a `_harness` worker, `seed_rt.report` writes
the headline table and the plots.

    python benchmarks/seed_rt_study.py --plan                         # dry run
    python benchmarks/seed_rt_study.py --small --out /tmp/seedstudy   # CPU smoke
    python benchmarks/seed_rt_study.py --part 1/6 --time-budget 450 \\
        --hard-stop 520 --timeout 240 --out DIR/part1                 # GPU, per part
    python benchmarks/seed_rt_study.py --plot-only DIR/part*/seed_rt_study.csv --out DIR
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

if __package__:  # run as -m, or imported: the package's modules
    from benchmarks import _harness
    from benchmarks import seed_rt
    from benchmarks.seed_rt import plan, report
else:  # run as a file: its folder is sys.path[0]
    import _harness
    import seed_rt
    from seed_rt import plan, report

COLUMNS = ["scene", "param", "p", "N", "tier", "cutoff", "method", "init_ms",
           "compute_ms", "search_ms", "total_ms", "build_ms", "query_ms",
           "interaction_ms", "paper_init_ms", "paper_compute_ms",
           "speedup_vs_jaxmd", "speedup_vs_cell", "k_mean", "pairs",
           "energy_sum", "capacity", "overflow", "init_reps", "compute_reps",
           "search_reps", "build_reps", "query_reps", "interaction_reps"]


def parse_args(argv=None) -> argparse.Namespace:
    parser = _harness.make_parser(seed_rt.__doc__)
    parser.add_argument("--plan", action="store_true",
                        help="print the job order with N and an H100 time guess; run nothing")
    parser.add_argument("--small", action="store_true",
                        help="CPU smoke: beta in {4,8}, alpha in {8,16}, p in {1,4}")
    parser.add_argument("--max-n", type=float, default=7e7,
                        help="skip configurations with more particles (default: "
                             "none of the seed's 60 is skipped)")
    parser.add_argument("--part", type=plan.parse_part, default=None, metavar="K[/M]",
                        help="run only part K of the plan cut by --part-budget "
                             "(--plan lists the parts; M, if given, must match)")
    parser.add_argument("--part-budget", type=float, default=480.0,
                        help="guessed seconds per part, start-up included (--plan, --part)")
    parser.add_argument("--no-split", dest="split", action="store_false",
                        help="skip the Warp build-only / query-only timings "
                             "(build_ms, query_ms)")
    parser.add_argument("--methods", nargs="+", default=list(plan.METHODS),
                        choices=list(plan.METHODS))
    parser.add_argument("--scenes", nargs="+", default=list(plan.SCENES),
                        choices=list(plan.SCENES))
    parser.add_argument("--params", type=int, nargs="+", default=None,
                        help="only these beta/alpha values")
    parser.add_argument("--p", type=int, nargs="+", default=None,
                        help="only these particles-per-cell values")
    parser.add_argument("--tiers", type=int, nargs="+", default=[1, 2, 3, 4],
                        help="priority tiers to plan (seed_rt's docstring)")
    parser.add_argument("--configs", nargs="+", default=None, metavar="SCENE:PARAM:P",
                        help="run exactly these configurations, in this order")
    parser.add_argument("--target-s", type=float, default=0.5,
                        help="aim for this much timed wall time per measurement")
    parser.add_argument("--min-repeats", type=int, default=3,
                        help="timed calls per measurement at least (one from "
                             "--large-n particles up)")
    parser.add_argument("--large-n", type=float, default=4e6,
                        help="from this many particles, one timed call per "
                             "measurement (calls take seconds there)")
    parser.add_argument("--heavy-s", type=float, default=60.0,
                        help="jobs guessed longer run last, each in a part of "
                             "its own (--plan marks them)")
    parser.add_argument("--max-repeats", type=int, default=10)
    parser.add_argument("--no-search", dest="search", action="store_false",
                        help="skip the search-only measurement (one compile less per job)")
    parser.add_argument("--search-limit-ms", type=float, default=300.0,
                        help="skip the search-only measurement when compute_ms is above")
    parser.add_argument("--time-budget", "--budget", type=float,
                        default=float("inf"),
                        help="seconds; no new configuration starts after it")
    parser.add_argument("--hard-stop", type=float, default=float("inf"),
                        help="seconds; kill the running job then, skip the rest")
    parser.add_argument("--timeout", type=float, default=300,
                        help="seconds per (configuration, method) job at least; "
                             f"a job guessed longer gets {plan.TIMEOUT_FACTOR:g}x "
                             "its guess (--plan's tmo column)")
    parser.add_argument("--startup-timeout", type=float, default=300,
                        help="seconds for a worker's imports and device start")
    parser.add_argument("--inject", nargs="+", default=None,
                        metavar="KIND@SCENE:PARAM:P:METHOD",
                        help="testing aid: make that job crash (abort), hang, "
                             "raise an error or a fake out-of-memory; KIND in "
                             "crash hang error oom")
    parser.add_argument("--out", default=None,
                        help="folder (default benchmarks/results/<device>/seed_rt/)")
    parser.add_argument("--plot-only", metavar="CSV", nargs="+", default=None,
                        help="report from these CSVs (the parts' files are merged: "
                             "per row, a measured one wins over a skipped one)")
    return parser.parse_args(argv)


def jobs_of(planned: list[dict], args) -> list[dict]:
    """One job per (configuration, method); a configuration is a group
    (never split by the budget); the configurations below ``--large-n``
    share a worker, each larger one has its own."""
    faults = {}
    for spec in args.inject or ():
        kind, _, target = spec.partition("@")
        faults[target] = kind
    jobs = []
    for c in planned:
        for m in c["methods"]:
            key = f"{c['scene']}:{c['param']}:{c['p']}"
            job = {"scene": c["scene"], "param": c["param"], "p": c["p"],
                   "N": c["N"], "tier": c["tier"], "method": m,
                   "target_s": args.target_s,
                   "min_repeats": plan.min_repeats(c["N"], args),
                   "max_repeats": args.max_repeats, "search": args.search,
                   "search_limit_ms": args.search_limit_ms, "split": args.split,
                   "_group": key,
                   # Configurations below --large-n share one worker (its
                   # imports, Warp's start and the device context paid
                   # once); each large one gets a fresh worker, so that
                   # it starts with the device's memory free.
                   "_worker": "shared" if c["N"] < args.large_n else key,
                   "_timeout": plan.timeout_s(c["scene"], c["param"], c["p"],
                                              m, args)}
            if f"{key}:{m}" in faults:
                job["_inject"] = faults[f"{key}:{m}"]
            jobs.append(job)
    return jobs


def main(argv=None) -> None:
    args = parse_args(argv)
    if args.plot_only:
        rows = merge_rows([_harness.read_csv(p) for p in args.plot_only])
        folder = Path(args.out) if args.out else Path(args.plot_only[0]).parent
        folder.mkdir(parents=True, exist_ok=True)
        if len(args.plot_only) > 1:
            _harness.write_csv(rows, str(folder / "seed_rt_study.csv"))
            print("merged", len(args.plot_only), "CSVs into",
                  folder / "seed_rt_study.csv")
        report.report(rows, folder)
        return

    t0 = time.monotonic()
    planned, skipped = plan.build_plan(args)
    if args.plan or args.part is None:
        plan.print_plan(planned, skipped, args)
    if args.plan:
        return
    if args.part is not None:
        planned, skipped = plan.select_part(planned, skipped, args)
        print(f"part {args.part[0]} of the plan (--plan lists all parts):")
        plan.print_plan(planned, skipped, argparse.Namespace(
            **{**vars(args), "part_budget": 0}), first_part=args.part[0])
    order = {(s, a, p): i for i, (s, a, p) in enumerate(plan.universe(args.small))}

    def finish(rows: list[dict]) -> None:
        """Add the plan's skipped rows (with the run's provenance), the
        speed-ups, and sort as the seed's grid."""
        prov = next(({k: r[k] for k in _harness.PROVENANCE if k in r}
                     for r in rows), _harness.host_provenance())
        for r in skipped:
            rows.append({**{c: None for c in _harness.ROW_COLUMNS},
                         "dtype": "float32", **r, **prov})
        report.add_speedups(rows)
        rows.sort(key=lambda r: (order.get((r["scene"], int(r["param"]), int(r["p"])),
                                           1 << 30),
                                 list(plan.METHODS).index(r["method"])))
        for r in rows:
            r["param_name"] = plan.SCENES[r["scene"]][0]

    _, path = _harness.run_jobs(
        "seed_rt.worker:run_job", jobs_of(planned, args),
        out=args.out and str(Path(args.out) / "seed_rt_study.csv"),
        name="seed_rt/seed_rt_study.csv", columns=COLUMNS,
        timeout=args.timeout, budget=args.time_budget,
        hard_stop=args.hard_stop, reuse_worker=True,
        startup_timeout=args.startup_timeout, finish=finish, t0=t0,
        table=False)
    report.report(_harness.read_csv(str(path)), path.parent)
    print(f"elapsed {time.monotonic() - t0:.0f} s")


# Reasons a part skipped a row that say nothing of the row itself.
_NOT_RUN_HERE = ("not selected", "not in --part", "time budget")


def merge_rows(tables: list[list[dict]]) -> list[dict]:
    """One row per (scene, param, p, method): the measured (or failed) row
    of whichever part ran it, else one skipped for a reason of its own
    (a list past what jaxrt indexes), else one that a part did not select
    or reach; in the first table's order, then the rest."""
    def rank(r: dict) -> int:
        if r.get("status") != "skipped":
            return 2
        why = r.get("failed") or ""
        return 0 if any(s in why for s in _NOT_RUN_HERE) else 1

    best: dict = {}
    for rows in tables:
        for r in rows:
            key = (r["scene"], str(r["param"]), str(r["p"]), r["method"])
            if key not in best or rank(r) > rank(best[key]):
                best[key] = r
    rows = list(best.values())
    order = {(s, a, p): i for i, (s, a, p) in enumerate(plan.universe(False))}
    rows.sort(key=lambda r: (order.get((r["scene"], int(r["param"]), int(r["p"])),
                                       1 << 30),
                             list(plan.METHODS).index(r["method"])
                             if r["method"] in plan.METHODS else 99))
    return rows


if __name__ == "__main__":
    main()
