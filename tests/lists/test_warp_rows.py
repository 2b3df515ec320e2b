"""The cell list on its Warp walk (``Cell(kernel="warp")``,
`jaxrt.backends.cell.warp_rows`) against the portable path
(``Cell(kernel="xla")``) and a float64 brute force: the same set in every
row, the same sizes and the same overflow flags. (Warp runs on the CPU
here; rows are compared as sets, since the walk lists each row in the
order it meets the neighbours.)"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax_md import partition, space

import jaxrt
from jaxrt import backends
from oracle import assert_layout, brute_pairs, expected_pairs, list_pairs
from scenes import kicked_updates, lattice, slab_displacement

WARP = backends.Cell(kernel="warp")
XLA = backends.Cell(kernel="xla")
FORMATS = [partition.Dense, partition.Sparse, partition.OrderedSparse]


def row_sets(nbrs) -> list[frozenset]:
    """Each Dense row's neighbours as a set (padding dropped)."""
    idx = np.asarray(nbrs.idx)
    n = idx.shape[0]
    return [frozenset(row[row < n].tolist()) for row in idx]


def brute_rows(R, cutoff, side, periodic, mask_self=True) -> list[frozenset]:
    pairs = brute_pairs(R, cutoff, side, periodic, mask_self)
    rows = [set() for _ in range(len(R))]
    for i, j in pairs:
        rows[i].add(j)
    return [frozenset(r) for r in rows]


def both(displacement, box, R, cutoff, fmt=partition.Dense, **kw):
    """The Warp and the portable lists of ``R``, allocated alike."""
    out = []
    for backend in (WARP, XLA):
        nbrs = jaxrt.neighbor_list(displacement, box, cutoff, format=fmt,
                                   backend=backend, **kw).allocate(R)
        assert not nbrs.did_buffer_overflow
        assert_layout(nbrs)
        out.append(nbrs)
    return out


def check_dense(displacement, box, R, cutoff, periodic, **kw):
    """Warp's Dense rows equal the portable path's and the brute force's,
    row by row as sets, at the same capacity."""
    warp, xla = both(displacement, box, R, cutoff, **kw)
    assert warp.idx.shape == xla.idx.shape
    got = row_sets(warp)
    assert got == row_sets(xla)
    assert got == brute_rows(R, cutoff, box, periodic,
                             kw.get("mask_self", True))
    return warp


def uniform(key, n, side, dim=3):
    return jax.random.uniform(jax.random.PRNGKey(key), (n, dim)) * side


def test_periodic_box_rows_equal_the_portable_path_and_brute_force():
    side = 8.0
    check_dense(space.periodic(side)[0], side, uniform(1, 400, side), 1.7,
                True)


@pytest.mark.parametrize("fmt", [partition.Sparse, partition.OrderedSparse])
def test_sparse_layouts_through_the_dense_rows(fmt):
    side = 7.0
    R = uniform(2, 300, side)
    displacement = space.periodic(side)[0]
    warp, xla = both(displacement, side, R, 1.5, fmt=fmt)
    assert warp.idx.shape == xla.idx.shape
    want = expected_pairs(fmt, brute_pairs(R, 1.5, side, True))
    assert list_pairs(warp) == list_pairs(xla) == want


# Sides over the cutoff where the stencil aliases: fewer cells across than
# it spans (2 across + 1 = 5: sides below 2.5 cutoffs), x rows of fewer than
# 2 along + 1 = 9 cells or exactly 9 (2.3), one cell across (1.2: the
# cutoff is over half the side, every particle a candidate).
@pytest.mark.filterwarnings("ignore::jaxrt.lists.neighbors.SmallBoxWarning")
@pytest.mark.parametrize("side_over_cutoff", [1.2, 2.01, 2.3, 2.6, 3.0])
def test_small_periodic_boxes_where_the_stencil_aliases(side_over_cutoff):
    cutoff = 1.0
    side = side_over_cutoff * cutoff
    check_dense(space.periodic(side)[0], side, uniform(3, 120, side),
                cutoff, True)


def test_per_axis_periodic_box():
    side = np.array([6.0, 9.0, 4.0], np.float32)
    check_dense(space.periodic(side)[0], side, uniform(4, 250, side), 1.3,
                True)


def test_fractional_coordinates_in_an_orthorhombic_box():
    box = jnp.diag(jnp.asarray([6.0, 7.0, 5.0]))
    frac = uniform(20, 250, 1.0)
    displacement = space.periodic_general(box, fractional_coordinates=True)[0]
    warp, xla = both(displacement, box, frac, 1.4,
                     fractional_coordinates=True)
    got = row_sets(warp)
    assert got == row_sets(xla)
    assert got == brute_rows(frac * jnp.diag(box), 1.4, jnp.diag(box), True)


def test_vmap_over_systems_equals_separate_calls():
    side = 5.0
    fns = jaxrt.neighbor_list(space.periodic(side)[0], side, 1.1,
                              backend=WARP, capacity_multiplier=2.0)
    Rs = uniform(14, 300, side).reshape(3, 100, 3)
    nbrs = fns.allocate(Rs[0])
    batch = jax.vmap(fns.update, in_axes=(0, None))(Rs, nbrs)
    assert not np.any(np.asarray(batch.did_buffer_overflow))
    for b in range(3):
        one = fns.update(Rs[b], nbrs)
        assert np.array_equal(np.asarray(batch.idx[b]), np.asarray(one.idx))
        assert row_sets(one) == brute_rows(Rs[b], 1.1, side, True)


def test_free_box_clustered_and_spread():
    # Two clusters far apart: the free axes span them, their cells
    # coarsened to fit the table.
    R = jnp.concatenate([uniform(5, 150, 4.0), 500.0 + uniform(6, 150, 4.0)])
    check_dense(space.free()[0], None, R, 1.2, False)


def test_slab_periodic_in_x_and_y_free_in_z():
    side = 6.0
    R = uniform(7, 250, side)
    R = R.at[:, 2].multiply(3.0)  # past the box along the free axis
    check_dense(slab_displacement(side), side, R, 1.4,
                [True, True, False])


def test_a_thin_cloud_in_a_large_periodic_box_coarsens_the_grid():
    # 200 particles in a 2-thick slab of a box of 80: the box-wide grid
    # would have more cells than the table holds.
    side = 80.0
    R = uniform(8, 200, side).at[:, 2].multiply(2.0 / side)
    check_dense(space.periodic(side)[0], side, R, 1.0, True)


def test_two_dimensions():
    side = 10.0
    R = uniform(9, 400, side, dim=2)
    check_dense(space.periodic(side)[0], side, R, 1.1, True)
    check_dense(space.free()[0], None, R, 1.1, False)


def test_coincident_particles_and_mask_self_false():
    R = jnp.asarray([[1, 1, 1], [1, 1, 1], [1, 1, 2], [1, 2, 1], [2, 1, 1],
                     [1, 1, 1], [4.9, 1, 1]], jnp.float32)
    for mask_self in (True, False):
        check_dense(space.periodic(5.0)[0], 5.0, R, 1.5, True,
                    mask_self=mask_self)


@pytest.mark.parametrize("periodic", [True, False])
def test_lattice_pairs_exactly_at_the_cutoff_are_excluded(periodic):
    # Spacing 0.5, cutoff 1: second neighbours along the axes lie exactly
    # at the cutoff (representable), in the shell the caller's metric
    # decides with a strict '<'.
    R = jnp.asarray(lattice(8, 0.5))
    displacement = space.periodic(4.0)[0] if periodic else space.free()[0]
    nbrs = check_dense(displacement, 4.0 if periodic else None, R, 1.0,
                       periodic)
    if periodic:  # 6 at 0.5, 12 at 0.707, 8 at 0.866; the 6 at 1.0 out
        assert all(len(row) == 26 for row in row_sets(nbrs))


def test_float64_pairs_just_inside_and_outside_the_cutoff():
    with jax.enable_x64(True):
        rng = np.random.default_rng(0)
        base = 100.0 + rng.uniform(0, 1, (40, 3))
        direction = rng.normal(size=(40, 3))
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        cutoff = 0.75
        R = jnp.asarray(np.concatenate([
            base, base + direction * cutoff * (1 - 1e-12),
            base + direction * cutoff * (1 + 1e-12)]))
        nbrs = check_dense(space.free()[0], None, R, cutoff, False)
        assert nbrs.idx.dtype == jnp.int32
        rows = row_sets(nbrs)
        for k in range(40):
            assert 40 + k in rows[k] and 80 + k not in rows[k]


@pytest.mark.parametrize("fmt", FORMATS)
def test_overflow_under_jit_is_flagged_as_on_the_portable_path(fmt):
    side = 6.0
    displacement = space.periodic(side)[0]
    R = uniform(15, 200, side)
    crowded = R.at[:40].set(R[0] + 0.01 * jnp.arange(40)[:, None])
    flags = []
    for backend in (WARP, XLA):
        fns = jaxrt.neighbor_list(displacement, side, 1.2, format=fmt,
                                  backend=backend)
        nbrs = fns.allocate(R)
        update = jax.jit(fns.update)
        over = update(crowded, nbrs)
        flags.append(bool(over.did_buffer_overflow))
        # Sticky, and fixed by allocating anew.
        assert update(R, over).did_buffer_overflow
        fresh = fns.allocate(crowded)
        assert not fresh.did_buffer_overflow
        assert list_pairs(fresh) == expected_pairs(
            fmt, brute_pairs(crowded, 1.2, side, True))
    assert flags == [True, True]


def test_rows_under_jit_equal_the_eager_rows():
    side = 6.0
    displacement = space.periodic(side)[0]
    fns = jaxrt.neighbor_list(displacement, side, 1.3, backend=WARP,
                              capacity_multiplier=1.5)
    R = uniform(17, 250, side)
    nbrs = fns.allocate(R)
    moved = R + 0.02 * jax.random.normal(jax.random.PRNGKey(18), R.shape)
    eager = fns.update(moved, nbrs)
    traced = jax.jit(fns.update)(moved, nbrs)
    assert not traced.did_buffer_overflow
    assert np.array_equal(np.asarray(eager.idx), np.asarray(traced.idx))
    assert row_sets(traced) == brute_rows(jnp.mod(moved, side), 1.3, side,
                                          True)


def test_the_internal_shell_buffers_overflow_as_the_kernels_do():
    """A unit lattice at cutoff 1: six pairs of every particle lie exactly
    at the cutoff (its shell), none inside; a shell or a count of particles with one
    smaller than that overflows, as on the other kernels."""
    from jaxrt.backends import Capacity, Geometry, MetricSq, Query
    from jaxrt.lists.neighbors import metric_sq_fn

    side = 6.0
    R = jnp.asarray(lattice(6, 1.0))
    query = Query(1.0, (True,) * 3, True, partition.Dense)
    geometry = Geometry(jnp.full(3, side), jnp.ones(3))
    metric = MetricSq(metric_sq_fn(space.periodic(side)[0], 3))
    sizes = WARP.measure(R, geometry, query, metric)
    assert sizes["shell"] >= 6 and sizes["shell_rows"] == len(R)
    fits = dict(row=len(R) - 1, window=sizes["window"], shell=sizes["shell"],
                shell_rows=sizes["shell_rows"])

    def search(**change):
        internal = tuple(sorted({**fits, **change}.items()))
        return WARP.search(R, geometry, query, Capacity(len(R) - 1, internal),
                           metric)

    ok = search()
    assert not ok.overflow and int(ok.occupancy) == sizes["row"] == 0
    assert search(shell=5).overflow
    assert not search(shell=6).overflow
    assert search(shell_rows=len(R) - 1).overflow


def test_update_in_scan_lists_every_pair_within_the_skin_every_step():
    side, cutoff, skin = 5.0, 1.0, 0.3
    displacement, shift = space.periodic(side)
    R = uniform(12, 120, side)
    fns = jaxrt.neighbor_list(displacement, side, cutoff, dr_threshold=skin,
                              capacity_multiplier=2.0, backend=WARP)
    last, Rs, idxs, refs = kicked_updates(fns.allocate(R), shift, R, 30)
    assert not last.did_buffer_overflow
    n = R.shape[0]
    for t in range(0, 30, 6):
        # Each step's list is the list of its reference positions.
        rows = [frozenset(r[r < n].tolist()) for r in np.asarray(idxs[t])]
        assert rows == brute_rows(refs[t], cutoff + skin, side, True)
        listed = {(i, j) for i, r in enumerate(rows) for j in r}
        assert brute_pairs(Rs[t], cutoff, side, True) <= listed


def test_where_the_walk_cannot_serve_the_error_names_the_fix():
    side = 6.0
    R = uniform(19, 100, side)
    # A triclinic box: the caller's metric decides every pair.
    box = jnp.asarray([[side, 0.5, 0.0], [0.0, side, 0.0], [0.0, 0.0, side]])
    displacement = space.periodic_general(box, fractional_coordinates=False)[0]
    fns = jaxrt.neighbor_list(displacement, box, 1.2, backend=WARP,
                              fractional_coordinates=False)
    with pytest.raises(ValueError, match=r"kernel='warp'.*kernel='xla'"):
        fns.allocate(R)
    # Per-particle radii run on the radius classes.
    fns = jaxrt.neighbor_list(space.periodic(side)[0], side, 1.2,
                              backend=WARP, radii=jnp.full((100,), 0.5))
    with pytest.raises(ValueError, match="kernel='warp'"):
        fns.allocate(R)


def test_a_bad_graph_mode_is_refused_naming_the_choices():
    with pytest.raises(ValueError, match=r"warp_graph='cuda'.*'none'"):
        backends.Cell(kernel="warp", warp_graph="cuda")


@pytest.mark.parametrize("n,table", [(1, 1), (1, 10), (5, 5), (1000, 100),
                                     (37, 20000)])
def test_cell_table_is_the_keys_lower_bound(n, table):
    """``start[c]`` is the first sorted particle whose key is ``>= c`` for
    every entry of the table, the empty tail past the last key included
    (tables far larger than their keys, as the list's are)."""
    import warp as wp
    from jaxrt.backends.cell import warp_kernels as wk
    # The kernel runs where the list's does: a GPU when there is one.
    device = "cuda:0" if wp.get_cuda_device_count() > 0 else "cpu"
    keys = np.sort(np.random.default_rng(n).integers(
        0, min(table, 3 * n + 1), n)).astype(np.int32)
    # The sort's keys array holds 2 N entries; the table reads the first N.
    scratch = wp.array(np.concatenate([keys, np.full(n, -1, np.int32)]),
                       dtype=wp.int32, device=device)
    start = wp.full(table + 1, -7, dtype=wp.int32, device=device)
    wp.launch(wk.cell_table, dim=wk.table_threads(n, table), device=device,
              inputs=[scratch, n, table, start])
    want = np.searchsorted(keys, np.arange(table + 1), side="left")
    np.testing.assert_array_equal(start.numpy(), want)


@pytest.mark.parametrize("row_width,trim", [
    (w, False) for w in (1, 2, 3, 4, 5, 6, 7, 9, 13, 64)] + [
    (w, True) for w in (3, 13, 64)])
def test_rows_of_every_width_hold_the_first_pairs_then_padding(
        row_width, trim, monkeypatch):
    """The walk's rows at widths of every residue mod 4 (its stores are
    16-byte quads of the whole ``(N * width,)`` buffer, so a row starts and
    ends anywhere in a quad), with stencil rows read whole or trimmed to
    the sphere they cover: every row holds the first ``min(count,
    width)`` of its sure pairs, all of them distinct true pairs, then ``N``;
    its count and shell are exact; nothing is written outside it."""
    from jaxrt.backends.cell import warp_grid, warp_rows
    monkeypatch.setattr(warp_rows, "TRIM", trim)
    from jaxrt.backends.rt import ffi
    n, side, cutoff = 300, 6.0, 1.2
    R = np.asarray(uniform(3, n, side), np.float32)
    reach = (4, 2, 2)
    table = 4 * n + 64
    grid, cells = warp_grid.build(
        jnp.asarray(R), jnp.full((3,), side, jnp.float32),
        periodic=(True,) * 3, padding=(False,) * 3, reach=reach, table=table,
        min_size=tuple(cutoff * (1 + 2.0 ** -10) / r for r in reach))
    inner, outer = cutoff - 0.05, cutoff
    flags = warp_rows.MASK_SELF | sum(warp_rows.PERIODIC << a
                                      for a in range(3))
    rows, count, shells, shell_count = ffi.cell_candidate_rows(
        jnp.asarray(R), grid, cells, jnp.asarray([inner ** 2, outer ** 2],
                                                 jnp.float32),
        flags=flags, table=table, row_width=row_width, shell=n)
    rows, count = np.asarray(rows), np.asarray(count)
    shells, shell_count = np.asarray(shells), np.asarray(shell_count)
    d = R[:, None, :] - R[None, :, :]
    d = d - side * np.round(d / side)
    d2 = np.sum(d.astype(np.float64) ** 2, axis=-1)
    np.fill_diagonal(d2, np.inf)
    # Pairs within float32 rounding of a threshold may land on either side.
    eps = 1e-4
    sure = d2 < inner ** 2 - eps
    maybe_sure = d2 < inner ** 2 + eps
    maybe_near = d2 < outer ** 2 + eps
    assert rows.shape == (n, row_width)
    for i in range(n):
        k = min(int(count[i]), row_width)
        assert sure[i].sum() <= count[i] <= maybe_sure[i].sum()
        got = rows[i, :k]
        assert len(set(got.tolist())) == k
        assert np.all(maybe_sure[i, got])
        if count[i] <= row_width:
            assert set(np.flatnonzero(sure[i])) <= set(got.tolist())
        np.testing.assert_array_equal(rows[i, k:], n)
        near = shells[i, :shell_count[i]]
        assert np.all(maybe_near[i, near]) and not np.any(sure[i, near])
    assert np.any(count > row_width) == (row_width < int(sure.sum(1).max()))
