"""Particles on the faces, edges and corners of a periodic box.

Danger: a coordinate at 0, -0.0, a denormal, one ulp below L, exactly L or
one ulp outside the box is binned into cell -1 or cell n (an out-of-range
gather), wrapped twice, or loses its partner one ulp away across the face.

Construction: every combination of the coordinates below on the three
axes (faces, edges, corners, and points outside [0, L) that wrap onto
them), plus a sprinkle of interior points. All designed distances are
either a few ulps (through the periodic wrap) or at least 1.5 from the
cutoff 1.0 (the coordinates are 0 + ulps, L - ulps or 3.0), so no rounding
can decide a pair: the float64 oracle and jax-md's metric agree, and the
bound is set equality (integers).
"""
from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax_md import partition, space

import jaxrt
from oracle import assert_layout, brute_pairs, list_pairs
from stability_common import BACKENDS_3D, grid, jax_md_pairs

SIDE, CUTOFF = 6.0, 1.0


def coordinates(dtype, spheres=False):
    L = dtype(SIDE)
    tiny = np.nextafter(dtype(0), dtype(1))  # a denormal
    below_L = np.nextafter(L, dtype(0))
    if spheres:  # no two closer than 2ε = 2**-39 · 6 (through the wrap)
        return [dtype(0), below_L, dtype(3.0)]
    return [dtype(0), dtype(-0.0), tiny, -tiny, below_L, L,
            np.nextafter(L, dtype(SIDE + 1)), dtype(3.0)]


def boundary_scene(dtype, spheres=False):
    values = coordinates(dtype, spheres)
    R = np.array(list(itertools.product(values, repeat=3)), dtype)
    inner = np.random.default_rng(3).uniform(1.2, 4.8, (30, 3)).astype(dtype)
    return np.concatenate([R, inner])


@pytest.mark.parametrize(*grid(
    lambda backend, dtype: dtype is np.float32 and backend != "cell",
    backend=BACKENDS_3D, dtype=[np.float32, np.float64]))
def test_faces_edges_and_corners(backend, dtype, request):
    if dtype is np.float64:
        request.getfixturevalue("x64")
    spheres = backend == "spheres"
    if spheres and dtype is np.float64:
        pytest.skip("every float64 face pair is closer than 2ε: see "
                    "test_spheres_refuse_face_pairs_closer_than_2_epsilon")
    R = jnp.asarray(boundary_scene(dtype, spheres))
    disp, _ = space.periodic(SIDE)
    fmt = partition.Sparse
    nbrs = jaxrt.neighbor_list(disp, SIDE, CUTOFF, format=fmt,
                               backend=backend).allocate(R)
    assert not nbrs.did_buffer_overflow
    assert_layout(nbrs)
    got = list_pairs(nbrs)
    want = brute_pairs(R, CUTOFF, SIDE, True)
    # spheres' 27 points: a corner cluster of 8 (56 ordered pairs), 3 edge
    # clusters of 4 (36), 3 face clusters of 2 (6), through the wrap: 98.
    assert len(want) > (1000 if not spheres else 98)
    assert got == want, (sorted(got - want)[:5], sorted(want - got)[:5])
    assert got == jax_md_pairs(disp, SIDE, CUTOFF, R, fmt)
    # The same points given to a jitted update, moved by whole boxes: the
    # sums round (prev(L) + L rounds to 2L in float32, landing on 0's
    # image), so the oracle is recomputed on the moved coordinates; the
    # spheres would rightly raise there (coincident through the wrap).
    if spheres:
        return
    shifted = R + jnp.asarray(SIDE * np.array([1.0, -2.0, 3.0]), dtype)
    again = jax.jit(nbrs.update)(shifted)
    assert not again.did_buffer_overflow
    assert list_pairs(again) == brute_pairs(shifted, CUTOFF, SIDE, True)


@pytest.mark.skipif("spheres" not in BACKENDS_3D, reason="needs Warp")
def test_spheres_refuse_face_pairs_closer_than_2_epsilon(x64):
    """0 and prev(L) are ulp(L) = 8.9e-16 apart through the wrap in
    float64, below the sphere method's resolution 2ε = 2**-39 · 6 = 1.1e-11
    (`jaxrt.backends.rt.epsilon`): a clear error, never a silent miss."""
    R = jnp.asarray(boundary_scene(np.float64, spheres=True))
    disp, _ = space.periodic(SIDE)
    with pytest.raises(Exception, match="closer than"):
        jaxrt.neighbor_list(disp, SIDE, CUTOFF,
                            backend="spheres").allocate(R)


@pytest.mark.parametrize("backend", [pytest.param("cell", marks=pytest.mark.slow),
                                     "brute"])
def test_fractional_coordinates_on_the_unit_cell_faces(backend):
    """Fractional positions at 0, a denormal, prev(1), 1 and one ulp above
    1 (cell and brute: the backends of triclinic / fractional boxes), in a
    sheared box. Bound: set equality with the float64 oracle of
    periodic_general (all designed distances are ulps or >= 1.5 from the
    cutoff, in a box whose heights are > 5)."""
    f32 = np.float32
    values = [f32(0), np.nextafter(f32(0), f32(1)), np.nextafter(f32(1), f32(0)),
              f32(1), np.nextafter(f32(1), f32(2)), f32(0.25)]
    frac = np.array(list(itertools.product(values, repeat=3)), f32)
    box = np.array([[6.0, 1.0, 0.5], [0.0, 6.0, -0.8], [0.0, 0.0, 6.0]], f32)
    disp, _ = space.periodic_general(jnp.asarray(box),
                                     fractional_coordinates=True)
    nbrs = jaxrt.neighbor_list(disp, jnp.asarray(box), CUTOFF,
                               fractional_coordinates=True,
                               format=partition.Sparse,
                               backend=backend).allocate(jnp.asarray(frac))
    from oracle import brute_pairs_general
    want = brute_pairs_general(frac, box, CUTOFF)
    assert len(want) > 100
    assert list_pairs(nbrs) == want


def test_crystal_with_half_box_fractional_differences_in_a_sheared_box():
    g = np.arange(4) / 4
    frac = np.array(list(itertools.product(g, repeat=3)), np.float32)
    box = np.array([[6.0, 1.0, 0.5], [0.0, 6.0, -0.8], [0.0, 0.0, 6.0]],
                   np.float32)
    disp, _ = space.periodic_general(jnp.asarray(box),
                                     fractional_coordinates=True)
    nbrs = jaxrt.neighbor_list(disp, jnp.asarray(box), 1.6,
                               fractional_coordinates=True,
                               backend="cell").allocate(jnp.asarray(frac))
    from oracle import brute_pairs_general
    assert list_pairs(nbrs) == brute_pairs_general(frac, box, 1.6)
