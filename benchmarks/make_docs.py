"""Generate docs/benchmarks.md (and the README's headline table) from the
CSVs under benchmarks/results/.

    python3 benchmarks/make_docs.py           # rewrite both
    python3 benchmarks/make_docs.py --check   # exit 1 if either is stale

Nothing in the page is written by hand: each table is one CSV as the
benchmark scripts wrote it (`benchmarks/_harness.py`), grouped by benchmark
and device. Files whose names differ only by a commit sha or a run letter
(``neighbors_1e5_254f92a_a.csv``, ``neighbors_1e5_8e964e8_b.csv``) are runs
of one table: the newest run (by the ``date`` of its rows) is shown, the
earlier ones are listed with their sha and date. Provenance (device,
versions, git sha, date) and the columns that hold one value across the
table go to the line above it; ``*_ratios.csv`` are shown under the table
they belong to; CSVs without provenance (per-call traces, power samples)
are listed as raw data. Only the standard library is used, so the test
suite can check that the committed page is up to date
(`tests/test_docs.py`).
"""
from __future__ import annotations

import argparse
import csv
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
PAGE = ROOT / "docs" / "benchmarks.md"
README = ROOT / "README.md"
START, END = "<!-- benchmarks:start -->", "<!-- benchmarks:end -->"

# Devices in the order the page shows them: folder under results/ -> title.
DEVICES = {
    "h200": "NVIDIA H200 (no RT cores)",
    "cpu-2core": "2-core CPU VM (its speed varies about 2x from day to day)",
    "h100": "NVIDIA H100 (earlier code, kept as history)",
}
# Devices whose CSVs are listed, not shown: no current code ran there.
HISTORY = {"h100"}

# Benchmarks in page order: key (the prefix of the CSV names it writes),
# title, script, what a row measures.
BENCHMARKS = [
    ("neighbors", "Neighbour-list rebuild", "benchmarks/neighbors.py",
     "One `update` (a rebuild, no skin) and `allocate` of each backend "
     "against jax-md's list: a uniform fluid (density 1, cutoff 2.5) and "
     "points on a sphere surface; time and memory. `reallocate_ms` is an "
     "`allocate` on a new structure of the same N."),
    ("rt_neighbors", "Ray-traced list against Warp's HashGrid",
     "benchmarks/rt_neighbors.py",
     "The `bvh` backend's list (rebuild and refit, eager and jitted) beside "
     "Warp's HashGrid build and query."),
    ("cold_start", "A newcomer's first list, beside jax-md",
     "benchmarks/cold_start.py",
     "Process CPU and wall seconds of each phase of a first use, each "
     "(library, N) in a fresh process: import, `neighbor_list` + "
     "`allocate`, the first eager `update`, the median of 5 more eager "
     "`update` calls, the first and the median later call of "
     "`jax.jit(update)`, then (warm) a second `neighbor_list` + `allocate` "
     "and its first `update`. Periodic uniform fluid (density 0.8), "
     "r_cutoff 1.5, dr_threshold 0.5, Dense, default backend."),
    ("allocate_parts", "Where an `allocate` goes", "benchmarks/allocate_parts.py",
     "An `allocate` on a new structure split into the metric model, the "
     "counting (`measure`), the build and the trim to jax-md's shapes."),
    ("md_step", "Lennard-Jones NVE step", "benchmarks/md_step.py",
     "One whole velocity-Verlet step of an LJ fluid: list update and "
     "forces (`jaxrt:<backend>/<layout>`, `jax-md/<layout>`) or no list at "
     "all (`fused:<backend>`, `jaxrt.energy.lennard_jones_fused`)."),
    ("list_forces", "A list step's pieces per layout", "benchmarks/list_forces.py",
     "The update, the Dense-to-Sparse conversion, the forces and the edge "
     "reductions, for Dense, Sparse and OrderedSparse lists."),
    ("list_order", "A Dense list's forces and rebuild per particle numbering",
     "benchmarks/list_order.py",
     "Forces on a fixed Dense list, the neighbours' gathers alone and a "
     "forced rebuild, with the LJ fluid's particles numbered x-major "
     "(`lattice`, as md_step), shuffled (`random`) or along a Hilbert "
     "curve (`jaxrt.spatial_order`); `gap` is the median index distance "
     "of a list's entries."),
    ("sph_step", "SPH step: lists against list-free", "benchmarks/sph_step.py",
     "One SPH step (density, pressure, viscosity) on a `cell` list "
     "(`list:`) or with `jaxrt.energy.density_fused` / "
     "`acceleration_fused` (`fused:`); `max_rel_diff` is the largest "
     "relative difference of the accelerations between the two."),
    ("roofline", "Roofline of the cell kernels", "benchmarks/roofline.py",
     "The cell rebuild and the list-free LJ sums against the copy bandwidth "
     "and FP32 rate measured in the same run (`of_limit`: the time over the "
     "bound's time)."),
    ("grid_stages", "The list-free step's cell grid, stage by stage",
     "benchmarks/grid_stages.py",
     "Keys, sort, cell starts and runs of the grid the list-free kernels "
     "walk, beside the alternatives."),
    ("warp_stages", "The Warp list-free LJ engine, stage by stage",
     "benchmarks/warp_stages.py",
     "Bin, radix sort, cell table, gather and the walk's variants of "
     "`Cell(kernel=\"warp\")` timed apart on the GPU (CUDA events), the "
     "pipeline whole, the host's launches, and each stage's floor from "
     "its bytes and flops."),
    ("warp_rebuild_stages", "The Warp cell-list rebuild, stage by stage",
     "benchmarks/warp_rebuild_stages.py",
     "Bin, radix sort, gather, grid, cell table and the rows walk of a "
     "`cell[warp]` Dense rebuild timed apart on the GPU (CUDA events), the "
     "jitted `update` whole, and the host's enqueue time."),
    ("warp_rows_variants", "How the Warp rows walk stores its rows",
     "benchmarks/warp_rows_variants.py",
     "The `cell[warp]` rows walk at N = 10^6 next to variants that differ "
     "only in their stores (none, 16- and 32-byte stores, rows in sorted "
     "order, a transposed layout, lane groups with ballot-compacted "
     "stores), each checked against the library's rows."),
    ("kernel_profile", "A jitted call's GPU kernels against its wall time",
     "benchmarks/kernel_profile.py",
     "JAX's profiler on `jaxrt.pairs`, the Warp rows call and the Dense "
     "list update: device time per kernel per call, the device's busy "
     "time and the wall time (the gap is launches and host read-backs)."),
    ("pairs", "`jaxrt.pairs` against ASE, matscipy, vesin",
     "benchmarks/pairs.py",
     "Pairs with lattice shifts of silicon (cutoff 5 Å, float64 on the "
     "CPU), jitted and eager, against the libraries it replaces."),
    ("graphs", "Graphs for ML potentials: `jaxrt.pairs` and `pairs_batch` "
     "against vesin", "benchmarks/graphs.py",
     "The issue's structures and flat batches (float64, cutoff 5 Å, the "
     "methods interleaved in one process): jitted with static sizes, eager, "
     "vesin, matscipy where installed, ASE on small systems; "
     "`graphs_compiles`: programs compiled and time over a data set of 50 "
     "atom counts; `graphs_dense_cells`: flat batches searched as dense "
     "blocks against the cell search (what `pairs_batch_sizes` chooses "
     "between)."),
    ("radii", "Per-particle radii", "benchmarks/radii.py",
     "Lists with per-particle radii on seed 003's scenes: the cell list by "
     "radius classes, one grid of the largest radius, and the BVH."),
    ("accuracy", "What accuracy costs in time (`jaxrt accuracy`)",
     "jaxrt/tools/accuracy",
     "One knob changed at a time from a scene's own setting: time per step "
     "against the force error (`force_rms_rel`), the NVE drift per particle "
     "per 10⁴ steps, the pairs missed against a float64 brute force and the "
     "RDF's difference. The `summary.md` beside each CSV states the "
     "cheapest setting per error bound."),
    ("seed_rt_study", "Seed 001's study: the ray-traced methods",
     "benchmarks/seed_rt_study.py",
     "Compute time (one list rebuild plus the LJ energy over it; for the "
     "`-fused` methods the energy summed during the traversal, no list) of "
     "every method on every configuration of seed 001's §5 (uniform "
     "(β, p), sphere surface (α, p)); a cell holds the status where a row "
     "did not run (`skipped`: refused at `allocate`, past what it can "
     "index)."),
    ("table2", "Seed 003's Table 2", "benchmarks/table2.py",
     "ms per LJ step of RT-REF, ORCS-forces, ORCS-persé, the cell lists "
     "and the fused cell kernel on seed 003's scenes and radius kinds, "
     "wall and periodic, beside the paper's numbers (`paper_ms`); the "
     "`_energy` runs add the GPU's energy per step."),
    ("figure8", "Seed 003's Figure 8: BVH policies", "benchmarks/figure8.py",
     "An RT-REF run under the gradient, avg and fixed rebuild policies "
     "(update + query per step); `vs_*` are the gradient policy's time over "
     "the others'; `forced_rebuilds` counts rebuilds no policy asked for; "
     "`dq_us` is Eq. 8's Δq, the query's growth per refit, measured against "
     "a tree rebuilt at every sample (runs before the refits became exact "
     "lack these columns)."),
    ("delaunay", "Seed 004: Delaunay against grids (2D, float64)",
     "benchmarks/delaunay.py",
     "Update time per step of the `delaunay` backend against `cell` and "
     "jax-md (Boids and random motion), flips and rebuilds per step."),
    ("domains", "Domain decomposition", "benchmarks/domains.py",
     "Strong and weak scaling of `jaxrt.sim.domains` (fake CPU devices: a "
     "check, not a speed-up)."),
]
# Scripts whose output is not a table of this page.
OTHER_SCRIPTS = [
    ("benchmarks/run_h200.sh", "the GPU tables behind the headline in one "
     "device call (`--quick`: a CPU smoke run)"),
    ("benchmarks/run_pending_h200.sh PART", "one part of the GPU work per "
     "device call (its header lists the parts)"),
    ("benchmarks/run_table2_h200.sh", "seed 003's Table 2 in parts"),
    ("benchmarks/run_figure8_h200.sh PART", "seed 003's Figure 8 in three "
     "parts, and their merge"),
    ("benchmarks/table2_energy_plot.py", "seed 003's energy figures from a "
     "`table2.py --energy` run"),
    ("benchmarks/step_overhead.py", "where a step's host time goes (dispatch, "
     "Warp callbacks, read-backs, launches)"),
    ("benchmarks/profile_cell_kernels.py", "a driver for Nsight Compute on "
     "the cell kernels"),
    ("benchmarks/tune_cell_list.py", "the cell list's stencil reach, swept"),
    ("benchmarks/debug/debug_pairs_gpu.py", "`jaxrt.pairs` under `vmap` "
     "against ASE with several `XLA_FLAGS` (XLA's GPU level 0 miscompiles "
     "it)"),
]
# CSV name prefixes written by a script of another name.
ALIASES = {"list_update": "list_forces", "rt_query_groups": "rt_neighbors"}

PROVENANCE = ("device", "device_kind", "device_slug", "host", "jax", "jaxlib",
              "jax_md", "warp", "python", "numpy", "git_sha", "library_git",
              "date", "how")
# Columns left out of the tables (spread and bookkeeping, not results).
DROPPED = re.compile(
    r"(^|_)(min|max)_ms$|_min_ms$|_max_ms$|_reps$|^warmup$|^target_s$"
    r"|^min_repeats$|^max_repeats$|^trace$|^dynamics$|^power_samples$")
# Per benchmark, the columns to show (in this order) where a CSV has them.
COLUMNS = {
    "accuracy": ["scene", "knob", "value", "status", "time_per_step_ms",
                 "force_rms_rel", "drift_per_particle_1e4", "pairs_missed",
                 "pairs_checked", "rdf_l2", "rebuilds", "overflows",
                 "failed"],
    "table2": ["scene", "radii", "boundary", "method", "format", "k",
               "median_ms", "paper_ms", "status", "energy_j",
               "mean_power_w", "interactions_per_joule", "failed"],
}
# Benchmarks whose runs each re-measure a part of one big table: their runs
# on a device are merged row by row (these columns name a row; the newest
# run of a row wins), except the files whose name has one of `separate`.
MERGED = {"table2": (("N", "radii", "scene", "boundary", "method"),
                     ("energy",))}
MAX_ROWS = 60
MAX_CELL = 60
HEX7 = re.compile(r"[0-9a-f]{7}")


def _is_sha(token: str) -> bool:
    return (bool(HEX7.fullmatch(token)) and re.search("[a-f]", token) is not None
            and re.search("[0-9]", token) is not None)


def _strip_runs(name: str) -> str:
    """A file or folder name without its commit shas and run letters."""
    tokens = name.split("_")
    out = [t for t in tokens if not _is_sha(t)]
    if len(out) < len(tokens) and out and re.fullmatch("[a-z]", out[-1]):
        out = out[:-1]  # a run letter after a sha: neighbors_1e5_254f92a_a
    return "_".join(out)


@dataclass
class Table:
    path: Path                       # the CSV
    rows: list[dict]
    columns: list[str]
    companions: list["Table"] = field(default_factory=list)

    @property
    def rel(self) -> str:
        return self.path.relative_to(RESULTS).as_posix()

    @property
    def date(self) -> str:
        return max((r.get("date") or "" for r in self.rows), default="")

    @property
    def shas(self) -> list[str]:
        seen: dict[str, None] = {}
        for r in self.rows:
            sha = (r.get("git_sha") or r.get("library_git") or "").strip()
            if sha:
                seen[sha[:7] + ("+" if len(sha) > 40 else "")] = None
        return list(seen)

    @property
    def has_provenance(self) -> bool:
        return any(c in self.columns for c in ("git_sha", "library_git",
                                               "date", "device"))


def _read(path: Path) -> Table:
    with path.open(newline="", encoding="utf-8") as f:
        reader = csv.DictReader(f)
        rows = [dict(r) for r in reader]
        columns = list(reader.fieldnames or [])
    return Table(path, rows, columns)


def benchmark_of(rel: Path) -> str | None:
    """The benchmark key a CSV belongs to, from its name or its folders."""
    keys = sorted([k for k, *_ in BENCHMARKS] + list(ALIASES), key=len,
                  reverse=True)
    for name in [rel.stem] + [p.name for p in reversed(rel.parents[:-1])]:
        for key in keys:
            if name == key or name.startswith(key + "_"):
                return ALIASES.get(key, key)
    return None


def series_of(bench: str, rel: Path) -> str:
    """The table a CSV is a run of: its path without shas and run letters."""
    if bench == "seed_rt_study":
        return "seed_rt_study"     # parts and merges of one study
    if bench in MERGED and not any(word in rel.name
                                   for word in MERGED[bench][1]):
        return "_merged"
    parts = [_strip_runs(p) for p in rel.with_suffix("").parts]
    return "/".join(p for p in parts if p)


def collect() -> dict[str, dict[str, dict[str, list[Table]]]]:
    """benchmark -> device -> series -> runs (newest first)."""
    found: dict[str, dict[str, dict[str, list[Table]]]] = {}
    raw: dict[tuple[str, str], list[Table]] = {}
    for path in sorted(RESULTS.rglob("*.csv")):
        rel = path.relative_to(RESULTS)
        device = rel.parts[0]
        bench = benchmark_of(Path(*rel.parts[1:]))
        if bench is None or device not in DEVICES:
            raise SystemExit(f"{rel}: no benchmark or device for this CSV; "
                             "add its prefix to BENCHMARKS or ALIASES")
        table = _read(path)
        if path.stem.endswith("_ratios"):
            continue                    # attached to its table below
        if not table.has_provenance:
            raw.setdefault((bench, device), []).append(table)
            continue
        ratios = path.with_name(path.stem + "_ratios.csv")
        if ratios.exists():
            table.companions.append(_read(ratios))
        series = series_of(bench, Path(*rel.parts[1:]))
        found.setdefault(bench, {}).setdefault(device, {}).setdefault(
            series, []).append(table)
    for bench, devices in found.items():
        for device, all_series in devices.items():
            for runs in all_series.values():
                runs.sort(key=lambda t: (t.date, "merged" in t.rel, t.rel),
                          reverse=True)
    for (bench, device), tables in raw.items():
        found.setdefault(bench, {}).setdefault(device, {})["_raw"] = tables
    return found


def _number(text: str) -> str:
    try:
        value = float(text)
    except ValueError:
        return text
    if re.fullmatch(r"-?\d+", text.strip()):
        return text.strip()
    if value != value or value in (float("inf"), float("-inf")):
        return text
    if value == 0:
        return "0"
    if abs(value) >= 1000:
        return f"{value:.0f}"
    if abs(value) >= 0.01:
        return f"{value:#.3g}".rstrip(".")
    return f"{value:.2e}"


def _value(row: dict, column: str) -> str:
    """A row's value, blank where the CSV holds nothing or NaN."""
    text = (row.get(column) or "").strip()
    return "" if text.lower() == "nan" else text


def _cell(text: str) -> str:
    text = " ".join((text or "").split())
    if len(text) > MAX_CELL:
        text = text[:MAX_CELL - 1] + "…"
    return _number(text).replace("|", "\\|")


def _md_table(header: list[str], rows: list[list[str]]) -> list[str]:
    out = ["| " + " | ".join(header) + " |",
           "| " + " | ".join("---" for _ in header) + " |"]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return out


def _out_of_budget(row: dict) -> bool:
    return (row.get("status") == "skipped"
            and "time budget" in (row.get("failed") or ""))


def _plain_table(bench: str, table: Table) -> tuple[list[str], list[str]]:
    """(constant columns as 'name = value', markdown lines)."""
    rows = [r for r in table.rows if not _out_of_budget(r)]
    left_out = len(table.rows) - len(rows)
    columns = [c for c in table.columns if c not in PROVENANCE
               and not DROPPED.search(c)]
    columns = [c for c in columns if any(_value(r, c) for r in rows)]
    wanted = COLUMNS.get(bench)
    constants, shown = [], []
    seen: dict[tuple, str] = {}
    for c in columns:
        values = tuple(_value(r, c) for r in rows)
        if len(rows) > 1 and len(set(values)) == 1:
            constants.append(f"{c} = {_cell(values[0])}")
        elif wanted and c not in wanted:
            continue
        elif values in seen:
            continue                    # a copy of another column
        else:
            seen[values] = c
            shown.append(c)
    body = [[_cell(_value(r, c)) for c in shown] for r in rows[:MAX_ROWS]]
    lines = _md_table(shown, body) if shown else []
    if left_out:
        lines += ["", f"({left_out} rows not run: the run's time budget was "
                  "spent)"]
    if len(rows) > MAX_ROWS:
        lines.append("")
        lines.append(f"(the first {MAX_ROWS} of {len(rows)} rows; the CSV "
                     "has them all)")
    return constants, lines


def _seed_rt_pivot(table: Table) -> tuple[list[str], list[str]]:
    """Compute time per configuration (rows) and method (columns)."""
    methods: dict[str, None] = {}
    configs: dict[tuple, dict[str, str]] = {}
    for r in table.rows:
        methods[r["method"]] = None
        key = (r["scene"], r["param"], r["p"], r["N"])
        cell = configs.setdefault(key, {})
        if r.get("param_name"):
            cell.setdefault("param_name", r["param_name"])
        status = (r.get("status") or "ok").strip()
        value = _value(r, "compute_ms")
        cell[r["method"]] = _cell(value) if status == "ok" and value else status
        if _value(r, "k_mean") and status == "ok":
            cell.setdefault("k", _cell(r["k_mean"]))
    header = ["scene", "param", "p", "N", "k"] + list(methods)
    body = []
    for (scene, param, p, n), cell in configs.items():
        name = cell.get("param_name")
        body.append([scene, f"{name} = {param}" if name else param, p, n,
                     cell.get("k", "")] + [cell.get(m, "") for m in methods])
    return ["compute_ms per method"], _md_table(header, body)


def _provenance(table: Table) -> str:
    r0 = next((r for r in table.rows if r.get("device")), table.rows[0])
    bits = []
    device = (r0.get("device") or "").split(":", 1)[-1]
    if device and device != "cpu" and r0.get("device", "").startswith("gpu"):
        bits.append(device)
    elif r0.get("device", "").startswith("cpu") or device == "cpu-2core":
        bits.append("CPU")
    shas = table.shas
    if shas:
        bits.append("git " + ", ".join(shas[:4])
                    + (f" (+{len(shas) - 4})" if len(shas) > 4 else ""))
    if table.date:
        bits.append(table.date[:10])
    versions = [f"{name} {r0[key]}" for key, name in
                (("jax", "jax"), ("jax_md", "jax-md"), ("warp", "warp"))
                if (r0.get(key) or "").strip() not in ("", "absent")]
    if versions:
        bits.append(", ".join(versions))
    return " · ".join(bits)


def render_merged(bench: str, runs: list[Table]) -> list[str]:
    """One table of the newest measurement of each row over all runs."""
    key_columns = MERGED[bench][0]
    newest: dict[tuple, tuple[str, dict, Table]] = {}
    for table in runs:
        for r in table.rows:
            key = tuple((r.get(c) or "").strip() for c in key_columns)
            # A row skipped for time is a measurement only if there is no other.
            when = ("1" if r.get("status") != "skipped" else "0") + (
                r.get("date") or table.date)
            if key not in newest or when > newest[key][0]:
                newest[key] = (when, r, table)
    columns = [c for c in COLUMNS.get(bench, []) if c not in key_columns
               and any((v[1].get(c) or "").strip() for v in newest.values())]
    header = [c for c in key_columns] + columns + ["git"]
    rows = []
    for key in sorted(newest, key=lambda k: tuple(
            (int(x) if x.isdigit() else 0, x) for x in k)):
        when, r, table = newest[key]
        sha = (r.get("git_sha") or "").strip()[:7]
        rows.append([_cell(x) for x in key]
                    + [_cell(r.get(c) or "") for c in columns]
                    + [sha])
    out = [f"The newest measurement of each row, over {len(runs)} runs "
           f"(each a CSV of its own): "
           + ", ".join(f"`{t.rel}`" for t in sorted(runs, key=lambda t: t.rel))
           + ".", ""]
    return out + _md_table(header, rows)


def render_table(bench: str, table: Table) -> list[str]:
    if bench == "seed_rt_study":
        constants, lines = _seed_rt_pivot(table)
    else:
        constants, lines = _plain_table(bench, table)
    out = [f"`{table.rel}` — {_provenance(table)}"]
    if constants:
        out[0] += "; " + ", ".join(constants)
    out += ["", *lines]
    for companion in table.companions:
        _, clines = _plain_table("", companion)
        if clines:
            out += ["", f"`{companion.rel}`:", "", *clines]
    return out


def _anchor(title: str) -> str:
    text = re.sub(r"[^\w\- ]", "", title.lower()).strip()
    return re.sub(r" ", "-", text)


# The headline table: rows of (label, file glob, {column: row filter}).
# A row's values come from the CSV matching the glob that holds the most of
# them (the newest among equals); values it lacks come from the newest CSV
# that has them. New runs replace these numbers once their CSVs are
# committed and this script is run.
HEADLINE_COLUMNS = ["jaxrt `cell`", "jaxrt `bvh`", "jax-md"]
HEADLINE = [
    ("neighbour-list rebuild, uniform fluid (k ≈ 65)",
     "h200/**/neighbors_uniform_1e6*.csv",
     {"jaxrt `cell`": {"method": "cell[pallas]"},
      "jaxrt `bvh`": {"method": "bvh"},
      "jax-md": {"method": "jax-md"}}),
    ("neighbour-list rebuild, sphere surface (k ≈ 30)",
     "h200/**/neighbors_sphere_1e6*.csv",
     {"jaxrt `cell`": {"method": "cell[pallas]"},
      "jaxrt `bvh`": {"method": "bvh"},
      "jax-md": {"method": "jax-md"}}),
    ("LJ NVE step, Dense list", "h200/**/md_step*.csv",
     {"jaxrt `cell`": {"list": "jaxrt:cell/Dense"},
      "jaxrt `bvh`": {"list": "jaxrt:bvh/Dense"},
      "jax-md": {"list": "jax-md/Dense"}}),
    ("LJ NVE step, OrderedSparse list (jax-md's default)",
     "h200/**/md_step*.csv",
     {"jaxrt `cell`": {"list": "jaxrt:cell/OrderedSparse"},
      "jax-md": {"list": "jax-md/OrderedSparse"}}),
    ("LJ NVE step, no list (`energy.lennard_jones_fused`)",
     "h200/**/md_step*.csv",
     {"jaxrt `cell`": {"list": "fused:cell"}}),
]


def _near_a_million(row: dict) -> bool:
    # The headline is at N = 10⁶; a run's CSV may also hold 10⁷ rows.
    try:
        return 0.9e6 <= float(row.get("N") or 1e6) <= 1.1e6
    except ValueError:
        return True


def _ok_value(table: Table, match: dict) -> str | None:
    for r in table.rows:
        if ((r.get("status") or "ok") == "ok" and r.get("median_ms")
                and _near_a_million(r)
                and all(r.get(k) == v for k, v in match.items())):
            return r["median_ms"]
    return None


def headline(sources_listed: bool = True) -> list[str]:
    lines = ["NVIDIA H200, N = 10⁶ particles, float32, ms per call "
             "(lower is better):", ""]
    body, sources = [], {}
    for label, pattern, cells in HEADLINE:
        tables = sorted((_read(p) for p in RESULTS.glob(pattern)),
                        key=lambda t: (t.date, t.rel), reverse=True)
        found = {id(t): {c: _ok_value(t, m) for c, m in cells.items()}
                 for t in tables}
        ranked = sorted(tables, key=lambda t: sum(
            v is not None for v in found[id(t)].values()), reverse=True)
        row = [label]
        for col in HEADLINE_COLUMNS:
            source = next((t for t in ranked if found[id(t)].get(col)), None)
            if source is None:
                row.append("—")
                continue
            row.append(_number(found[id(source)][col]))
            sources[source.rel] = (f"{', '.join(source.shas[:1]) or '?'}, "
                                   f"{source.date[:10]}")
        body.append(row)
    lines += _md_table([""] + HEADLINE_COLUMNS, body)
    if sources_listed:
        lines += ["", "From " + "; ".join(f"`{k}` ({v})" for k, v in
                                          sorted(sources.items())) + "."]
    else:
        dates = sorted(v.rsplit(", ", 1)[1] for v in sources.values())
        span = dates[0] if dates[0] == dates[-1] else f"{dates[0]} to {dates[-1]}"
        lines += ["", f"Measured {span}; each number's CSV is named in "
                  "[docs/benchmarks.md](docs/benchmarks.md#headline)."]
    return lines


def page() -> str:
    found = collect()
    out = [
        "# Benchmarks",
        "",
        "<!-- Generated by `python3 benchmarks/make_docs.py` from the CSVs "
        "under benchmarks/results/; do not edit by hand. -->",
        "",
        "Every number here is a row of a CSV under `benchmarks/results/<device>/`, "
        "written by the script named in its section through "
        "`benchmarks/_harness.py`: the median of the timed calls (warm-up "
        "and compilation excluded, every call synchronised), float32 unless "
        "a `dtype` says otherwise, with its provenance (device, versions, "
        "git sha, date). Compare rows of one table only: one run, one "
        "device. A `status` other than `ok` says why a row has no time "
        "(`oom`, `timeout`, `error`, `skipped`; `failed` holds the reason). "
        "The newest run of each table comes first; earlier runs of the same "
        "table are listed under it. What the numbers mean, and what was "
        "tried and did not pay: [benchmarks-notes.md](benchmarks-notes.md).",
        "",
        "Re-measure the GPU tables with `bash benchmarks/run_h200.sh` (its "
        "header says what it runs), commit the CSVs, and regenerate this "
        "page and the README's table with `python3 benchmarks/make_docs.py` "
        "(the test suite fails while either is stale).",
        "",
        "## Headline",
        "",
        *headline(),
        "",
        "## Contents",
        "",
    ]
    for key, title, script, _ in BENCHMARKS:
        if key in found:
            out.append(f"- [{title}](#{_anchor(title)})")
    for key, title, script, what in BENCHMARKS:
        if key not in found:
            continue
        out += ["", f"## {title}", "", f"`{script}`. {what}"]
        for device, device_title in DEVICES.items():
            all_series = found[key].get(device)
            if not all_series:
                continue
            out += ["", f"### {device_title}"]
            if device in HISTORY:
                files = sorted(t.rel for runs in all_series.values()
                               for t in runs)
                out += ["", "CSVs: " + ", ".join(f"`{f}`" for f in files)
                        + "."]
                continue
            ordered = sorted(
                ((s, runs) for s, runs in all_series.items() if s != "_raw"),
                key=lambda item: (item[1][0].date, item[0]), reverse=True)
            for series, runs in ordered:
                if series == "_merged":
                    out += ["", *render_merged(key, runs)]
                    continue
                newest = runs[0]
                current = [t for t in runs if t.date == newest.date
                           and t.shas == newest.shas][:1]
                if key != "seed_rt_study":
                    current = [t for t in runs if t.date[:10] == newest.date[:10]
                               and t.shas == newest.shas]
                for table in current:
                    out += ["", *render_table(key, table)]
                earlier = [t for t in runs if t not in current]
                if earlier:
                    out += ["", "Earlier runs: " + "; ".join(
                        f"`{t.rel}` ({', '.join(t.shas[:2]) or 'no sha'}"
                        f"{', ' + t.date[:10] if t.date else ''})"
                        for t in earlier) + "."]
            if "_raw" in all_series:
                out += ["", "Raw data (per-call traces, power samples): "
                        + ", ".join(f"`{t.rel}`" for t in all_series["_raw"])
                        + "."]
    out += ["", "## Other scripts", ""]
    out += [f"- `{script}`: {what}." for script, what in OTHER_SCRIPTS]
    return "\n".join(out) + "\n"


def readme(text: str) -> str:
    """The README with its headline block regenerated."""
    if START not in text or END not in text:
        raise SystemExit(f"README.md lacks the {START} / {END} markers")
    head, rest = text.split(START, 1)
    _, tail = rest.split(END, 1)
    block = "\n".join(headline(sources_listed=False))
    return f"{head}{START}\n{block}\n{END}{tail}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true",
                        help="exit 1 if docs/benchmarks.md or the README's "
                        "block is not what this script writes")
    args = parser.parse_args(argv)
    want = {PAGE: page(), README: readme(README.read_text(encoding="utf-8"))}
    stale = [p for p, text in want.items()
             if not p.exists() or p.read_text(encoding="utf-8") != text]
    if args.check:
        for p in stale:
            print(f"{p.relative_to(ROOT)} is stale: run python3 "
                  "benchmarks/make_docs.py", file=sys.stderr)
        return 1 if stale else 0
    for p in stale:
        p.write_text(want[p], encoding="utf-8")
        print(f"wrote {p.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
