"""Seed 003's Figure 8: the BVH maintenance policies over a run, per scene and radius kind.

RT-REF (Meneses et al. §4): every step fits each policy's BVH to the
positions (a refit or a rebuild, `jaxrt.backends.rt.policy`) and queries
the neighbour list on it (OrderedSparse: count, scan, fill), then moves the
particles. The policies' trees (`jaxrt.backends.rt.aabb.AabbSearch`, with
the `bvh` backend's options) run side by side on the same positions, so
they see one trajectory: ``gradient`` (Eq. 8), ``avg`` and ``fixed``
(k = 200). Each step's cost is what the policies weigh, timed by the trees
(CUDA events on a GPU, the host clock on a CPU): the update (refit or
rebuild) plus the query. The first call (every tree's build) is not in
the totals. A refit is exact whatever the particles did, so only a policy
rebuilds (`reason` in the traces: ``policy``; anything else is counted in
``forced_rebuilds``), and every tree's edge count is checked against the
others' at every step (``mismatches``).

Δq of Eq. 8 (the query's growth per refit) is measured per scene by two
reference trees on the same positions, every ``sample_every`` steps: one
never rebuilt (policy ``refit``) and one rebuilt every time
(``rebuild``). ``dq_us`` is the least-squares slope through zero of their
query times' difference against the refits done, so the trajectory's own
change of the query cost cancels; ``t_r_ms``, ``t_u_ms`` are their median
rebuild and refit times, ``k_opt`` Eq. 8 from the three. Where Δq is tiny
against t_r - t_u the policies cannot differ by much, whatever they do.

Scenes (`jaxrt.sim.distributions`, §4.1): Lattice, Disordered, Cluster in a
periodic box of 1000³, radii r = 1, r = 160, U[1, 160] and LN(1, 2) clipped
to [1, 330] (31 % of the radii at 1; histogram beside the figure). Equal
radii run the equal-radius query, other kinds the per-particle one.
A configuration whose list would pass Warp's 2**29 entries (Cluster with
large radii: k near N, estimated from a sample of particles before any
tree is built) is refused as a list and says so.

Dynamics (the paper gives none; every value is in the CSV): overdamped
Brownian motion, ``x += clip(mobility_dt · F, ±max_drift) + noise · ξ`` per
axis, ξ ~ N(0, 1), with LJ forces (ε = 1, pair cut ``max(r_i, r_j)``,
``sigma_ij = max(r_i, r_j) / 2.5``, smooth switch from 0.8 of the cut,
`jaxrt.energy.lennard_jones_radii`) summed over the gradient tree's list.

Runs in parts: each invocation runs the (radii, scene) pairs asked for,
one worker job each, each stopped after ``--steps`` steps or
``--seconds`` of wall time; ``--merge`` joins the parts' folders into one
table, figure and ratios.

    python benchmarks/figure8.py --radii r=160 --out DIR_A          # one part
    python benchmarks/figure8.py --merge DIR_A DIR_B --out DIR      # join parts
    python benchmarks/figure8.py --quick                            # CPU smoke
"""
from __future__ import annotations

import csv
import math
import tempfile
import textwrap
import time
from pathlib import Path

if __package__:  # run as -m, or imported: the package's modules
    from benchmarks import _harness
else:  # run as a file: its folder is sys.path[0]
    import _harness

SCENES = ("lattice", "disordered", "cluster")
RADII = ("r=1", "r=160", "U[1,160]", "LN[1,330]")  # the paper's columns
POLICIES = ("gradient", "avg", "fixed")
REFERENCES = ("refit", "rebuild")  # the pair that measures Δq
DYNAMICS = dict(epsilon=1.0, sigma_per_cut=1 / 2.5, onset_fraction=0.8,
                mobility_dt=0.01, max_drift=0.1, noise=0.005, box=1000.0)
STEPS = {"r=1": 2000}       # default steps per radius kind (others: 300)
SAMPLE_EVERY = {"r=1": 1}   # reference trees' stride (others: 10)
# The paper's ratios (§4.2, Fig. 8): the gradient policy against others.
PAPER = {("cluster", "r=160", "avg"): 1.87, ("cluster", "r=160", "fixed"): 10.8,
         ("cluster", "U[1,160]", "second best"): 3.21,
         ("cluster", "LN[1,330]", "second best"): 1.8}
PAPER_RANGE = ("r = 1: gradient 1.16-3.4x faster than the second-best "
               "policy; up to 3.4x overall")
COLUMNS = ["scene", "radii", "policy", "N", "k", "steps", "total_ms",
           "per_step_ms", "rebuilds", "forced_rebuilds", "refits",
           "mismatches", "wall_s"]
TRACE_COLUMNS = ["scene", "radii", "policy", "call", "action", "reason",
                 "update_ms", "query_ms", "edges", "k", "dq_us", "k_opt"]
TRACES = "figure8_traces.csv"


def _scene(scene: str, radii: str, n: int, seed: int):
    import numpy as np
    from jaxrt.sim import distributions as sd
    make = {"lattice": lambda: sd.lattice(n),
            "disordered": lambda: sd.disordered(n, seed),
            "cluster": lambda: sd.cluster(n, seed)}[scene]
    return make(), sd.radii(radii, n, seed + 1).astype(np.float64)


def estimate_pairs(position, radii, side: float, sample: int = 256,
                   seed: int = 0) -> float:
    """N k / 2, the list's pairs, from the neighbours (``d < max(r_i,
    r_j)``, minimum image) of ``sample`` random particles, in float64."""
    import numpy as np
    rng = np.random.default_rng(seed)
    n = len(position)
    picks = rng.choice(n, size=min(sample, n), replace=False)
    counts = []
    for i in picks:
        d = position - position[i]
        d -= side * np.round(d / side)
        close = np.einsum("ij,ij->i", d, d) < np.maximum(radii, radii[i]) ** 2
        counts.append(int(close.sum()) - 1)
    return n * float(np.mean(counts)) / 2


def _row_base(job: dict) -> dict:
    return {**{k: v for k, v in job.items() if not k.startswith("_")},
            "steps_asked": job["steps"], "policies": " ".join(job["_policies"])}


def run_scene(job: dict) -> list[dict]:
    """Every policy's tree, and the two reference trees, on one scene: the
    per-call trace (written to ``job["_trace"]``) and one row per tree."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    import warp as wp
    from jax_md import space

    import jaxrt
    from jaxrt.backends.rt import aabb, ffi

    d = job["_dynamics"]
    position, radii = _scene(job["scene"], job["radii"], job["N"], job["seed"])
    side, n = float(d["box"]), job["N"]
    pairs_est = estimate_pairs(position, radii, side, seed=job["seed"])
    base = {**_row_base(job), "pairs_estimate": round(pairs_est),
            "dtype": "float32", "radius_rule": "LN clipped to [1, 330]",
            **{f"dyn_{k}": v for k, v in d.items()}}
    names = list(job["_policies"]) + list(REFERENCES)
    if pairs_est > ffi.MAX_LIST_ENTRIES:
        why = (f"refused as a list: k ≈ {2 * pairs_est / n:.0f} neighbours "
               f"per particle, N·k/2 ≈ {pairs_est:.2e} pairs past Warp's "
               f"2**29 - 1 list entries (ORCS, list-free, is the method here)")
        return [{**base, "policy": p, "status": "skipped", "failed": why,
                 "k": round(2 * pairs_est / n, 1)} for p in names]

    wp.config.quiet = True
    wp.init()
    device = "cuda:0" if jax.default_backend() in ("gpu", "cuda") else "cpu"
    equal = bool(np.all(radii == radii[0]))
    cutoff = float(np.float32(radii.max()))
    periodic = (True, True, True)
    with wp.ScopedDevice(device):
        side_array = wp.array([(side, side, side)], dtype=wp.vec3)
        reach = None if equal else wp.array(radii.astype(np.float32),
                                            dtype=wp.float32)
    aabb.load(device)

    def tree(policy):
        t = jaxrt.backends.Bvh(policy=policy).search_structure(
            n, wp.vec3, device)
        t.history = []
        return t

    trees = {p: tree(p) for p in names}
    R = jnp.asarray(position, jnp.float32)

    # Buffers sized from a count on a tree of their own (so no policy's
    # first call is timed twice).
    with wp.ScopedDevice(device):
        sizing = jaxrt.backends.Bvh(policy="rebuild").search_structure(
            n, wp.vec3, device)
        points = wp.from_jax(R, dtype=wp.vec3)
        sizing.update(points, side_array, periodic, cutoff, reach)
        count = wp.zeros(n, dtype=wp.int32)
        sizing.query(side_array, mask_self=True, lower_only=True,
                     mode=aabb.MODE_COUNT, count=count)
        edges0 = int(count.numpy().sum(dtype=np.int64))
        del sizing
    capacity = min(int(1.3 * edges0) + n, ffi.MAX_LIST_ENTRIES)

    def buffers(capacity):
        with wp.ScopedDevice(device):
            return {"main": wp.empty((2, capacity), dtype=wp.int32),
                    "scratch": wp.empty((2, capacity), dtype=wp.int32)}

    pairs = buffers(capacity)
    steps = int(job["steps"])
    with wp.ScopedDevice(device):
        scratch = {p: (wp.empty(n, dtype=wp.int32), wp.empty(n, dtype=wp.int32))
                   for p in names}
        totals = {p: wp.zeros(1, dtype=wp.int32) for p in names}
        logs = {p: wp.full(steps + 1, -1, dtype=wp.int32) for p in names}

    displacement, shift = space.periodic(side)
    radii_j = jnp.asarray(radii, jnp.float32)
    sigma = d["sigma_per_cut"] * 2.5

    def energy(R, idx):
        j, i = idx[0], idx[1]
        valid = j < n
        i, j = jnp.where(valid, i, 0), jnp.where(valid, j, 0)
        dr = space.distance(jax.vmap(displacement)(R[i], R[j]))
        radius = jnp.maximum(radii_j[i], radii_j[j])
        dr = jnp.where(valid, dr, 2 * radius)  # masked pairs: past the cut
        e = jaxrt.energy.lennard_jones_radii(
            dr, sigma, d["epsilon"], radius, r_onset=2.5 * d["onset_fraction"],
            r_cutoff=2.5)
        return jnp.sum(jnp.where(valid, e, 0.0))

    @jax.jit
    def move(R, idx, key):
        force = -jax.grad(energy)(R, idx)
        force = jnp.nan_to_num(force, nan=0.0, posinf=1e30, neginf=-1e30)
        key, sub = jax.random.split(key)
        drift = jnp.clip(d["mobility_dt"] * force, -d["max_drift"],
                         d["max_drift"])
        dx = drift + d["noise"] * jax.random.normal(sub, R.shape, R.dtype)
        return shift(R, dx), key

    driver = job["_policies"][0]
    sample = int(job["sample_every"])
    key = jax.random.PRNGKey(job["seed"])
    k_trace, dq_trace, overflows = [], [], 0
    start = time.perf_counter()
    done = 0
    for call in range(steps + 1):
        if call == 1:  # the wall-time cap leaves out the builds and compiles
            start = time.perf_counter()
        elif call and time.perf_counter() - start > job["seconds"]:
            break
        R = jax.block_until_ready(R)
        points = wp.from_jax(R, dtype=wp.vec3)
        sampled = call % sample == 0
        with wp.ScopedDevice(device):
            for p in names:
                t = trees[p]
                if p == "rebuild" and not sampled:
                    continue
                t.update(points, side_array, periodic, cutoff, reach)
                if p == "refit" and not sampled:
                    continue
                offset, counts = scratch[p]
                t.query_sparse(side_array, mask_self=True, lower_only=True,
                               pairs=pairs["main" if p == driver else "scratch"],
                               count=counts, offset=offset, total=totals[p])
                wp.copy(logs[p], totals[p], dest_offset=call, count=1)
            # Warp's stream done before JAX reads the list, and JAX's before
            # Warp reads the positions (block_until_ready above).
            wp.synchronize_device(device)
            edges = int(totals[driver].numpy()[0])
        g = trees.get("gradient")
        dq_trace.append(math.nan if g is None or g.state.delta_q is None
                        else (g.state.delta_q, g.state.k_opt()))
        k_trace.append(2.0 * edges / n)
        # A view of the list, read by move before the next step's Warp
        # calls (which wait for R) overwrite it.
        R, key = move(R, wp.to_jax(pairs["main"]), key)
        if edges > capacity:  # this step's forces missed pairs; grow
            overflows += 1
            capacity = min(int(1.3 * edges) + n, ffi.MAX_LIST_ENTRIES)
            pairs = buffers(capacity)
        done = call
    R = jax.block_until_ready(R)
    wall = time.perf_counter() - start
    for t in trees.values():
        t.flush_history()
    log = {p: logs[p].numpy()[:done + 1] for p in names}
    ran = np.stack([log[p] for p in names]).astype(np.int64)
    seen = ran >= 0  # -1: that tree did not query at that call
    high = np.where(seen, ran, -1).max(0)
    low = np.where(seen, ran, np.iinfo(np.int64).max).min(0)
    mismatches = int(np.sum(seen.any(0) & (high != low)))

    # The trace: one line per tree and call.
    lines, rows = [], []
    for p in names:
        calls = [c for c in range(done + 1)
                 if not (p == "rebuild" and c % sample)]
        history = trees[p].history
        for c, (action, reason, t_u, t_q) in zip(calls, history):
            dq = dq_trace[c] if p == "gradient" else math.nan
            lines.append({
                "scene": job["scene"], "radii": job["radii"], "policy": p,
                "call": c, "action": action, "reason": reason,
                "update_ms": f"{1e3 * t_u:.5f}" if math.isfinite(t_u) else "",
                "query_ms": f"{1e3 * t_q:.5f}" if math.isfinite(t_q) else "",
                "edges": int(log[p][c]) if log[p][c] >= 0 else "",
                "k": f"{k_trace[c]:.3f}",
                "dq_us": (f"{1e6 * dq[0]:.4f}" if isinstance(dq, tuple)
                          else ""),
                "k_opt": f"{dq[1]:.2f}" if isinstance(dq, tuple) else ""})
        summary = summarize([(ln["action"], ln["reason"],
                              _num(ln["update_ms"]), _num(ln["query_ms"]))
                             for ln in lines if ln["policy"] == p])
        rows.append({**base, "policy": p, "steps": done,
                     "role": "reference" if p in REFERENCES else "policy",
                     "k": round(float(np.mean(k_trace[:done + 1])), 2),
                     **summary, "mismatches": mismatches,
                     "overflows": overflows, "edges_start": edges0,
                     "radii_query": "equal" if equal else "per-particle",
                     "wall_s": round(wall, 2), "status": "ok"})
    with open(job["_trace"], "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=TRACE_COLUMNS)
        w.writeheader()
        w.writerows(lines)
    return rows


def _num(text) -> float:
    try:
        return float(text)
    except (TypeError, ValueError):
        return math.nan


def summarize(calls: list[tuple[str, str, float, float]]) -> dict:
    """Totals of one tree's calls after the first (the build):
    ``(action, reason, update_ms, query_ms)`` each."""
    steps = calls[1:]
    cost = [u + (q if math.isfinite(q) else 0.0) for _, _, u, q in steps
            if math.isfinite(u)]
    total = sum(cost)
    return {"total_ms": round(total, 4),
            "per_step_ms": round(total / max(len(cost), 1), 5),
            "update_ms": round(sum(u for _, _, u, _ in steps
                                   if math.isfinite(u)), 4),
            "query_ms": round(sum(q for *_, q in steps if math.isfinite(q)), 4),
            "rebuilds": sum(a != "refit" for a, *_ in steps),
            "forced_rebuilds": sum(a != "refit" and why != "policy"
                                   for a, why, *_ in steps),
            "refits": sum(a == "refit" for a, *_ in steps)}


# ---------------------------------------------------------------------------
# Reading runs back: traces, Δq, ratios.


def read_traces(folders) -> dict[tuple[str, str, str], list[dict]]:
    """(scene, radii, policy) -> calls in order, from each folder's merged
    traces file and any per-job traces left by an interrupted run."""
    out: dict[tuple[str, str, str], list[dict]] = {}
    for folder in folders:
        folder = Path(folder)
        files = ([folder / TRACES] if (folder / TRACES).is_file() else [])
        files += sorted((folder / "traces").glob("*.csv"))
        for path in files:
            with open(path, newline="") as f:
                for line in csv.DictReader(f):
                    key = (line["scene"], line["radii"], line["policy"])
                    calls = out.setdefault(key, [])
                    if not calls or int(line["call"]) > int(calls[-1]["call"]):
                        calls.append(line)
    return out


def cost(line: dict) -> float:
    u, q = _num(line["update_ms"]), _num(line["query_ms"])
    return (u if math.isfinite(u) else 0.0) + (q if math.isfinite(q) else 0.0)


def delta_q(traces: dict, scene: str, radii: str) -> dict:
    """Δq per refit from the reference pair (µs), the median rebuild and
    refit times, Eq. 8's k_opt from them, and Δq as the fixed policy's
    first cycle sees it (its query against its build's, trajectory
    included)."""
    import statistics
    refit = {int(c["call"]): c for c in traces.get((scene, radii, "refit"), [])}
    rebuild = {int(c["call"]): c for c in traces.get((scene, radii, "rebuild"), [])}
    out = {}
    pairs = [(c, _num(refit[c]["query_ms"]) - _num(rebuild[c]["query_ms"]))
             for c in sorted(set(refit) & set(rebuild)) if c > 0
             and math.isfinite(_num(refit[c]["query_ms"]))
             and math.isfinite(_num(rebuild[c]["query_ms"]))]
    if len(pairs) >= 2:
        dq = sum(c * e for c, e in pairs) / sum(c * c for c, _ in pairs)
        q0 = statistics.median(_num(rebuild[c]["query_ms"]) for c, _ in pairs)
        last, extra = pairs[-1]
        t_r = statistics.median(_num(rebuild[c]["update_ms"]) for c, _ in pairs)
        t_u = statistics.median(_num(c["update_ms"]) for c in refit.values()
                                if int(c["call"]) > 0)
        k_opt = (-1 + math.sqrt(max(0.0, 1 + 2 * (t_r - t_u) / dq))
                 if dq > 0 else math.inf)
        out.update({"q0_ms": round(q0, 4), "dq_us": round(1e3 * dq, 4),
                    "dq_pct_per_100_refits": round(100 * 100 * dq / q0, 3)
                    if q0 > 0 else math.nan,
                    "refit_slowdown_at_end": round(1 + extra / q0, 3)
                    if q0 > 0 else math.nan, "refits_at_end": last,
                    "t_r_ms": round(t_r, 4), "t_u_ms": round(t_u, 4),
                    "k_opt": round(k_opt, 1) if math.isfinite(k_opt) else "inf"})
    fixed = traces.get((scene, radii, "fixed"), [])
    if len(fixed) > 3:
        q0 = _num(fixed[0]["query_ms"])
        cycle = []
        for c in fixed[1:]:
            if c["action"] != "refit":
                break
            cycle.append((int(c["call"]), _num(c["query_ms"]) - q0))
        if len(cycle) >= 2:
            out["dq_fixed_us"] = round(1e3 * sum(j * e for j, e in cycle)
                                       / sum(j * j for j, _ in cycle), 4)
    return out


def ratios(rows: list[dict], traces: dict) -> list[dict]:
    """Per scene and radius kind: totals over the steps every policy ran,
    the gradient policy's speed-up against each other one (the paper's
    beside), rebuilds and their reasons, and Δq (`delta_q`)."""
    out = []
    for scene in SCENES:
        for radii in RADII:
            mine = [r for r in rows if r.get("scene") == scene
                    and r.get("radii") == radii]
            got = {r["policy"]: r for r in mine if r.get("status") == "ok"}
            policies = [p for p in POLICIES if p in got]
            if not policies:
                reasons = {str(r.get("failed") or "") for r in mine}
                out.append({"scene": scene, "radii": radii,
                            "note": "; ".join(sorted(filter(None, reasons)))[:300]
                            or "not run"})
                continue
            calls = {p: traces.get((scene, radii, p), []) for p in policies}
            common = min(len(c) for c in calls.values()) - 1
            if common < 1:
                out.append({"scene": scene, "radii": radii,
                            "note": "no trace of a completed step"})
                continue
            total = {p: sum(cost(c) for c in calls[p][1:common + 1])
                     for p in policies}
            row = {"scene": scene, "radii": radii, "steps": common,
                   "k": got[policies[0]].get("k"),
                   **{f"{p}_ms": round(total[p], 2) for p in policies},
                   **{f"{p}_rebuilds": sum(c["action"] != "refit"
                                           for c in calls[p][1:common + 1])
                      for p in policies},
                   "forced_rebuilds": sum(c["action"] != "refit"
                                          and c["reason"] != "policy"
                                          for p in policies
                                          for c in calls[p][1:common + 1]),
                   "mismatches": max(int(got[p].get("mismatches") or 0)
                                     for p in policies)}
            g = total.get("gradient")
            for p in policies:
                if p != "gradient" and g:
                    row[f"vs_{p}"] = round(total[p] / g, 3)
            others = sorted(total[p] for p in policies if p != "gradient")
            if g and others:
                row["vs_second_best"] = round(others[0] / g, 3)
            row["paper"] = ", ".join(f"{who} {v}x" for (s, r, who), v
                                     in PAPER.items() if (s, r) == (scene, radii))
            row.update(delta_q(traces, scene, radii))
            out.append(row)
    return out


# ---------------------------------------------------------------------------
# Figures.


def plot(rows: list[dict], traces: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(len(SCENES), len(RADII), figsize=(20, 11),
                             squeeze=False)
    colours = {"gradient": "tab:red", "avg": "tab:blue", "fixed": "tab:green"}
    for a, scene in enumerate(SCENES):
        for b, radii in enumerate(RADII):
            ax = axes[a][b]
            ax.set_title(f"{scene}, {radii}", fontsize=10)
            drawn = False
            for p in POLICIES:
                calls = traces.get((scene, radii, p), [])[1:]
                if not calls:
                    continue
                steps = [int(c["call"]) for c in calls]
                cost_ms = [cost(c) for c in calls]
                ax.plot(steps, cost_ms, lw=0.6, color=colours[p],
                        label=f"{p}: {sum(cost_ms):.0f} ms")
                for want, marker in (("policy", "o"), ("forced", "x")):
                    hit = [(s, c) for s, c, line in zip(steps, cost_ms, calls)
                           if line["action"] != "refit"
                           and (line["reason"] == "policy") == (want == "policy")]
                    if hit:
                        ax.plot(*zip(*hit), marker, color=colours[p], ms=3,
                                mfc="none" if marker == "o" else None)
                drawn = True
            if drawn:
                ax.set_yscale("log")
                ax.legend(fontsize=7, loc="upper left")
                calls = traces.get((scene, radii, POLICIES[0]), [])[1:]
                twin = ax.twinx()
                twin.fill_between([int(c["call"]) for c in calls],
                                  [_num(c["k"]) for c in calls],
                                  color="grey", alpha=0.15, lw=0)
                twin.set_ylim(bottom=0)
                if b == len(RADII) - 1:
                    twin.set_ylabel("neighbours per particle (grey)",
                                    fontsize=8)
            else:
                note = next((str(r.get("failed") or "") for r in rows
                             if (r.get("scene"), r.get("radii")) == (scene, radii)
                             and r.get("failed")), "not run")
                # Wrapped to the panel (matplotlib's wrap= wraps to the figure).
                ax.text(0.5, 0.5, textwrap.fill(note[:160], 32),
                        ha="center", va="center", fontsize=7,
                        transform=ax.transAxes)
                ax.set_xticks([])
                ax.set_yticks([])
            if b == 0:
                ax.set_ylabel("update + query, ms / step")
            if a == len(SCENES) - 1:
                ax.set_xlabel("step (o: policy rebuild, x: forced)")
    fig.suptitle("Seed 003 Fig. 8 on this device: BVH policies, RT-REF")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_dq(traces: dict, path: Path) -> None:
    """Query time of the never-rebuilt tree minus the rebuilt one's against
    the refits done, per scene: Δq is its slope."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(len(SCENES), len(RADII), figsize=(20, 11),
                             squeeze=False)
    for a, scene in enumerate(SCENES):
        for b, radii in enumerate(RADII):
            ax = axes[a][b]
            ax.set_title(f"{scene}, {radii}", fontsize=10)
            refit = {int(c["call"]): _num(c["query_ms"])
                     for c in traces.get((scene, radii, "refit"), [])}
            rebuild = {int(c["call"]): _num(c["query_ms"])
                       for c in traces.get((scene, radii, "rebuild"), [])}
            both = [c for c in sorted(set(refit) & set(rebuild))
                    if math.isfinite(refit[c]) and math.isfinite(rebuild[c])]
            if not both:
                ax.text(0.5, 0.5, "not run", ha="center", va="center",
                        transform=ax.transAxes)
                continue
            ax.plot(both, [refit[c] - rebuild[c] for c in both], ".", ms=2,
                    label="refit-only − rebuilt")
            dq = delta_q(traces, scene, radii).get("dq_us")
            if dq is not None:
                ax.plot([0, both[-1]], [0, dq * 1e-3 * both[-1]], "k-", lw=0.8,
                        label=f"Δq = {dq:.3g} µs / refit")
            ax.legend(fontsize=7)
            if b == 0:
                ax.set_ylabel("query slowdown, ms")
            if a == len(SCENES) - 1:
                ax.set_xlabel("refits since the build")
    fig.suptitle("Δq (Eq. 8): how much a refit slows the next query")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


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
    plt.close(fig)


# ---------------------------------------------------------------------------
# Driver.


def _merge_traces(folder: Path) -> None:
    """The per-job traces into the folder's one traces file (kept in the
    order of the jobs; the per-job files are removed)."""
    parts = sorted((folder / "traces").glob("*.csv"))
    if not parts:
        return
    traces = read_traces([folder])
    with open(folder / TRACES, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=TRACE_COLUMNS, extrasaction="ignore")
        w.writeheader()
        for calls in traces.values():
            w.writerows(calls)
    for p in parts:
        p.unlink()
    (folder / "traces").rmdir()


def finish(rows: list[dict], folder: Path, traces: dict, csv_path: Path,
           n: int, seed: int) -> None:
    table = ratios(rows, traces)
    _harness.write_csv(table, csv_path.with_name(csv_path.stem + "_ratios.csv"))
    print()
    print(f"gradient's speed-up over the other policies (paper: {PAPER_RANGE}),"
          " and Δq (µs per refit) from the reference trees")
    _harness.print_table(table, [
        "scene", "radii", "steps", "k", "gradient_ms", "avg_ms", "fixed_ms",
        "gradient_rebuilds", "avg_rebuilds", "fixed_rebuilds",
        "forced_rebuilds", "mismatches", "vs_avg", "vs_fixed",
        "vs_second_best", "paper", "q0_ms", "dq_us", "dq_pct_per_100_refits",
        "t_r_ms", "t_u_ms", "k_opt", "note"])
    plot(rows, traces, folder / "figure8.png")
    plot_dq(traces, folder / "figure8_dq.png")
    histogram(n, seed, folder / "figure8_ln_radii.png")
    print("wrote", csv_path, "and", folder / "figure8.png")


def plan(args) -> list[dict]:
    """One job per (radius kind, scene), in the order asked."""
    jobs = []
    for radii in args.radii:
        for scene in args.scenes:
            tag = f"{scene}_{radii}".translate(str.maketrans("", "", "[]=,"))
            jobs.append({
                "scene": scene, "radii": radii, "N": args.n, "seed": args.seed,
                "steps": args.steps or STEPS.get(radii, 300),
                "seconds": args.seconds,
                "sample_every": args.sample_every or SAMPLE_EVERY.get(radii, 10),
                "_policies": list(args.policies), "_dynamics": DYNAMICS,
                "_trace": str(Path(args.trace_dir) / f"{tag}.csv"),
                "_worker": "all", "_group": f"{scene}/{radii}",
                "_timeout": args.seconds + 300.0})
    return jobs


def main(argv=None) -> None:
    parser = _harness.make_parser(__doc__)
    parser.add_argument("--n", type=int, default=140_000)
    parser.add_argument("--steps", type=int, default=None,
                        help="steps per scene (default 2000 at r = 1, else 300)")
    parser.add_argument("--seconds", type=float, default=420.0,
                        help="wall time per scene; its steps stop there")
    parser.add_argument("--scenes", nargs="+", default=SCENES, choices=SCENES)
    parser.add_argument("--radii", nargs="+", default=RADII, choices=RADII)
    parser.add_argument("--policies", nargs="+", default=POLICIES,
                        choices=POLICIES, help="the first drives the dynamics")
    parser.add_argument("--sample-every", type=int, default=None,
                        help="stride of the Δq reference trees (default 1 at "
                        "r = 1, else 10)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true",
                        help="CPU smoke: n = 2000, 20 steps")
    parser.add_argument("--merge", nargs="+", metavar="DIR",
                        help="only join the runs in these folders into --out")
    _harness.add_common_args(parser, name="figure8.csv", timeout=900.0)
    args = parser.parse_args(argv)
    if args.merge:
        rows = []
        for folder in args.merge:
            for path in sorted(Path(folder).glob("figure8*.csv")):
                if path.name != TRACES and not path.stem.endswith("_ratios"):
                    rows += _harness.read_csv(path)
        out = Path(args.out or ".")
        out.mkdir(parents=True, exist_ok=True)
        traces = read_traces(args.merge)
        csv_path = out / args.name
        _harness.write_csv(rows, csv_path)
        with open(out / TRACES, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=TRACE_COLUMNS, extrasaction="ignore")
            w.writeheader()
            for calls in traces.values():
                w.writerows(calls)
        first = next((r for r in rows if r.get("N")), {"N": 140_000, "seed": 0})
        finish(rows, out, traces, csv_path, int(first["N"]),
               int(first.get("seed") or 0))
        return
    if args.quick:
        args.n, args.steps = 2000, args.steps or 20
        args.sample_every = args.sample_every or 2
    if args.out is None:  # the folder is known once a worker named the device
        args.trace_dir = str(Path(tempfile.mkdtemp(prefix="figure8_")) / "traces")
    else:
        args.trace_dir = str(_harness.out_path(args.out, args.name, "")
                             .parent / "traces")
    Path(args.trace_dir).mkdir(parents=True, exist_ok=True)
    rows, csv_path = _harness.run_jobs("figure8:run_scene", plan(args),
                                       columns=COLUMNS, reuse_worker=True,
                                       **_harness.run_options(args))
    folder = csv_path.parent
    trace_folder = Path(args.trace_dir).parent
    if trace_folder != folder:  # default --out: move the traces beside the CSV
        (folder / "traces").mkdir(parents=True, exist_ok=True)
        for p in Path(args.trace_dir).glob("*.csv"):
            p.replace(folder / "traces" / p.name)
        Path(args.trace_dir).rmdir()
        trace_folder.rmdir()
    _merge_traces(folder)
    finish(rows, folder, read_traces([folder]), csv_path, args.n, args.seed)


if __name__ == "__main__":
    main()
