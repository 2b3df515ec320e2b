"""The Warp engine's grid builder (`jaxrt.backends.cell.warp_grid.build`,
shared by ``Cell(kernel="warp")`` lists and the list-free sums) on
adversarial inputs: flat clouds, one particle or none, extents and sides
far past what the table holds, traced periodic sides under ``jit``.

Every grid must hold at most ``table`` cells and have cells at least the
minimum size wide (checked in the positions' dtype, the kernels' own
arithmetic; a periodic side under it is one cell); a grid that fits is
not coarsened (one more cell on any axis would be too small), and one
that does not is coarsened evenly rather than collapsed, so that a builder
returning one cell everywhere fails here too. Pure JAX: no Warp.
"""
from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrt.backends.cell import warp_grid

DTYPES = ["float32", "float64"]


@pytest.fixture(params=DTYPES)
def dtype(request):
    with jax.enable_x64(request.param == "float64"):
        yield jnp.dtype(request.param)


def check(grid, cells, points, *, periodic, padding, min_size, reach, table,
          side=None):
    """The builder's contract; returns the cells per axis (ints)."""
    grid, cells = np.asarray(grid), np.asarray(cells)
    assert grid.shape == (3, 3) and cells.shape == (6,)
    assert cells.dtype == np.int32
    n = cells[:3].astype(np.int64)
    assert np.all(n >= 1)
    assert math.prod(n.tolist()) <= table
    assert cells[3:].tolist() == list(reach)
    origin, width, sides = grid
    least = np.asarray(min_size, grid.dtype)
    # A periodic side under the minimum is one cell, the whole side.
    assert np.all((width >= least) | (n == 1)), (width, least)
    pts = np.asarray(points)
    for a in range(3):
        if padding[a]:
            assert n[a] == 1 and origin[a] == 0 and sides[a] == 1
        elif periodic[a]:
            assert origin[a] == 0
            assert sides[a] == np.asarray(side[a], grid.dtype)
            exact = sides[a] / grid.dtype.type(n[a])
            # XLA on CUDA need not round a float32 division correctly (one
            # ulp off seen on an H100); the safety assertion above stays
            # exact, and the kernels clamp the last cell, so n * width may
            # fall an ulp short of the side.
            ulps = 1 if grid.dtype == np.float32 else 0
            assert abs(width[a] - exact) <= ulps * np.spacing(exact), (
                width[a], exact)
        else:
            assert sides[a] == 1
            if len(pts):
                lo, hi = pts[:, a].min(), pts[:, a].max()
                assert origin[a] == lo
                # The cells span the cloud (the kernels clamp the last).
                assert n[a] * width[a] >= (hi - lo) * (1 - 1e-6)
    return n.tolist()


def maximal(cells, span, min_size, dtype):
    """One more cell on any axis would make its cells too small (the
    grid was not coarsened)."""
    span = np.asarray(span, dtype)
    least = np.asarray(min_size, dtype)
    more = span / (np.asarray(cells) + 1).astype(dtype)
    assert np.all((more < least) | (np.asarray(cells) == 0)), (cells, more)


def build(points, side, **kw):
    return warp_grid.build(points, side, **kw)


FREE3 = dict(periodic=(False,) * 3, padding=(False,) * 3)


def test_a_cloud_that_fits_keeps_the_ideal_cells(dtype):
    rng = np.random.default_rng(0)
    R = jnp.asarray(rng.uniform(0, 10, (200, 3)), dtype)
    kw = dict(FREE3, min_size=(0.5, 1.0, 1.0), reach=(4, 2, 2), table=10_000)
    got = check(*build(R, (1.0,) * 3, **kw), R, **kw)
    maximal(got, np.asarray(R).max(0) - np.asarray(R).min(0),
            kw["min_size"], dtype)


@pytest.mark.parametrize("table", [1, 27, 200])
def test_a_flat_free_cloud_fits_the_table(dtype, table):
    # z held at one cell: the even coarsening alone would leave x and y
    # over the table.
    rng = np.random.default_rng(1)
    R = np.concatenate([rng.uniform(0, 1000, (300, 2)),
                        np.zeros((300, 1))], 1)
    R = jnp.asarray(R, dtype)
    kw = dict(FREE3, min_size=(0.25, 0.5, 0.5), reach=(4, 2, 2),
              table=table)
    got = check(*build(R, (1.0,) * 3, **kw), R, **kw)
    assert got[2] == 1
    assert got[0] * got[1] > table // 2  # coarsened evenly, not collapsed


@pytest.mark.parametrize("n", [0, 1])
def test_one_particle_or_none(dtype, n):
    R = jnp.full((n, 3), 3.5, dtype)
    kw = dict(periodic=(True, False, False), padding=(False, False, True),
              min_size=(1.0, 1.0, 1.0), reach=(1, 1, 1), table=64)
    side = (10.0, 1.0, 1.0)
    assert check(*build(R, side, **kw), R, side=side, **kw) == [10, 1, 1]


def test_huge_extent_against_a_small_table(dtype):
    big = 1e30 if dtype == jnp.float32 else 1e200
    R = jnp.asarray([[-big, 0.0, -big], [big, 1e-3, big],
                     [0.0, 5.0, 0.0]], dtype)
    kw = dict(FREE3, min_size=(1e-3, 1e-3, 1e-3), reach=(1, 1, 1), table=64)
    got = check(*build(R, (1.0,) * 3, **kw), R, **kw)
    assert math.prod(got) > 64 // 8  # coarsened evenly, not to one cell


def test_static_periodic_cells_are_kept_and_free_axes_take_the_rest(dtype):
    # The list-free sums' case: the table sized as the periodic cells
    # times the free axes' budget; the box's cells never coarsen.
    rng = np.random.default_rng(2)
    side = (20.0, 13.0, 1.0)
    R = jnp.asarray(rng.uniform(0, 1, (500, 3)) * [20, 13, 400], dtype)
    min_size = (0.25, 0.5, 0.5)
    fixed = warp_grid.periodic_cells(side[:2], min_size[:2])
    assert fixed == (80, 26)
    budget = 27
    kw = dict(periodic=(True, True, False), padding=(False,) * 3,
              min_size=min_size, reach=(4, 2, 2),
              table=math.prod(fixed) * budget)
    got = check(*build(R, side, **kw), R, side=side, **kw)
    assert got == [80, 26, budget]


@pytest.mark.parametrize("side", [8.0, 80.0, 1e7, 2.3, 0.3, 0.2])
def test_traced_periodic_sides_under_jit(dtype, side):
    # Sides traced (a list's box), so the periodic axes coarsen too when
    # the box holds more cells than the table.
    rng = np.random.default_rng(3)
    R = jnp.asarray(rng.uniform(0, 1, (100, 3)) * [side, side, 2.0], dtype)
    # The list's sizes: cutoff 1 with its margin, reach (4, 2), 4 cells a
    # particle.
    cutoff = 1.0 + 2 ** -10
    kw = dict(periodic=(True, True, True), padding=(False,) * 3,
              min_size=(cutoff / 4, cutoff / 2, cutoff / 2), reach=(4, 2, 2),
              table=4 * 100 + 64)
    sides = jnp.asarray([side, side, side], dtype)
    fn = jax.jit(lambda R, s: build(R, s, **kw))
    got = check(*fn(R, sides), R, side=np.asarray(sides), **kw)
    ideal = [max(1, int(side // m)) for m in kw["min_size"]]
    if math.prod(ideal) <= kw["table"]:
        maximal(got, np.asarray(sides), kw["min_size"], dtype)
    else:
        assert math.prod(got) > kw["table"] // 8


def test_traced_periodic_slab_with_a_free_axis_and_padding(dtype):
    # A 2D list: x periodic (traced), y free, z padding.
    R = jnp.asarray([[0.5, -300.0, 0.0], [7.9, 300.0, 0.0]], dtype)
    kw = dict(periodic=(True, False, False), padding=(False, False, True),
              min_size=(0.2, 0.2, 0.2), reach=(2, 2, 1), table=72)
    fn = jax.jit(lambda R, s: build(R, s, **kw))
    side = jnp.asarray([8.0, 1.0, 1.0], dtype)
    got = check(*fn(R, side), R, side=np.asarray(side), **kw)
    # The free axis coarsens first: the box's 40 cells leave it one.
    assert got == [40, 1, 1]


def test_bad_arguments_name_the_argument():
    R = jnp.zeros((4, 3))
    kw = dict(periodic=(True, False, False), padding=(True, False, False),
              min_size=(1.0,) * 3, reach=(1, 1, 1), table=8)
    with pytest.raises(ValueError, match="padding"):
        warp_grid.build(R, (1.0,) * 3, **kw)
    kw.update(padding=(False,) * 3, min_size=(0.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="min_size"):
        warp_grid.build(R, (1.0,) * 3, **kw)
    kw.update(min_size=(1.0,) * 3, table=0)
    with pytest.raises(ValueError, match="table"):
        warp_grid.build(R, (1.0,) * 3, **kw)
    with pytest.raises(ValueError, match="points"):
        warp_grid.build(R[:, :2], (1.0,) * 3, **dict(kw, table=8))
