"""Provenance for benchmark CSVs: which device, which versions, which commit."""
from __future__ import annotations

import csv
import datetime
import os
import platform
import re
import statistics
import subprocess
import time
from pathlib import Path

import jax


def device_slug() -> str:
    """Folder name under benchmarks/results/: 'h100', 'cpu-2core', ..."""
    dev = jax.devices()[0]
    if dev.platform == "cpu":
        return f"cpu-{os.cpu_count()}core"
    kind = dev.device_kind.lower()
    match = re.search(r"(h100|h200|a100|l40s?|v100|rtx ?\w+)", kind)
    return (match.group(1) if match else re.sub(r"\W+", "-", kind)).replace(" ", "")


def provenance() -> dict:
    from importlib import metadata
    versions = {"jax": jax.__version__}
    for mod, dist in (("jax_md", "jax-md"), ("warp", "warp-lang")):
        try:  # jax_md has no __version__; ask the installed distribution
            versions[mod] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            versions[mod] = "absent"
    sha = os.environ.get("GIT_SHA")
    if not sha:
        try:
            sha = subprocess.run(["git", "rev-parse", "--short", "HEAD"],
                                 capture_output=True, text=True,
                                 check=True).stdout.strip()
        except Exception:  # noqa: BLE001
            sha = "unknown"
    dev = jax.devices()[0]
    return {"device": f"{dev.platform}:{dev.device_kind}", "host": platform.node(),
            "jax": versions["jax"], "jax_md": versions["jax_md"],
            "warp": versions["warp"], "git_sha": sha,
            "date": datetime.datetime.now().isoformat(timespec="seconds")}


def median_ms(fn, inputs, repeats: int) -> float:
    """Median wall time of ``fn(x)`` in ms, rotating over ``inputs``; the
    first call per input (compilation, warm-up) is excluded."""
    for x in inputs:
        jax.block_until_ready(fn(x))
    times = []
    for k in range(repeats):
        x = inputs[k % len(inputs)]
        t = time.perf_counter()
        jax.block_until_ready(fn(x))
        times.append((time.perf_counter() - t) * 1e3)
    return statistics.median(times)


def write_csv(rows: list[dict], name: str, out_dir: str | None = None) -> Path:
    """Write rows (plus provenance columns) to ``out_dir`` or
    ``$OUT`` or ``benchmarks/results/<device>/``."""
    prov = provenance()
    folder = Path(out_dir or os.environ.get("OUT") or
                  Path(__file__).parent / "results" / device_slug())
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    rows = [{**row, **prov} for row in rows]
    fields = list(dict.fromkeys(k for row in rows for k in row))
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        writer.writerows(rows)
    return path


def print_table(rows: list[dict], columns: list[str]) -> None:
    widths = {c: max(len(c), *(len(_fmt(r.get(c))) for r in rows)) for c in columns}
    print("  ".join(c.rjust(widths[c]) for c in columns))
    for r in rows:
        print("  ".join(_fmt(r.get(c)).rjust(widths[c]) for c in columns))


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.3g}" if abs(v) < 1e4 else f"{v:.3e}"
    return "" if v is None else str(v)
