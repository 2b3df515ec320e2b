"""Seed 003's Table 2: mean ms per LJ step, RT-REF against ORCS and cell lists.

Methods (Meneses et al. §4.2; all jaxrt, all one leapfrog step
``v += dt F / m; x += dt v`` on the same positions):

* ``RT-REF``: the ``bvh`` list (`jaxrt.neighbor_list`, no skin, so every
  step refits or rebuilds the BVH by the policy and queries it) plus the
  forces (``jax.grad`` of `jaxrt.energy.lennard_jones_pair_neighbor_list`).
* ``ORCS-forces``: `jaxrt.energy.lennard_jones_fused` on the same kind of
  BVH: forces from the traversal, no list.
* ``ORCS-persé``: `jaxrt.energy.lennard_jones_perse_step`, the whole step in
  one kernel; equal radii only (r = 1, r = 160; the other kinds are rows
  with status ``skipped`` and the reason).
* ``GPU-CELL``: jaxrt's ``cell`` list plus the same forces, on JAX's default
  device (on a CPU-only machine that is the CPU).
* ``GPU-CELL-fused``: `jaxrt.energy.lennard_jones_fused` with
  ``backend="cell"``: forces from jaxrt's cell grid with no list (on CUDA
  one Pallas kernel, `jaxrt.backends.cell.kernel`; elsewhere array programs), the
  step of ORCS-forces; any radii. Not in the paper (no ``paper_ms``): the
  list-free counterpart of GPU-CELL, against the list-free ORCS-forces.
* ``CPU-CELL``: the same on JAX's CPU device (``--cpu-cores`` are what this
  machine has, not the paper's 64).

The BVH methods use the ``gradient`` policy (``--policy``), as the paper's.
The lists (RT-REF, GPU-CELL, CPU-CELL) are Dense (``--list-format`` sets
another layout; the CSV's ``format`` column says which ran). Until b88f2a3
they were OrderedSparse at r > 1, and at k = 700 (r = 160, n = 50 000) the
forces on those lists took 333 ms on the H200 against 1.65 ms on Dense
(benchmarks/list_forces.py; jax-md's own energy the same): the list rows
then measured the layout, not the search.
Scenes and radii (`jaxrt.sim.distributions`, §4.1): Lattice, Disordered,
Cluster in a box of 1000³ with walls (free axes; nothing leaves the box in
these steps) or periodic; r = 1, r = 160, U[1, 160], LN(1, 2) clipped to
[1, 330]. With radii, pair ij is cut at max(r_i, r_j) and sigma_ij =
max(r_i, r_j) / 2.5, epsilon 1, smooth switch from 0.8 of the cut; equal
radii run without a radii array (the same potential).

Dynamics: the paper gives none, so none is simulated: each timed step
starts from one of ``--snapshots`` copies of the scene jittered by
``--jitter`` (a fraction of the smallest radius), so consecutive steps see
slightly moved particles (the BVH is refit or rebuilt by the policy, as in
a slowly moving system) and random overlaps cannot blow the system up.
Times are the median over ``--repeats`` steps after ``--warmup``.
Out-of-memory rows (RT-REF's list, as in the paper's "–" cells) are
``oom`` with the reason; lists past the backends' 2**29 int32 entries are
``oom`` too (the reason says which).

The paper's milliseconds (RTX PRO 6000 Blackwell, RT cores; CPU-CELL on 64
cores) are the ``paper_ms`` column; ``table2_ratios.csv`` compares ratios
(RT-REF / ORCS-forces, RT-REF / persé, CPU-CELL / ORCS-forces, GPU-CELL /
ORCS-forces) with the paper's for each configuration, and ours alone for
GPU-CELL-fused against ORCS-forces and against GPU-CELL. Compare shapes
and ratios, not absolute ms (H200 has no RT cores).

Energy (``--energy``; seed 003 §4.3, Figs 11-12, `_energy`): after a
row's timing its step is repeated for ``--energy-seconds`` (default 2 s:
NVML's energy counter ticks every 20-100 ms) between two reads of the
energy counter of the method's device: NVML's for a GPU method, RAPL's
CPU packages for CPU-CELL (its GPU-idle energy is only ``gpu_energy_j``).
Columns: ``energy_j``, ``mean_power_w``, ``peak_power_w``,
``interactions_per_step`` (unordered pairs within the cut: the fused
count of ORCS-forces and GPU-CELL-fused, the list's pairs for RT-REF and
the cell lists, ORCS-forces' count on the same positions for persé), ``interactions_per_joule`` (Eq. 10: pairs per
step x steps / joules), ``energy_window_s``, ``energy_steps``,
``energy_source`` and ``energy_reason`` (why a value is empty: "no NVML",
"no GPU", "no RAPL"). The GPU's power samples (every
``--energy-interval``) go to ``<csv stem>_power.csv``, one line per sample
keyed by method/scene/radii/boundary/N; `table2_energy_plot` draws Figs
11-12 from the two (``--plot-energy CSV`` redraws). ``--cases
paper-energy`` selects the paper's cases: lattice r = 160, disordered r = 1,
cluster LN, with --boundaries (both by default).

    python benchmarks/table2.py --quick                     # CPU smoke
    python benchmarks/table2.py --quick --energy --cases paper-energy
    python benchmarks/table2.py --n 50000 --cases paper-energy --energy \
        --budget 480                                        # GPU, Figs 11-12
    python benchmarks/table2.py --n 50000 --budget 1500     # GPU, part 1
    python benchmarks/table2.py --n 1000000 --methods ORCS-forces ORCS-persé \
        --radii r=1 LN[1,330] --budget 1500 --name table2_1e6_a.csv
"""
from __future__ import annotations

import math
import os
import sys
from pathlib import Path

if __package__:  # run as -m, or imported: the package's modules
    from benchmarks import _energy
    from benchmarks import _harness
else:  # run as a file: its folder is sys.path[0]
    import _energy
    import _harness

SCENES = ("lattice", "disordered", "cluster")
RADII = ("r=1", "r=160", "U[1,160]", "LN[1,330]")
BOUNDARIES = ("wall", "periodic")
METHODS = ("RT-REF", "ORCS-forces", "ORCS-persé", "GPU-CELL",
           "GPU-CELL-fused", "CPU-CELL")
NS = (50_000, 1_000_000)
DYNAMICS = dict(epsilon=1.0, sigma_per_cut=1 / 2.5, onset_fraction=0.8,
                dt=1e-4, mass=1.0, box=1000.0)
COLUMNS = ["method", "scene", "radii", "boundary", "N", "median_ms",
           "paper_ms", "k", "format"]
ENERGY_COLUMNS = ["energy_j", "mean_power_w", "interactions_per_joule",
                  "energy_window_s", "energy_reason"]
# Seed 003 §4.3's energy cases (Figs 11-12), each with wall and periodic BC.
CASES = {"paper-energy": (("lattice", "r=160"), ("disordered", "r=1"),
                          ("cluster", "LN[1,330]"))}
TRACE_KEY = ("method", "scene", "radii", "boundary", "N")

# Seed 003 Table 2 (SPECS.md §5), mean ms per step; None: "–" (RT-REF out
# of memory, or persé not applicable). Column order: radius kind, then
# (wall 50k, wall 1M, periodic 50k, periodic 1M).
_PAPER_TEXT = """
lattice CPU-CELL 1.80 9.64 1.80 10.4 17.9 5482 28.0 9864 11.7 3958 21.2 7891 56.4 22311 141 60612
lattice GPU-CELL 0.415 2.97 0.399 2.61 43.6 3185 38.4 5379 27.1 2163 26.3 3957 130 7767 151 25864
lattice RT-REF 0.165 0.599 0.199 0.844 17.6 2235 31.8 5520 6.99 835 10.9 1801 10.6 - 14.8 -
lattice ORCS-forces 0.166 0.612 0.181 0.729 19.5 4836 35.8 7844 4.99 1323 7.99 2064 2.33 548 4.26 976
lattice ORCS-persé 0.127 0.506 0.147 0.632 19.6 5201 36.4 8674 - - - - - - - -
disordered CPU-CELL 1.97 13.7 2.01 14.2 21.6 8229 31.5 12156 12.0 4221 21.2 7935 56.0 22204 268 106472
disordered GPU-CELL 0.433 3.49 0.419 3.08 48.6 4569 42.5 7174 28.4 2697 27.7 4664 131 8073 156 26890
disordered RT-REF 0.163 0.658 0.192 1.03 18.6 2861 39.7 7525 7.08 972 12.4 2250 8.73 - 14.9 -
disordered ORCS-forces 0.153 0.660 0.173 0.894 22.3 5398 45.7 10989 5.41 1464 9.95 2671 2.59 674 5.60 1484
disordered ORCS-persé 0.117 0.552 0.137 0.792 22.5 6017 47.0 12573 - - - - - - - -
cluster CPU-CELL 1.52 15.4 1.56 18.1 153 13820 147 17827 111 10969 194 21459 66.8 21617 188 95351
cluster GPU-CELL 0.638 6.82 0.617 7.62 333 7119 201 9392 278 6114 302 10278 229 12241 318 30759
cluster RT-REF 0.200 4.77 0.227 7.43 251 - 354 - 182 - 342 - 145 - 295 -
cluster ORCS-forces 0.176 6.32 0.186 7.82 223 19150 281 57670 119 6796 202 13780 40.8 2586 75.0 5617
cluster ORCS-persé 0.146 7.44 0.158 8.99 232 23445 301 78784 - - - - - - - -
"""


def paper_table() -> dict:
    """{(scene, method, radii, boundary, N): ms or None}."""
    out = {}
    for line in _PAPER_TEXT.strip().splitlines():
        scene, method, *values = line.split()
        assert len(values) == 16, line
        for c, v in enumerate(values):
            radii = RADII[c // 4]
            boundary = BOUNDARIES[(c % 4) // 2]
            n = NS[c % 2]
            out[(scene, method, radii, boundary, n)] = (None if v == "-"
                                                        else float(v))
    return out


PAPER = paper_table()
# The paper's headline claims (§4.2, abstract), for the report.
PAPER_CLAIMS = ("persé ~1.3x RT-REF at r = 1; ORCS-forces up to ~1.6x "
                "RT-REF's best case on LN (40x vs 25x over CPU-CELL), ~2x "
                "on periodic LN; abstract: 1.3x (small radius) to 2.0x (LN)")


def _scene(scene: str, radii: str, n: int, seed: int):
    import numpy as np
    from jaxrt.sim import distributions as sd
    make = {"lattice": lambda: sd.lattice(n),
            "disordered": lambda: sd.disordered(n, seed),
            "cluster": lambda: sd.cluster(n, seed)}[scene]
    return make(), sd.radii(radii, n, seed + 1).astype(np.float64)


def _list_too_large(exc: BaseException) -> bool:
    """A list refused at allocate for its size (the paper's "–" cells):
    more int32 entries than the backend indexes, or the candidate buffers
    that would build it past int32 indices or the device's memory."""
    import jaxrt
    return isinstance(exc, jaxrt.ListTooLargeError)


def _step_fns(job: dict, position, radii):
    """(step(state) -> state, state0, format, k_fn) for the job's method."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax_md import partition, space

    import jaxrt
    from jaxrt.energy import (lennard_jones_fused,
                              lennard_jones_pair_neighbor_list,
                              lennard_jones_perse_step)

    d = job["dynamics"]
    side = d["box"]
    periodic = job["boundary"] == "periodic"
    displacement, shift = space.periodic(side) if periodic else space.free()
    box = side if periodic else None
    equal = bool(np.all(radii == radii[0]))
    cut = float(radii.max())
    # sigma_ij = cut_ij / 2.5 (reference cut 2.5 sigma); with equal radii
    # the reference cut is the radius itself.
    sigma = 1.0 if not equal else cut * d["sigma_per_cut"]
    onset = 2.5 * d["onset_fraction"]
    radii_arg = None if equal else jnp.asarray(radii, jnp.float32)
    policy = jaxrt.backends.Bvh(policy=job["policy"])
    dt, mass = d["dt"], d["mass"]
    method = job["method"]
    V0 = jnp.zeros_like(position)

    if method == "ORCS-persé":
        step = lennard_jones_perse_step(displacement, box, dt=dt, mass=mass,
                                        sigma=sigma, epsilon=d["epsilon"],
                                        r_onset=onset, r_cutoff=2.5,
                                        backend=policy, periodic=periodic)
        # persé returns no count; the same traversal's fused sums count
        # the unordered pairs within the cut (what persé's kernel visits,
        # each from both ends). Only called for --energy (one more compile).
        counter = lennard_jones_fused(displacement, box, sigma=sigma,
                                      epsilon=d["epsilon"], r_onset=onset,
                                      r_cutoff=2.5, backend=policy,
                                      periodic=periodic)

        def k_fn(R):
            return 2.0 * float(counter.sums(R).count) / R.shape[0]
        return (lambda s: step(*s)), (position, V0), "none", k_fn

    if method in ("ORCS-forces", "GPU-CELL-fused"):
        energy = lennard_jones_fused(
            displacement, box, sigma=sigma, epsilon=d["epsilon"],
            r_onset=onset, r_cutoff=2.5, radii=radii_arg, periodic=periodic,
            backend=policy if method == "ORCS-forces" else "cell")

        @jax.jit
        def step(state):
            R, V = state
            V = V - (dt / mass) * jax.grad(energy)(R)
            return shift(R, dt * V), V

        def k_fn(R):
            return 2.0 * float(energy.sums(R).count) / R.shape[0]
        return step, (position, V0), "none", k_fn

    backend = {"RT-REF": policy, "GPU-CELL": "cell", "CPU-CELL": "cell"}[method]
    fmt = getattr(partition, job.get("list_format", "Dense"))
    nfn = jaxrt.neighbor_list(displacement, side, cut, 0.0, format=fmt,
                              backend=backend, periodic=periodic,
                              radii=None if equal else radii)
    energy = lennard_jones_pair_neighbor_list(
        displacement, sigma=sigma, epsilon=d["epsilon"], r_onset=onset * sigma,
        r_cutoff=2.5 * sigma, radii=radii_arg)
    nbrs = nfn.allocate(position)

    @jax.jit
    def step(state):
        R, V, nbrs = state
        nbrs = nfn.update(R, nbrs)
        V = V - (dt / mass) * jax.grad(energy)(R, nbrs)
        return shift(R, dt * V), V, nbrs

    def k_fn(R):
        idx = np.asarray(nbrs.idx)
        if fmt is partition.Dense:  # both directions of every pair
            return float(np.sum(idx < R.shape[0])) / R.shape[0]
        return 2.0 * float(np.sum(idx[0] < R.shape[0])) / R.shape[0]
    return step, (position, V0, nbrs), fmt.name, k_fn


def run_row(job: dict) -> dict:
    """One method on one configuration: median ms per step."""
    import contextlib

    import jax
    import jax.numpy as jnp
    import numpy as np

    base = {k: v for k, v in job.items() if not k.startswith("_")
            and k != "dynamics"}
    base.update({f"dyn_{k}": v for k, v in job["dynamics"].items()},
                radius_rule="LN clipped to [1, 330]",
                paper_ms=PAPER.get((job["scene"], job["method"], job["radii"],
                                    job["boundary"], job["N"])))
    position, radii = _scene(job["scene"], job["radii"], job["N"], job["seed"])
    if job["method"] == "ORCS-persé" and not np.all(radii == radii[0]):
        return {**base, "status": "skipped",
                "failed": "persé needs equal radii (seed 003 §3.2.3)"}
    device = (jax.devices("cpu")[0] if job["method"] == "CPU-CELL"
              else jax.devices()[0])
    rng = np.random.default_rng(job["seed"] + 7)
    jitter = job["jitter"] * float(radii.min())
    snapshots = [position + rng.uniform(-jitter, jitter, position.shape)
                 for _ in range(job["snapshots"])]
    if job["boundary"] == "periodic":
        snapshots = [np.mod(s, job["dynamics"]["box"]) for s in snapshots]
    else:  # walls: keep them inside the box
        snapshots = [np.clip(s, 0.0, job["dynamics"]["box"] * (1 - 1e-7))
                     for s in snapshots]
    with jax.default_device(device) if job["method"] == "CPU-CELL" \
            else contextlib.nullcontext():
        R = [jnp.asarray(s, jnp.float32) for s in snapshots]
        try:
            step, state, fmt, k_fn = _step_fns(job, R[0], radii)
        except Exception as exc:  # noqa: BLE001 - classified below
            if _harness.is_out_of_memory(exc) or _list_too_large(exc):
                return {**base, "status": "oom",
                        "failed": f"{type(exc).__name__}: {exc}"[:300]}
            raise
        states = [(r,) + tuple(state[1:]) for r in R]
        timing = _harness.time_calls(step, states, repeats=job["repeats"],
                                     warmup=job["warmup"],
                                     target_s=job.get("target_s"),
                                     max_repeats=job.get("max_repeats"))
        out = timing.first
        if not bool(jnp.all(jnp.isfinite(out[1]))):
            return {**base, **timing.columns(), "status": "error",
                    "failed": "non-finite velocities after one step"}
        # persé's k costs a compile of its own: only where energy needs it.
        wants_k = job["method"] != "ORCS-persé" or job.get("energy_seconds")
        k = k_fn(R[0]) if k_fn is not None and wants_k else math.nan
        energy = (_energy_columns(job, step, states, k, device)
                  if job.get("energy_seconds") else {})
    return {**base, **timing.columns(), "format": fmt,
            "k": round(k, 2) if math.isfinite(k) else None,
            "method_device": str(device), "status": "ok", "dtype": "float32",
            **energy}


def _energy_columns(job: dict, step, states: list, k: float, device) -> dict:
    """Seed 003 §4.3: repeat the step for ``job["energy_seconds"]`` inside
    `_energy.measure`; interactions per joule (Eq. 10) from the method's
    unordered pairs per step (k N / 2) times the steps.

    The method's own meter gives ``energy_j``: NVML's counter for a method
    on the GPU, RAPL for one on the CPU (CPU-CELL), whose GPU-idle energy
    is not counted in it but kept in ``gpu_energy_j``. ``power_trace``
    (the GPU's samples; the driver moves them to ``*_power.csv``)."""
    import jax
    with _energy.measure(job.get("energy_interval_s", 0.01)) as m:
        steps, seconds = _energy.repeat_for(step, states,
                                            job["energy_seconds"],
                                            sync=jax.block_until_ready)
    on_cpu = device.platform == "cpu"
    own = m.cpu if on_cpu else m.gpu
    # k = 2 pairs / N exactly, so this is the integer pair count.
    per_step = round(k * job["N"] / 2) if math.isfinite(k) else None
    reason = own.reason
    if on_cpu:  # say what became of the GPU meter (a CPU-only host: why)
        reason = "; ".join(filter(None, [reason, (
            f"GPU: {m.gpu.reason}" if m.gpu.reason else
            "GPU idle energy in gpu_energy_j, not counted")]))
    ee = (per_step * steps / own.joules
          if per_step is not None and own.joules else None)
    return {"energy_j": own.joules, "mean_power_w": own.mean_watts,
            "peak_power_w": own.peak_watts,
            "interactions_per_step": per_step,
            "interactions_per_joule": ee, "energy_window_s": seconds,
            "energy_steps": steps, "energy_meter": "cpu" if on_cpu else "gpu",
            "energy_source": own.source, "energy_reason": reason or None,
            "gpu_energy_j": m.gpu.joules, "cpu_energy_j": m.cpu.joules,
            "power_trace": [(round(t, 4), round(w, 2)) for t, w in m.gpu.trace]}


def ratios(rows: list[dict]) -> list[dict]:
    """Ours against the paper's, per configuration."""
    got = {(r["scene"], r["method"], r["radii"], r["boundary"], int(r["N"])):
           float(r["median_ms"]) for r in rows if r.get("status") == "ok"}
    pairs = (("RT-REF", "ORCS-forces"), ("RT-REF", "ORCS-persé"),
             ("CPU-CELL", "ORCS-forces"), ("GPU-CELL", "ORCS-forces"),
             ("GPU-CELL-fused", "ORCS-forces"), ("GPU-CELL", "GPU-CELL-fused"))
    keys = sorted({(r["scene"], r["radii"], r["boundary"], int(r["N"]))
                   for r in rows})
    out = []
    for scene, radii, boundary, n in keys:
        row = {"scene": scene, "radii": radii, "boundary": boundary, "N": n}
        for a, b in pairs:
            ka, kb = ((scene, m, radii, boundary, n) for m in (a, b))
            ours = got[ka] / got[kb] if ka in got and kb in got else None
            pa, pb = PAPER.get(ka), PAPER.get(kb)
            paper = pa / pb if pa and pb else None
            name = f"{a}/{b}"
            row[name] = None if ours is None else round(ours, 3)
            row[f"paper {name}"] = None if paper is None else round(paper, 3)
        out.append(row)
    return out


def _finish(rows: list[dict], path: Path) -> None:
    table = ratios(rows)
    _harness.write_csv(table, path)
    print("\npaper's claims:", PAPER_CLAIMS)
    cols = [c for c in table[0] if c not in ("scene", "radii", "boundary", "N")] \
        if table else []
    _harness.print_table(table, ["scene", "radii", "boundary", "N"] + cols)
    print("wrote", path)


def main(argv=None) -> None:
    parser = _harness.make_parser(__doc__)
    parser.add_argument("--n", type=int, nargs="+", default=list(NS))
    parser.add_argument("--scenes", nargs="+", default=SCENES, choices=SCENES)
    parser.add_argument("--radii", nargs="+", default=RADII, choices=RADII)
    parser.add_argument("--boundaries", nargs="+", default=BOUNDARIES,
                        choices=BOUNDARIES)
    parser.add_argument("--methods", nargs="+", default=METHODS,
                        choices=METHODS)
    parser.add_argument("--policy", default="gradient",
                        help="BVH policy of the RT methods (jaxrt.backends.rt.policy)")
    parser.add_argument("--list-format", default="Dense",
                        choices=("Dense", "Sparse", "OrderedSparse"),
                        help="layout of RT-REF's, GPU-CELL's and CPU-CELL's "
                        "lists")
    parser.add_argument("--snapshots", type=int, default=3)
    parser.add_argument("--jitter", type=float, default=0.01,
                        help="snapshot jitter, in smallest radii")
    parser.add_argument("--target-s", type=float, default=2.0,
                        help="seconds of timed steps per row (at least "
                        "--repeats, at most --max-repeats)")
    parser.add_argument("--max-repeats", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--fresh-workers", action="store_true",
                        help="one worker process per row (default: one for "
                        "the rows below n = 10^6, one per configuration "
                        "above; fresh after a failure)")
    parser.add_argument("--quick", action="store_true",
                        help="CPU smoke: n = 2000; disordered and cluster; "
                        "r = 1 and LN; >= 5 repeats, 0.5 s per row; "
                        "0.2 s energy windows")
    parser.add_argument("--cases", choices=("all",) + tuple(CASES),
                        default="all",
                        help="scene/radius pairs: all of --scenes x --radii, "
                        "or paper-energy (seed 003 §4.3: lattice r=160, "
                        "disordered r=1, cluster LN; replaces them)")
    parser.add_argument("--energy", action="store_true",
                        help="after each row's timing, repeat its step for "
                        "--energy-seconds under NVML (GPU) / RAPL (CPU): "
                        "energy_j, mean_power_w, interactions_per_joule; "
                        "power traces in <csv stem>_power.csv")
    parser.add_argument("--energy-seconds", type=float, default=None,
                        help="energy window per row (default 2 s, 0.2 with "
                        "--quick); NVML's counter ticks every 20-100 ms, so "
                        "keep it >= 1 s on a GPU")
    parser.add_argument("--energy-interval", type=float, default=0.01,
                        help="seconds between power samples")
    parser.add_argument("--plot-energy", metavar="CSV",
                        help="only redraw the energy figures from a run's CSV")
    _harness.add_common_args(parser, name="table2.csv", repeats=5, warmup=2,
                             timeout=900.0)
    args = parser.parse_args(argv)
    if args.plot_energy:
        import table2_energy_plot
        table2_energy_plot.plot_run(args.plot_energy)
        return
    if args.quick:
        args.n, args.repeats, args.target_s = [2000], 5, 0.5
        if args.scenes == SCENES:
            args.scenes = ("disordered", "cluster")
        if args.radii == RADII:
            args.radii = ("r=1", "LN[1,330]")
    if args.energy_seconds is None:
        args.energy_seconds = 0.2 if args.quick else 2.0
    # --scenes narrows a named case set too (e.g. the energy figures'
    # cluster row alone, when a budget ended before it).
    cases = ([c for c in CASES[args.cases] if c[0] in args.scenes]
             if args.cases in CASES else
             [(scene, radii) for radii in args.radii for scene in args.scenes])
    jobs = []
    # Small configurations first, so a budget keeps the most rows.
    for n in sorted(args.n):
        for radii in dict.fromkeys(r for _, r in cases):
            for boundary in args.boundaries:
                for scene in (s for s, r in cases if r == radii):
                    group = f"{n}/{radii}/{boundary}/{scene}"
                    for method in args.methods:
                        jobs.append({
                            "method": method, "scene": scene, "radii": radii,
                            "boundary": boundary, "N": n, "seed": args.seed,
                            "policy": args.policy,
                            "list_format": args.list_format,
                            "snapshots": args.snapshots, "jitter": args.jitter,
                            "repeats": args.repeats, "warmup": args.warmup,
                            "target_s": args.target_s,
                            "max_repeats": args.max_repeats,
                            "dynamics": DYNAMICS,
                            "_group": group,
                            # Below 10^6 one worker for all such rows
                            # (its start-up paid once); from 10^6 one per
                            # configuration, so that each starts with the
                            # device's memory free. A failure ends it.
                            "_worker": "run" if n < 1_000_000 else group})
                        if args.energy:
                            jobs[-1].update(
                                energy_seconds=args.energy_seconds,
                                energy_interval_s=args.energy_interval)
    columns = COLUMNS + (ENERGY_COLUMNS if args.energy else [])
    traces = TraceWriter(args, columns)
    # Shared workers (``_worker`` above; a failed row gets a fresh one for
    # the next); --fresh-workers: one per row.
    rows, path = _harness.run_jobs("table2:run_row", jobs, columns=columns,
                                   reuse_worker=not args.fresh_workers,
                                   on_row=traces, **_harness.run_options(args))
    _finish(rows, path.with_name(path.stem + "_ratios.csv"))
    if args.energy:
        _finish_energy(rows, path, traces.path)


def power_path(csv_path: Path) -> Path:
    """The power traces of a run: ``<stem>_power.csv`` beside its CSV."""
    csv_path = Path(csv_path)
    return csv_path.with_name(csv_path.stem + "_power.csv")


class TraceWriter:
    """``run_jobs``'s ``on_row``: moves each row's ``power_trace`` (a list
    the worker sent) into the long power CSV, one line per sample keyed by
    `TRACE_KEY`, written as the rows come (an interrupted run keeps them),
    then prints the row."""

    FIELDS = list(TRACE_KEY) + ["meter", "t_s", "power_w"]

    def __init__(self, args, columns: list[str]):
        self.args, self.columns = args, columns
        self.path: Path | None = None

    def __call__(self, row: dict) -> None:
        trace = row.pop("power_trace", None)
        if trace is not None:
            row["power_samples"] = len(trace)
        if self.args.energy:
            self._append(row, trace or [])
        _harness.print_row(row, self.columns)

    def _append(self, row: dict, trace: list) -> None:
        import csv
        if self.path is None:  # the first row: a fresh file for this run
            main_csv = _harness.out_path(self.args.out, self.args.name,
                                         row.get("device_slug", "unknown"))
            self.path = power_path(main_csv)
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with open(self.path, "w", newline="") as f:
                csv.writer(f).writerow(self.FIELDS)
        with open(self.path, "a", newline="") as f:
            w = csv.writer(f)
            key = [row.get(c) for c in TRACE_KEY]
            for t, watts in trace:
                w.writerow(key + ["gpu", t, watts])


def _finish_energy(rows: list[dict], path: Path, power: Path | None) -> None:
    """The energy table (Fig 12's numbers) and the figures."""
    import table2_energy_plot
    print("\ninteractions per joule (seed 003 Eq. 10; energy of the "
          "method's device over the energy window)")
    _harness.print_table([r for r in rows if r.get("energy_window_s")],
                         ["method", "scene", "radii", "boundary", "N",
                          "interactions_per_step", "energy_steps",
                          "energy_window_s", "energy_j", "mean_power_w",
                          "peak_power_w", "interactions_per_joule",
                          "gpu_energy_j", "energy_reason"])
    table2_energy_plot.plot_run(path, power)


if __name__ == "__main__":
    main()
