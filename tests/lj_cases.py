"""Checks shared by the list-free Lennard-Jones tests on the Warp engine
(tests/energy/test_fused_warp.py, tests/energy/test_fused_warp_cluster.py).
Tolerances are the test modules'."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax_md import space

from jaxrt.energy import lennard_jones_fused
from scenes import fluid


def close(a, b, rtol):
    """``a == b`` to ``rtol`` of b's largest entry."""
    a, b = np.asarray(a), np.asarray(b)
    scale = max(float(np.max(np.abs(b), initial=0.0)), 1e-300)
    np.testing.assert_allclose(a, b, rtol=0, atol=rtol * scale)


def check_sums(s, t, e_rtol, f_rtol):
    """A walk's `CellSums` ``s`` == brute force's ``t``: the pair count
    exactly, energies and the sigma / epsilon gradients to ``e_rtol``,
    forces to ``f_rtol`` (of the largest entry)."""
    assert int(s.count) == int(t.count)
    close(s.energy, t.energy, e_rtol)
    close(s.forces, t.forces, f_rtol)
    close(s.d_sigma, t.d_sigma, e_rtol)
    close(s.d_epsilon, t.d_epsilon, e_rtol)


def check_descent_in_scan_2d(backend, e_rtol):
    """A 2D periodic fluid: the energy under ``jit`` matches brute force,
    and five steepest-descent steps under ``jit`` and ``lax.scan`` lower
    it, ending at brute force's energy. Returns (energy, brute, end
    positions, displacement, side) for the callers' force checks."""
    R, side = fluid(n_side=10, dim=2)
    R = jnp.asarray(R)
    displacement, shift = space.periodic(side)
    energy = lennard_jones_fused(displacement, side, backend=backend)
    brute = lennard_jones_fused(displacement, side, backend="brute")
    close(jax.jit(energy)(R), brute(R), e_rtol)

    def descend(R, _):
        R = shift(R, -1e-4 * jax.grad(energy)(R))
        return R, energy(R)

    R_end, energies = jax.jit(lambda R: jax.lax.scan(descend, R, None,
                                                     length=5))(R)
    close(energies[-1], brute(R_end), e_rtol)
    assert np.all(np.diff(np.asarray(energies)) < 0)
    return energy, brute, R_end, displacement, side
