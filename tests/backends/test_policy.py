"""BVH rebuild policies (`jaxrt.backends.rt.policy`, seed 003 §3.1): the decisions
given injected times, the drift signal (read by the drift policy alone),
and lists that stay exact while a policy refits."""
from __future__ import annotations

import math

import jax
import numpy as np
import pytest
from jax_md import space

import jaxrt
from oracle import brute_pairs

pytest.importorskip("warp")
rt = pytest.importorskip("jaxrt.rt")
from jaxrt.backends.rt import ffi  # noqa: E402
from jaxrt.backends.rt import policy


def drive(value, steps, times, drifted=()):
    """Run ``value``'s decisions for ``steps`` calls, the first of them a
    build, feeding ``times(action, refits_since_rebuild)`` -> (t_action,
    t_query); a particle drifted past the bound at the calls in
    ``drifted``. Returns the calls that (re)built."""
    state = value.start()
    built, refits = [], 0
    for step in range(steps):
        action = policy.choose(state, has_tree=step > 0,
                               drifted=step in drifted)
        refits = refits + 1 if action == "refit" else 0
        if action != "refit":
            built.append(step)
        state.record(action, *times(action, refits))
    return built


def constant(action, refits):
    return (8.0 if action != "refit" else 1.0), 2.0


def test_fixed_rebuilds_every_k_calls():
    assert drive(policy.Fixed(k=4), 13, constant) == [0, 4, 8, 12]
    assert drive(policy.Fixed(k=1), 4, constant) == [0, 1, 2, 3]


def test_rebuild_refit_and_drift():
    assert drive(policy.Rebuild(), 5, constant) == [0, 1, 2, 3, 4]
    assert drive(policy.Refit(), 50, constant, drifted={5, 9}) == [0]
    assert drive(policy.Drift(), 50, constant) == [0]
    assert drive(policy.Drift(), 12, constant, drifted={5, 9}) == [0, 5, 9]


@pytest.mark.parametrize("value", [policy.Fixed(k=100), policy.Avg(),
                                   policy.Gradient(), policy.Refit()])
def test_only_the_drift_policy_rebuilds_for_drift(value):
    """A refit is exact however far particles moved, so a drift forces
    nothing: the other policies decide from their clocks alone."""
    assert not value.needs_drift and policy.Drift.needs_drift
    assert drive(value, 12, constant, drifted={5, 9}) == [0]


def growing(action, refits):
    """Rebuild 8 + query 2; a refit 1 + a query that grows by 2 per refit."""
    if action != "refit":
        return 8.0, 2.0
    return 1.0, 2.0 + 2.0 * refits


def test_avg_rebuilds_once_refits_cost_more_on_average():
    # After m refits their mean cost is 1 + (2 + 2 (m + 1) / 2 ... ) = 4 + m,
    # against 10 for a rebuild and its query: the 7th refit tips it.
    assert drive(policy.Avg(), 20, growing) == [0, 8, 16]


def linear(action, refits, t_rebuild=8.0, t_refit=1.0, dq=0.5):
    if action != "refit":
        return t_rebuild, 2.0
    return t_refit, 2.0 + dq * refits


def test_gradient_follows_eq_8():
    # k_opt = -1 + sqrt(1 + 2 (8 - 1) / 0.5) = 4.39: five refits per
    # rebuild once two refits have measured the growth of the query.
    k = -1 + math.sqrt(1 + 2 * (8 - 1) / 0.5)
    assert math.floor(k) == 4
    assert drive(policy.Gradient(), 20, linear) == [0, 6, 12, 18]
    state = policy.Gradient().start()
    state.record("build", 8.0, 2.0)
    for j in (1, 2, 3):
        state.record("refit", 1.0, 2.0 + 0.5 * j)
    assert state.delta_q == pytest.approx(0.5)
    assert state.k_opt() == pytest.approx(k)


def test_gradient_rebuilds_every_call_when_a_refit_costs_more():
    # t_u >= t_r: the square root is at most 1, so k = 0 once the growth is
    # known (two refits), and every call after that rebuilds.
    def times(action, refits):
        return linear(action, refits, t_rebuild=8.0, t_refit=9.0)
    assert drive(policy.Gradient(), 8, times) == [0, 3, 4, 5, 6, 7]


def test_gradient_keeps_refitting_while_the_query_does_not_slow():
    def flat(action, refits):
        return (8.0, 2.0) if action != "refit" else (1.0, 2.0)
    assert drive(policy.Gradient(k_max=50), 120, flat) == [0, 51, 102]


def test_bad_policies_are_refused_clearly():
    with pytest.raises(ValueError, match="policy='nope' is not known"):
        jaxrt.backends.Bvh(policy="nope")
    with pytest.raises(TypeError, match="policy must be a name"):
        jaxrt.backends.Bvh(policy=3)
    with pytest.raises(ValueError, match="k must be an int >= 1"):
        policy.Fixed(k=0)
    with pytest.raises(ValueError, match=r"drift_fraction must be in \[0, 0.25\)"):
        jaxrt.backends.Bvh(drift_fraction=0.3)
    assert jaxrt.backends.Bvh(policy="fixed") == jaxrt.backends.Bvh(
        policy=policy.Fixed(k=200))
    assert jaxrt.backends.Bvh(policy="refit").policy == policy.Refit()


@pytest.mark.parametrize("value", [policy.Fixed(k=5), policy.Gradient(),
                                   policy.Avg()])
def test_lists_stay_exact_while_a_policy_refits(value):
    n, side, cutoff = 200, 7.0, 1.5
    disp, shift = space.periodic(side)
    R0 = jax.random.uniform(jax.random.PRNGKey(40), (n, 3)) * side
    velocity = jax.random.normal(jax.random.PRNGKey(41), (n, 3)) * 0.002
    fns = jaxrt.neighbor_list(disp, side, cutoff,
                              backend=jaxrt.backends.Bvh(policy=value))
    nbrs = fns.allocate(R0)

    def step(carry, _):
        R, nbrs = carry
        R = shift(R, velocity)
        nbrs = fns.update(R, nbrs)
        return (R, nbrs), (R, nbrs.idx)

    before = ffi.update_counts.copy()
    reasons = ffi.rebuild_reasons.copy()
    (_, last), (Rs, idxs) = jax.jit(lambda R, nbrs: jax.lax.scan(
        step, (R, nbrs), None, length=30))(R0, nbrs)
    jax.block_until_ready(idxs)
    done = ffi.update_counts - before
    assert not last.did_buffer_overflow
    assert done["refit"] + done["rebuild"] == 30, done
    assert set(ffi.rebuild_reasons - reasons) <= {"policy"}
    if isinstance(value, policy.Fixed):
        # allocate built; then 4 refits and a rebuild, six times
        assert done == {"refit": 24, "rebuild": 6}, done
    for s in range(30):
        rows = np.asarray(idxs[s])
        got = {(i, int(j)) for i in range(n) for j in rows[i] if j < n}
        assert got == brute_pairs(Rs[s], cutoff, side, True), f"step {s}"
