"""Degenerate triangulations for backend="delaunay" (2D, float64).

Danger: cocircular points make the Delaunay triangulation non-unique and
every in-circle test a tie; collinear points make orientations zero. A
predicate that decides ties by rounding flips edges forever (no
convergence), inverts a triangle, or leaves the triangulation
non-Delaunay so that the BFS misses a neighbour. jaxrt's predicates leave
ties undecided (Shewchuk's static bounds, `jaxrt.backends.delaunay`) and the BFS is
exact on any DT of cocircular points.

Bounds: set equality (integers) with jax-md's all-pairs list (the metric
decides; on the triangular lattice 40 second-shell pairs are within an ulp
of the cut, where the float64 oracle's arithmetic differs from the
metric's), and with the float64 oracle where no pair is that close; at
allocate and
after jitted updates that keep the degeneracy (a rotation of a circle, a
translation of a lattice by exactly one spacing), with no overflow and no
failure bit (a failure would be loud, but here it would be a wrong call:
these inputs are valid).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax_md import space

import jaxrt
from jaxrt.errors import ErrorCode
from oracle import brute_pairs, list_pairs
from stability_common import jax_md_pairs

Sparse = jaxrt.Sparse

pytestmark = pytest.mark.usefixtures("x64")


def check(nbrs, R, cutoff, side, periodic, disp):
    """The list (Sparse) against jax-md's all-pairs list, which decides
    with the same metric; where no pair is within rounding of the cutoff,
    also against the float64 oracle."""
    assert not int(np.asarray(nbrs.error.code)) & ErrorCode.SEARCH_FAILED
    assert not nbrs.did_buffer_overflow
    got = list_pairs(nbrs)
    want = jax_md_pairs(disp, side if periodic else 1.0, cutoff, R, Sparse)
    assert got == want, (sorted(got - want)[:5], sorted(want - got)[:5])
    return want


def test_all_points_on_one_circle_in_free_space():
    """64 points on a circle of radius 3 (every quadruple cocircular) and
    its centre (equidistant from all: 64 ties at once); cutoff 0.65 holds
    two neighbours on each side (chords 2·3·sin(kπ/64) = 0.29, 0.59, 0.88
    for k = 1, 2, 3)."""
    n, radius, cutoff = 64, 3.0, 0.65
    t = 2 * np.pi * np.arange(n) / n
    R = jnp.asarray(np.concatenate([np.stack([radius * np.cos(t),
                                              radius * np.sin(t)], 1) + 5.0,
                                    [[5.0, 5.0]]]))
    disp, _ = space.free()
    fns = jaxrt.neighbor_list(disp, None, cutoff, backend="delaunay", format=Sparse,
                              periodic=False, capacity_multiplier=2.0)
    nbrs = fns.allocate(R)
    want = check(nbrs, R, cutoff, None, False, disp)
    assert want == brute_pairs(np.asarray(R), cutoff)  # no pair near the cut
    assert all(sum(1 for i, _ in want if i == k) == 4 for k in range(n))
    update = jax.jit(fns.update)
    for step in range(1, 4):  # rotations: still one circle
        a = step * 0.01
        rot = jnp.asarray([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        moved = (R - 5.0) @ rot.T + 5.0
        nbrs = update(moved, nbrs)
        check(nbrs, moved, cutoff, None, False, disp)


@pytest.mark.slow
@pytest.mark.parametrize("cutoff", [1.0, np.sqrt(2.0)])
def test_square_lattice_translated_by_whole_spacings(cutoff):
    """A periodic 10 x 10 square lattice (every cell's 4 corners
    cocircular, every row collinear) with the cutoff on a lattice distance
    (1: excluded, strict; sqrt(2)**2 = 2 + 1 ulp > 2: the diagonals
    included, as the oracle decides), moved under jit by exactly one
    spacing along x, then along the diagonal: the same degenerate lattice,
    reached by maintenance (flips), not a rebuild."""
    side = 10.0
    g = np.arange(10.0)
    R = jnp.asarray(np.stack(np.meshgrid(g, g, indexing="ij"),
                             -1).reshape(-1, 2))
    disp, _ = space.periodic(side)
    fns = jaxrt.neighbor_list(disp, side, float(cutoff), backend="delaunay", format=Sparse,
                              periodic=True, capacity_multiplier=2.0)
    nbrs = fns.allocate(R)
    want = check(nbrs, R, cutoff, side, True, disp)
    # integer coordinates: every d**2 is exact, so the oracle agrees; at
    # cutoff 1 the axis neighbours are out (d = 1, strict), at sqrt(2) they
    # and the 4 diagonals are in.
    assert want == brute_pairs(np.asarray(R), cutoff, side, True)
    assert len(want) == (800 if cutoff > 1.2 else 0)
    update = jax.jit(fns.update)
    for shift in ([1.0, 0.0], [1.0, 1.0], [0.5, 0.0]):
        R = jnp.mod(R + jnp.asarray(shift), side)
        nbrs = update(R, nbrs)
        check(nbrs, R, cutoff, side, True, disp)


@pytest.mark.slow
def test_triangular_lattice_with_hexagon_ties():
    """A periodic triangular lattice (6 cocircular neighbours around every
    point), cutoff exactly the spacing times sqrt(3) (second shell on the
    cut, up to rounding of the lattice coordinates, which the oracle
    decides), and a shear of the whole lattice under jit."""
    nx, ny = 8, 8
    a = 1.0
    h = a * np.sqrt(3) / 2
    pts = [((i + 0.5 * (j % 2)) * a, j * h) for j in range(ny) for i in range(nx)]
    R = jnp.asarray(np.array(pts) + 0.1)
    side = np.array([nx * a, ny * h])
    disp, _ = space.periodic(side)
    cutoff = float(np.sqrt(3.0) * a)
    fns = jaxrt.neighbor_list(disp, side, cutoff, backend="delaunay", format=Sparse,
                              periodic=True, capacity_multiplier=2.0)
    nbrs = fns.allocate(R)
    check(nbrs, R, cutoff, side, True, disp)
    moved = jnp.mod(R + jnp.asarray([0.3, 0.0]) * (R[:, 1:2] / side[1]),
                    jnp.asarray(side))
    nbrs = jax.jit(fns.update)(moved, nbrs)
    check(nbrs, moved, cutoff, side, True, disp)
