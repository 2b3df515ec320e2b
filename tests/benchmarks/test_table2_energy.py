"""Seed 003's energy measurement (benchmarks/_energy.py, table2.py
--energy, table2_energy_plot.py): the meters against fake NVML and RAPL,
a CPU row with the energy window (no NVML here: empty energy with its
reason, the pair count filled), the power-trace file, and the figures from
made-up data."""
import csv
import sys
import time
import types

import pytest

from benchmarks import _energy


class FakeNvml(types.SimpleNamespace):
    """pynvml's calls that `_energy.GpuMeter` makes: the energy counter
    steps through ``energy_mj`` (one value per read), the power is
    ``power_mw``."""

    class NVMLError(Exception):
        pass

    def __init__(self, energy_mj=(1_000_000, 1_002_500), power_mw=250_000,
                 count=1, init_error=None, energy_error=None):
        super().__init__(reads=list(energy_mj), power_mw=power_mw,
                         count=count, init_error=init_error,
                         energy_error=energy_error, shut=False)

    def nvmlInit(self):
        if self.init_error:
            raise self.NVMLError(self.init_error)

    def nvmlShutdown(self):
        self.shut = True

    def nvmlDeviceGetCount(self):
        return self.count

    def nvmlDeviceGetHandleByIndex(self, index):
        return ("handle", index)

    def nvmlDeviceGetTotalEnergyConsumption(self, handle):
        if self.energy_error:
            raise self.NVMLError(self.energy_error)
        return self.reads.pop(0)

    def nvmlDeviceGetPowerUsage(self, handle):
        return self.power_mw


def _region(seconds=0.12, **kwargs):
    with _energy.measure(0.01, rapl_root="/nonexistent", **kwargs) as m:
        time.sleep(seconds)
    return m


def test_counter_difference_and_trace(monkeypatch):
    fake = FakeNvml()
    # Through the import, as on a machine with nvidia-ml-py.
    monkeypatch.setitem(sys.modules, "pynvml", fake)
    m = _region(gpu_index=0)
    gpu = m.gpu
    assert gpu.joules == pytest.approx(2.5)  # (1 002 500 - 1 000 000) mJ
    assert gpu.source == "nvml-counter:0" and gpu.reason == ""
    assert gpu.seconds >= 0.12
    assert gpu.mean_watts == pytest.approx(2.5 / gpu.seconds)
    # ~12 samples at 10 ms, all 250 W, times increasing within the region
    # (a loaded 2-core machine may start the sampler late and drop samples:
    # only the order and the bounds are sure).
    assert len(gpu.trace) >= 2 and gpu.peak_watts == 250.0
    assert all(w == 250.0 for _, w in gpu.trace)
    ts = [t for t, _ in gpu.trace]
    assert ts == sorted(ts) and 0 <= ts[0] < ts[-1] <= gpu.seconds + 0.05
    assert fake.shut and not fake.reads
    assert m.cpu.joules is None and "no RAPL" in m.cpu.reason


def test_no_counter_integrates_the_trace():
    fake = FakeNvml(power_mw=100_000, energy_error="Not Supported")
    gpu = _region(nvml=fake, gpu_index=0).gpu
    assert gpu.source == "nvml-power-integral:0"
    assert "Not Supported" in gpu.reason
    span = gpu.trace[-1][0] - gpu.trace[0][0]
    assert gpu.joules == pytest.approx(100.0 * span)  # constant 100 W


def test_counter_that_did_not_tick_is_not_zero_joules():
    gpu = _region(nvml=FakeNvml(energy_mj=(5, 5)), gpu_index=0).gpu
    assert "did not advance" in gpu.reason
    assert gpu.source.startswith("nvml-power-integral")


@pytest.mark.parametrize("fake,why", [
    (FakeNvml(init_error="Driver Not Loaded"), "no NVML"),
    (FakeNvml(count=0), "no GPU")])
def test_failures_are_reasons(fake, why):
    gpu = _region(0.02, nvml=fake, gpu_index=0).gpu
    assert gpu.joules is None and gpu.mean_watts is None and not gpu.trace
    assert gpu.reason.startswith(why)


def test_this_machine_never_raises():
    # Whatever is installed (here: no driver), a reading comes back.
    m = _region(0.02)
    assert m.gpu.seconds > 0
    assert m.gpu.joules is not None or m.gpu.reason


def test_rapl_packages_and_wrap(tmp_path):
    for name, start in (("intel-rapl:0", 900), ("intel-rapl:1", 10)):
        d = tmp_path / name
        d.mkdir()
        (d / "energy_uj").write_text(f"{start}\n")
        (d / "max_energy_range_uj").write_text("1000\n")
        (d / "name").write_text(f"package-{name[-1]}\n")
    (tmp_path / "intel-rapl:0:0").mkdir()  # a sub-domain: not summed
    meter = _energy.RaplMeter(str(tmp_path))
    meter.start()
    (tmp_path / "intel-rapl:0" / "energy_uj").write_text("100\n")  # wrapped
    (tmp_path / "intel-rapl:1" / "energy_uj").write_text("510\n")
    r = meter.stop()
    assert r.joules == pytest.approx((200 + 500) / 1e6)
    assert r.source == "rapl:package-0+package-1"


def test_repeat_for_counts_calls():
    seen = []
    calls, seconds = _energy.repeat_for(seen.append, [1, 2, 3], 0.0,
                                        sync=lambda x: x, min_calls=4)
    assert calls == 4 and seen == [1, 2, 3, 1] and seconds >= 0


# jax-md's high_precision_sum asks for float64 sums without x64.
@pytest.mark.filterwarnings("ignore:Explicitly requested dtype float64")
def test_table2_row_with_energy_on_cpu(tmp_path):
    pytest.importorskip("warp")
    from benchmarks import table2
    counts = {}
    for method in ("ORCS-persé", "RT-REF"):
        job = {"method": method, "scene": "disordered", "radii": "r=160",
               "boundary": "periodic", "N": 300, "seed": 0,
               "policy": "gradient", "snapshots": 2, "jitter": 0.01,
               "repeats": 2, "warmup": 1, "target_s": None,
               "max_repeats": None, "dynamics": table2.DYNAMICS,
               "energy_seconds": 0.05, "energy_interval_s": 0.01}
        row = table2.run_row(job)
        assert row["status"] == "ok" and row["energy_steps"] >= 1
        assert row["energy_window_s"] >= 0.05
        if row["energy_j"] is None:  # this CPU machine
            assert row["interactions_per_joule"] is None
            assert "no NVML" in row["energy_reason"] \
                or "no GPU" in row["energy_reason"]
        counts[method] = row["interactions_per_step"]
    # persé's fused count and RT-REF's list hold the same pairs.
    assert counts["RT-REF"] > 0 and counts["ORCS-persé"] == counts["RT-REF"]


def test_trace_writer_and_figures(tmp_path):
    import argparse

    from benchmarks import table2
    from benchmarks import table2_energy_plot
    args = argparse.Namespace(energy=True, out=str(tmp_path / "run.csv"),
                              name="x.csv")
    writer = table2.TraceWriter(args, table2.COLUMNS)
    row = {"method": "RT-REF", "scene": "disordered", "radii": "r=1",
           "boundary": "wall", "N": 50, "status": "ok",
           "power_trace": [(0.0, 100.0), (0.01, 110.0)]}
    writer(row)
    assert "power_trace" not in row and row["power_samples"] == 2
    with open(tmp_path / "run_power.csv", newline="") as f:
        lines = list(csv.DictReader(f))
    assert [float(x["power_w"]) for x in lines] == [100.0, 110.0]
    assert lines[0]["method"] == "RT-REF" and lines[0]["meter"] == "gpu"
    # The figures from a made-up run (all cases, n/a bars, idle lines).
    csv_path, power = table2_energy_plot.write_fake(tmp_path / "fake")
    eff, pw = table2_energy_plot.plot_run(csv_path, power)
    assert eff.stat().st_size > 10_000 and pw.stat().st_size > 10_000


def test_ctypes_nvml_calls(monkeypatch):
    """The driver-library fallback (no nvidia-ml-py on the GPU machine):
    the C entry points it calls, their out-parameters, the error path."""
    class Fn:
        def __init__(self, out=None, ret=0):
            self.out, self.ret = out, ret

        def __call__(self, *args):
            if self.out is not None:  # the last argument is byref(out)
                args[-1]._obj.value = self.out
            return self.ret

    lib = types.SimpleNamespace(
        nvmlErrorString=lambda ret: b"Not Supported",
        nvmlInit_v2=Fn(), nvmlShutdown=Fn(),
        nvmlDeviceGetCount_v2=Fn(1), nvmlDeviceGetHandleByIndex_v2=Fn(1234),
        nvmlDeviceGetTotalEnergyConsumption=Fn(ret=3),
        nvmlDeviceGetPowerUsage=Fn(300_000))
    monkeypatch.setattr(_energy.ctypes, "CDLL", lambda name: lib)
    monkeypatch.setitem(sys.modules, "pynvml", None)  # import fails
    nv, reason = _energy.load_nvml()
    assert isinstance(nv, _energy._CtypesNvml) and not reason
    nv.nvmlInit()
    assert nv.nvmlDeviceGetCount() == 1
    handle = nv.nvmlDeviceGetHandleByIndex(0)
    assert handle.value == 1234
    assert nv.nvmlDeviceGetPowerUsage(handle) == 300_000
    with pytest.raises(nv.NVMLError, match="Not Supported"):
        nv.nvmlDeviceGetTotalEnergyConsumption(handle)
    # In a meter: no counter, so the trace's integral at 300 W.
    gpu = _region(nvml=nv, gpu_index=0).gpu
    assert gpu.source == "nvml-power-integral:0" and gpu.peak_watts == 300.0


@pytest.mark.filterwarnings("ignore:Explicitly requested dtype float64")
def test_table2_row_refused_at_allocate_is_reported_not_raised(monkeypatch):
    # The paper's "-" cells: a list past what the backend indexes is a row
    # with status "oom" and jaxrt's reason (any of jaxrt.ListTooLargeError's
    # refusals), not an error. Here CPU-CELL's cell list may index 1 000
    # entries, far fewer than its buffers need for 300 particles.
    from benchmarks import table2
    from jaxrt.backends.cell import search as cell_list
    monkeypatch.setattr(cell_list.Cell, "max_list_entries", 1000,
                        raising=False)
    job = {"method": "CPU-CELL", "scene": "lattice", "radii": "r=160",
           "boundary": "wall", "N": 300, "seed": 0, "policy": "gradient",
           "snapshots": 1, "jitter": 0.01, "repeats": 1, "warmup": 1,
           "target_s": None, "max_repeats": None,
           "dynamics": table2.DYNAMICS}
    row = table2.run_row(job)
    assert row["status"] == "oom", row
    assert row["failed"].startswith("ListTooLargeError: ")
    assert "more than backend='cell'" in row["failed"]
