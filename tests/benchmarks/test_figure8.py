"""The Figure 8 benchmark on a tiny system (CPU): every policy's tree and
the two reference trees run on one trajectory, every call is traced with
what it did and why, the trees' lists agree at every step, only the
policies rebuild, and the ratios table holds the totals and Δq."""
import csv

import pytest

pytest.importorskip("warp")
from benchmarks import figure8  # noqa: E402  (after the skip)


def job(tmp_path, scene, radii, n=300, steps=8):
    return {"scene": scene, "radii": radii, "N": n, "seed": 0,
            "steps": steps, "seconds": 60.0, "sample_every": 2,
            "_policies": list(figure8.POLICIES),
            "_dynamics": figure8.DYNAMICS,
            "_trace": str(tmp_path / "traces" / f"{scene}.csv")}


# jax-md's high_precision_sum asks for float64 sums without x64.
@pytest.mark.filterwarnings("ignore:Explicitly requested dtype float64")
def test_policies_and_references_run_on_one_trajectory(tmp_path):
    (tmp_path / "traces").mkdir()
    rows = figure8.run_scene(job(tmp_path, "disordered", "U[1,160]"))
    by = {r["policy"]: r for r in rows}
    assert set(by) == set(figure8.POLICIES) | set(figure8.REFERENCES)
    for p, r in by.items():
        assert r["status"] == "ok" and r["steps"] == 8, r
        assert r["mismatches"] == 0 and r["forced_rebuilds"] == 0, r
        assert r["total_ms"] > 0
    assert by["refit"]["rebuilds"] == 0 and by["rebuild"]["refits"] == 0
    assert by["fixed"]["rebuilds"] == 0  # k = 200
    with open(tmp_path / "traces" / "disordered.csv", newline="") as f:
        trace = list(csv.DictReader(f))
    calls = [t for t in trace if t["policy"] == "gradient"]
    assert len(calls) == 9 and calls[0]["action"] == "build"
    assert calls[0]["reason"] == "new"
    assert {t["reason"] for t in trace if t["action"] == "rebuild"} <= {"policy"}
    # the rebuilt reference runs every second call, the others every call
    assert [int(t["call"]) for t in trace if t["policy"] == "rebuild"] == [
        0, 2, 4, 6, 8]
    traces = figure8.read_traces([tmp_path])
    table = figure8.ratios(rows, traces)
    got = [r for r in table if (r["scene"], r["radii"])
           == ("disordered", "U[1,160]")]
    assert got[0]["steps"] == 8 and got[0]["vs_second_best"] > 0
    assert got[0]["forced_rebuilds"] == 0
    assert "dq_us" in got[0] and "k_opt" in got[0]


def test_a_list_past_warps_entries_is_refused_before_any_tree(tmp_path):
    """Cluster, r = 160: k ≈ N, so 40 000 particles make 8e8 pairs, past
    Warp's 2**29 list entries: refused from a sample, saying why."""
    rows = figure8.run_scene(job(tmp_path, "cluster", "r=160", n=40_000))
    assert {r["status"] for r in rows} == {"skipped"}
    assert "refused as a list" in rows[0]["failed"]
    assert rows[0]["k"] > 30_000
