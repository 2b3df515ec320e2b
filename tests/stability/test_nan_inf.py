"""NaN and Inf injected into positions.

Danger: a non-finite position is binned into some cell (floor(NaN) is
undefined), compared false against the cutoff (so the particle silently
has no neighbours), or poisons a sort key; a list update inside a scan
then carries on with a list that lacks the particle and the energy looks
fine. jaxrt's contract (`jaxrt.errors`): allocate raises naming the
particle and axis; under jit the NONFINITE_POSITION bit and the overflow
bit are set, and they stay set (error codes are OR-ed, never cleared by
later finite positions); `jaxrt.check` raises.

Bounds: exact integer checks of error bits and of the first step where
they appear in a scan.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax_md import space

import jaxrt
from jaxrt import energy
from jaxrt.errors import ErrorCode
from stability_common import BACKENDS_3D, grid

BAD = ErrorCode.NONFINITE_POSITION | ErrorCode.NEIGHBOR_LIST_OVERFLOW


def scene(dim=3, n=60, side=6.0):
    return jnp.asarray(np.random.default_rng(9).uniform(0, side, (n, dim)),
                       jnp.float32)


@pytest.mark.parametrize(*grid(lambda backend, value: value == "nan" and backend != "cell",
                              backend=BACKENDS_3D,
                              value=["nan", "inf", "-inf"]))
def test_non_finite_position_is_refused_and_flagged(backend, value):
    R = scene()
    disp, _ = space.periodic(6.0)
    fns = jaxrt.neighbor_list(disp, 6.0, 1.0, backend=backend)
    bad = R.at[17, 1].set(float(value))
    with pytest.raises(ValueError, match="non-finite value at particle 17, "
                                         "axis 1"):
        fns.allocate(bad)
    nbrs = fns.allocate(R)
    flagged = jax.jit(fns.update)(bad, nbrs)
    assert int(flagged.error.code) & BAD == BAD
    assert not int(flagged.error.code) & ErrorCode.METRIC_MISMATCH
    assert flagged.did_buffer_overflow
    with pytest.raises(jaxrt.NeighborListError, match="NaN or infinite"):
        jaxrt.check(flagged)


@pytest.mark.parametrize("periodic", [True, False])
def test_non_finite_position_is_reported_alone(periodic):
    """The rebuild's metric check reads the extreme particles of each axis;
    a NaN among them must not also be reported as a metric that disagrees
    with the box (found: check's message blamed displacement_or_metric and
    a buffer overflow next to the NaN)."""
    R = scene()
    disp = space.periodic(6.0)[0] if periodic else space.free()[0]
    fns = jaxrt.neighbor_list(disp, 6.0 if periodic else None, 1.0,
                              backend="cell")
    nbrs = fns.allocate(R)
    flagged = jax.jit(fns.update)(R.at[17, 1].set(jnp.nan), nbrs)
    code = ErrorCode(int(flagged.error.code))
    assert code & BAD == BAD
    assert not code & ErrorCode.METRIC_MISMATCH
    with pytest.raises(jaxrt.NeighborListError) as info:
        jaxrt.check(flagged)
    message = str(info.value)
    assert "NaN" in message
    assert "displacement_or_metric" not in message
    assert "buffer overflowed" not in message


@pytest.mark.parametrize(*grid(lambda backend: backend == "bvh",
                              backend=BACKENDS_3D))
def test_flag_is_sticky_through_a_scan(backend):
    """NaN injected at step 4 of 10 and removed at step 6: the bit appears
    at step 4 exactly and stays set to the end (a later finite update must
    not clear it). Rebuilds every step (no skin)."""
    R = scene()
    disp, shift = space.periodic(6.0)
    fns = jaxrt.neighbor_list(disp, 6.0, 1.0, backend=backend)
    nbrs = fns.allocate(R)

    def step(nbrs, k):
        moved = shift(R, 0.001 * k * jnp.ones_like(R))
        moved = jnp.where((k >= 4) & (k < 6), moved.at[3, 0].set(jnp.nan),
                          moved)
        nbrs = fns.update(moved, nbrs)
        return nbrs, nbrs.error.code

    _, codes = jax.jit(lambda n: jax.lax.scan(step, n, jnp.arange(10)))(nbrs)
    codes = np.asarray(codes)
    bad = (codes & int(BAD)) == int(BAD)
    assert bad.tolist() == [False] * 4 + [True] * 6


def test_lj_energy_of_a_non_finite_position_is_nan_not_masked():
    """On a list built before the blow-up, the LJ energy of a NaN position
    is NaN (so the scan's energies show it), never a finite sum without
    that particle's pairs. (Found here: the pair functions' masks and
    jax-md's switch treat a NaN distance as one past the cutoff, and the
    energy came out finite, 4.6e8, without the particle; fixed in
    `jaxrt.energy.lj`.)"""
    R = scene()
    disp, _ = space.periodic(6.0)
    nbrs = jaxrt.neighbor_list(disp, 6.0, 2.5, backend="brute").allocate(R)
    e_fn = energy.lennard_jones_pair_neighbor_list(disp, r_onset=2.0,
                                                   r_cutoff=2.5)
    assert np.isfinite(float(e_fn(R, nbrs)))
    e = float(e_fn(R.at[5, 2].set(jnp.nan), nbrs))
    assert np.isnan(e)


def test_pairs_refuse_non_finite_positions():
    """jaxrt.pairs (the ASE-like list): a NaN position raises (or, traced,
    sets its error) rather than dropping the atom's pairs."""
    R = np.array(scene(n=30, side=5.0))
    R[4, 0] = np.nan
    with pytest.raises((ValueError, jaxrt.PairsError), match="(?i)finite|nan"):
        jaxrt.pairs(jnp.asarray(R), 1.2, cell=np.eye(3) * 5.0,
                    pbc=(True, True, True))


@pytest.mark.slow
def test_delaunay_flags_non_finite_positions(x64):
    R = jnp.asarray(np.random.default_rng(9).uniform(0, 6.0, (60, 2)))
    disp, _ = space.periodic(6.0)
    fns = jaxrt.neighbor_list(disp, 6.0, 1.0, backend="delaunay",
                              periodic=True)
    nbrs = fns.allocate(R)
    flagged = jax.jit(fns.update)(R.at[7, 0].set(jnp.inf), nbrs)
    assert int(flagged.error.code) & BAD == BAD
    with pytest.raises(jaxrt.NeighborListError, match="NaN or infinite"):
        jaxrt.check(flagged)
