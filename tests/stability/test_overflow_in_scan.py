"""Overflow and reallocation in the middle of a scan.

Danger: a buffer that fills up at step k of a ``lax.scan`` truncates rows
silently from then on; an error bit that a later, emptier step clears; a
reallocation that restarts from the wrong state, so the redone chunk
differs from an uninterrupted run.

Bounds: the first step with the overflow bit equals the first step where
the float64 oracle's largest row exceeds the capacity (integers, exact),
and the bit stays set to the end; after the usual reallocation loop the
run equals one allocated with room to spare (positions to float32
rounding of a summation order: 1e-5 relative over 60 steps of a gas
whose Lyapunov time is far longer).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax_md import partition, space

import jaxrt
from jaxrt import sim as S
from oracle import brute_pairs
from stability_common import BACKENDS_3D, grid

SIDE, CUTOFF, STEPS = 8.0, 1.0, 12


def squeeze(R, k):
    """Step k pulls every particle 4% closer to the centre (periodic box,
    so neighbour counts grow)."""
    return SIDE / 2 + (R - SIDE / 2) * (0.96 ** k)


@pytest.mark.parametrize(*grid(
    lambda backend, fmt: (fmt is partition.Dense
                         and backend not in ("spheres", "cell")),
    backend=BACKENDS_3D, fmt=[partition.Dense, partition.Sparse]))
def test_overflow_bit_appears_at_the_right_step_and_stays(backend, fmt):
    R0 = jnp.asarray(np.random.default_rng(11).uniform(1.0, 7.0, (150, 3)),
                     jnp.float32)
    disp, _ = space.periodic(SIDE)
    fns = jaxrt.neighbor_list(disp, SIDE, CUTOFF, format=fmt,
                              backend=backend, capacity_multiplier=1.5)
    nbrs = fns.allocate(R0)
    capacity = nbrs.idx.shape[-1]

    def step(nbrs, k):
        nbrs = fns.update(squeeze(R0, k), nbrs)
        return nbrs, nbrs.error.code

    _, codes = jax.jit(lambda nb: jax.lax.scan(
        step, nb, jnp.arange(1, STEPS + 1)))(nbrs)
    flagged = (np.asarray(codes) & 1).astype(bool)
    need = []
    for k in range(1, STEPS + 1):
        pairs = brute_pairs(np.asarray(squeeze(R0, k)), CUTOFF, SIDE, True)
        if fmt is partition.Dense:
            rows = np.bincount([i for i, _ in pairs], minlength=150)
            need.append(rows.max())
        else:
            need.append(len(pairs))
    over = np.asarray(need) > capacity
    assert over.any() and not over[0], "the scene must overflow mid-scan"
    first = int(np.argmax(over))
    assert flagged.tolist() == [False] * first + [True] * (STEPS - first)
    # The usual loop: reallocate where it overflowed; the list is exact.
    last = squeeze(R0, STEPS)
    again = fns.allocate(last)
    assert not again.did_buffer_overflow
    want = brute_pairs(np.asarray(last), CUTOFF, SIDE, True)
    from oracle import expected_pairs, list_pairs
    assert list_pairs(again) == expected_pairs(fmt, want)


def _implosion(capacity_multiplier):
    """A gas whose particles all fly towards the centre: the density
    grows ~10% per chunk of 10 steps (contraction 0.6 · 0.05 = 3% per axis),
    so a list with 30% head-room overflows after a few chunks and the
    redone chunk fits."""
    g = (np.arange(5) + 0.5) * 2.0
    pos = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    # jittered, so that the lattice's shells do not cross the cutoff at once
    pos = pos + np.random.default_rng(12).uniform(-0.3, 0.3, pos.shape)
    vel = -0.6 * (pos - 5.0)
    return S.Scene(
        particles=S.make_particles(positions=pos, velocities=vel),
        box=S.Box((10.0,) * 3, ("periodic",) * 3),
        effects=(S.LJ(r_cutoff=2.5, r_onset=2.0, epsilon=0.01),),
        integrator=S.Integrator(dt=0.005),
        neighbors=S.Neighbors(skin=0.3, format="Dense",
                              capacity_multiplier=capacity_multiplier))


@pytest.mark.slow  # ~50 s on 2 CPU cores: each reallocation recompiles
def test_reallocation_mid_chunk_redoes_the_chunk_exactly():
    """run_chunk: the chunk whose list overflowed is redone from its start
    with a list reallocated there; the result equals a run whose list
    never overflowed."""
    results = {}
    for multiplier in (1.3, 8.0):
        compiled = S.compile_scene(_implosion(multiplier))
        state, nbrs = compiled.init()
        stats = S.RunStats()
        for _ in range(6):
            state, nbrs = S.run_chunk(compiled, state, nbrs, steps=10,
                                      stats=stats)
        results[multiplier] = (np.asarray(state.position), stats)
    tight, loose = results[1.3], results[8.0]
    assert tight[1].overflows >= 1 and loose[1].overflows == 0
    np.testing.assert_allclose(tight[0], loose[0], rtol=1e-5, atol=1e-5)
