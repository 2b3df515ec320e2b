"""The seed study's report: speed-ups, the headline table (markdown) and
the seed-style bar plots, from the rows (or from a CSV read by
`_harness.read_csv`, ``--plot-only``)."""
from __future__ import annotations

import math
from pathlib import Path

if __package__ == "benchmarks.seed_rt":  # the package's module
    from benchmarks import _harness
    from benchmarks.seed_rt.plan import METHODS, SCENES, n_of
else:  # seed_rt_study.py run as a file: benchmarks/ is sys.path[0]
    import _harness
    from seed_rt.plan import METHODS, SCENES, n_of

COLORS = {"aabb-unsorted": "#ff7f0e", "aabb-sorted": "#d62728",
          "spheres": "#2ca02c", "squares": "#1f77b4", "cell": "#9467bd",
          "jax-md": "#7f7f7f",
          # the fused mode: the list method's hue, darker
          "aabb-unsorted-fused": "#a65206", "aabb-sorted-fused": "#8b1a1b",
          "spheres-fused": "#1a661a", "squares-fused": "#0f4470"}


def _ok(row) -> bool:
    v = row.get("total_ms")
    return v not in (None, "") and status_of(row) == "ok" and math.isfinite(float(v))


_LABELS = {"oom": "OOM", "timeout": "timeout", "crashed": "crash",
           "error": "fail"}


def status_of(row) -> str:
    """A row's ``status`` (`_harness.STATUSES`). CSVs written before the
    harness (results/h100/seed_rt/) have no status column: there it is
    read off the ``failed`` text this script wrote itself, the one place
    that parses it."""
    status = str(row.get("status") or "")
    if status:
        return status
    f = str(row.get("failed") or "")
    if not f:
        return "ok"
    if f.startswith("skipped"):
        return "skipped"
    if f.startswith("out of memory"):
        return "oom"
    if f.startswith(("timeout", "killed")):
        return "timeout"
    if f.startswith("crashed"):
        return "crashed"
    return "error"


def short_reason(row) -> str:
    """The label of a row without times on the plots and in the headline."""
    status = status_of(row)
    if status == "ok":
        return ""
    if status == "skipped":
        f = str(row.get("failed") or "")
        if f.startswith("skipped: not selected"):
            return "n/s"
        if f.startswith("skipped: N > --max-n"):
            return "N>max"
        if f.startswith(("skipped: Dense list", "skipped: 4N")):
            # The plan skips what allocate would refuse (jax-md: its list
            # would pass int32, as it did where it ran).
            return "int32" if row.get("method") == "jax-md" else "refused"
        return "skip"
    if status == "error":
        f = str(row.get("failed") or "")
        for pattern, label in _ERROR_LABELS:
            if pattern in f:
                return label
    return _LABELS.get(status, "fail")


# Errors that are a method's documented refusal, not a fault: jaxrt's
# refusal of a list it cannot index, jax-md failing to size one past
# int32, and the spheres method's refusal of near-coincident particles.
_ERROR_LABELS = (("more than backend=", "refused"),
                 ("out of bounds for int32", "int32"),
                 ("ParticlesTooCloseError", "too close"))


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
                 "refused = the list passes what jaxrt can index (2^29 "
                 "entries for Warp, 2^31 otherwise); int32 = jax-md's list "
                 "passes int32; too close = spheres' refusal of "
                 "near-coincident particles; timeout / crash / fail: see the "
                 "CSV's `failed` column.")
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
                     "budget; refused / int32 / too close / timeout / crash / "
                     "fail: see the CSV", fontsize=8)
        path = folder / fname
        fig.savefig(path, dpi=130)
        plt.close(fig)
        paths.append(path)
    return paths


def report(rows: list[dict], folder: Path) -> None:
    """Plots, the table of the rows that were planned, and the headline
    (printed and written to ``seed_rt_headline.md``) in ``folder``."""
    for p in plot(rows, folder):
        print("wrote", p)
    shown = _attempted(rows)
    _harness.print_table(shown, ["scene", "param", "p", "N", "method", "init_ms",
                                 "compute_ms", "search_ms", "speedup_vs_jaxmd",
                                 "k_mean", "init_reps", "compute_reps",
                                 "overflow", "status", "failed"])
    md = headline_markdown(rows)
    (folder / "seed_rt_headline.md").write_text(md + "\n")
    print("\nHeadline (also in", folder / "seed_rt_headline.md", "):")
    print(md)
