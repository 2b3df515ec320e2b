"""Compacted periodic axes (`jaxrt.backends.cell.cell_grid.grid`): a cloud that leaves an
empty slab at least a cutoff wide across a periodic axis is gridded there
as on a free axis, over its own span, instead of over the whole box.

Oracle: float64 brute force (`oracle.brute_pairs`, the fused energy's
``backend="brute"``), exact sets of pairs and pair counts; the kernels run
in Pallas' interpreter as well as on the portable path. Each scene also
checks that the axis really was compacted (the grid's spans and runs),
so that a grid which ignored the slab would fail here even though its
pairs are right.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax_md import partition, space

import jaxrt
from jaxrt import backends
from jaxrt.backends.cell import search as cell_list
from jaxrt.backends.cell import grid as cell_grid
from jaxrt.backends.contract import Geometry, Query
from jaxrt.energy import lennard_jones_fused
from jaxrt.energy.listfree.lj import CellSums
from oracle import (assert_layout, brute_pairs, brute_pairs_radii,
                    expected_pairs, list_pairs)
from scenes import fluid as fused_fluid

# The default run keeps one case per property; the rest run with -m slow.
SLOW = pytest.mark.slow



def cloud(n, centre, sigma, side, seed=0):
    """float64 ``(n, dim)``: a normal cloud around ``centre``, wrapped into
    the box ``side`` (so a centre near a face straddles it)."""
    rng = np.random.default_rng(seed)
    centre = np.asarray(centre, np.float64)
    return (centre + sigma * rng.standard_normal((n, len(centre)))) % side


def droplet(centre, radius, side, spacing=1.1, seed=0):
    """float64 ``(N, dim)``: a jittered lattice (no two particles much
    closer than ``spacing``: LJ terms of a liquid) inside a ball around
    ``centre``, wrapped into the box ``side``."""
    dim = len(centre)
    k = np.arange(-radius, radius + spacing, spacing)
    g = np.stack(np.meshgrid(*[k] * dim, indexing="ij"), -1).reshape(-1, dim)
    g = g[np.sum(g * g, axis=1) < radius ** 2]
    g = g + np.random.default_rng(seed).uniform(-0.1, 0.1, g.shape)
    return (np.asarray(centre, np.float64) + g) % side


def query(cutoff, periodic):
    return Query(cutoff=cutoff, periodic=tuple(periodic), mask_self=True,
                 format=partition.Dense)


def grid(R, side, cutoff, periodic, coarsen=True):
    """`jaxrt.backends.cell.grid.grid` of the list path: (positions, cells, cells per
    axis), as numpy."""
    dim = R.shape[1]
    side = jnp.broadcast_to(jnp.asarray(side, R.dtype), (dim,))
    geometry = Geometry(side=side, scale=jnp.ones((dim,), R.dtype))
    wrapped, cell, cells = (np.asarray(x) for x in jax.jit(
        lambda R: cell_grid.grid(R, geometry, query(cutoff, periodic),
                                  coarsen=coarsen))(R))
    # Every key inside the cell-start table.
    assert np.prod(cells, dtype=np.int64) <= cell_grid.table_size(len(R)) - 1
    assert np.all((cell >= 0) & (cell < cells))
    return wrapped, cell, cells


def longest_run(R, side, cutoff, periodic):
    """The most candidates of one stencil row (`cell_grid.runs`)."""
    dim = R.shape[1]
    side = jnp.broadcast_to(jnp.asarray(side, R.dtype), (dim,))
    geometry = Geometry(side=side, scale=jnp.ones((dim,), R.dtype))
    _, _, (_, len1, _, len2) = cell_list._sorted_system(
        R, geometry, query(cutoff, periodic))
    return int(np.max(len1 + len2))


def periodic_metric(side, periodic):
    """jax-md's displacement, periodic on the ``periodic`` axes of a box of
    sides ``side`` (an array)."""
    side = jnp.asarray(side)
    per = jnp.asarray(periodic)

    def displacement(a, b, **unused):
        d = a - b
        return jnp.where(per, jnp.mod(d + side / 2, side) - side / 2, d)
    return displacement


def list_matches_brute(R, side, cutoff, periodic, kernel,
                       fmt=partition.Dense):
    """The cell list's pairs equal brute force's, exactly."""
    side = np.broadcast_to(np.asarray(side, np.float64), (R.shape[1],))
    nbrs = jaxrt.neighbor_list(
        periodic_metric(side, periodic), side, cutoff, format=fmt,
        backend=backends.Cell(kernel=kernel),
        periodic=tuple(periodic)).allocate(R)
    assert not nbrs.did_buffer_overflow
    assert_layout(nbrs)
    want = brute_pairs(np.asarray(R), cutoff, side, periodic)
    assert want, "a scene with no pairs tests nothing"
    assert list_pairs(nbrs) == expected_pairs(fmt, want)


SIDE = 400.0
# A cloud of 1000 (sigma 4) in a periodic box of 400 (cutoff 1.5): box-wide,
# the cell-start table's budget coarsens the cells to ~20 x 80 x 80, and
# the longest run holds 30-90 % of the cloud; compacted, 14 %.
SCENES = {
    # name: (centre, periodic)
    "inside": ((150.0, 220.0, 90.0), (True, True, True)),
    # through the faces: the slab sits in the box's middle on every axis
    "straddling": ((0.5, SIDE - 1.0, 0.0), (True, True, True)),
    # periodic x, y (compacted) and free z (its span, as always)
    "mixed": ((SIDE - 2.0, 100.0, 50.0), (True, True, False)),
    "2d": ((1.0, SIDE / 2), (True, True)),
}


@pytest.mark.parametrize("name, kernel", [
    ("straddling", "xla"),
    *[pytest.param(name, kernel, marks=SLOW) for name in SCENES
      for kernel in ("xla", "interpret")
      if (name, kernel) != ("straddling", "xla")]])
def test_cluster_in_a_huge_periodic_box(name, kernel):
    """Pairs exact against brute force; every periodic axis compacted: the
    grid's positions span the cloud, not the box (a cloud through the
    faces is moved whole), and a run holds a few cells' particles, not the
    cloud."""
    centre, periodic = SCENES[name]
    dim = len(centre)
    n = 1000 if dim == 3 else 400
    R = jnp.asarray(cloud(n, centre, 4.0, SIDE), jnp.float32)
    cutoff = 1.5 if dim == 3 else 1.0
    list_matches_brute(R, SIDE, cutoff, periodic, kernel)
    wrapped, _, cells = grid(R, SIDE, cutoff, periodic)
    assert np.all(np.ptp(wrapped, axis=0) < 60.0), np.ptp(wrapped, axis=0)
    # Box-wide: 295 to 868 (3D), 397 (2D).
    assert longest_run(R, SIDE, cutoff, periodic) < n // 5
    # The empty cells past the span of each compacted axis.
    pad = np.array([9] + [3] * (dim - 1))
    assert np.all(cells >= pad + 1)


@SLOW
@pytest.mark.parametrize("kernel", ["xla", "interpret"])
def test_cluster_in_a_huge_periodic_box_ordered_sparse(kernel):
    R = jnp.asarray(cloud(300, (SIDE - 0.3, 3.0, 0.0), 4.0, SIDE),
                    jnp.float32)
    list_matches_brute(R, SIDE, 1.5, (True,) * 3, kernel,
                       fmt=partition.OrderedSparse)


def chain(gap, cutoff=1.0, spacing=0.75, links=40, rows=3):
    """Chains along a periodic x, links ``spacing`` apart (less than the
    cutoff), whose ends face each other across the box's faces ``gap``
    apart: the only slab that could be taken on x. ``rows x rows`` chains,
    1.6 apart across in a periodic box just holding them (no slab there),
    sparse enough that the box-wide grid coarsens a little (by 1.25), so
    that slabs are searched for. The two ends of a chain have the same
    y and z: their pair is decided by ``gap`` alone.
    Returns (R float64 ``(rows**2 · links, 3)``, sides ``(3,)``)."""
    x = spacing * np.arange(links, dtype=np.float64)
    rng = np.random.default_rng(3)
    out = []
    for y in range(rows):
        for z in range(rows):
            yz = 0.8 + 1.6 * np.array([y, z]) + rng.uniform(
                -0.2, 0.2, (links, 2))
            yz[[0, -1]] = 0.8 + 1.6 * np.array([y, z])
            out.append(np.concatenate([x[:, None], yz], axis=1))
    across = 1.6 * rows
    return np.concatenate(out), np.array([x[-1] + gap, across, across])


# gap / cutoff: a hair below (the ends are a pair), exactly, a hair above,
# and wide enough to be taken.
GAPS = {"hair below": 1 - 2.0 ** -40, "exact": 1.0,
        "hair above": 1 + 2.0 ** -40, "taken": 4.0}


@pytest.mark.parametrize("gap, kernel", [
    ("hair below", "xla"), ("taken", "xla"),
    *[pytest.param(gap, kernel, marks=SLOW) for gap in GAPS
      for kernel in ("xla", "interpret")
      if (gap, kernel) not in (("hair below", "xla"), ("taken", "xla"))]])
def test_gaps_around_the_cutoff(x64, gap, kernel):
    """Chain ends across a gap of about the cutoff: their pair is found
    exactly when they are within it, and such a gap is never taken; a
    wide one is (x compacted: shifted, and gridded over the chains), and
    every pair is still there."""
    R, side = chain(GAPS[gap])
    periodic = (True,) * 3
    links = 40
    ends = {(links * k + links - 1, links * k) for k in range(9)}
    want = brute_pairs(R, 1.0, side, periodic)
    assert (ends <= want) == (gap == "hair below")
    assert not ends & want or gap == "hair below"
    list_matches_brute(jnp.asarray(R), side, 1.0, periodic, kernel)
    found, _ = cell_list._gaps(jnp.asarray(R) % side, jnp.asarray(side),
                               query(1.0, periodic))
    assert bool(found[0]) == (gap == "taken")
    wrapped, _, cells = grid(jnp.asarray(R), side, 1.0, periodic)
    taken = not np.array_equal(wrapped[:, 0], R[:, 0])
    assert taken == (gap == "taken")
    # y and z are filled: the box's cells (1.25 cutoffs wide, coarsened).
    assert np.array_equal(wrapped[:, 1:], R[:, 1:])
    assert list(cells[1:]) == [3, 3], cells


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_a_slab_is_taken_only_where_it_is_empty(x64, dtype):
    """`_gaps` against the exact empty arcs of points on a circle whose
    widest arc lies around the threshold, half of them moved onto bin
    edges (and an ulp either side): wherever it takes a slab, the empty
    arc around its middle spans the cutoff with the margin; and it takes
    one wherever an arc is three bins wider."""
    rng = np.random.default_rng(12)
    cutoff, margin = 1.0, cell_list._GAP_MARGIN
    q = query(cutoff, (True,))
    gaps = jax.jit(lambda x, side: cell_list._gaps(x, side, q))
    taken = 0
    for trial in range(60):
        n = 200
        arc = rng.uniform(0.3, 1.0, n)
        arc[rng.integers(n)] = rng.uniform(0.9, 1.4)  # the widest
        side = np.asarray(arc.sum(), dtype)
        width = float(side) / cell_list._GAP_BINS
        x = (np.cumsum(arc) + rng.uniform(0, float(side))) % float(side)
        edges = rng.random(n) < 0.5
        x = np.where(edges, np.round(x / width) * width, x).astype(dtype)
        x = np.where(edges, np.nextafter(x, rng.choice([-1.0, 2e3], n)
                                         .astype(dtype)), x)
        x = np.asarray(np.mod(x, side), dtype)
        found, cut = (np.asarray(v)[0] for v in gaps(
            jnp.asarray(x)[:, None], jnp.asarray(side)[None]))
        s = np.sort(x.astype(np.float64))
        arcs = np.diff(np.concatenate([s, [s[0] + float(side)]]))
        if found:
            taken += 1
            below = np.searchsorted(s, cut, side="right") - 1  # -1: wraps
            assert arcs[below] >= cutoff * (1 + margin), (trial, arcs[below])
        if arcs.max() >= cutoff * (1 + margin) + 3 * width:
            assert found, (trial, arcs.max())
    assert 10 < taken < 50  # both sides of the threshold were tried


@SLOW
def test_gap_on_one_axis_only():
    """A layer that fills a periodic x and y, thin in a tall periodic z: only
    z is compacted, x and y keep the box's cells; pairs exact."""
    rng = np.random.default_rng(5)
    n, side = 600, np.array([20.0, 20.0, 2000.0])
    R = np.concatenate([rng.uniform(0, 20.0, (n, 2)),
                        1000.0 + 2.0 * rng.standard_normal((n, 1))], axis=1)
    R = jnp.asarray(R, jnp.float32)
    periodic = (True,) * 3
    found, _ = cell_list._gaps(R % side, jnp.asarray(side, jnp.float32),
                               query(1.5, periodic))
    assert tuple(np.asarray(found)) == (False, False, True)
    wrapped, _, cells = grid(R, side, 1.5, periodic)
    assert np.array_equal(wrapped[:, :2], np.asarray(R[:, :2]))
    assert cells[2] < 25  # ~12 cutoffs of layer + 3 empty, not the box's
    list_matches_brute(R, side, 1.5, periodic, "xla")


def fluid(n_side=8, dim=3):
    """`test_fused.fluid` in float32: (R float32 (N, dim), side)."""
    R, side = fused_fluid(n_side=n_side, dim=dim)
    return jnp.asarray(R, jnp.float32), side


@pytest.mark.parametrize("dim", [2, 3])
def test_a_filled_box_keeps_its_grid_bitwise(dim):
    """A dense periodic fluid never coarsens: the list path's grid (which
    searches for slabs only where it would coarsen) is bitwise the grid
    without the search; and a dense cloud in free space is untouched."""
    R, side = fluid(n_side=8 if dim == 3 else 20, dim=dim)
    periodic = (True,) * dim
    searched = grid(R, side, 2.5, periodic)
    plain = grid(R, side, 2.5, periodic, coarsen=False)
    for a, b in zip(searched, plain):
        assert a.dtype == b.dtype and np.array_equal(a, b)
    assert np.array_equal(searched[0], np.asarray(R) % np.float32(side))


def test_fused_grid_of_a_proven_box_has_no_search():
    """Where `_static_cells` proves the fused grid never coarsens (the
    md_step fluid), the slab search is not even in the program."""
    from jaxrt.energy.listfree import lj as fused
    R, side = fluid()
    params = fused.static_params(space.periodic(side)[0], side, None, 3,
                                  2.0, 2.5, 2.5)
    program = str(jax.make_jaxpr(lambda R: fused.cell_runs(R, params))(R))
    assert "cummax" not in program and "cond" not in program
    big = fused.static_params(space.periodic(SIDE)[0], SIDE, None, 3, 2.0,
                               2.5, 2.5)
    program = str(jax.make_jaxpr(lambda R: fused.cell_runs(R, big))(R))
    assert "cummax" in program  # a sparse box searches


# The fused sums: the kernel walks runs through each run's periodic image
# (`fused.run_image_axes`), which on a compacted axis is 0.
FUSED = {"xla": CellSums(kernel="xla"), "kernel": CellSums(kernel="interpret"),
         "tiles": CellSums(kernel="interpret", block=16, tile=16),
         "stored": CellSums(kernel="interpret", runs="stored")}


@pytest.mark.parametrize("backend, centre", [
    ("kernel", (SIDE - 1.0, 2.0, 200.0)),
    pytest.param("xla", (SIDE - 1.0, 2.0, 200.0), marks=SLOW),
    pytest.param("tiles", (1.0, SIDE - 2.0, 0.0), marks=SLOW),
    pytest.param("stored", (200.0, 0.0, SIDE - 0.5), marks=SLOW),
    pytest.param("kernel", (50.0, 60.0), marks=SLOW)])
def test_fused_sums_of_a_cluster_match_brute_force(x64, backend, centre):
    """Energy, forces and pair count of the fused cell sums against brute
    force, for a droplet through the box's faces, with the runs' images on
    every axis."""
    from jaxrt.energy.listfree import lj as fused
    dim = len(centre)
    R = jnp.asarray(droplet(centre, 4.5 if dim == 3 else 8.0, SIDE))
    displacement = space.periodic(SIDE)[0]
    params = fused.static_params(displacement, SIDE, None, dim, 2.0, 2.5,
                                  2.5)
    assert fused.run_image_axes(params, len(R))[:dim] == (True,) * dim
    # Compacted: a run holds a few cells' particles (box-wide 90 to 215 of
    # the 275 in 3D), walked with the droplet's positions moved whole.
    _, runs, images = fused.cell_runs(jnp.pad(R, ((0, 0), (0, 3 - dim))),
                                      params)
    assert int(runs.length.max()) < len(R) // 5
    assert np.all(np.ptp(np.asarray(images.position), axis=0) < 20.0)
    cell = lennard_jones_fused(displacement, SIDE, backend=FUSED[backend])
    brute = lennard_jones_fused(displacement, SIDE, backend="brute")
    count = int(brute.sums(R).count)
    assert count > 100
    assert int(cell.sums(R).count) == count
    e, b = float(cell(R)), float(brute(R))
    assert abs(e - b) <= 1e-12 * max(abs(b), 1.0)
    f, g = np.asarray(jax.grad(cell)(R)), np.asarray(jax.grad(brute)(R))
    np.testing.assert_allclose(f, g, rtol=0, atol=1e-10 * np.abs(g).max())


@SLOW
def test_radius_classes_in_a_huge_periodic_box():
    """Per-particle radii: each class's grid is compacted as well."""
    rng = np.random.default_rng(9)
    R = np.asarray(jnp.asarray(cloud(300, (1.0, 200.0, SIDE - 1.0), 4.0,
                                     SIDE), jnp.float32))
    radii = rng.uniform(0.2, 1.5, len(R))
    nbrs = jaxrt.neighbor_list(space.periodic(SIDE)[0], SIDE, 1.5,
                               format=partition.Dense, backend="cell",
                               radii=radii).allocate(jnp.asarray(R))
    assert not nbrs.did_buffer_overflow
    want = brute_pairs_radii(R, radii, SIDE, True)
    assert want and list_pairs(nbrs) == want
