"""A time step too large: the blow-up is detected, with a clear message.

Danger: with dt past velocity Verlet's stability limit (omega dt > 2 for
the stiffest mode) the LJ energy grows by orders of magnitude within a
few steps, velocities reach 1e21, and, in a periodic box, positions stay
finite (they are wrapped): before `jaxrt.sim.run.BlowUpError` the run
simply went on (measured: the lj-fluid scene at dt = 0.05 ran 100 steps
to an infinite energy without a word).

Bounds (`jaxrt.sim.run`): a conservative scene's energy may change within
a chunk by at most 0.5 (|KE| + |PE|); a particle may move at most the
interaction range per step; nothing may be non-finite. The 0.5 is
justified by measurement in the test: the healthy run's largest relative
change is below 0.05 (so the threshold has 10x margin) and the blown-up
run's is above 5 (10x the other way).
"""
from __future__ import annotations

import functools

import numpy as np
import pytest

from jaxrt import sim as S


def gas(dt, kind="verlet", n_side=4, side=6.4):
    g = (np.arange(n_side) + 0.5) * side / n_side
    pos = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    extra = dict(kT=1.0, gamma=1.0) if kind == "langevin" else {}
    return S.Scene(
        particles=S.make_particles(positions=pos, temperature=1.0, seed=3),
        box=S.Box((side,) * 3, ("periodic",) * 3),
        effects=(S.LJ(r_cutoff=2.5, r_onset=2.0),),
        integrator=S.Integrator(dt=dt, kind=kind, **extra),
        neighbors=S.Neighbors(backend="brute", skin=0.3,
                              capacity_multiplier=2.0))


@functools.lru_cache(maxsize=None)
def compiled_gas(dt, kind="verlet"):
    """One compiled scene per time step, shared (each compiles its chunk
    of CHUNK steps once)."""
    return S.compile_scene(gas(dt, kind))


CHUNK = 20


def relative_change(compiled, chunks=3):
    state, nbrs = compiled.init()
    e0 = float(compiled.energy(state, nbrs))
    ke0 = 0.5 * float(np.sum(np.asarray(state.velocity) ** 2))
    stats = S.RunStats()
    try:
        for _ in range(chunks):
            state, nbrs = S.run_chunk(compiled, state, nbrs, steps=CHUNK,
                                      stats=stats, energy_tolerance=None)
    except S.BlowUpError:
        pass  # non-finite: the change is infinite
    e = np.concatenate(stats.kinetic) + np.concatenate(stats.potential)
    with np.errstate(invalid="ignore"):
        change = np.abs(e - e0) / (abs(ke0) + abs(e0 - ke0))
    return float(np.nanmax(np.where(np.isfinite(change), change, np.inf)))


def test_healthy_time_step_runs_and_too_large_one_raises_clearly():
    healthy = compiled_gas(0.002)
    assert relative_change(healthy) < 0.05
    state, nbrs = healthy.init()
    for _ in range(3):
        state, nbrs = S.run_chunk(healthy, state, nbrs, steps=CHUNK)
    assert np.all(np.isfinite(np.asarray(state.position)))

    blown = compiled_gas(0.05)
    assert relative_change(blown) > 5.0
    state, nbrs = blown.init()
    with pytest.raises(S.BlowUpError, match=r"dt = 0\.05 is likely too "
                                            r"large.*lower integrator\.dt"):
        for _ in range(5):
            state, nbrs = S.run_chunk(blown, state, nbrs, steps=CHUNK)


def test_a_non_finite_velocity_is_caught_by_name():
    compiled = compiled_gas(0.002)
    state, nbrs = compiled.init()
    state = state._replace(velocity=state.velocity.at[11, 2].set(np.inf))
    with pytest.raises(S.BlowUpError, match="blew up") as err:
        S.run_chunk(compiled, state, nbrs, steps=CHUNK)
    assert "non-finite" in str(err.value) or "NaN or infinite" in str(
        err.value)


@pytest.mark.slow
def test_langevin_blow_up_is_caught_without_the_energy_test():
    """NVT is not conservative (no energy test): the blow-up must still be
    caught, by the per-step displacement or the non-finite check."""
    compiled = compiled_gas(0.05, "langevin")
    assert not compiled.conservative
    state, nbrs = compiled.init()
    with pytest.raises(S.BlowUpError, match="dt = 0.05"):
        for _ in range(10):
            state, nbrs = S.run_chunk(compiled, state, nbrs, steps=CHUNK)
