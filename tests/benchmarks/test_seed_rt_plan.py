"""The seed 001 study's plan (`benchmarks/seed_rt/plan.py`, no JAX): all
60 configurations of the seed's §5, the fused methods, the jobs it refuses
and why, and the parts (`--part`), which must cover every planned job
exactly once, in the plan's order, each under its budget."""
from __future__ import annotations


import pytest

from benchmarks import seed_rt_study
from benchmarks.seed_rt import plan


def args_of(*argv):
    return seed_rt_study.parse_args(list(argv))


def jobs(configs):
    return [(c["scene"], c["param"], c["p"], m) for c in configs for m in c["methods"]]


def test_all_sixty_configurations_and_fused_methods():
    args = args_of()
    planned, skipped = plan.build_plan(args)
    assert len(plan.universe(False)) == 60
    assert {"aabb-sorted-fused", "aabb-unsorted-fused", "spheres-fused",
            "squares-fused"} <= set(plan.METHODS)
    configs = {(c["scene"], c["param"], c["p"]) for c in planned}
    assert configs == set(plan.universe(False))
    # Every one of the 600 rows is either planned or skipped with a reason.
    rows = jobs(planned) + [(r["scene"], r["param"], r["p"], r["method"]) for r in skipped]
    assert len(rows) == len(set(rows)) == 60 * len(plan.METHODS)
    assert all(r["failed"].startswith("skipped: ") for r in skipped)
    # Refused: only list methods on huge lists, and squares past Warp's offsets;
    # the fused methods run every configuration but the squares' largest one.
    for r in skipped:
        assert r["method"] not in plan.FUSED or (
            r["method"] == "squares-fused" and (r["param"], r["p"]) == (128, 32))
    assert ("sphere", 128, 32, "aabb-sorted-fused") in set(jobs(planned))
    assert ("sphere", 64, 16, "aabb-sorted") not in set(jobs(planned))


def test_largest_first_within_a_tier_heavy_jobs_last():
    args = args_of()
    planned, _ = plan.build_plan(args)
    light = [c for c in planned if not c.get("heavy")]
    heavy = [c for c in planned if c.get("heavy")]
    assert planned == light + heavy
    for tier in {c["tier"] for c in light}:
        ns = [c["N"] for c in light if c["tier"] == tier]
        assert ns == sorted(ns, reverse=True)
    guesses = [plan.guess_job_s(c["scene"], c["param"], c["p"], c["methods"][0],
                                args) for c in heavy]
    assert all(len(c["methods"]) == 1 for c in heavy)
    assert guesses == sorted(guesses, reverse=True)
    assert all(g > args.heavy_s for g in guesses)
    # The H200's part 1: spheres-fused at N = 67M timed out at 150 s.
    assert ("sphere", 128, 32, "spheres-fused") in set(jobs(heavy))


def test_large_configurations_repeat_less_and_wait_longer():
    """From --large-n up one timed call per measurement; each job's
    timeout is at least --timeout and 3x its guess; heavy jobs get parts
    of their own (the 67M configuration once ate a whole part)."""
    args = args_of("--timeout", "150")
    planned, _ = plan.build_plan(args)
    for job in seed_rt_study.jobs_of(planned, args):
        guess = plan.guess_job_s(job["scene"], job["param"], job["p"],
                                 job["method"], args)
        assert job["_timeout"] >= max(150.0, plan.TIMEOUT_FACTOR * guess)
        assert job["min_repeats"] == (1 if job["N"] >= args.large_n else 3)
    parts = plan.split_parts(planned, args)
    for part in parts:
        if any(c.get("heavy") for c in part):
            assert len(part) == 1 and len(part[0]["methods"]) == 1
    # The guesses know the H200's rows at 67M (k = 288): aabb-sorted-fused
    # 1.21 s and aabb-unsorted-fused 5.24 s per call.
    for method, seconds in (("aabb-sorted-fused", 1.21),
                            ("aabb-unsorted-fused", 5.24)):
        fixed, per_pair = plan._GUESS[method]
        pairs = plan.n_of(128, 32) * plan.k_expected("sphere", 128, 32)
        assert abs((fixed + per_pair * pairs) / 1e3 / seconds - 1) < 0.1


@pytest.mark.parametrize("budget", [480.0, 250.0])
def test_parts_cover_the_plan_once_in_order_under_budget(budget):
    args = args_of("--part-budget", str(budget))
    planned, skipped = plan.build_plan(args)
    parts = plan.split_parts(planned, args)
    assert len(parts) > 1
    assert [j for part in parts for j in jobs(part)] == jobs(planned)
    for part in parts:
        total = plan.GUESS_STARTUP_S + sum(
            plan.config_overhead_s(c["N"], args.large_n)
            + sum(plan.guess_job_s(c["scene"], c["param"], c["p"], m, args)
                  for m in c["methods"]) for c in part)
        one_job = len(jobs(part)) == 1
        assert total <= budget or one_job
    # --part K selects part K; the rest become skipped rows.
    args.part = (2, len(parts))
    chosen, rest = plan.select_part(planned, skipped, args)
    assert jobs(chosen) == jobs(parts[1])
    assert len(rest) == len(skipped) + len(jobs(planned)) - len(jobs(parts[1]))
    args.part = (1, len(parts) + 1)
    with pytest.raises(SystemExit, match="parts"):
        plan.select_part(planned, skipped, args)


def test_merge_prefers_measured_rows():
    a = [{"scene": "uniform", "param": 4, "p": 1, "method": "cell", "status": "skipped"},
         {"scene": "uniform", "param": 4, "p": 1, "method": "jax-md", "status": "ok"}]
    b = [{"scene": "uniform", "param": 4, "p": 1, "method": "cell", "status": "ok"},
         {"scene": "uniform", "param": 4, "p": 1, "method": "jax-md", "status": "skipped"}]
    merged = seed_rt_study.merge_rows([a, b])
    assert [r["status"] for r in merged] == ["ok", "ok"]


def test_merge_prefers_a_reason_of_the_row_to_not_selected():
    """A list refused for its size in one part beats "not selected" in
    another (the report then says "refused", not "–"), and neither beats
    a measured row."""
    row = {"scene": "sphere", "param": 128, "p": 16, "status": "skipped"}
    first = [{**row, "method": m, "failed": "skipped: not selected (--configs)"}
             for m in ("cell", "jax-md")]
    second = [{**row, "method": "cell", "failed": "skipped: Dense list >= "
               "N*ceil(1.25k) entries, above 2**31 (jaxrt refuses it)"},
              {**row, "method": "jax-md", "failed": "skipped: time budget 9s reached"}]
    third = [{**row, "method": "jax-md", "status": "ok", "failed": ""}]
    merged = seed_rt_study.merge_rows([first, second, third])
    assert [r["failed"][:22] for r in merged] == ["skipped: Dense list >=", ""]
    assert merged[1]["status"] == "ok"
