"""Seed 003's Figure 8: the BVH maintenance policies over a run, per scene and radius kind.

RT-REF (Meneses et al. §4): each step rebuilds the neighbour list (the
``bvh`` backend with per-particle radii, no skin, so every step runs a BVH
update or rebuild plus a query; OrderedSparse, as the largest LN rows
would make a Dense list N x 20 000 wide and r = 160's Sparse list passes
Warp's 2**29 entries) and then the Lennard-Jones forces on it.
Three policies of `jaxrt.backends.rt.policy` run the same trajectory statistics:
``gradient`` (Eq. 8), ``avg`` and ``fixed`` (k = 200). Each step's cost is
what the policy weighs, measured by the tree with CUDA events on a GPU (the
host clock on a CPU): the update (refit or rebuild) plus the query.

Scenes (`jaxrt.sim.distributions`, §4.1): Lattice, Disordered, Cluster in a
periodic box of 1000³, radii r = 1, r = 160, U[1, 160] and LN(1, 2) clipped
to [1, 330] (clipping, not resampling: 31 % of the radii sit at 1; the
histogram is written next to the figure).

Dynamics (the paper gives none; every value is in the CSV): overdamped
Brownian motion, ``x += clip(mobility_dt · F, ±max_drift) + noise · ξ`` per
axis, ξ ~ N(0, 1), with LJ forces ε = 1, pair cut ``max(r_i, r_j)`` and
``sigma_ij = max(r_i, r_j) / 2.5`` (`jaxrt.energy.lennard_jones_radii`,
smooth switch from 0.8 of the cut). A lattice then oscillates about its
sites; a disordered or clustered system relaxes and spreads, which is what
makes refitted trees slow down. The refit safety rule of `jaxrt.backends.rt.policy`
(a particle drifted 0.2 of the largest radius from where the tree was
built: rebuild) binds every policy alike; it is why r = 1 scenes rebuild
often whatever the policy.

GPU time is short: each (scene, radius) runs its three policies for
``--steps`` steps or until ``--job-seconds`` of wall time, whichever comes
first; totals and ratios use the steps all three completed (``steps``).
Configurations whose list cannot be held (Cluster with large radii: about
N² pairs) fail at ``allocate`` with the reason, and are kept as such rows.

    python benchmarks/figure8.py                   # the H200 run (n = 140k)
    python benchmarks/figure8.py --quick           # CPU smoke: n = 3000, 60 steps
    python benchmarks/figure8.py --plot CSV        # redraw from a run
"""
from __future__ import annotations

import csv
import math
import os
import sys
from pathlib import Path

if __package__:  # run as -m, or imported: the package's modules
    from benchmarks import _harness
else:  # run as a file: its folder is sys.path[0]
    import _harness

SCENES = ("lattice", "disordered", "cluster")
RADII = ("r=160", "U[1,160]", "LN[1,330]", "r=1")  # largest first
POLICIES = ("gradient", "avg", "fixed")
DYNAMICS = dict(epsilon=1.0, sigma_per_cut=1 / 2.5, onset_fraction=0.8,
                mobility_dt=0.01, max_drift=0.1, noise=0.005, box=1000.0)
# The paper's headline ratios (§4.2, Fig 8): gradient against others.
PAPER = {("cluster", "r=160", "avg"): 1.87, ("cluster", "r=160", "fixed"): 10.8,
         ("cluster", "U[1,160]", "second best"): 3.21,
         ("cluster", "LN[1,330]", "second best"): 1.8}
PAPER_RANGE = "gradient 1.16-3.4x faster than the second-best policy"
COLUMNS = ["scene", "radii", "policy", "N", "k", "steps", "total_ms",
           "per_step_ms", "rebuilds", "refits", "reallocations", "wall_s"]


def _scene(scene: str, radii: str, n: int, seed: int):
    import numpy as np
    from jaxrt.sim import distributions as sd
    make = {"lattice": lambda: sd.lattice(n),
            "disordered": lambda: sd.disordered(n, seed),
            "cluster": lambda: sd.cluster(n, seed)}[scene]
    return make(), sd.radii(radii, n, seed + 1).astype(np.float64)


def run_row(job: dict) -> dict:
    """One policy on one scene: the per-step trace (written to
    ``job["trace"]``) and its summary row."""
    import time

    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax_md import partition, space

    import jaxrt
    from jaxrt.backends.rt import ffi

    d = job["dynamics"]
    position, radii = _scene(job["scene"], job["radii"], job["N"], job["seed"])
    side = d["box"]
    displacement, shift = space.periodic(side)
    fn = jaxrt.neighbor_list(
        displacement, side, float(radii.max()), 0.0, format=partition.OrderedSparse,
        backend=jaxrt.backends.Bvh(policy=job["policy"]), radii=radii)
    energy_fn = jaxrt.energy.lennard_jones_pair_neighbor_list(
        displacement, sigma=d["sigma_per_cut"] * 2.5, epsilon=d["epsilon"],
        r_onset=2.5 * d["onset_fraction"], r_cutoff=2.5,
        radii=jnp.asarray(radii, jnp.float32))
    R = jnp.asarray(position, jnp.float32)
    history = ffi.owner_of(fn).keep_history()
    nbrs = fn.allocate(R)

    @jax.jit
    def step(R, nbrs, key):
        nbrs = fn.update(R, nbrs)
        force = -jax.grad(energy_fn)(R, nbrs)
        key, sub = jax.random.split(key)
        drift = jnp.clip(d["mobility_dt"] * force, -d["max_drift"],
                         d["max_drift"])
        dx = drift + d["noise"] * jax.random.normal(sub, R.shape, R.dtype)
        return shift(R, dx), nbrs, key

    key = jax.random.PRNGKey(job["seed"])
    # k summed on the device: a float() per step would wait for each step.
    reallocations, done, k_sum = 0, 0, jnp.zeros((), jnp.float32)
    start = time.perf_counter()
    while done < job["steps"] and time.perf_counter() - start < job["seconds"]:
        R_next, new, key = step(R, nbrs, key)
        if bool(new.did_buffer_overflow):
            if int(new.error.code) & ~1:  # not a plain overflow: say why
                jaxrt.errors.check(new)
            nbrs = fn.allocate(R)
            reallocations += 1
            continue
        k_sum = k_sum + 2.0 * jnp.sum(new.idx[0] < R.shape[0]) / R.shape[0]
        R, nbrs = R_next, new
        done += 1
    jax.block_until_ready(R)
    wall = time.perf_counter() - start
    for tree in ffi.owner_of(fn).trees():
        tree.flush_history()
    # The first entry is allocate's build; then one per step (plus any
    # reallocation's build, marked).
    trace = [(a, 1e3 * (u if math.isfinite(u) else 0.0),
              1e3 * (q if math.isfinite(q) else 0.0)) for a, u, q in history]
    with open(job["trace"], "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["call", "action", "update_ms", "query_ms"])
        for c, (a, u, q) in enumerate(trace):
            w.writerow([c, a, f"{u:.5f}", f"{q:.5f}"])
    steps = trace[1:1 + done]
    return {**{k: v for k, v in job.items() if not k.startswith("_")
               and k not in ("dynamics", "seconds")},
            "steps": done, "k": round(float(k_sum) / max(done, 1), 2),
            "total_ms": sum(u + q for _, u, q in steps),
            "per_step_ms": sum(u + q for _, u, q in steps) / max(len(steps), 1),
            "rebuilds": sum(a != "refit" for a, _, _ in steps),
            "refits": sum(a == "refit" for a, _, _ in steps),
            "reallocations": reallocations, "wall_s": round(wall, 2),
            **{f"dyn_{k}": v for k, v in d.items()},
            "radius_rule": "LN clipped to [1, 330]",
            "status": "ok", "dtype": "float32"}


def _merge_traces(rows: list[dict], path: Path) -> None:
    """All per-run traces in one CSV beside the figure (the per-run files,
    written by the workers, are removed)."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["scene", "radii", "policy", "call", "action", "update_ms",
                    "query_ms"])
        for r in rows:
            trace = Path(str(r.get("trace") or ""))
            if r.get("status") != "ok" or not trace.is_file():
                continue
            with open(trace, newline="") as t:
                for line in csv.DictReader(t):
                    w.writerow([r["scene"], r["radii"], r["policy"],
                                line["call"], line["action"],
                                line["update_ms"], line["query_ms"]])
            r["trace"] = f"{path}#{r['scene']}/{r['radii']}/{r['policy']}"
            trace.unlink()


def _read_trace(path) -> list[tuple[str, float]]:
    """(action, update + query ms) per call after the build, from one run's
    trace file or from ``figure8_traces.csv#scene/radii/policy`` (the
    merged file `_merge_traces` writes, which ``--plot`` reads)."""
    name, _, key = str(path).partition("#")
    with open(name, newline="") as f:
        rows = list(csv.DictReader(f))
    if key:
        scene, radii, policy = key.split("/")
        rows = [r for r in rows if (r["scene"], r["radii"], r["policy"])
                == (scene, radii, policy)]
    return [(r["action"], float(r["update_ms"]) + float(r["query_ms"]))
            for r in rows[1:]]


def ratios(rows: list[dict]) -> list[dict]:
    """Totals over the steps all three policies ran, and gradient's speed-up
    against each other policy, with the paper's figures beside."""
    out = []
    for scene in SCENES:
        for radii in RADII:
            got = {r["policy"]: r for r in rows if r.get("scene") == scene
                   and r.get("radii") == radii and r.get("status") == "ok"}
            if set(got) != set(POLICIES):
                reasons = {r.get("failed") for r in rows
                           if r.get("scene") == scene and r.get("radii") == radii
                           and r.get("status") != "ok"}
                out.append({"scene": scene, "radii": radii,
                            "note": "; ".join(sorted(filter(None, reasons)))[:200]
                            or "not run"})
                continue
            traces = {p: _read_trace(got[p]["trace"]) for p in POLICIES}
            common = min(len(t) for t in traces.values())
            total = {p: sum(c for _, c in traces[p][:common]) for p in POLICIES}
            row = {"scene": scene, "radii": radii, "steps": common,
                   **{f"{p}_ms": round(total[p], 2) for p in POLICIES},
                   **{f"{p}_rebuilds": sum(a != "refit" for a, _ in traces[p][:common])
                      for p in POLICIES}}
            others = sorted((total[p], p) for p in POLICIES if p != "gradient")
            g = total["gradient"]
            row["vs_avg"] = round(total["avg"] / g, 3) if g else math.nan
            row["vs_fixed"] = round(total["fixed"] / g, 3) if g else math.nan
            row["vs_second_best"] = round(others[0][0] / g, 3) if g else math.nan
            paper = [f"{who} {v}x" for (s, r, who), v in PAPER.items()
                     if s == scene and r == radii]
            row["paper"] = ", ".join(paper)
            out.append(row)
    return out


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(len(SCENES), len(RADII), figsize=(18, 11),
                             squeeze=False)
    colours = {"gradient": "tab:red", "avg": "tab:blue", "fixed": "tab:green"}
    for a, scene in enumerate(SCENES):
        for b, radii in enumerate(RADII):
            ax = axes[a][b]
            ax.set_title(f"{scene}, {radii}", fontsize=10)
            done = False
            for r in rows:
                if (r.get("scene"), r.get("radii")) != (scene, radii):
                    continue
                if r.get("status") != "ok":
                    continue
                trace = _read_trace(r["trace"])
                cost = [c for _, c in trace]
                p = r["policy"]
                ax.plot(cost, lw=0.7, color=colours[p],
                        label=f"{p}: {sum(cost):.0f} ms")
                rebuilt = [s for s, (act, _) in enumerate(trace) if act != "refit"]
                ax.plot(rebuilt, [cost[s] for s in rebuilt], ".",
                        color=colours[p], ms=3)
                done = True
            if done:
                ax.legend(fontsize=7)
                ax.set_yscale("log")
            else:
                note = next((r.get("failed") for r in rows
                             if (r.get("scene"), r.get("radii")) == (scene, radii)), "")
                ax.text(0.5, 0.5, "not run:\n" + str(note)[:80], ha="center",
                        va="center", fontsize=7, wrap=True,
                        transform=ax.transAxes)
            if b == 0:
                ax.set_ylabel("update + query, ms / step")
            if a == len(SCENES) - 1:
                ax.set_xlabel("step (dots: rebuilds)")
    fig.suptitle("Seed 003 Fig. 8 on this device: BVH policies, RT-REF")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def histogram(n: int, seed: int, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    from jaxrt.sim import distributions as sd
    r = sd.radii("LN[1,330]", n, seed + 1)
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.hist(r, bins=np.logspace(0, np.log10(330), 60))
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("radius")
    ax.set_ylabel("particles")
    ax.set_title(f"LN(1, 2) clipped to [1, 330], n = {n}: "
                 f"{np.mean(r == 1):.1%} at 1, {np.mean(r == 330):.2%} at 330")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> None:
    parser = _harness.make_parser(__doc__)
    parser.add_argument("--n", type=int, default=140_000)
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--job-seconds", type=float, default=60.0,
                        help="wall time per policy run (steps stop there)")
    parser.add_argument("--scenes", nargs="+", default=SCENES, choices=SCENES)
    parser.add_argument("--radii", nargs="+", default=RADII, choices=RADII)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true",
                        help="CPU smoke: n = 3000, 60 steps, 20 s per run")
    parser.add_argument("--plot", metavar="CSV", help="only redraw from a run")
    parser.add_argument("--skip", nargs="+", default=(), metavar="SCENE/RADII",
                        help="configurations not to run (written as skipped "
                        "with --skip-reason)")
    parser.add_argument("--skip-reason", default="not run")
    _harness.add_common_args(parser, name="figure8.csv", timeout=900.0)
    args = parser.parse_args(argv)
    if args.plot:
        rows = _harness.read_csv(args.plot)
        _finish(rows, Path(args.plot).parent)
        return
    if args.quick:
        args.n, args.steps, args.job_seconds = 3000, 60, 20.0
    out = Path(args.out) if args.out and not args.out.endswith(".csv") else None
    trace_dir = out or _harness.RESULTS / "figure8_traces"
    trace_dir.mkdir(parents=True, exist_ok=True)
    jobs = []
    for radii in args.radii:
        for scene in args.scenes:
            for policy in POLICIES:
                tag = f"{scene}_{radii}_{policy}".replace("[", "").replace(
                    "]", "").replace(",", "-").replace("=", "")
                jobs.append({"scene": scene, "radii": radii, "policy": policy,
                             "N": args.n, "seed": args.seed,
                             "steps": args.steps, "seconds": args.job_seconds,
                             "dynamics": DYNAMICS,
                             "trace": str(trace_dir / f"{tag}.csv"),
                             "_group": radii})
    skip = {tuple(x.split("/")) for x in args.skip}
    planned = []
    for job in jobs:
        if (job["scene"], job["radii"]) in skip:
            planned.append({**job, "_skip": args.skip_reason})
        else:
            planned.append(job)
    jobs = [j for j in planned if "_skip" not in j]
    skipped = [{k: v for k, v in j.items() if not k.startswith("_")
                and k not in ("dynamics", "seconds", "trace")}
               | {"status": "skipped", "failed": j["_skip"]}
               for j in planned if "_skip" in j]
    # One worker per radius kind: its three policies and scenes share the
    # compiled kernels (a worker's start costs more than a short run).
    rows, path = _harness.run_jobs("figure8:run_row", jobs, columns=COLUMNS,
                                   reuse_worker=True, **_harness.run_options(args))
    rows = rows + skipped
    _harness.write_csv(rows, path)
    _finish(rows, path.parent, args.n, args.seed, csv_path=path)


def _finish(rows, folder: Path, n: int | None = None, seed: int = 0,
            csv_path: Path | None = None) -> None:
    table = ratios(rows)
    _harness.write_csv(table, folder / "figure8_ratios.csv")
    print()
    print(f"gradient's speed-up over the other policies (paper: {PAPER_RANGE})")
    _harness.print_table(table, ["scene", "radii", "steps", "gradient_ms",
                                 "avg_ms", "fixed_ms", "gradient_rebuilds",
                                 "avg_rebuilds", "fixed_rebuilds", "vs_avg",
                                 "vs_fixed", "vs_second_best", "paper", "note"])
    plot(rows, folder / "figure8.png")
    if any(Path(str(r.get("trace") or "")).is_file() for r in rows):
        # A fresh run (not --plot): one traces file, and the CSV pointing
        # at it.
        _merge_traces(rows, folder / "figure8_traces.csv")
        _harness.write_csv(rows, csv_path or folder / "figure8.csv")
    histogram(n or int(rows[0]["N"]), seed, folder / "figure8_ln_radii.png")
    print("wrote", folder / "figure8.png", "and", folder / "figure8_ratios.csv")


if __name__ == "__main__":
    main()
