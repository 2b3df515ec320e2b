"""The accuracy sweep's outputs: the CSV (`write_csv`), one plot per knob
(`plot_knob`) and the Markdown summary (`summary_lines`,
`write_summary`)."""
from __future__ import annotations

import csv
import math
import pathlib

import numpy as np

from jaxrt.tools.accuracy.knobs import KNOBS
from jaxrt.tools.accuracy.measures import ROUNDING_ULPS, pareto_front
from jaxrt.tools.provenance import PROVENANCE


# ---------------------------------------------------------------------------
# Outputs

ERRORS = (("force_rms_rel", "force RMS error (rel., vs float64 same "
           "potential)"),
          ("force_rms_rel_full", "force RMS error (rel., vs float64 LJ to "
           "r_ref)"),
          ("drift_per_particle_1e4", "|energy drift| per particle per 1e4 "
           "steps"),
          ("max_abs_dE_per_particle", "max |E(t) - E(t1)| / N"),
          ("pairs_missed", "pairs missed (vs float64 brute force)"),
          ("rdf_l2", "RDF L2 difference"),
          ("position_rms", "final position RMS deviation"))
"""The error columns, with the axis label of each."""

COLUMNS = ("scene", "knob", "value", "status", "failed", "time_per_step_ms",
           "time_min_ms", "time_max_ms", "repeats", "time_per_tau_ms",
           "force_rms_rel", "force_rms_rel_full", "drift_per_particle_1e4",
           "drift_se", "max_abs_dE_per_particle", "pairs_missed",
           "missed_depth_ulps", "pairs_checked", "rdf_l2", "rdf_linf",
           "position_rms", "rebuilds", "triangulation_rebuilds", "overflows",
           "steps", "N", "k", "dtype", "backend", "format", "skin",
           "capacity_multiplier", "dt",
           "cutoff", "truncation", "auto_backend")
"""The CSV's columns, then `PROVENANCE`."""


def write_csv(rows: list[dict], path: pathlib.Path) -> pathlib.Path:
    """All rows (`COLUMNS`, any others, then `PROVENANCE`), rewritten
    whole (via a temporary file) so an interrupted run keeps its rows."""
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    extra = [k for r in rows for k in r
             if k not in COLUMNS and k not in PROVENANCE]
    fields = list(COLUMNS) + list(dict.fromkeys(extra)) + [
        c for c in PROVENANCE if any(c in r for r in rows)]
    tmp = path.with_suffix(".tmp")
    with open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: _cell(v) for k, v in r.items()})
    tmp.replace(path)
    return path


def _cell(v):
    if isinstance(v, float):
        return "" if math.isnan(v) else f"{v:.6g}"
    return v


def num(row: dict, col: str) -> float:
    v = row.get(col)
    try:
        return float(v)
    except (TypeError, ValueError):
        return float("nan")


def _err(row: dict, col: str) -> float:
    v = num(row, col)
    return abs(v) if col == "drift_per_particle_1e4" else v


def plot_knob(rows: list[dict], knob: str, path: pathlib.Path
              ) -> pathlib.Path | None:
    """``path``: one panel per error column that varies, each error
    against the time per step (per unit of simulated time for ``dt``),
    every value labelled, the Pareto front
    drawn (the drift with ± one standard error); errors equal for every
    value are named in the title instead."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    mine = [r for r in rows if r["knob"] == knob and r.get("status") == "ok"]
    if not mine:
        return None
    cols, same = [], []
    for c, label in ERRORS:
        v = [_err(r, c) for r in mine]
        if not any(np.isfinite(v)):
            continue
        if len(mine) > 1 and all(x == v[0] for x in v):
            same.append(f"{c} = {fmt_value(v[0])}")
        else:
            cols.append((c, label))
    if not cols:
        cols = [("force_rms_rel", dict(ERRORS)["force_rms_rel"])]
    ncol = 2 if len(cols) > 1 else 1
    nrow = math.ceil(len(cols) / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(5.2 * ncol, 3.4 * nrow),
                             squeeze=False)
    # The time step's cost is per unit of simulated time, not per step.
    xcol, xlabel = (("time_per_tau_ms", "time per unit of simulated time "
                     "(ms)") if knob == "dt" else
                    ("time_per_step_ms", "time per step (ms)"))
    t = np.array([num(r, xcol) for r in mine])
    for ax, (col, label) in zip(axes.ravel(), cols):
        e = np.array([_err(r, col) for r in mine])
        if col == "drift_per_particle_1e4":
            se = np.array([num(r, "drift_se") for r in mine])
            ax.errorbar(t, e, yerr=np.where(np.isfinite(se), se, 0),
                        fmt="o", color="C0", ms=5, capsize=2, zorder=3)
        else:
            ax.scatter(t, e, color="C0", zorder=3)
        for r, x, y in zip(mine, t, e):
            if np.isfinite(y):
                ax.annotate(str(r["value"]), (x, y), fontsize=7,
                            xytext=(3, 3), textcoords="offset points")
        front = pareto_front(t, e)
        if front:
            ax.step(t[front], e[front], where="post", color="C3", lw=1.2,
                    label="Pareto front", zorder=2)
            ax.scatter(t[front], e[front], facecolors="none",
                       edgecolors="C3", s=80, zorder=4)
            ax.legend(fontsize=7)
        pos = e[np.isfinite(e) & (e > 0)]
        if pos.size and pos.max() / pos.min() > 20:
            if np.all(e[np.isfinite(e)] > 0):
                ax.set_yscale("log")
            else:
                ax.set_yscale("symlog", linthresh=pos.min())
        ax.set_xlabel(xlabel)
        ax.set_ylabel(label, fontsize=8)
        ax.grid(alpha=0.3)
    for ax in axes.ravel()[len(cols):]:
        ax.set_visible(False)
    title = f"{mine[0]['scene']}: knob {knob}"
    if same:
        title += "\nthe same for every value: " + ", ".join(same)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=72)
    plt.close(fig)
    return path


def depth_note(row) -> str:
    """How deep the missed pairs lay, for the summary ('' when unknown)."""
    depth = num(row, "missed_depth_ulps")
    if not np.isfinite(depth):
        return ""
    why = (": rounding of the distance in the positions' dtype, as "
           "jax-md's metric decides" if depth <= ROUNDING_ULPS else
           ": deeper than rounding, a wrong list")
    return f"; the deepest {fmt_value(depth)} ulps inside the cut{why}"


TARGETS = (("drift_per_particle_1e4", (1e-3, 1e-4),
            "an energy drift resolved below {x:g} per particle per 10^4 "
            "steps (|drift| + 2 standard errors)"),
           ("max_abs_dE_per_particle", (1e-3, 1e-4),
            "energy excursions max |E(t) - E(t1)| / N below {x:g}"),
           ("force_rms_rel", (1e-3, 1e-6),
            "a force RMS error below {x:g} (relative, vs float64 of the "
            "same potential)"),
           ("force_rms_rel_full", (1e-2, 1e-3),
            "a force RMS error below {x:g} against LJ cut at r_ref"))
"""Targets of the summary's sentences: (column, thresholds, phrase)."""

NOT_FOR = {"force_rms_rel": ("dt",), "force_rms_rel_full": ("dt",)}
"""Knobs a target does not judge: the force at one configuration does not
depend on the time step (its cost shows in the energy instead)."""


def fmt_value(v) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if v == 0:
        return "0"
    return f"{v:.3g}"


def _setting(r: dict) -> str:
    return f"`{r['knob']} = {r['value']}`"


def _bound(r: dict, col: str) -> float:
    """The error a target compares: the drift's |slope| + 2 standard
    errors (a drift resolved below the target), else the error itself."""
    if col == "drift_per_particle_1e4":
        return abs(num(r, col)) + 2 * num(r, "drift_se")
    return _err(r, col)


def cheapest(rows: list[dict], col: str, below: float) -> dict | None:
    """The ok row, fastest per unit of simulated time, whose error ``col``
    (`_bound`) is below ``below`` (rows of the knobs `NOT_FOR` excludes
    left out)."""
    ok = [r for r in rows if r.get("status") == "ok"
          and r["knob"] not in NOT_FOR.get(col, ())
          and _bound(r, col) < below
          and np.isfinite(num(r, "time_per_tau_ms"))]
    return min(ok, key=lambda r: num(r, "time_per_tau_ms"), default=None)


def _cost(r: dict) -> str:
    return (f"{fmt_value(num(r, 'time_per_step_ms'))} ms per step, "
            f"{fmt_value(num(r, 'time_per_tau_ms'))} ms per unit of time")


def summary_lines(rows: list[dict], meta: dict) -> list[str]:
    """The Markdown summary: what was run, the sentences, the table."""
    measured = [r for r in rows if r["knob"] != "reference"]
    ok = [r for r in measured if r.get("status") == "ok"]
    return (_summary_head(ok, meta) + _what_to_choose(measured, ok, meta)
            + _per_knob(measured, ok) + _all_rows(rows, meta))


def _summary_head(ok: list[dict], meta: dict) -> list[str]:
    """What was run, and the backend ``auto`` chose."""
    L = [f"# What accuracy costs in time: {meta['scene']}", ""]
    L.append(f"{meta['scene']}, N = {meta['N']}, {meta['steps']} steps per "
             f"run (chunks of {meta['chunk']}), on {meta.get('device', '?')}"
             f", git {meta.get('git_sha', '?')}, {meta.get('date', '?')}"
             f"{meta.get('load', '')}. "
             f"Base setting: {meta['base']}. Each row changes one knob from "
             "the base. Reference: the same scene in float64 from the same "
             "equilibrated state (its list by `cell`; its forces by a float64 "
             "brute force). \"Cheapest\" ranks by time per unit of simulated "
             "time (time per step / dt), which orders every knob but `dt` "
             "as the time per step does.")
    if meta.get("own_scenes"):
        L.append("")
        L.append("Knobs run elsewhere: " + "; ".join(meta["own_scenes"])
                 + " (its reference row: `reference = float64, <scene>`).")
    if not meta.get("only_own_scenes"):  # else stated with its scene
        L.append("")
        L.append(f"`backend=\"auto\"` chose **{meta['auto']}** for this "
                 "scene on this device (`jaxrt.lists.neighbors.choose_backend`).")
    backends_ok = [r for r in ok if r["knob"] == "backend"]
    if backends_ok:
        fastest = min(backends_ok, key=lambda r: num(r, "time_per_step_ms"))
        auto_row = next((r for r in backends_ok if r["value"] == meta["auto"]),
                        None)
        L.append(f"The fastest backend measured here was "
                 f"`{fastest['value']}` "
                 f"({fmt_value(num(fastest, 'time_per_step_ms'))} ms per step)"
                 + (f"; auto's `{meta['auto']}` took "
                    f"{fmt_value(num(auto_row, 'time_per_step_ms'))} ms."
                    if auto_row is not None and auto_row is not fastest
                    else "."))
    return L


def _what_to_choose(rows: list[dict], ok: list[dict], meta: dict
                    ) -> list[str]:
    """The cheapest setting per target, the lists that missed pairs, the
    RDFs beyond the noise, the settings not measured."""
    L = []
    L.append("")
    L.append("## What to choose")
    L.append("")
    for col, thresholds, phrase in TARGETS:
        if not any(np.isfinite(_bound(r, col)) for r in ok):
            continue
        for x in thresholds:
            best = cheapest(ok, col, x)
            if best is None:
                hint = ""
                if col == "drift_per_particle_1e4":
                    se = min(num(r, "drift_se") for r in ok)
                    hint = (f" (the smallest standard error of a drift here "
                            f"is {fmt_value(se)} per 10^4 steps: runs of "
                            f"{meta['steps']} steps cannot resolve much "
                            "less)")
                L.append(f"- For {phrase.format(x=x)}: no setting measured "
                         f"meets it{hint}.")
            else:
                L.append(f"- For {phrase.format(x=x)}, the cheapest setting "
                         f"is {_setting(best)}: {_cost(best)} "
                         f"({col} = {fmt_value(num(best, col))}).")
    if any(np.isfinite(num(r, "pairs_missed")) for r in ok):
        lossy = [r for r in ok if num(r, "pairs_missed") > 0]
        if lossy:
            L.append("- Settings whose list missed pairs: " + ", ".join(
                f"{_setting(r)} ({fmt_value(num(r, 'pairs_missed'))} of "
                f"{fmt_value(num(r, 'pairs_checked'))}{depth_note(r)})"
                for r in lossy) + ".")
        else:
            L.append("- No setting's list missed a pair (checked against a "
                     "float64 brute force after every chunk, with radii at "
                     "max(r_i, r_j)): the list knobs (skin, format, "
                     "backend, cell kernel, Delaunay's options, BVH policy, "
                     "ε, jaxrt.pairs, radii) trade time only.")
    by_knob = meta.get("rdf_noise_by_knob") or {}

    def floor(r):
        v = by_knob.get(r["knob"], meta.get("rdf_noise"))
        return math.nan if v is None else v
    floors = [f"{fmt_value(meta['rdf_noise'])} (L2)"] if meta.get(
        "rdf_noise") is not None else []
    floors += [f"{fmt_value(v)} for `{k}`'s own scene" for k, v in by_knob.items()
               if v is not None]
    if floors and any(np.isfinite(num(r, "rdf_l2")) for r in ok):
        above = [r for r in ok if num(r, "rdf_l2") > 2 * floor(r)]
        L.append(f"- The RDFs of the reference run's two halves differ by "
                 f"{', '.join(floors)}: the noise floor. Settings beyond "
                 "twice that: " + (", ".join(
                     f"{_setting(r)} ({fmt_value(num(r, 'rdf_l2'))})"
                     for r in above) if above else "none") + ".")
    bad = [r for r in rows if r.get("status") != "ok"]
    if bad:
        L.append("- Not measured: " + "; ".join(
            f"{_setting(r)} ({r.get('status')}: "
            f"{str(r.get('failed', ''))[:100]})" for r in bad) + ".")
    return L


def _per_knob(rows: list[dict], ok: list[dict]) -> list[str]:
    """Per knob: the fastest, the most accurate, the Pareto front."""
    L = []
    L.append("")
    L.append("## Per knob")
    L.append("")
    whats = {k.name: k.what for k in KNOBS}
    L.append("What each knob varies: " + "; ".join(
        f"**{k}**: {whats[k]}" for k in dict.fromkeys(r["knob"] for r in rows)
        if whats.get(k)) + ".")
    L.append("")
    judges = {k.name: k.judge for k in KNOBS}
    for knob in dict.fromkeys(r["knob"] for r in rows):
        mine = [r for r in ok if r["knob"] == knob]
        if not mine:
            continue
        judge = judges.get(knob, "force_rms_rel")
        if not any(np.isfinite(_err(r, judge)) for r in mine):
            fast = min(mine, key=lambda r: num(r, "time_per_tau_ms"))
            L.append(f"- **{knob}**: no error measure here applies to it "
                     f"(no energy in this scene); fastest `{fast['value']}` "
                     f"({_cost(fast)}).")
            continue
        t = [num(r, "time_per_tau_ms") for r in mine]
        e = [_err(r, judge) for r in mine]
        front = [mine[i] for i in pareto_front(t, e)]
        fast = min(mine, key=lambda r: num(r, "time_per_tau_ms"))
        best = min(mine, key=lambda r: (_err(r, judge)
                                        if np.isfinite(_err(r, judge))
                                        else math.inf))
        # Values without the measure (a list-free value's pairs) do not
        # make the others differ.
        measured = [_err(r, judge) for r in mine
                    if np.isfinite(_err(r, judge))]
        if all(v == measured[0] for v in measured):
            some = "" if len(measured) == len(mine) else " that has it"
            L.append(f"- **{knob}** ({judge} the same for every value{some}"
                     f", {fmt_value(measured[0])}): fastest "
                     f"`{fast['value']}` ({_cost(fast)}).")
            continue
        L.append(f"- **{knob}** (by {judge}): fastest `{fast['value']}` "
                 f"({_cost(fast)}; {fmt_value(_err(fast, judge))}); most "
                 f"accurate `{best['value']}` ({_cost(best)}; "
                 f"{fmt_value(_err(best, judge))}); Pareto front: " + ", ".join(
                     f"`{r['value']}`" for r in front) + ".")
    return L


def _all_rows(table: list[dict], meta: dict) -> list[str]:
    """Every row, the reference's included, and the definitions."""
    L = []
    L.append("")
    L.append("## All rows")
    L.append("")
    rows = table
    cols = ["time_per_step_ms", "force_rms_rel", "force_rms_rel_full",
            "drift_per_particle_1e4", "drift_se", "max_abs_dE_per_particle",
            "pairs_missed", "rdf_l2", "position_rms", "rebuilds",
            "triangulation_rebuilds"]
    cols = [c for c in cols if any(np.isfinite(num(r, c)) for r in rows)]
    heads = {"time_per_step_ms": "ms/step", "force_rms_rel": "force err",
             "force_rms_rel_full": "force err vs r_ref",
             "drift_per_particle_1e4": "drift /N/1e4 steps",
             "drift_se": "± (s.e.)", "max_abs_dE_per_particle": "max |ΔE|/N",
             "pairs_missed": "missed", "rdf_l2": "RDF L2",
             "position_rms": "pos. RMS", "rebuilds": "rebuilds",
             "triangulation_rebuilds": "DT rebuilds"}
    L.append("| knob | value | " + " | ".join(heads[c] for c in cols)
             + " | status |")
    L.append("| --- | --- | " + " | ".join("---" for _ in cols) + " | --- |")
    for r in rows:
        vals = [fmt_value(num(r, c)) if c not in ("pairs_missed", "rebuilds",
                                              "triangulation_rebuilds")
                or not np.isfinite(num(r, c)) else str(int(num(r, c)))
                for c in cols]
        L.append(f"| {r['knob']} | {r['value']} | " + " | ".join(vals)
                 + f" | {r.get('status')} |")
    L.append("")
    L.append("Definitions: `jaxrt/tools/accuracy/__init__.py`'s docstring. Drift: the "
             "least-squares slope of (E(t) − E(t₁))/N over the run, scaled "
             f"to 10⁴ steps (runs of {meta['steps']} steps), ± its standard "
             "error from 10 block means. Times: median over the run's "
             "chunks, compilation excluded.")
    return L




def write_summary(rows: list[dict], meta: dict, path: pathlib.Path
                  ) -> pathlib.Path:
    pathlib.Path(path).write_text("\n".join(summary_lines(rows, meta)) + "\n")
    return path
