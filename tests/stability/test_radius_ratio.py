"""Per-particle radii with a ratio of 1:330.

Danger: cells sized for the smallest radius make a stencil of 330 cells
per axis for the largest, cells sized for the largest put thousands of
small particles in one cell; a radius class boundary rounds a radius into
the wrong class; the pair rule ``d < max(r_i, r_j)`` taken as ``min`` or
as ``r_i`` (asymmetric) for a big-small pair.

Construction: 3 large particles (r = 3.3) among 240 small ones
(r = 0.01), in a periodic 10-box, with small pairs placed at 0.01 ± ulps.
Bounds: set equality with the float64 oracle `brute_pairs_radii`
(integers); the big-small pairs (a big particle's row holds ~100 small
ones) are asserted present so the ratio is exercised. Kept small: the
cell backend's radius classes crashed XLA's CPU compiler in long xdist
runs (tests/lists/test_radii.py), so one scene, float32, Sparse.
"""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from jax_md import partition, space

import jaxrt
from oracle import brute_pairs_radii, list_pairs
from stability_common import RADII_BACKENDS, grid


def scene():
    rng = np.random.default_rng(7)
    small = rng.uniform(0, 10.0, (240, 3))
    # pairs of small particles 0.01 apart, one ulp either side
    f = np.float32
    small[1] = small[0] + [np.nextafter(f(0.01), f(0)), 0, 0]
    small[3] = small[2] + [np.nextafter(f(0.01), f(1)), 0, 0]
    big = np.array([[2.0, 2.0, 2.0], [7.0, 7.0, 7.0], [2.0, 7.5, 4.0]])
    R = np.concatenate([big, small]).astype(f)
    radii = np.full(len(R), 0.01, f)
    radii[:3] = 3.3  # 1:330
    return R, radii


@pytest.mark.parametrize(*grid(lambda backend: backend != "cell",
                              backend=RADII_BACKENDS))
def test_radius_ratio_330(backend):
    R, radii = scene()
    disp, _ = space.periodic(10.0)
    nbrs = jaxrt.neighbor_list(disp, 10.0, 3.3, radii=radii,
                               format=partition.Sparse,
                               backend=backend).allocate(jnp.asarray(R))
    assert not nbrs.did_buffer_overflow
    want = brute_pairs_radii(R, radii, 10.0, True)
    big_small = {(i, j) for i, j in want if i < 3 <= j}
    assert len(big_small) > 80  # expected 3 · 240 · (4π/3 · 3.3³) / 10³ = 108
    assert list_pairs(nbrs) == want
