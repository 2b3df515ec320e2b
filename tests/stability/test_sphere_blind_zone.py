"""The sphere method's ε blind zone, through `jaxrt.neighbor_list`.

Danger: seed 001's sphere method misses pairs closer than ε (Appendix 7;
on the cube diagonal the blind zone reaches √3·ε, `jaxrt.backends.rt.epsilon`).
jaxrt's contract: every pair at least 2ε apart is found; anything closer
raises `ParticlesTooCloseError` (at allocate, and from a jitted update as
the FFI call's error), never a list that silently lacks the pair.

Bounds: ε = 2**-40 · scale with scale = max(cutoff, max |coordinate|,
side on periodic axes) (`seed_epsilon`), so the separations below are
exact multiples of the ε the kernel uses; the factors 0.5, 1, 1.8 lie
below the resolution factor 2 (flagged), 2.2 and 3 above it (found). The
bvh and squares backends have no separation limit: they must list every
one of these pairs (set equality with the float64 oracle).
"""
from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax_md import space

import jaxrt
from oracle import brute_pairs, list_pairs
from stability_common import WARP

pytestmark = pytest.mark.skipif("spheres" not in WARP, reason="needs Warp")

SIDE, CUTOFF = 4.0, 0.5
EPS = 2.0 ** -40 * SIDE  # the periodic side is the largest scale here


def pair_scene(multiple, direction):
    base = np.array([1.0, 1.0, 1.0])
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    others = np.array([[2.0, 2.0, 2.0], [3.0, 1.0, 2.5], [1.2, 1.1, 1.0]])
    return np.stack([base, base + multiple * EPS * d, *others])


@pytest.mark.parametrize("direction", [(1, 0, 0), (1, 1, 1)])
def test_blind_zone_raises_and_resolution_is_kept(direction, x64):
    disp, _ = space.periodic(SIDE)
    fns = jaxrt.neighbor_list(disp, SIDE, CUTOFF, backend="spheres")
    update = jax.jit(fns.update)
    safe = fns.allocate(jnp.asarray(pair_scene(3.0, direction)))
    for multiple, flagged in ((0.5, True), (1.0, True), (1.8, True),
                              (2.2, False), (3.0, False)):
        R = jnp.asarray(pair_scene(multiple, direction))
        if flagged:
            with pytest.raises(Exception, match="closer than"):
                fns.allocate(R)
            with pytest.raises(Exception, match="ParticlesTooCloseError"):
                jax.block_until_ready(update(R, safe).idx)
        else:
            got = list_pairs(update(R, safe))
            assert (0, 1) in got and (1, 0) in got
            assert got == brute_pairs(R, CUTOFF, SIDE, True)
    for backend in [b for b in WARP if b != "spheres"]:
        R = jnp.asarray(pair_scene(0.5, direction))
        nbrs = jaxrt.neighbor_list(disp, SIDE, CUTOFF,
                                   backend=backend).allocate(R)
        assert list_pairs(nbrs) == brute_pairs(R, CUTOFF, SIDE, True)


def test_blind_zone_through_the_periodic_wrap(x64):
    """A pair 1.5ε apart through the face x = 0 (one at 0.75ε, one at
    L - 0.75ε): the gamma rays' images must flag it too."""
    disp, _ = space.periodic(SIDE)
    R = pair_scene(3.0, (1, 0, 0))
    R[0, 0] = 0.75 * EPS
    R[1] = R[0]
    R[1, 0] = SIDE - 0.75 * EPS
    with pytest.raises(Exception, match="closer than"):
        jaxrt.neighbor_list(disp, SIDE, CUTOFF,
                            backend="spheres").allocate(jnp.asarray(R))
    assert math.isclose(SIDE - R[1, 0] + R[0, 0], 1.5 * EPS, rel_tol=1e-3)
