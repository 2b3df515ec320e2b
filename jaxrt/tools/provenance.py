"""Where a measurement ran: the provenance columns of every benchmark row
(`benchmarks/_harness.py`) and of the accuracy sweep (`jaxrt.tools.accuracy`).
"""
from __future__ import annotations

import datetime
import os
import pathlib
import platform
import re
import subprocess
from importlib import metadata

PROVENANCE = ("device", "device_kind", "device_slug", "host", "jax", "jaxlib",
              "jax_md", "warp", "python", "git_sha", "date")
"""Provenance columns added to every row (the row's own N, k and dtype are
columns of the row)."""

# The checkout this package runs from, if it is one (git finds none
# otherwise, and the sha is "unknown").
CHECKOUT = pathlib.Path(__file__).resolve().parents[2]


def git_sha() -> str:
    """``$GIT_SHA`` (how the GPU runs pass it), else ``git rev-parse``."""
    sha = os.environ.get("GIT_SHA", "").strip()
    if sha:
        return sha
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True, check=True,
                              cwd=CHECKOUT, timeout=10).stdout.strip() \
            or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def version(dist: str) -> str:
    """The installed version of distribution ``dist``, or ``"absent"``."""
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return "absent"


def host_provenance() -> dict:
    """What the driver knows without touching a device: versions (of the
    installed distributions, which the worker imports), git sha, date."""
    return {"host": platform.node(), "jax": version("jax"),
            "jaxlib": version("jaxlib"), "jax_md": version("jax-md"),
            "warp": version("warp-lang"),
            "python": platform.python_version(), "git_sha": git_sha(),
            "date": datetime.datetime.now(datetime.timezone.utc)
            .isoformat(timespec="seconds")}


def cpu_cores() -> int:
    """The CPU cores this process may use."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def device_slug(platform_name: str, kind: str) -> str:
    """Folder name under ``benchmarks/results/``: ``h200`` for an NVIDIA
    H200, ``h100`` for an H100, ``cpu-2core`` for a CPU with 2 usable cores;
    otherwise the device kind in lower case with dashes."""
    if platform_name == "cpu":
        return f"cpu-{cpu_cores()}core"
    kind = kind.lower()
    match = re.search(r"\b(gh200|gb200|b200|h200|h100|a100|a10g?|l40s?|l4|"
                      r"v100|t4)\b", kind)
    if match:
        return match.group(1)
    return re.sub(r"[^a-z0-9]+", "-", kind.replace("nvidia", "")).strip("-") \
        or "unknown"


def device_provenance() -> dict:
    """The device JAX runs on (imports JAX and starts its backend)."""
    import jax
    dev = jax.devices()[0]
    return {"device": f"{dev.platform}:{dev.device_kind}",
            "device_kind": dev.device_kind,
            "device_slug": device_slug(dev.platform, dev.device_kind)}


def provenance() -> dict:
    """Every `PROVENANCE` column: the host's and the device's."""
    return {**host_provenance(), **device_provenance()}
