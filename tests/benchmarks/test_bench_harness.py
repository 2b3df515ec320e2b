"""The benchmark harness's worker isolation (`benchmarks/_harness.py`):
which jobs share a worker process and which get a fresh one. A job's row
says which process measured it (a trivial target module that returns its
pid), so the sharing is observed, not assumed."""
import os

import pytest

from benchmarks import _harness

TARGET = '''
import os

def run(job):
    return {"pid": os.getpid()}
'''


@pytest.fixture
def target(tmp_path, monkeypatch):
    (tmp_path / "pid_target.py").write_text(TARGET)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(
        [str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    return "pid_target:run"


def _pids(target, jobs, tmp_path, **options):
    rows, _ = _harness.run_jobs(target, jobs, out=str(tmp_path / "o.csv"),
                                name="o.csv", columns=["name"], table=False,
                                **options)
    assert [r["status"] for r in rows] == ["ok"] * len(jobs)
    return [r["pid"] for r in rows]


def test_groups_get_a_worker_each_unless_they_share_a_worker_key(
        target, tmp_path):
    jobs = [{"name": f"{g}{i}", "_group": g} for g in "ab" for i in range(2)]
    pids = _pids(target, jobs, tmp_path, reuse_worker=True)
    # One worker per group: a's two jobs share one, b's another.
    assert pids[0] == pids[1] != pids[2] == pids[3]
    shared = [{**j, "_worker": "one"} for j in jobs]
    pids = _pids(target, shared, tmp_path, reuse_worker=True)
    assert len(set(pids)) == 1
    # Without reuse_worker every job has its own worker, keys or not.
    pids = _pids(target, shared[:2], tmp_path)
    assert pids[0] != pids[1]


def test_a_failed_job_ends_the_shared_worker(target, tmp_path):
    jobs = [{"name": f"j{i}", "_group": f"g{i}", "_worker": "one"}
            for i in range(3)]
    rows, _ = _harness.run_jobs(target, jobs, out=str(tmp_path / "o.csv"),
                                name="o.csv", columns=["name"], table=False,
                                reuse_worker=True, inject=["error@2"])
    assert [r["status"] for r in rows] == ["ok", "error", "ok"]
    # The job after the failure ran in a fresh worker.
    assert rows[0]["pid"] != rows[2]["pid"]
