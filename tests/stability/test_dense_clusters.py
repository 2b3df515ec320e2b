"""Dense clusters: k >= 300 neighbours per particle.

Danger: a cell holding hundreds of particles overflows a fixed window, a
per-cell or per-row buffer, a bit word or a shell buffer; a Warp row
write past its width; int16-sized counters. Every backend must list the
cluster exactly, and when an update makes it denser than the buffers
allow, flag overflow (never truncate silently).

Construction: 360 particles in a ball of radius 0.45 (every pair within
0.9 < cutoff 1.0: k = 359 for each) plus 200 background particles. Bounds:
set equality with the float64 oracle (integers); the minimum row length
is 359, asserted, so the case cannot degrade into a sparse one.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax_md import partition, space

import jaxrt
from oracle import assert_layout, brute_pairs, list_pairs
from stability_common import BACKENDS_3D, grid

K = 360


def cluster_scene(seed=0):
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(K, 3))
    u *= (0.45 * rng.uniform(0, 1, (K, 1)) ** (1 / 3)
          / np.linalg.norm(u, axis=1, keepdims=True))
    background = rng.uniform(0, 12.0, (200, 3))
    background = background[np.linalg.norm(background - 6.0, axis=1) > 2.0]
    return np.concatenate([6.0 + u, background]).astype(np.float32)


@pytest.mark.parametrize(*grid(
    lambda backend, fmt: fmt is partition.Dense and backend != "cell",
    backend=BACKENDS_3D, fmt=[partition.Dense, partition.OrderedSparse]))
def test_cluster_of_k_360_is_exact_and_its_growth_overflows_loudly(backend,
                                                                   fmt):
    R = jnp.asarray(cluster_scene())
    disp, _ = space.periodic(12.0)
    fns = jaxrt.neighbor_list(disp, 12.0, 1.0, format=fmt, backend=backend,
                              capacity_multiplier=1.0)
    nbrs = fns.allocate(R)
    assert not nbrs.did_buffer_overflow
    assert_layout(nbrs)
    want = brute_pairs(R, 1.0, 12.0, True)
    if fmt is partition.OrderedSparse:
        want = {(i, j) for i, j in want if j < i}
    else:
        assert min(np.sum(np.asarray(nbrs.idx)[:K] < R.shape[0], axis=1)) \
            >= K - 1
    assert list_pairs(nbrs) == want
    # Pull 30 background particles into the cluster: more neighbours than
    # capacity_multiplier=1 left room for. Overflow must be flagged.
    far = np.flatnonzero(np.linalg.norm(np.asarray(R) - 6.0, axis=1) > 2.0)
    denser = R.at[far[:30]].set(6.0 + 0.01 * jnp.arange(30)[:, None]
                                * jnp.ones(3) / 30)
    grown = jax.jit(fns.update)(denser, nbrs)
    assert grown.did_buffer_overflow
    assert int(grown.error.code) & jaxrt.ErrorCode.NEIGHBOR_LIST_OVERFLOW
    again = fns.allocate(denser)
    want = brute_pairs(denser, 1.0, 12.0, True)
    if fmt is partition.OrderedSparse:
        want = {(i, j) for i, j in want if j < i}
    assert not again.did_buffer_overflow
    assert list_pairs(again) == want
