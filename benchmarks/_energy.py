"""Energy of a timed region: NVML's GPU energy counter and power trace,
RAPL's CPU package counter (seed 003 §4.3, SPECS.md §5, issue #17).

`measure` is the one entry point::

    with _energy.measure(interval_s=0.01) as m:
        steps, seconds = _energy.repeat_for(step, inputs, 2.0)
    m.gpu.joules, m.gpu.mean_watts, m.gpu.trace, m.gpu.reason
    m.cpu.joules, m.cpu.reason

GPU (`GpuMeter`): ``nvmlDeviceGetTotalEnergyConsumption`` (mJ since the
driver loaded; Volta and newer) is read before and after the region, and a
background thread samples ``nvmlDeviceGetPowerUsage`` (mW) every
``interval_s`` into a trace of (seconds since the start, watts). NVML comes
from ``pynvml`` (package ``nvidia-ml-py``) or, where that is not installed
(the lent GPU machines cannot install packages), from ``libnvidia-ml.so.1``
through ctypes (`_CtypesNvml`, the same few calls). Where neither loads, or
NVML sees no GPU, every value is None and ``reason`` says why; nothing
raises.

CPU (`RaplMeter`): the package domains' ``energy_uj`` of
``/sys/class/powercap/intel-rapl:*`` (also AMD's on recent kernels), with
the counters' wrap-around; None and a reason where not readable (often
root-only, absent in containers).

How long the region must be. The energy counter does not tick every
millisecond: it is refreshed every 20-100 ms on recent GPUs (PETSc's
``PetscLogGpuEnergyMeter`` notes), so a region of a few ms can read 0 J or
one whole refresh too much. Repeat the measured step for at least ~1 s
(`repeat_for`; table2.py's ``--energy-seconds``, default 2 s), which bounds
that error to a few per cent. On Ampere (other than GA100) and newer, Hopper
included, ``nvmlDeviceGetPowerUsage`` is itself a 1 s moving average (NVML
reference), so the trace is smooth at the 10 ms sampling and lags the load by
up to a second: use it for Fig 11-style shapes, and the counter (not the
trace's integral) for the joules. Only where the counter is not supported
are the joules the trace's trapezoid integral (``source`` says so), which is
how the paper group's powermon integrates (100 ms samples).
"""
from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import glob
import os
import threading
import time
from typing import Any, Callable, Iterator


@dataclasses.dataclass
class Reading:
    """One meter's result for a region; None values come with ``reason``.

    Attributes:
      joules: energy over the region, J.
      mean_watts: joules / seconds.
      peak_watts: the trace's largest sample (None without a trace).
      seconds: the region's wall time.
      trace: (seconds since the region's start, watts) samples.
      source: where the joules came from (``"nvml-counter:0"``,
        ``"nvml-power-integral:0"``, ``"rapl:package-0+package-1"``).
      reason: why a value is None (empty when all is measured).
    """

    joules: float | None = None
    mean_watts: float | None = None
    peak_watts: float | None = None
    seconds: float | None = None
    trace: list = dataclasses.field(default_factory=list)
    source: str = ""
    reason: str = ""


def _integrate(trace: list) -> float | None:
    """Trapezoid integral of (t, W) samples, J; None with < 2 samples."""
    if len(trace) < 2:
        return None
    return sum((t1 - t0) * (w0 + w1) / 2
               for (t0, w0), (t1, w1) in zip(trace, trace[1:]))


# ---------------------------------------------------------------------------
# NVML


class _NvmlError(Exception):
    """What `_CtypesNvml` raises (pynvml raises its own NVMLError)."""


class _CtypesNvml:
    """The few NVML calls `GpuMeter` needs, with pynvml's names, straight
    from the driver's ``libnvidia-ml.so.1``: the GPU machines have the
    driver but may not have ``nvidia-ml-py``."""

    NVMLError = _NvmlError

    def __init__(self, lib: str = "libnvidia-ml.so.1"):
        self._lib = ctypes.CDLL(lib)  # OSError where there is no driver
        self._lib.nvmlErrorString.restype = ctypes.c_char_p

    def _call(self, name: str, *args) -> None:
        ret = getattr(self._lib, name)(*args)
        if ret != 0:  # NVML_SUCCESS
            msg = self._lib.nvmlErrorString(ret) or b"unknown"
            raise _NvmlError(f"{name}: {msg.decode()} ({ret})")

    def nvmlInit(self) -> None:
        self._call("nvmlInit_v2")

    def nvmlShutdown(self) -> None:
        self._call("nvmlShutdown")

    def nvmlDeviceGetCount(self) -> int:
        n = ctypes.c_uint()
        self._call("nvmlDeviceGetCount_v2", ctypes.byref(n))
        return n.value

    def nvmlDeviceGetHandleByIndex(self, index: int):
        handle = ctypes.c_void_p()
        self._call("nvmlDeviceGetHandleByIndex_v2", ctypes.c_uint(index),
                   ctypes.byref(handle))
        return handle

    def nvmlDeviceGetTotalEnergyConsumption(self, handle) -> int:
        mj = ctypes.c_ulonglong()
        self._call("nvmlDeviceGetTotalEnergyConsumption", handle,
                   ctypes.byref(mj))
        return mj.value

    def nvmlDeviceGetPowerUsage(self, handle) -> int:
        mw = ctypes.c_uint()
        self._call("nvmlDeviceGetPowerUsage", handle, ctypes.byref(mw))
        return mw.value


def load_nvml() -> tuple[Any, str]:
    """(NVML module or None, reason when None): ``pynvml`` first, then the
    driver's library through ctypes."""
    try:
        import pynvml
        return pynvml, ""
    except ImportError:
        pass
    try:
        return _CtypesNvml(), ""
    except (OSError, AttributeError) as exc:
        return None, f"no NVML (pynvml not importable; {exc})"


def nvml_index() -> int:
    """NVML's index of the GPU JAX calls 0: the first of
    ``CUDA_VISIBLE_DEVICES`` where that is a number (NVML ignores the
    variable), else 0 (one-GPU machines)."""
    first = os.environ.get("CUDA_VISIBLE_DEVICES", "").split(",")[0].strip()
    return int(first) if first.isdigit() else 0


class GpuMeter:
    """NVML energy counter around a region plus a power-sampling thread.

    ``start()`` then ``stop() -> Reading``. Every NVML failure becomes the
    reading's ``reason``; the meter never raises.
    """

    def __init__(self, index: int | None = None, interval_s: float = 0.01,
                 nvml=None):
        self.index = nvml_index() if index is None else index
        self.interval_s = interval_s
        self._nvml = nvml
        self._handle = None
        self._inited = False
        self._reason = ""
        self._trace: list = []
        self._thread: threading.Thread | None = None
        self._done = threading.Event()

    def _open(self) -> None:
        nv = self._nvml
        if nv is None:
            nv, self._reason = load_nvml()
            if nv is None:
                return
        try:
            nv.nvmlInit()
        except Exception as exc:  # noqa: BLE001 - NVMLError_* or ctypes'
            self._reason = f"no NVML ({exc})"
            return
        self._nvml, self._inited = nv, True
        try:
            if nv.nvmlDeviceGetCount() <= self.index:
                self._reason = "no GPU (NVML sees none at index %d)" % self.index
                return
            self._handle = nv.nvmlDeviceGetHandleByIndex(self.index)
        except Exception as exc:  # noqa: BLE001
            self._reason = f"no GPU ({exc})"

    def _energy_mj(self) -> tuple[int | None, str]:
        try:
            return self._nvml.nvmlDeviceGetTotalEnergyConsumption(
                self._handle), ""
        except Exception as exc:  # noqa: BLE001 - NotSupported before Volta
            return None, f"energy counter: {exc}"

    def _sample(self) -> None:
        """The sampling thread: one (t, W) per interval until stopped. A
        failed read ends the trace (it would fail every time)."""
        while not self._done.is_set():
            try:
                mw = self._nvml.nvmlDeviceGetPowerUsage(self._handle)
            except Exception:  # noqa: BLE001
                return
            self._trace.append((time.perf_counter() - self._t0, mw / 1e3))
            self._done.wait(self.interval_s)

    def start(self) -> None:
        self._open()
        self._t0 = time.perf_counter()
        if self._handle is None:
            return
        self._mj0, self._mj_reason = self._energy_mj()
        self._done.clear()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()

    def stop(self) -> Reading:
        seconds = time.perf_counter() - self._t0
        if self._handle is None:
            self._shutdown()
            return Reading(seconds=seconds, reason=self._reason)
        mj1, reason = self._energy_mj()
        self._done.set()
        self._thread.join()
        trace = list(self._trace)
        self._shutdown()
        peak = max((w for _, w in trace), default=None)
        out = Reading(seconds=seconds, trace=trace, peak_watts=peak)
        if self._mj0 is not None and mj1 is not None and mj1 > self._mj0:
            out.joules = (mj1 - self._mj0) / 1e3
            out.source = f"nvml-counter:{self.index}"
        else:
            # No counter (or it did not tick): the trace's integral, as the
            # paper group's powermon does.
            out.joules = _integrate(trace)
            why = self._mj_reason or reason or (
                "energy counter did not advance (region too short)")
            if out.joules is None:
                out.reason = why + "; no power samples"
            else:
                out.source = f"nvml-power-integral:{self.index}"
                out.reason = why
        if out.joules is not None and seconds > 0:
            out.mean_watts = out.joules / seconds
        return out

    def _shutdown(self) -> None:
        if self._inited:
            self._inited = False
            with contextlib.suppress(Exception):
                self._nvml.nvmlShutdown()


# ---------------------------------------------------------------------------
# RAPL


class RaplMeter:
    """CPU package energy from the Linux powercap interface (RAPL): the sum
    of the top-level ``intel-rapl:N`` domains (packages; their DRAM and core
    sub-domains are inside them), wrap-around corrected."""

    def __init__(self, root: str = "/sys/class/powercap"):
        self.root = root
        self._domains: list[str] = []
        self._reason = ""

    def _read(self) -> list[int] | None:
        try:
            return [int(open(os.path.join(d, "energy_uj")).read())
                    for d in self._domains]
        except (OSError, ValueError) as exc:
            self._reason = f"no RAPL ({exc.__class__.__name__}: {exc})"
            return None

    def start(self) -> None:
        # Top level only: "intel-rapl:0", not "intel-rapl:0:0".
        self._domains = sorted(d for d in glob.glob(
            os.path.join(self.root, "intel-rapl:*")) if d.count(":") == 1)
        if not self._domains:
            self._reason = "no RAPL (no powercap package domains)"
        self._t0 = time.perf_counter()
        self._uj0 = self._read() if self._domains else None

    def stop(self) -> Reading:
        seconds = time.perf_counter() - self._t0
        uj1 = self._read() if self._uj0 is not None else None
        if uj1 is None:
            return Reading(seconds=seconds, reason=self._reason)
        total = 0
        for d, a, b in zip(self._domains, self._uj0, uj1):
            if b < a:  # wrapped once (regions are seconds, wraps are minutes)
                b += int(open(os.path.join(d, "max_energy_range_uj")).read())
            total += b - a
        names = []
        for d in self._domains:
            with contextlib.suppress(OSError):
                names.append(open(os.path.join(d, "name")).read().strip())
        joules = total / 1e6
        return Reading(joules=joules, seconds=seconds,
                       mean_watts=joules / seconds if seconds > 0 else None,
                       source="rapl:" + "+".join(names or ["?"]))


# ---------------------------------------------------------------------------
# The region


@dataclasses.dataclass
class Measurement:
    """What `measure` fills in when its region ends."""

    gpu: Reading = dataclasses.field(default_factory=Reading)
    cpu: Reading = dataclasses.field(default_factory=Reading)


@contextlib.contextmanager
def measure(interval_s: float = 0.01, *, nvml=None, gpu_index=None,
            rapl_root: str = "/sys/class/powercap") -> Iterator[Measurement]:
    """Meter the ``with`` block: GPU (NVML) and CPU (RAPL) readings in the
    yielded `Measurement`, filled when the block ends (also when it
    raises). ``nvml``: an NVML-like module (tests pass a fake)."""
    gpu = GpuMeter(gpu_index, interval_s, nvml=nvml)
    cpu = RaplMeter(rapl_root)
    m = Measurement()
    cpu.start()
    gpu.start()
    try:
        yield m
    finally:
        m.gpu = gpu.stop()
        m.cpu = cpu.stop()


def repeat_for(fn: Callable, inputs: list, seconds: float, *,
               sync: Callable, min_calls: int = 1) -> tuple[int, float]:
    """Call ``sync(fn(x))``, ``x`` rotating over ``inputs``, until
    ``seconds`` have passed (at least ``min_calls``). Every call is
    synchronised, as in the timing, so the region holds exactly the counted
    calls. Returns (calls, wall seconds)."""
    t0 = time.perf_counter()
    calls = 0
    while calls < min_calls or time.perf_counter() - t0 < seconds:
        sync(fn(inputs[calls % len(inputs)]))
        calls += 1
    return calls, time.perf_counter() - t0
