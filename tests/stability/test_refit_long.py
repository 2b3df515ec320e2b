"""BVH refits over many steps: no missed pair.

Danger: a kept BVH that is refit (boxes recomputed, topology kept) while
particles wander far from where it was built: items outside the band that
the padded boxes and the gamma rays cover, or a stale box, miss pairs
silently. A refit must be exact however far particles moved
(`jaxrt.backends.rt.aabb`); only the policy decides when to rebuild.

Bounds: every step's list equals the float64 oracle's (set equality,
integers), over a random walk whose total displacement is several
cutoffs (so the drift policy's bound is crossed and it rebuilds; the
never-rebuild policy refits throughout), and the steps were mostly refits
(counted by `jaxrt.backends.rt.ffi.update_counts`), so the case cannot pass by
rebuilding every time.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax_md import space

import jaxrt
from oracle import brute_pairs
from stability_common import WARP

pytestmark = pytest.mark.skipif("bvh" not in WARP, reason="needs Warp")


def walk(steps, n=120, side=6.0, cutoff=1.0, step_size=0.02, seed=21,
         policy="drift"):
    from jaxrt.backends.rt import ffi
    disp, shift = space.periodic(side)
    R0 = jax.random.uniform(jax.random.PRNGKey(seed), (n, 3)) * side
    kicks = jax.random.normal(jax.random.PRNGKey(seed + 1), (steps, n, 3))
    fns = jaxrt.neighbor_list(disp, side, cutoff,
                              backend=jaxrt.backends.Bvh(policy=policy),
                              capacity_multiplier=2.0)
    nbrs = fns.allocate(R0)

    def step(carry, kick):
        R, nbrs = carry
        R = shift(R, step_size * kick)
        nbrs = fns.update(R, nbrs)
        return (R, nbrs), (R, nbrs.idx, nbrs.error.code)

    before = ffi.update_counts.copy()
    _, (Rs, idxs, codes) = jax.jit(lambda R, nb: jax.lax.scan(
        step, (R, nb), kicks))(R0, nbrs)
    jax.block_until_ready(idxs)
    done = ffi.update_counts - before
    Rs, idxs, codes = np.asarray(Rs), np.asarray(idxs), np.asarray(codes)
    assert not codes.any()
    for s in range(steps):
        rows = idxs[s]
        got = {(i, int(j)) for i in range(n) for j in rows[i] if j < n}
        assert got == brute_pairs(Rs[s], cutoff, side, True), f"step {s}"
    return done


def test_refits_over_200_steps_never_miss_a_pair():
    """200 steps of 0.02·N(0,1) per axis: an r.m.s. walk of
    0.02·sqrt(3·200) = 0.49 per particle, the farthest several cutoffs."""
    done = walk(200)
    assert done["refit"] + done["rebuild"] == 200
    assert done["refit"] > 100, done


@pytest.mark.slow
@pytest.mark.parametrize("policy", ["drift", "gradient", "avg", "refit"])
def test_refits_over_2000_steps_never_miss_a_pair(policy):
    done = walk(2000, policy=policy)
    assert done["refit"] + done["rebuild"] == 2000
