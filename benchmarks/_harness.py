"""The one benchmark harness: provenance, timing, CSV, tables, and one
worker subprocess per row with out-of-memory and timeout isolation.

Every script in ``benchmarks/`` uses it the same way:

* The script's *driver* (its ``main``) plans rows as jobs (JSON-able dicts)
  and hands them to `run_jobs`, naming the function that measures one job
  (``"neighbors:run_row"``: module ``neighbors`` of this folder, function
  ``run_row``). The driver never imports JAX's device, so it cannot run out
  of GPU memory itself.
* `run_jobs` starts a worker, ``python benchmarks/_harness.py --serve
  neighbors:run_row``, per job (or one for a run of jobs with
  ``reuse_worker=True``), sends it the job and waits for its rows. A row that
  raised out-of-memory (`is_out_of_memory`), raised anything else, crashed
  the worker, or ran past its timeout is written with ``status`` = ``oom`` /
  ``error`` / ``crashed`` / ``timeout`` and the reason in ``failed``; the
  script carries on with a fresh worker. Rows not started because the
  script's ``--budget`` ran out are written as ``skipped``.
* Inside the worker, `time_calls` (and `time_carry`, `time_self_timed`)
  time the measured function: warm-up calls excluded, every call
  synchronised (`jax.block_until_ready` unless told otherwise), median of
  the repeats plus min and max.
* Every row gets the provenance columns (`PROVENANCE`): the device (from
  the worker: ``jax.devices()[0].device_kind``), jax / jaxlib / jax-md /
  warp versions, the git sha (``$GIT_SHA``, else ``git rev-parse``), the
  date, and the row's own ``N``, ``k`` and ``dtype``. The CSV is rewritten
  after every row (an interrupted run keeps what it measured) under
  ``benchmarks/results/<device>/`` (`device_slug`: ``h200``, ``cpu-2core``)
  unless ``--out`` names a folder or a ``.csv`` file. `print_table` prints
  the rows at the end.

Command line of the harness itself:

    python benchmarks/_harness.py --serve MODULE:FUNCTION   # a worker
    python benchmarks/_harness.py --summary CSV_OR_DIR ...  # compact table
                                                            # per CSV
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import importlib
import json
import math
import os
import queue
import re
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import traceback
from pathlib import Path
from typing import Any, Callable, Iterable

# Provenance is the library's (the accuracy sweep writes the same columns).
from jaxrt.tools.provenance import (PROVENANCE, cpu_cores,  # noqa: F401
                                    device_provenance, device_slug, git_sha,
                                    host_provenance)

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
RESULTS = HERE / "results"

STATUSES = ("ok", "oom", "timeout", "crashed", "error", "skipped")
"""Values of a row's ``status`` column; ``failed`` holds the reason of any
status but ``ok``."""

ROW_COLUMNS = ("N", "k", "dtype", "status", "failed")
"""Columns every CSV has, empty where a row does not know them."""


# ---------------------------------------------------------------------------
# Timing (inside a worker)


@dataclasses.dataclass
class Timing:
    """Wall times of the timed calls, in ms; ``first`` is the output of the
    first (untimed) call, for callers that need it."""

    median_ms: float
    min_ms: float
    max_ms: float
    repeats: int
    warmup: int
    first: Any = dataclasses.field(default=None, repr=False)

    def columns(self) -> dict:
        """``median_ms``, ``min_ms``, ``max_ms``, ``repeats``, ``warmup``
        for a row."""
        return {"median_ms": self.median_ms, "min_ms": self.min_ms,
                "max_ms": self.max_ms, "repeats": self.repeats,
                "warmup": self.warmup}


def summarize(samples_ms: list[float], warmup: int, first=None) -> Timing:
    return Timing(float(statistics.median(samples_ms)), float(min(samples_ms)),
                  float(max(samples_ms)), len(samples_ms), warmup, first)


def _jax_sync(out):
    import jax
    return jax.block_until_ready(out)


def time_calls(fn: Callable, inputs: list, *, repeats: int = 10,
               warmup: int = 2, sync: Callable | None = None,
               target_s: float | None = None, max_repeats: int | None = None,
               keep: Callable | None = None) -> Timing:
    """Time ``sync(fn(x))`` for ``x`` rotating over ``inputs`` (so no call
    repeats its predecessor's input).

    ``warmup`` untimed calls first (compilation, first builds, lazy loads;
    at least one). Then ``repeats`` timed calls; with ``target_s``, the first
    timed call's time ``t`` sets their number instead, to
    ``clamp(ceil(target_s / t), repeats, max_repeats)``. ``keep(out)`` sees
    every timed output. ``sync`` defaults to `jax.block_until_ready`.
    """
    sync = sync or _jax_sync
    warmup = max(1, int(warmup))
    first = None
    for w in range(warmup):
        out = sync(fn(inputs[w % len(inputs)]))
        if w == 0:
            first = out
        del out
    samples: list[float] = []
    want = max(1, int(repeats))
    k = warmup
    while len(samples) < want:
        x = inputs[k % len(inputs)]
        k += 1
        t = time.perf_counter()
        out = sync(fn(x))
        samples.append((time.perf_counter() - t) * 1e3)
        if len(samples) == 1 and target_s is not None:
            hi = max(want, int(max_repeats or want))
            want = min(max(math.ceil(target_s * 1e3 / max(samples[0], 1e-3)),
                           want), hi)
        if keep is not None:
            keep(out)
        del out
    return summarize(samples, warmup, first)


def time_self_timed(run: Callable[[Any], float], inputs: list, *,
                    repeats: int = 10, warmup: int = 2) -> Timing:
    """Like `time_calls` for a ``run(x)`` that times (and synchronises)
    the part that counts itself and returns it in ms."""
    for w in range(max(1, warmup)):
        run(inputs[w % len(inputs)])
    samples = [float(run(inputs[(warmup + r) % len(inputs)]))
               for r in range(max(1, repeats))]
    return summarize(samples, max(1, warmup))


def time_carry(fn: Callable, carry, *, repeats: int = 10, warmup: int = 2,
               per_call: int = 1) -> tuple[Timing, Any]:
    """Time ``carry = fn(carry)`` (a jitted loop that threads its state),
    synchronised; each sample is divided by ``per_call`` (e.g. the steps of
    one ``lax.scan``). Returns the timing and the last carry."""
    for _ in range(max(1, warmup)):
        carry = _jax_sync(fn(carry))
    samples = []
    for _ in range(max(1, repeats)):
        t = time.perf_counter()
        carry = _jax_sync(fn(carry))
        samples.append((time.perf_counter() - t) * 1e3 / per_call)
    return summarize(samples, max(1, warmup)), carry


# ---------------------------------------------------------------------------
# Out of memory


def is_out_of_memory(exc: BaseException) -> bool:
    """Whether ``exc`` means the device (or host) ran out of memory.

    Structured signals first: Python's `MemoryError` (numpy on the host),
    and XLA's ``RESOURCE_EXHAUSTED`` status, which JAX raises as a
    `jax.errors.JaxRuntimeError` whose message starts with the status name
    (the only place XLA's status code reaches Python). The one string match
    that cannot be avoided: Warp reports a failed allocation as a plain
    `RuntimeError` "Failed to allocate N bytes on device ..." (warp
    ``context.py``), also when it reaches JAX through jaxrt's custom calls,
    wrapped in the JaxRuntimeError's message.
    """
    if isinstance(exc, MemoryError):
        return True
    msg = str(exc)
    try:
        from jax.errors import JaxRuntimeError
    except ImportError:  # noqa: BLE001 - no JAX, no XLA status
        JaxRuntimeError = ()  # type: ignore[assignment]
    if JaxRuntimeError and isinstance(exc, JaxRuntimeError) and \
            msg.lstrip().startswith("RESOURCE_EXHAUSTED"):
        return True
    return isinstance(exc, RuntimeError) and "Failed to allocate" in msg


# ---------------------------------------------------------------------------
# Worker side


class InjectedFault(RuntimeError):
    """Raised for ``--inject error@...`` (a testing aid of the isolation)."""


def _inject(kind: str) -> None:
    if kind == "crash":
        os.abort()  # as a segfault or a CUDA abort would
    elif kind == "hang":
        time.sleep(1e6)
    elif kind == "oom":
        raise MemoryError("injected out of memory (--inject)")
    elif kind == "error":
        raise InjectedFault("injected error (--inject)")


def _json_default(v):
    """numpy scalars and arrays, Paths, anything else as its str."""
    for attr in ("item", "tolist"):
        if hasattr(v, attr):
            try:
                return getattr(v, attr)()
            except (TypeError, ValueError):
                pass
    return str(v)


def serve(target: str) -> None:
    """Worker loop: jobs as JSON lines on stdin; on the protocol channel,
    ``READY {provenance}`` once, then ``ROW {"rows": [...]}`` or ``ROW
    {"error": {...}}`` per job. The protocol channel is the original stdout;
    the process's fd 1 is pointed at stderr, so nothing a library prints
    (Python or C) can mix with it. Exits after a failed job: a fresh
    worker (clean memory, clean CUDA state) takes the next."""
    proto = os.fdopen(os.dup(1), "w", buffering=1)
    os.dup2(2, 1)

    def say(tag: str, payload) -> None:
        proto.write(f"{tag} {json.dumps(payload, default=_json_default)}\n")
        proto.flush()

    module_name, _, func_name = target.partition(":")
    fn = getattr(importlib.import_module(module_name), func_name)
    say("READY", device_provenance())
    for line in sys.stdin:
        if not line.strip():
            continue
        job = json.loads(line)
        try:
            if job.get("_inject"):
                _inject(job["_inject"])
            out = fn(job)
            rows = list(out) if isinstance(out, (list, tuple)) else [out]
            for row in rows:
                row.setdefault("status", "ok")
            say("ROW", {"rows": rows})
        except Exception as exc:  # noqa: BLE001 - one failure, one row
            traceback.print_exc()
            status = "oom" if is_out_of_memory(exc) else "error"
            msg = f"{type(exc).__name__}: {exc}".replace("\n", " ")
            say("ROW", {"error": {"status": status, "failed": msg[:300]}})
            return


# ---------------------------------------------------------------------------
# Driver side


def _reader(stream, q: queue.Queue) -> None:
    for line in stream:
        q.put(line.rstrip("\n"))
    q.put(None)


def _stderr_tail(path: Path, start: int) -> str:
    """The last line of a worker's stderr since ``start`` that is not
    Warp's module-load chatter."""
    try:
        with open(path, errors="replace") as f:
            f.seek(start)
            text = f.read()
    except OSError:
        return ""
    lines = [ln.strip() for ln in text.splitlines()
             if ln.strip() and not ln.startswith(("Module ", "Warp "))]
    return lines[-1][:200] if lines else ""


class _Worker:
    """One worker process (`serve`), in its own process group."""

    def __init__(self, target: str, log: Path, env: dict):
        self.log = log
        self.err = open(log, "a")
        self.err_pos = log.stat().st_size
        self.proc = subprocess.Popen(
            [sys.executable, str(Path(__file__).resolve()), "--serve", target],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self.err,
            text=True, bufsize=1, env=env, cwd=REPO, start_new_session=True)
        self.q: queue.Queue = queue.Queue()
        threading.Thread(target=_reader, args=(self.proc.stdout, self.q),
                         daemon=True).start()

    def expect(self, tag: str, timeout: float):
        """The payload of the next ``tag`` line; None on timeout, ``""``
        when the worker's channel closed (it exited)."""
        end = time.monotonic() + timeout
        while True:
            try:
                line = self.q.get(timeout=max(0.05, end - time.monotonic()))
            except queue.Empty:
                if time.monotonic() >= end:
                    return None
                continue
            if line is None:
                self.proc.wait()
                return ""
            if line.startswith(tag + " "):
                return json.loads(line[len(tag) + 1:])

    def send(self, job: dict) -> None:
        self.err.flush()
        self.err_pos = self.log.stat().st_size
        self.proc.stdin.write(json.dumps(job, default=_json_default) + "\n")
        self.proc.stdin.flush()

    def tail(self) -> str:
        if not self.err.closed:
            self.err.flush()
        return _stderr_tail(self.log, self.err_pos)

    def exit_reason(self) -> tuple[str, str]:
        """(status, reason) of a worker that exited without answering."""
        try:
            rc = self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:  # its channel closed, yet it lives
            self.kill()
            return "crashed", "closed its channel without exiting (killed)"
        tail = self.tail()
        if rc is not None and rc < 0:
            try:
                how = signal.Signals(-rc).name
            except ValueError:
                how = f"signal {-rc}"
            if -rc == signal.SIGKILL:
                # Not sent by the harness (its kills are timeouts): the
                # kernel's (or the machine's) out-of-memory killer.
                return "oom", f"killed by {how} (host out of memory)" + \
                    (f": {tail}" if tail else "")
            return "crashed", f"crashed ({how})" + (f": {tail}" if tail else "")
        return "crashed", f"exited (rc {rc})" + (f": {tail}" if tail else "")

    def kill(self) -> None:
        if self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                self.proc.kill()
        self.proc.wait()
        self.err.close()

    def close(self) -> None:
        try:
            self.proc.stdin.close()
            self.proc.wait(timeout=30)
        except (OSError, subprocess.TimeoutExpired):
            pass
        self.kill()


class Runner:
    """Runs jobs in `serve` workers: a fresh one per job, or (with
    ``reuse_worker``) one kept for the following jobs of the same
    ``_worker`` key (default: their ``_group``) as long as they succeed.
    Every failure ends its worker.

    Attributes:
      device: the provenance of the device the last worker saw (`READY`).
      log: the file with the workers' stderr.
    """

    def __init__(self, target: str, *, reuse_worker: bool = False,
                 startup_timeout: float = 300.0, log: Path | None = None):
        self.target = target
        self.reuse = reuse_worker
        self.startup_timeout = startup_timeout
        if log is None:
            fd, name = tempfile.mkstemp(prefix="jaxrt-bench-", suffix=".log")
            os.close(fd)
            log = Path(name)
        self.log = Path(log)
        self.device: dict = {}
        self.start_failures = 0
        self._worker: _Worker | None = None
        self._key = None
        self.env = dict(os.environ)
        self.env.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
        # Workers share compiled programs on disk: a row in a fresh worker
        # (one per row, for isolation) need not compile again what an
        # earlier row of the same shapes compiled. Times exclude warm-up
        # either way; on a lent GPU this saves device time.
        self.env.setdefault("JAX_COMPILATION_CACHE_DIR", str(
            Path(tempfile.gettempdir()) / "jaxrt-jax-cache"))
        self.env.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS",
                            "0.5")
        self.env["GIT_SHA"] = git_sha()
        self.env["PYTHONPATH"] = os.pathsep.join(
            [str(HERE), str(REPO)] + [p for p in
                                      [self.env.get("PYTHONPATH", "")] if p])

    def _start(self, timeout: float) -> tuple[str, str] | None:
        """Start a worker; None when ready, else (status, reason)."""
        self._worker = _Worker(self.target, self.log, self.env)
        ready = self._worker.expect("READY", timeout)
        if isinstance(ready, dict):
            self.device = ready
            self.start_failures = 0
            return None
        self.start_failures += 1
        if ready is None:
            self._worker.kill()
            self._worker = None
            return "timeout", f"worker start-up timed out ({timeout:g}s)"
        status, reason = self._worker.exit_reason()
        self._worker.kill()
        self._worker = None
        return status, f"worker failed to start: {reason}"

    def run(self, job: dict, timeout: float) -> list[dict]:
        """The job's rows, each with ``status`` (and ``failed``)."""
        base = {k: v for k, v in job.items() if not k.startswith("_")}
        key = job.get("_worker", job.get("_group"))
        if self._worker is not None and key != self._key:
            self._end()  # a worker serves one key's jobs
        self._key = key
        w = self._worker
        if w is None or w.proc.poll() is not None:
            if w is not None:
                w.kill()
            began = time.monotonic()
            failure = self._start(min(self.startup_timeout, timeout))
            if failure:
                return [{**base, "status": failure[0], "failed": failure[1]}]
            timeout = max(1.0, timeout - (time.monotonic() - began))
        w = self._worker
        try:
            w.send(job)
        except (BrokenPipeError, OSError):
            status, reason = w.exit_reason()
            self._end()
            return [{**base, "status": status, "failed": reason}]
        reply = w.expect("ROW", timeout)
        if reply is None:
            self._end()
            return [{**base, "status": "timeout",
                     "failed": f"timeout {timeout:.0f}s"}]
        if reply == "":
            status, reason = w.exit_reason()
            self._end()
            return [{**base, "status": status, "failed": reason}]
        if "error" in reply:
            self._end()
            return [{**base, **reply["error"]}]
        if not self.reuse:
            self._end()
        return [{**base, **row} for row in reply["rows"]]

    def _end(self) -> None:
        if self._worker is not None:
            self._worker.close()
            self._worker = None

    def close(self) -> None:
        self._end()


def out_path(out: str | None, default_name: str, slug: str) -> Path:
    """``out`` if it names a ``.csv`` file, else ``out/default_name``; with
    no ``out``, ``benchmarks/results/<slug>/default_name``."""
    if out and out.endswith(".csv"):
        return Path(out)
    return Path(out) / default_name if out else RESULTS / slug / default_name


def run_jobs(target: str, jobs: Iterable[dict], *, out: str | None,
             name: str, columns: list[str], timeout: float = 600.0,
             budget: float = math.inf, hard_stop: float = math.inf,
             reuse_worker: bool = False, startup_timeout: float = 300.0,
             inject: Iterable[str] = (),
             on_row: Callable[[dict], None] | None = None, table: bool = True,
             finish: Callable[[list[dict]], None] | None = None,
             t0: float | None = None) -> tuple[list[dict], Path]:
    """Run every job (`Runner`), write the CSV after each, print the table.

    Args:
      target: ``"module:function"`` measuring one job (a dict) in a worker
        and returning a row (dict) or a list of rows.
      jobs: the plan, in order. A job's keys not starting with ``_`` are
        also the columns of its failed rows; a job's ``_group`` (optional)
        groups jobs that the budget does not split; its ``_worker``
        (optional, default its ``_group``) names the jobs that share a
        worker with ``reuse_worker`` (several groups may share one: a
        worker's start-up is paid once).
      out, name: `out_path`.
      columns: the printed table's columns.
      timeout: seconds per job (a worker's start-up included); a job's
        ``_timeout`` (optional) replaces it for that job.
      budget: seconds after ``t0`` after which no new job (group) starts;
        the rest are written as ``skipped``.
      hard_stop: seconds after ``t0`` at which the running job is killed.
      reuse_worker: keep a worker for the following jobs of the same
        ``_worker`` key (else ``_group``) while they succeed.
      startup_timeout: seconds for a worker's imports and device start.
      inject: ``KIND@I``, testing aid: job number I (1-based) crashes,
        hangs, raises an error or a fake out-of-memory (KIND in crash,
        hang, error, oom).
      on_row: called with each finished row (default: `print_row`).
      table: print the table of all rows at the end.
      finish: called with all rows before the last write (ratios etc.).
    Returns:
      the rows and the CSV's path.
    """
    t0 = time.monotonic() if t0 is None else t0
    jobs = list(jobs)
    faults = {}
    for spec in inject:
        kind, _, index = spec.partition("@")
        faults[int(index)] = kind
    host = host_provenance()
    runner = Runner(target, reuse_worker=reuse_worker,
                    startup_timeout=startup_timeout)
    print(f"{len(jobs)} rows; worker stderr in {runner.log}", flush=True)
    rows: list[dict] = []
    path = None
    group = object()
    started_group = False
    try:
        for i, job in enumerate(jobs, 1):
            now = time.monotonic() - t0
            if job.get("_group", i) != group:
                group = job.get("_group", i)
                started_group = now < budget and now < hard_stop
            base = {k: v for k, v in job.items() if not k.startswith("_")}
            if not started_group or now >= hard_stop:
                why = (f"skipped: time budget {budget:g}s reached"
                       if now >= budget else
                       f"skipped: hard stop {hard_stop:g}s reached")
                new = [{**base, "status": "skipped", "failed": why}]
            elif runner.start_failures >= 2:
                new = [{**base, "status": "skipped",
                        "failed": "skipped: workers failed to start twice"}]
            else:
                if i in faults:
                    job = {**job, "_inject": faults[i]}
                own = job.get("_timeout", timeout)
                limit = max(1.0, min(own, hard_stop - now))
                new = runner.run(job, limit)
                if limit < own:
                    for row in new:
                        if row["status"] == "timeout":
                            row["failed"] = f"killed at the hard stop ({hard_stop:g}s)"
            for row in new:
                row.update({c: row.get(c) for c in ROW_COLUMNS if c not in row})
                if row.get("dtype") is None:
                    row["dtype"] = "float32"  # every script's inputs
                row.update(runner.device or {"device": "unknown",
                                             "device_kind": "unknown",
                                             "device_slug": "unknown"})
                row.update(host)
                rows.append(row)
                if on_row:
                    on_row(row)
                else:
                    print_row(row, columns)
            path = out_path(out, name, runner.device.get("device_slug",
                                                         "unknown"))
            write_csv(rows, path)
    finally:
        runner.close()
    if finish:
        finish(rows)
    path = out_path(out, name, runner.device.get("device_slug", "unknown"))
    write_csv(rows, path)
    if table:
        print()
        print_table(rows, columns + ["status", "failed"])
    print("wrote", path, flush=True)
    return rows, path


# ---------------------------------------------------------------------------
# CSV and tables


def write_csv(rows: list[dict], path: Path) -> Path:
    """All rows, the union of their columns (row columns first, then
    `PROVENANCE`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fields = list(dict.fromkeys(k for row in rows for k in row
                                if k not in PROVENANCE))
    fields += [c for c in PROVENANCE if any(c in row for row in rows)]
    tmp = path.with_suffix(path.suffix + ".tmp")
    with open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    tmp.replace(path)
    return path


def read_csv(path: str | Path) -> list[dict]:
    """Rows as dicts of strings; numbers where a column parses as float."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    for r in rows:
        for k, v in r.items():
            if k in PROVENANCE or v in (None, ""):
                continue
            try:
                r[k] = float(v) if not v.lstrip("-").isdigit() else int(v)
            except ValueError:
                pass
    return rows


def fmt(v) -> str:
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        return f"{v:.3g}" if abs(v) < 1e4 else f"{v:.4g}"
    return "" if v is None else str(v)


def print_row(row: dict, columns: list[str]) -> None:
    """One progress line: the row's columns as ``name=value``."""
    parts = [f"{c}={fmt(row.get(c))}" for c in columns
             if row.get(c) not in (None, "")]
    if row.get("status") != "ok":
        parts.append(f"{row.get('status')}: {fmt(row.get('failed'))[:120]}")
    print("  " + "  ".join(parts), flush=True)


def print_table(rows: list[dict], columns: list[str], width: int = 60) -> None:
    """Aligned table of ``columns`` (those any row has), cells cut to
    ``width`` characters."""
    cols = [c for c in columns if any(r.get(c) not in (None, "") for r in rows)]
    if not rows or not cols:
        print("(no rows)")
        return
    cells = [[fmt(r.get(c))[:width] for c in cols] for r in rows]
    widths = [max(len(c), *(len(row[i]) for row in cells))
              for i, c in enumerate(cols)]
    print("  ".join(c.rjust(w) for c, w in zip(cols, widths)))
    for row in cells:
        print("  ".join(v.rjust(w) for v, w in zip(row, widths)))


# ---------------------------------------------------------------------------
# Command-line pieces every script shares


def make_parser(doc: str) -> argparse.ArgumentParser:
    """A script's parser: ``doc``'s first line as the description, the
    rest, as written, as the epilog of ``--help``."""
    first, _, rest = doc.partition("\n")
    return argparse.ArgumentParser(
        description=first, epilog=rest,
        formatter_class=argparse.RawDescriptionHelpFormatter)


def add_common_args(parser: argparse.ArgumentParser, *, name: str,
                    repeats: int = 10, warmup: int = 2,
                    timeout: float = 600.0) -> None:
    """The options every `run_jobs` script has (`run_options` reads them back);
    ``name``: the default CSV file name."""
    g = parser.add_argument_group("harness")
    g.add_argument("--name", default=name,
                   help="CSV file name (in --out's folder)")
    g.add_argument("--repeats", type=int, default=repeats,
                   help="timed calls per row (median, min, max)")
    g.add_argument("--warmup", type=int, default=warmup,
                   help="untimed calls before them (compilation excluded)")
    g.add_argument("--timeout", type=float, default=timeout,
                   help="seconds per row (its worker's start-up included)")
    g.add_argument("--budget", type=float, default=math.inf,
                   help="seconds; no new row starts after it (the rest are "
                   "written as skipped)")
    g.add_argument("--hard-stop", type=float, default=math.inf,
                   help="seconds; the running row is killed then")
    g.add_argument("--out", default=None,
                   help="folder or .csv file (default "
                   "benchmarks/results/<device>/)")
    g.add_argument("--inject", nargs="+", default=(), metavar="KIND@ROW",
                   help="testing aid: row number ROW (1-based, plan order) "
                   "crashes, hangs, raises an error or a fake out-of-memory "
                   "(KIND in crash hang error oom)")


def run_options(args: argparse.Namespace) -> dict:
    """`run_jobs`'s keywords from the options of `add_common_args`."""
    return dict(out=args.out, name=args.name, timeout=args.timeout,
                budget=args.budget, hard_stop=args.hard_stop,
                inject=args.inject)


# ---------------------------------------------------------------------------
# Options of jaxrt's backends, from and to row labels


_OPTION_CLASSES = {"cell": "Cell", "bvh": "Bvh", "brute": "Brute",
                   "delaunay": "Delaunay",
                   "spheres": "Spheres", "squares": "Squares"}
_SHORTHAND = {("cell", "auto"): {"kernel": "auto"},
              ("cell", "pallas"): {"kernel": "pallas"},
              ("cell", "xla"): {"kernel": "xla"},
              ("cell", "interpret"): {"kernel": "interpret"},
              ("cell", "warp"): {"kernel": "warp"},
              ("bvh", "unsorted"): {"sort": False},
              ("bvh", "sorted"): {"sort": True},
              ("bvh", "always-rebuild"): {"policy": "rebuild"}}


def parse_backend(label: str) -> tuple[str, dict]:
    """``"cell[xla]"`` -> ``("cell", {"kernel": "xla"})``; also
    ``"bvh[unsorted]"``, ``"bvh[always-rebuild]"`` (``policy="rebuild"``),
    ``"bvh[cluster_size=8,leaf_size=4]"``, the old
    ``"cell:xla"`` and the name ``"bvh-unsorted"``; a plain name -> no
    options."""
    if label == "bvh-unsorted":
        return "bvh", {"sort": False}
    if ":" in label and "[" not in label:
        name, _, opt = label.partition(":")
        label = f"{name}[{opt}]"
    m = re.fullmatch(r"([\w-]+)(?:\[(.*)\])?", label)
    if not m:
        raise ValueError(f"backend label {label!r} is not name or name[options]")
    name, opts = m.group(1), {}
    for part in filter(None, (m.group(2) or "").split(",")):
        key, eq, value = part.partition("=")
        if not eq:
            if (name, key) not in _SHORTHAND:
                raise ValueError(f"{label!r}: {key!r} is not an option of "
                                 f"{name!r}; write key=value")
            opts.update(_SHORTHAND[(name, key)])
            continue
        value = value.strip()
        opts[key.strip()] = (None if value == "None" else
                             value == "True" if value in ("True", "False") else
                             int(value) if value.lstrip("-").isdigit() else value)
    return name, opts


def backend(label: str):
    """What to pass as ``backend=`` for a row labelled ``label``: the name
    for a plain name, else the options object
    (``jaxrt.backends.Cell(kernel="xla")`` for ``"cell[xla]"``)."""
    name, opts = parse_backend(label)
    if not opts:
        return name
    import jaxrt
    cls = getattr(jaxrt.backends, _OPTION_CLASSES.get(name, ""), None)
    if cls is None:
        raise ValueError(f"{label!r}: jaxrt.backends has no options class for "
                         f"{name!r} (known: {sorted(_OPTION_CLASSES)})")
    return cls(**opts)


# ---------------------------------------------------------------------------
# Summary of a run's CSVs (run_h200.sh prints it at the end)


SUMMARY_COLUMNS = ["scene", "system", "method", "list", "N", "k",
                   "median_ms", "min_ms", "max_ms", "repeats", "speedup",
                   "peak_mb", "same_as_xla", "bvh_updates", "status", "failed"]


def summary(paths: list[str]) -> None:
    """A compact table per CSV (``paths``: files, or folders searched for
    them)."""
    files = []
    for p in map(Path, paths):
        if p.is_dir():
            files += sorted(p.rglob("*.csv"))
        elif p.exists():
            files.append(p)
    for path in files:
        rows = read_csv(path)
        sha = next((r.get("git_sha") for r in rows if r.get("git_sha")), "")
        dev = next((r.get("device") for r in rows if r.get("device")), "")
        print(f"\n== {path}  ({dev}, git {sha})")
        print_table(rows, SUMMARY_COLUMNS, width=40)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--serve", metavar="MODULE:FUNCTION")
    parser.add_argument("--summary", nargs="+", metavar="CSV_OR_DIR")
    args = parser.parse_args(argv)
    if args.serve:
        sys.path[:0] = [str(HERE), str(REPO)]
        serve(args.serve)
    elif args.summary:
        summary(args.summary)
    else:
        parser.error("give --serve or --summary")


if __name__ == "__main__":
    main()
