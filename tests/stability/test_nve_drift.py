"""Long NVE runs: energy drift bounded, and no worse than jax-md's.

Danger: a list that drops or gains a pair now and then (an ulp decision,
a stale rebuild, a missed refit) gives the force a jump that velocity
Verlet cannot integrate: the energy takes a step each time and drifts; a
float32 roundoff that accumulates (a position wrapped with a different
rounding every step) drifts too.

Setup: a Lennard-Jones liquid (N = 256 on a lattice at density 0.8,
kT = 1, jax-md's smooth cut from 2.0 to 2.5, skin 0.3), jax-md's own
energy function and integrator (`jax_md.simulate.nve`), the same initial
state; only the neighbour list differs: `jaxrt.neighbor_list` (each
backend) or jax-md's cell list.

Bounds (E per particle, drift = max_t |E(t) - E(0)|):
* no worse than jax-md: drift_jaxrt <= 2 drift_jax_md + floor. Both runs
  integrate the same Hamiltonian with the same step; as the lists are the
  same sets the trajectories differ only by summation order and diverge
  chaotically, so their drifts are two samples of one quantity: the
  factor 2 covers that spread; floor = 32 ulps of |E|/N (the rounding of
  the energy sum itself, ~sqrt(N) ulps, with margin).
* bounded, from a float64 reference measured in the test (slow part):
  velocity Verlet's energy error is O(dt^2) (its shadow Hamiltonian), so
  the float64 drift at dt/2 is a quarter of that at dt (asserted within
  [0.15, 0.4]: the O(dt^4) terms and the chaotic spread), and the
  float32 drift may exceed the float64 one only by the float32 rounding
  random walk, 32 ulps of |E|/N times sqrt(steps).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax_md import energy as jmd_energy
from jax_md import partition, simulate, space

import jaxrt
from jaxrt.sim import distributions as seed_distributions
from stability_common import BACKENDS_3D, grid

N, DENSITY, DT = 256, 0.8, 0.005


def run(backend, steps, dtype, dt=DT, chunk=100):
    """Total energy per particle at every step (float64 numpy)."""
    side = (N / DENSITY) ** (1 / 3)
    disp, shift = space.periodic(side)
    R = jnp.asarray(seed_distributions.lattice(N, side), dtype)
    # jax-md's all-pairs list (disable_cell_list): the same pairs as its
    # cell list, and no array-valued cell_size in the list's static fields,
    # which jit caches compare with a jaxrt list's when one process runs
    # both (a TracerBoolConversionError inside jax-md's simulate.nve).
    nbr_fn, energy_fn = jmd_energy.lennard_jones_neighbor_list(
        disp, side, r_onset=2.0, r_cutoff=2.5, dr_threshold=0.3,
        capacity_multiplier=1.5, format=partition.Dense,
        disable_cell_list=True)
    if backend != "jax-md":
        nbr_fn = jaxrt.neighbor_list(disp, side, 2.5, dr_threshold=0.3,
                                     capacity_multiplier=1.5,
                                     backend=backend)
    init, apply = simulate.nve(energy_fn, shift, dt)
    nbrs = nbr_fn.allocate(R)
    state = init(jax.random.PRNGKey(0), R, kT=1.0, neighbor=nbrs)

    def total(state, nbrs):
        ke = 0.5 * jnp.sum(state.momentum ** 2 / state.mass)
        return ke + energy_fn(state.position, nbrs)

    @jax.jit
    def chunk_fn(state, nbrs):
        def body(carry, _):
            state, nbrs = carry
            state = apply(state, neighbor=nbrs)
            nbrs = nbrs.update(state.position)
            return (state, nbrs), total(state, nbrs)
        return jax.lax.scan(body, (state, nbrs), None, length=chunk)

    energies = [np.array([float(total(state, nbrs))])]
    for _ in range(steps // chunk):
        (state, nbrs), e = chunk_fn(state, nbrs)
        assert not nbrs.did_buffer_overflow
        energies.append(np.asarray(e, np.float64))
    return np.concatenate(energies) / N


def drift(e):
    return float(np.max(np.abs(e - e[0])))


def floor(e, steps=1):
    ulp = np.finfo(np.float32).eps * float(np.max(np.abs(e)))
    return 32 * ulp * np.sqrt(steps)


@pytest.mark.parametrize(*grid(lambda backend: backend == "bvh",
                              backend=[b for b in BACKENDS_3D
                                       if b != "spheres"]))
def test_short_nve_drift_no_worse_than_jax_md(backend):
    """300 steps, float32: drift_jaxrt <= 2 drift_jax_md + floor."""
    mine = run(backend, 300, jnp.float32)
    theirs = run("jax-md", 300, jnp.float32)
    assert np.all(np.isfinite(mine))
    assert drift(mine) <= 2 * drift(theirs) + floor(theirs), (
        drift(mine), drift(theirs))


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["cell", "bvh"])
def test_long_nve_drift_bounded_float32_and_float64(backend, x64):
    steps = 5_000
    ref = run(backend, steps, jnp.float64)
    half = run(backend, steps * 2, jnp.float64, dt=DT / 2, chunk=200)
    # O(dt^2): halving the step quarters the float64 drift.
    ratio = drift(half) / drift(ref)
    assert 0.15 <= ratio <= 0.4, ratio
    for dtype in (jnp.float64, jnp.float32):
        mine = run(backend, steps, dtype)
        theirs = run("jax-md", steps, dtype)
        slack = floor(theirs, steps) if dtype == jnp.float32 else 0.0
        assert drift(mine) <= 2 * drift(theirs) + floor(theirs), (
            dtype, drift(mine), drift(theirs))
        assert drift(mine) <= 2 * drift(ref) + slack, (
            dtype, drift(mine), drift(ref))
