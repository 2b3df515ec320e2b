"""Seed 003's Figs 11-12 from a ``table2.py --energy`` run: power traces
and interactions per joule, per method, per case (scene and radius kind)
and boundary.

    python benchmarks/table2_energy_plot.py RUN.csv [--power RUN_power.csv]
    python benchmarks/table2_energy_plot.py --fake DIR   # made-up data, to
                                                          # check the drawing

Writes ``<stem>_efficiency.png`` (Fig 12: a bar per method, the window's
joules on top; "n/a" with no energy, e.g. CPU-CELL without RAPL; a failed,
out-of-memory or skipped row's slot says so) and
``<stem>_power.png`` (Fig 11: watts against seconds into the energy window;
CPU-CELL's line is the GPU idling, dashed) beside the CSV. Rows: wall,
periodic; columns: the cases present, in the paper's order.
"""
from __future__ import annotations

import argparse
import csv
import math
import os
import random
import sys
from pathlib import Path

if __package__:  # run as -m, or imported: the package's modules
    from benchmarks import _harness
else:  # run as a file: its folder is sys.path[0]
    import _harness

METHODS = ("RT-REF", "ORCS-forces", "ORCS-persé", "GPU-CELL",
           "GPU-CELL-fused", "CPU-CELL")
BOUNDARIES = ("wall", "periodic")
CASE_ORDER = (("lattice", "r=160"), ("disordered", "r=1"),
              ("cluster", "LN[1,330]"))
COLORS = {"RT-REF": "tab:blue", "ORCS-forces": "tab:orange",
          "ORCS-persé": "tab:green", "GPU-CELL": "tab:red",
          "GPU-CELL-fused": "tab:brown", "CPU-CELL": "tab:purple"}
KEY = ("method", "scene", "radii", "boundary", "N")


def _key(row: dict) -> tuple:
    return tuple(str(row.get(c)) for c in KEY)


def read_power(path: str | Path) -> dict[tuple, list[tuple[float, float]]]:
    """{(method, scene, radii, boundary, N) as strings: [(t_s, W), ...]}
    from a ``*_power.csv``; {} when the file is missing."""
    out: dict[tuple, list] = {}
    if not Path(path).is_file():
        return out
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            out.setdefault(_key(r), []).append((float(r["t_s"]),
                                                float(r["power_w"])))
    return out


def _cases(rows: list[dict]) -> list[tuple[str, str]]:
    """The (scene, radii) pairs present, the paper's three first."""
    seen = list(dict.fromkeys((r["scene"], r["radii"]) for r in rows))
    return ([c for c in CASE_ORDER if c in seen]
            + [c for c in seen if c not in CASE_ORDER])


def _number(v) -> float | None:
    try:
        v = float(v)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _grid(rows: list[dict]):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    cases = _cases(rows)
    fig, axes = plt.subplots(2, max(1, len(cases)), squeeze=False,
                             figsize=(4.2 * max(1, len(cases)), 6.5))
    return plt, fig, axes, cases


def _title(scene: str, radii: str, boundary: str, rows: list[dict]) -> str:
    ns = sorted({int(r["N"]) for r in rows if r["scene"] == scene
                 and r["radii"] == radii})
    return f"{scene.capitalize()} {radii}, {boundary}" + (
        f" (N={'/'.join(map(str, ns))})" if ns else "")


def _measured(row: dict) -> bool:
    return row.get("status") == "ok" and _number(
        row.get("energy_window_s")) is not None


def _no_bar(row: dict, value: float | None) -> str:
    """The label of a method's empty slot: why the row has no bar."""
    if not _measured(row):
        status = str(row.get("status") or "failed")
        reason = str(row.get("failed") or "")
        if "budget" in reason:
            return "not run\n(budget)"
        return {"oom": "OOM", "skipped": "skipped"}.get(status, status)
    return "n/a" if value is None else "0"


def plot_efficiency(rows: list[dict], path: Path) -> Path:
    """Fig 12: interactions per joule, a bar per method; log scale where
    the panel spans more than 30x."""
    plt, fig, axes, cases = _grid(rows)
    for c, (scene, radii) in enumerate(cases):
        for b, boundary in enumerate(BOUNDARIES):
            ax = axes[b][c]
            got = {r["method"]: r for r in rows if r["scene"] == scene
                   and r["radii"] == radii and r["boundary"] == boundary}
            methods = [m for m in METHODS if m in got]
            values = [_number(got[m].get("interactions_per_joule"))
                      if _measured(got[m]) else None for m in methods]
            real = [v for v in values if v]
            if real and max(real) / min(real) > 30:
                ax.set_yscale("log")
            if not methods or not any(_measured(got[m]) for m in methods):
                ax.text(0.5, 0.5, "no row measured", ha="center",
                        va="center", transform=ax.transAxes, fontsize=8)
            for x, (m, v) in enumerate(zip(methods, values)):
                if not v:  # why there is no bar: the row's status, n/a, 0
                    ax.text(x, 0.02, _no_bar(got[m], v), ha="center",
                            va="bottom", transform=ax.get_xaxis_transform(),
                            fontsize=7)
                    continue
                ax.bar(x, v, color=COLORS.get(m, "gray"))
                j = _number(got[m].get("energy_j"))
                if j is not None:
                    ax.annotate(f"{j:.3g} J", (x, v), ha="center",
                                va="bottom", fontsize=7)
            ax.set_xlim(-0.6, len(methods) - 0.4)  # n/a slots included
            ax.set_xticks(range(len(methods)))
            ax.set_xticklabels(methods, rotation=30, ha="right", fontsize=8)
            ax.set_title(_title(scene, radii, boundary, rows), fontsize=9)
            if c == 0:
                ax.set_ylabel("interactions / J")
    return _save(plt, fig, path, "Energy efficiency (seed 003 Fig 12; "
                 "energy over the energy window)")


def _save(plt, fig, path: Path, title: str) -> Path:
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_power(rows: list[dict], traces: dict, path: Path) -> Path:
    """Fig 11: the GPU's power samples against time in the window."""
    plt, fig, axes, cases = _grid(rows)
    for c, (scene, radii) in enumerate(cases):
        for b, boundary in enumerate(BOUNDARIES):
            ax = axes[b][c]
            drew = False
            for r in rows:
                if (r["scene"], r["radii"], r["boundary"]) != (
                        scene, radii, boundary) or not _measured(r):
                    continue
                trace = traces.get(_key(r), [])
                if not trace:
                    continue
                m = r["method"]
                cpu = str(r.get("energy_meter")) == "cpu"
                t, w = zip(*trace)
                ax.plot(t, w, color=COLORS.get(m, "gray"),
                        ls="--" if cpu else "-", lw=1,
                        label=m + (" (GPU idle)" if cpu else ""))
                drew = True
            if drew:
                ax.legend(fontsize=7)
            else:
                ax.text(0.5, 0.5, "no power samples", ha="center",
                        va="center", transform=ax.transAxes, fontsize=8)
            ax.set_title(_title(scene, radii, boundary, rows), fontsize=9)
            ax.set_xlabel("s into the energy window", fontsize=8)
            if c == 0:
                ax.set_ylabel("GPU power (W)")
    return _save(plt, fig, path, "Power (seed 003 Fig 11; NVML power "
                 "usage, a 1 s average on Hopper)")


def plot_run(csv_path: str | Path, power: str | Path | None = None
             ) -> tuple[Path, Path]:
    """Both figures beside a run's CSV (power: default ``<stem>_power.csv``).
    A row without an energy window (failed, out of memory, skipped) keeps
    its method's slot in Fig 12, labelled with its status."""
    csv_path = Path(csv_path)
    power = Path(power) if power else csv_path.with_name(
        csv_path.stem + "_power.csv")
    rows = _harness.read_csv(csv_path)
    eff = plot_efficiency(rows, csv_path.with_name(csv_path.stem
                                                   + "_efficiency.png"))
    pw = plot_power(rows, read_power(power),
                    csv_path.with_name(csv_path.stem + "_power.png"))
    print("wrote", eff, "and", pw)
    return eff, pw


def write_fake(folder: str | Path, seed: int = 0) -> tuple[Path, Path]:
    """A made-up run (the paper's cases, all methods, plausible watts;
    CPU-CELL without RAPL, persé skipped on LN) as ``fake.csv`` and
    ``fake_power.csv``: for checking the figures without a GPU."""
    rng = random.Random(seed)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rows, samples = [], []
    for scene, radii in CASE_ORDER:
        for boundary in BOUNDARIES:
            for m in METHODS:
                row = {"method": m, "scene": scene, "radii": radii,
                       "boundary": boundary, "N": 50000}
                if m == "ORCS-persé" and radii.startswith("LN"):
                    rows.append({**row, "status": "skipped",
                                 "failed": "persé needs equal radii"})
                    continue
                watts = rng.uniform(150, 400)
                seconds = 2.0 + rng.random()
                joules = watts * seconds
                per_step = rng.uniform(1e6, 1e8)
                steps = rng.randint(20, 400)
                cpu = m == "CPU-CELL"
                rows.append({**row, "status": "ok", "energy_window_s": seconds,
                             "energy_steps": steps,
                             "interactions_per_step": per_step,
                             "energy_meter": "cpu" if cpu else "gpu",
                             "energy_j": None if cpu else joules,
                             "mean_power_w": None if cpu else watts,
                             "interactions_per_joule":
                                 None if cpu else per_step * steps / joules,
                             "energy_reason": "no RAPL (fake)" if cpu else None})
                base = 75.0 if cpu else watts
                t = 0.0
                while t < seconds:
                    samples.append([m, scene, radii, boundary, 50000, "gpu",
                                    round(t, 3),
                                    round(base + rng.gauss(0, 5), 2)])
                    t += 0.01
    csv_path = _harness.write_csv(rows, folder / "fake.csv")
    power = folder / "fake_power.csv"
    with open(power, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(list(KEY) + ["meter", "t_s", "power_w"])
        w.writerows(samples)
    return csv_path, power


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("csv", nargs="?", help="a table2.py --energy CSV")
    parser.add_argument("--power", help="its power traces (default "
                        "<stem>_power.csv)")
    parser.add_argument("--fake", metavar="DIR",
                        help="write a made-up run into DIR and plot it")
    args = parser.parse_args(argv)
    if args.fake:
        csv_path, power = write_fake(args.fake)
        plot_run(csv_path, power)
    elif args.csv:
        plot_run(args.csv, args.power)
    else:
        parser.error("give a CSV or --fake DIR")


if __name__ == "__main__":
    main()
