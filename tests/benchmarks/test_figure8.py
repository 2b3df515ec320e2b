"""The Figure 8 benchmark's per-run measurement on a tiny system (CPU):
the trace has one entry per call, every policy is timed, and the ratios
table compares the three policies over the steps all completed."""
import csv

import pytest

pytest.importorskip("warp")
from benchmarks import figure8  # noqa: E402  (after the skip)


# jax-md's high_precision_sum asks for float64 sums without x64.
@pytest.mark.filterwarnings("ignore:Explicitly requested dtype float64")
def test_policies_run_and_are_timed(tmp_path):
    rows = []
    for policy in figure8.POLICIES:
        job = {"scene": "disordered", "radii": "U[1,160]", "policy": policy,
               "N": 300, "seed": 0, "steps": 6, "seconds": 60.0,
               "dynamics": figure8.DYNAMICS,
               "trace": str(tmp_path / f"{policy}.csv")}
        row = figure8.run_row(job)
        assert row["steps"] == 6 and row["status"] == "ok"
        assert row["rebuilds"] + row["refits"] == 6
        assert row["total_ms"] > 0  # timed, fixed included
        with open(job["trace"], newline="") as f:
            trace = list(csv.DictReader(f))
        assert trace[0]["action"] == "build" and len(trace) == 7
        rows.append(row)
    table = figure8.ratios(rows)
    got = [r for r in table if r["radii"] == "U[1,160]"
           and r["scene"] == "disordered"]
    assert got and got[0]["steps"] == 6 and got[0]["vs_second_best"] > 0
