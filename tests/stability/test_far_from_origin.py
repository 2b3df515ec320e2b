"""Positions far from the origin, in float32 and float64.

Danger: at |x| ~ 1e6 (float32) or 1e12 (float64) a coordinate's ulp is a
sizeable fraction of the cutoff (0.0625 and 1.2e-4 here): a backend that
bins, wraps or subtracts in a different order from the caller's metric, or
pads its boxes by a fixed absolute amount, gains or loses pairs. The bound:
the list equals jax-md's all-pairs list on the same stored coordinates
(set equality, integers): pairs are decided as the metric decides them,
whatever the rounding.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax_md import partition, space

import jaxrt
from oracle import list_pairs
from stability_common import BACKENDS_3D, grid, jax_md_pairs
from test_cutoff_ulp import RT_ARITHMETIC

OFFSETS = {np.float32: 1e6, np.float64: 1e12}


@pytest.mark.parametrize(*grid(
    lambda backend, dtype: dtype is np.float32 and backend in ("brute", "bvh"),
    backend=BACKENDS_3D, dtype=[np.float32, np.float64]))
def test_free_space_far_from_the_origin(backend, dtype, request):
    """300 particles in a 40-cube at 1e6 (float32) or 1e12 (float64), in
    free space; also in the negative octant."""
    if dtype is np.float64:
        request.getfixturevalue("x64")
    offset = OFFSETS[dtype]
    local = np.random.default_rng(5).uniform(0, 12.0, (300, 3))
    disp, _ = space.free()
    for sign in (1.0, -1.0):
        R = jnp.asarray(sign * offset + local, dtype)
        if backend == "spheres" and dtype is np.float64:
            # ε = 2**-40 · 1e12 = 0.91 (`jaxrt.backends.rt.epsilon`): the spheres'
            # documented resolution 2ε exceeds the spacing; a clear error.
            with pytest.raises(Exception, match="closer than 1.82"):
                jaxrt.neighbor_list(disp, None, 1.5, backend=backend
                                    ).allocate(R)
            return
        nbrs = jaxrt.neighbor_list(disp, None, 1.5, format=partition.Sparse,
                                   backend=backend).allocate(R)
        want = jax_md_pairs(disp, 1.0, 1.5, R, partition.Sparse)
        assert len(want) > 300
        assert list_pairs(nbrs) == want


@pytest.mark.parametrize(*grid(
    lambda backend, dtype: dtype is np.float32 and backend == "cell",
    lambda backend, dtype: (RT_ARITHMETIC if backend in ("spheres", "squares")
                            and dtype is np.float32 else None),
    backend=BACKENDS_3D, dtype=[np.float32, np.float64]))
def test_periodic_positions_many_boxes_away(backend, dtype, request):
    """Periodic positions unwrapped by 1e4 boxes (float32: ulp 0.0078 at
    1e5) and by 1e10 boxes (float64: ulp 1.5e-5 at 1e11), then moved under
    a jitted update. Bound: set equality with jax-md's all-pairs list on
    the same coordinates, before and after the move.

    jax-md's metric subtracts the unwrapped coordinates (up to 2e5 apart:
    a rounding of ulp(2e5) = 0.0156 in float32) before it wraps; the cell
    list's cheap test on wrapped positions must leave every pair within
    that rounding of the cutoff to the metric (found here: its tolerance
    counted ulps of the wrapped coordinates only, and two pairs flipped;
    fixed in `jaxrt.backends.cell.search._tolerance`)."""
    if dtype is np.float64:
        request.getfixturevalue("x64")
    side = 10.0
    boxes = 1e4 if dtype is np.float32 else 1e10
    rng = np.random.default_rng(6)
    inside = rng.uniform(0, side, (250, 3))
    R = jnp.asarray(inside + side * boxes * rng.choice([-1, 1], (250, 3)),
                    dtype)
    disp, _ = space.periodic(side)
    fns = jaxrt.neighbor_list(disp, side, 1.5, format=partition.Sparse,
                              backend=backend, capacity_multiplier=2.0)
    nbrs = fns.allocate(R)
    assert list_pairs(nbrs) == jax_md_pairs(disp, side, 1.5, R,
                                            partition.Sparse)
    moved = R + jnp.asarray(rng.normal(0, 0.05, R.shape), dtype)
    nbrs = jax.jit(fns.update)(moved, nbrs)
    assert not nbrs.did_buffer_overflow
    assert list_pairs(nbrs) == jax_md_pairs(disp, side, 1.5, moved,
                                            partition.Sparse)
