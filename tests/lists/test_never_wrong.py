"""Never a silently wrong list: a box that does not match the displacement,
metrics that are not the Euclidean minimum image, cutoffs of half a box,
triclinic boxes, jax-md's ignored keywords, and the small adversarial
systems. The oracles are the float64 brute force and jax-md's own list."""
from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax_md import partition, space

import jaxrt
from oracle import (assert_layout, brute_pairs, brute_pairs_general,
                    expected_pairs, list_pairs)

FORMATS = [partition.Dense, partition.Sparse, partition.OrderedSparse]
GRID_BACKENDS = ["cell"] + [b for b in ("bvh", "spheres", "squares")
                            if b in jaxrt.available_backends()]


def jax_md_brute(metric, box, cutoff, R, fmt=partition.Dense, **kwargs):
    """jax-md's own all-pairs list, which asks the metric about every pair."""
    return partition.neighbor_list(metric, box, cutoff, format=fmt,
                                   disable_cell_list=True, **kwargs).allocate(R)


# --------------------------------------------------------------------------
# 1. A periodic displacement with box=None.


@pytest.mark.parametrize("backend", GRID_BACKENDS)
def test_periodic_displacement_without_box_is_refused(backend):
    disp, _ = space.periodic(100.0)
    R = jnp.array([[0.5, 50.0, 50.0], [99.5, 50.0, 50.0]])
    with pytest.raises(ValueError, match="box=.*space.periodic"):
        jaxrt.neighbor_list(disp, None, 2.0, backend=backend).allocate(R)
    # With the box the pair across the face is found, by every backend.
    nbrs = jaxrt.neighbor_list(disp, 100.0, 2.0, backend=backend).allocate(R)
    assert list_pairs(nbrs) == {(0, 1), (1, 0)}
    # The all-pairs search asks the metric itself: right either way.
    nbrs = jaxrt.neighbor_list(disp, None, 2.0, backend="brute").allocate(R)
    assert list_pairs(nbrs) == {(0, 1), (1, 0)}


def test_periodic_displacement_without_box_sets_an_error_bit_under_jit():
    # Allocated where the particles span little of the box (every distance
    # looks free), then moved across a face: the rebuild notices.
    disp, _ = space.periodic(100.0)
    fns = jaxrt.neighbor_list(disp, None, 2.0)
    R = jnp.array([[10.0, 50.0, 50.0], [20.0, 50.0, 50.0], [15.0, 50, 50]])
    nbrs = fns.allocate(R)
    assert not nbrs.did_buffer_overflow
    moved = R.at[0, 0].set(0.5).at[1, 0].set(99.5)
    nbrs = jax.jit(fns.update)(moved, nbrs)
    assert int(nbrs.error.code) & jaxrt.ErrorCode.METRIC_MISMATCH
    assert nbrs.did_buffer_overflow  # the usual loop reallocates ...
    with pytest.raises(jaxrt.NeighborListError, match="box=None"):
        jaxrt.check(nbrs)
    with pytest.raises(ValueError, match="box="):  # ... and allocate says why
        fns.allocate(moved)


# --------------------------------------------------------------------------
# 2. Metrics that are not the Euclidean minimum image.


def scaled(factor):
    free, _ = space.free()
    return lambda ra, rb, **kw: factor * space.distance(free(ra, rb))


def anisotropic(weights, side=None):
    def metric(ra, rb, **kw):
        d = ra - rb
        if side is not None:
            d = d - side * jnp.round(d / side)
        return space.distance(d * jnp.asarray(weights))
    return metric


def soft_core(ra, rb, **kw):
    # Never shorter than the Euclidean distance, and not a quadratic form:
    # the cell list must let the metric decide every candidate.
    d2 = jnp.sum((ra - rb) ** 2)
    return jnp.sqrt(d2 + 0.1 * d2 * d2)


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("name, metric, periodic", [
    ("twice", scaled(2.0), False),
    ("half", scaled(0.5), False),
    ("anisotropic", anisotropic([1.0, 0.5, 2.0]), False),
    ("anisotropic periodic", anisotropic([1.0, 0.5, 2.0], 8.0), True),
    ("soft core", soft_core, False),
])
def test_non_euclidean_metrics_match_jax_md(name, metric, periodic, fmt):
    R = jax.random.uniform(jax.random.PRNGKey(11), (300, 3)) * 8.0
    nbrs = jaxrt.neighbor_list(metric, 8.0, 1.2, format=fmt, backend="cell",
                               periodic=periodic).allocate(R)
    ref = jax_md_brute(metric, 8.0, 1.2, R, fmt)
    assert_layout(nbrs)
    assert len(list_pairs(ref)) > 50
    assert list_pairs(nbrs) == list_pairs(ref)
    nbrs = nbrs.update(R + 0.01)
    assert list_pairs(nbrs) == list_pairs(jax_md_brute(metric, 8.0, 1.2,
                                                       R + 0.01, fmt))


def test_metric_shorter_than_the_grid_allows_is_refused():
    def saturating(ra, rb, **kw):  # far pairs come closer than Euclidean
        d2 = jnp.sum((ra - rb) ** 2)
        return jnp.sqrt(d2 / (1.0 + 0.05 * d2))

    R = jax.random.uniform(jax.random.PRNGKey(12), (200, 3)) * 8.0
    with pytest.raises(ValueError, match="backend='brute'"):
        jaxrt.neighbor_list(saturating, None, 1.0, periodic=False
                            ).allocate(R)
    nbrs = jaxrt.neighbor_list(saturating, None, 1.0, periodic=False,
                               backend="brute").allocate(R)
    assert list_pairs(nbrs) == list_pairs(jax_md_brute(saturating, 8.0, 1.0, R))




@pytest.mark.parametrize("where", ["host", "device"])
@pytest.mark.parametrize("scene", ["random", "lattice with ties"])
def test_allocate_samples_neighbours_along_each_axis(where, scene, monkeypatch):
    """The model check's samples: the first extremes of each axis and the
    particles at evenly spaced ranks of its order with their successors,
    whether the host sorts or the device does (on GPUs from 2^16
    particles); forced here to either on the CPU."""
    from jaxrt.lists import metric as _space
    if scene == "random":  # distinct coordinates on each axis
        rng = np.random.default_rng(3)
        q = np.stack([rng.permutation(3000) for _ in range(3)], 1) * 0.003
    else:  # every coordinate shared by 100 particles or more
        q = np.stack(np.meshgrid(*[np.arange(9.0)] * 3), -1).reshape(-1, 3)
        q = np.concatenate([q, q[::-1]])
    q = q.astype(np.float32)
    take = np.linspace(0, len(q) - 2, 500).astype(int)
    sample = {"host": _space._axis_samples_on_host,
              "device": _space._axis_samples_on_device}[where]
    lowest, highest, before, after = sample(jnp.asarray(q), take)
    np.testing.assert_array_equal(lowest, np.argmin(q, axis=0))
    np.testing.assert_array_equal(highest, np.argmax(q, axis=0))
    for a in range(3):
        ranked = np.sort(q[:, a])
        np.testing.assert_array_equal(q[before[a], a], ranked[take])
        np.testing.assert_array_equal(q[after[a], a], ranked[take + 1])
        assert np.all(before[a] != after[a])
    if scene == "random":  # no ties: both sorts give the same particles
        other = {"host": _space._axis_samples_on_device,
                 "device": _space._axis_samples_on_host}[where]
        for mine, theirs in zip(sample(jnp.asarray(q), take),
                                other(jnp.asarray(q), take)):
            np.testing.assert_array_equal(np.asarray(mine), np.asarray(theirs))

    # And allocate's refusal of a too short metric holds on either path.
    monkeypatch.setattr(_space, "_DEVICE_SORT_MIN", 0)
    monkeypatch.setattr(_space, "_on_accelerator", lambda x: where == "device")
    test_metric_shorter_than_the_grid_allows_is_refused()
@pytest.mark.skipif("bvh" not in jaxrt.available_backends(),
                    reason="needs Warp")
def test_ray_traced_backends_refuse_metrics_they_cannot_honour():
    R = jax.random.uniform(jax.random.PRNGKey(12), (100, 3)) * 8.0
    with pytest.raises(ValueError, match="backend='cell'"):
        jaxrt.neighbor_list(soft_core, None, 1.0, periodic=False,
                            backend="bvh").allocate(R)
    # A metric scaled per axis is a Euclidean distance in scaled
    # coordinates: the ray-traced search honours it.
    metric = anisotropic([1.0, 0.5, 2.0])
    nbrs = jaxrt.neighbor_list(metric, None, 1.2, backend="bvh").allocate(R)
    assert list_pairs(nbrs) == list_pairs(jax_md_brute(metric, 8.0, 1.2, R))


# --------------------------------------------------------------------------
# 3. Cutoffs of half a periodic box or more (tests/test_small_box.py has
# the lists of `cell` and `brute` there).

RAY_TRACED = [b for b in GRID_BACKENDS if b != "cell"]


@pytest.mark.skipif(not RAY_TRACED, reason="needs Warp")
@pytest.mark.parametrize("backend", RAY_TRACED)
def test_cutoff_of_half_the_box_is_refused_by_the_ray_traced_backends(
        backend):
    side = np.array([10.0, 6.0, 10.0])
    disp, _ = space.periodic(side)
    R = jax.random.uniform(jax.random.PRNGKey(13), (60, 3)) * side
    with pytest.raises(ValueError, match=r"axis 1 \(L/2 = 3\).*"
                       r"backend='cell' or backend='brute'"):
        jaxrt.neighbor_list(disp, side, 3.0, backend=backend).allocate(R)
    with pytest.raises(ValueError, match="axis 1"):  # the skin counts too
        jaxrt.neighbor_list(disp, side, 2.9, dr_threshold=0.2,
                            backend=backend).allocate(R)
    # Just below half the box: every pair, through its nearest image.
    below = 3.0 * (1 - 2.0 ** -12)
    nbrs = jaxrt.neighbor_list(disp, side, below, backend=backend,
                               format=partition.Sparse).allocate(R)
    assert list_pairs(nbrs) == brute_pairs(R, below, side, True)


@pytest.mark.parametrize("backend", ["cell"] + RAY_TRACED[:1])
def test_a_box_shrinking_under_update_sets_an_error_bit_where_refused(
        backend):
    """On a backend that refuses small boxes (bvh), a box passed to a
    jitted update that shrinks below twice the cutoff sets BOX_TOO_SMALL;
    on cell, which lists small boxes, it does not (test_small_box checks
    that list)."""
    box = jnp.array([6.0, 6.0, 6.0])
    disp, _ = space.periodic_general(box, fractional_coordinates=True)
    fns = jaxrt.neighbor_list(disp, box, 1.4, fractional_coordinates=True,
                              backend=backend)
    frac = jax.random.uniform(jax.random.PRNGKey(14), (100, 3))
    nbrs = fns.allocate(frac)
    ok = jax.jit(fns.update)(frac, nbrs, box=box * 0.5)  # L/2 = 1.5 > 1.4
    # (8x denser: the neighbour buffer itself may overflow, nothing else)
    assert not int(ok.error.code) & jaxrt.ErrorCode.BOX_TOO_SMALL
    small = jax.jit(fns.update)(frac, nbrs, box=box * 0.45)  # L/2 = 1.35
    if backend == "cell":
        assert not int(small.error.code) & jaxrt.ErrorCode.BOX_TOO_SMALL
        return
    assert int(small.error.code) & jaxrt.ErrorCode.BOX_TOO_SMALL
    assert small.did_buffer_overflow
    with pytest.raises(jaxrt.NeighborListError, match="half its height"):
        jaxrt.check(small)


# --------------------------------------------------------------------------
# 4. jax-md's ignored keywords, and triclinic boxes in the cell list.


def test_jax_md_static_keywords_warn_and_near_misses_raise():
    disp, _ = space.periodic(5.0)
    with pytest.warns(UserWarning, match=r"ignores .*\['cell_size', 't'\]"):
        fns = jaxrt.neighbor_list(disp, 5.0, 1.0, cell_size=0.2, t=0.0)
    R = jax.random.uniform(jax.random.PRNGKey(15), (50, 3)) * 5.0
    assert list_pairs(fns.allocate(R)) == brute_pairs(R, 1.0, 5.0, True)
    with pytest.raises(TypeError, match="did you mean 'capacity_multiplier'"):
        jaxrt.neighbor_list(disp, 5.0, 1.0, capacity_multiplyer=1.5)
    with pytest.raises(TypeError, match="did you mean 'dr_threshold'"):
        jaxrt.neighbor_list(disp, 5.0, 1.0, dr_treshold=0.1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no warning without extra keywords
        jaxrt.neighbor_list(disp, 5.0, 1.0)


SHEARED = np.array([[6.0, 1.5, 0.8], [0.0, 5.5, -1.2], [0.0, 0.0, 6.5]])


@pytest.mark.parametrize("backend", ["cell", "brute"])
@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("fractional", [True, False])
def test_triclinic_boxes_in_every_layout(backend, fmt, fractional):
    frac = jax.random.uniform(jax.random.PRNGKey(16), (250, 3))
    box = jnp.asarray(SHEARED, jnp.float32)
    disp, _ = space.periodic_general(box, fractional_coordinates=fractional)
    R = frac if fractional else frac @ box.T
    fns = jaxrt.neighbor_list(disp, box, 1.6, format=fmt, backend=backend,
                              fractional_coordinates=fractional)
    nbrs = fns.allocate(R)
    assert_layout(nbrs)
    want = expected_pairs(fmt, brute_pairs_general(frac, SHEARED, 1.6))
    assert len(want) > 250
    assert list_pairs(nbrs) == want
    ref = partition.neighbor_list(disp, box, 1.6, format=fmt,
                                  fractional_coordinates=fractional,
                                  disable_cell_list=True).allocate(R)
    assert list_pairs(nbrs) == list_pairs(ref)


def test_triclinic_box_changing_under_update():
    box = jnp.asarray(SHEARED, jnp.float32)
    disp, _ = space.periodic_general(box)
    fns = jaxrt.neighbor_list(disp, box, 1.6, fractional_coordinates=True)
    frac = jax.random.uniform(jax.random.PRNGKey(17), (250, 3))
    nbrs = fns.allocate(frac)
    for new in (SHEARED * 1.2, SHEARED * np.array([1.0, 1.1, 0.9])):
        got = jax.jit(fns.update)(frac, nbrs, box=jnp.asarray(new, jnp.float32))
        assert not got.did_buffer_overflow
        assert list_pairs(got) == brute_pairs_general(frac, new, 1.6)


def test_shear_appearing_after_an_orthorhombic_allocate_is_flagged():
    box = jnp.diag(jnp.array([6.0, 6.0, 6.0]))
    disp, _ = space.periodic_general(box)
    fns = jaxrt.neighbor_list(disp, box, 1.2, fractional_coordinates=True,
                              format=partition.Sparse)
    frac = jax.random.uniform(jax.random.PRNGKey(18), (200, 3))
    nbrs = fns.allocate(frac)
    sheared = box.at[0, 1].set(2.5)
    got = jax.jit(fns.update)(frac, nbrs, box=sheared)
    assert int(got.error.code) & jaxrt.ErrorCode.METRIC_MISMATCH
    # Allocated in the sheared box, the list is right.
    again = fns.allocate(frac, box=sheared)
    assert list_pairs(again) == brute_pairs_general(frac, np.asarray(sheared),
                                                    1.2)


@pytest.mark.skipif("bvh" not in jaxrt.available_backends(),
                    reason="needs Warp")
def test_ray_traced_backends_refuse_triclinic_boxes_clearly():
    box = jnp.asarray(SHEARED, jnp.float32)
    disp, _ = space.periodic_general(box)
    frac = jax.random.uniform(jax.random.PRNGKey(16), (50, 3))
    with pytest.raises(ValueError, match="triclinic.*backend='cell'"):
        jaxrt.neighbor_list(disp, box, 1.6, fractional_coordinates=True,
                            backend="bvh").allocate(frac)


# --------------------------------------------------------------------------
# Small and extreme systems.


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("backend", ["cell", "brute"])
def test_one_particle_and_an_empty_list(fmt, backend):
    disp, _ = space.periodic(5.0)
    one = jnp.array([[1.0, 2.0, 3.0]])
    nbrs = jaxrt.neighbor_list(disp, 5.0, 1.0, format=fmt,
                               backend=backend).allocate(one)
    assert_layout(nbrs)
    assert list_pairs(nbrs) == set() and not nbrs.did_buffer_overflow
    far = jnp.array([[0.5, 0.5, 0.5], [2.5, 2.5, 2.5], [4.0, 1.0, 2.5]])
    nbrs = jaxrt.neighbor_list(disp, 5.0, 1.0, format=fmt,
                               backend=backend).allocate(far)
    assert list_pairs(nbrs) == set()
    assert not nbrs.update(far).did_buffer_overflow


@pytest.mark.parametrize("axis", [0, 1, 2])
@pytest.mark.parametrize("backend", GRID_BACKENDS)
def test_two_particles_across_each_face(axis, backend):
    side = np.array([5.0, 6.0, 7.0], np.float32)
    disp, _ = space.periodic(side)
    R = np.full((2, 3), 2.0, np.float32)
    R[0, axis], R[1, axis] = 0.1, side[axis] - 0.2
    for fmt in FORMATS:
        nbrs = jaxrt.neighbor_list(disp, side, 0.5, format=fmt,
                                   backend=backend).allocate(R)
        assert list_pairs(nbrs) == expected_pairs(fmt, {(0, 1), (1, 0)})


@pytest.mark.parametrize("fmt", FORMATS)
def test_all_particles_at_one_point(fmt):
    disp, _ = space.periodic(4.0)
    R = jnp.full((40, 3), 1.25)
    nbrs = jaxrt.neighbor_list(disp, 4.0, 1.0, format=fmt,
                               mask_self=False).allocate(R)
    assert_layout(nbrs)
    assert list_pairs(nbrs) == expected_pairs(
        fmt, {(i, j) for i in range(40) for j in range(40)})
    free, _ = space.free()
    nbrs = jaxrt.neighbor_list(free, None, 1.0, format=fmt).allocate(R)
    assert list_pairs(nbrs) == expected_pairs(
        fmt, {(i, j) for i in range(40) for j in range(40) if i != j})


def test_thin_periodic_slab():
    # One axis barely more than twice the cutoff, the others wide.
    side = np.array([20.0, 2.05, 20.0], np.float32)
    disp, _ = space.periodic(side)
    R = jax.random.uniform(jax.random.PRNGKey(19), (400, 3)) * side
    for fmt in FORMATS:
        nbrs = jaxrt.neighbor_list(disp, side, 1.0, format=fmt).allocate(R)
        assert list_pairs(nbrs) == expected_pairs(
            fmt, brute_pairs(R, 1.0, side, True))


def test_positions_near_a_million_in_free_space():
    # float32 spacing is 0.0625 at 1e6: pairs are decided by the caller's
    # metric on those coordinates, exactly as jax-md decides them.
    R = 1e6 + jax.random.uniform(jax.random.PRNGKey(20), (300, 3)) * 40.0
    free, _ = space.free()
    for fmt in FORMATS:
        nbrs = jaxrt.neighbor_list(free, None, 3.0, format=fmt).allocate(R)
        assert list_pairs(nbrs) == list_pairs(jax_md_brute(free, 1.0, 3.0, R,
                                                           fmt))
        assert list_pairs(nbrs) == expected_pairs(fmt, brute_pairs(R, 3.0))


def test_metric_noisy_below_its_model_is_searched_a_little_farther():
    # A metric up to 1e-4 shorter than its quadratic model, as jax-md's
    # periodic_general is on a GPU that rounds its matrix product to TF32:
    # the grid searches that much farther and the metric decides.
    def noisy(ra, rb, **kw):
        d = space.distance(ra - rb)
        return d * (1.0 - 1e-4 * jnp.sin(997.0 * (ra[0] + rb[0])) ** 2)

    R = jax.random.uniform(jax.random.PRNGKey(21), (300, 3)) * 8.0
    nbrs = jaxrt.neighbor_list(noisy, None, 1.2, periodic=False,
                               format=partition.Sparse).allocate(R)
    assert nbrs.cell_list_capacity.metric_decides
    assert 0 < nbrs.cell_list_capacity.slack <= 2 ** -7
    assert list_pairs(nbrs) == list_pairs(
        jax_md_brute(noisy, 8.0, 1.2, R, partition.Sparse))
    # Pairs just inside the cutoff by the metric but outside by the model.
    base = np.array([[1.0, 1.0, 1.0]], np.float32)
    edge = base + np.array([[1.2 * (1 + 2e-5), 0.0, 0.0]], np.float32)
    pair = jnp.asarray(np.concatenate([base, edge, R[:50]]))
    got = jaxrt.neighbor_list(noisy, None, 1.2, periodic=False).allocate(pair)
    assert list_pairs(got) == list_pairs(jax_md_brute(noisy, 8.0, 1.2, pair))


@pytest.mark.parametrize("side", [3.9764039394333266, 4.0 - 4e-6, 7.99, 1.9999])
@pytest.mark.parametrize("backend", GRID_BACKENDS)
def test_box_sides_just_below_a_power_of_two_stay_orthorhombic(side, backend):
    # jax-md's wrap adds L/2: a probe step that carried L/2 past a power of
    # two rounded, and the box read as sheared (hypothesis found 3.9764 in
    # 2D, which the ray-traced backends then refused as triclinic).
    disp, _ = space.periodic(side)
    R = jax.random.uniform(jax.random.PRNGKey(22), (60, 2)) * side
    nbrs = jaxrt.neighbor_list(disp, side, 0.9, backend=backend).allocate(R)
    capacity = nbrs.cell_list_capacity
    assert capacity.orthorhombic and not capacity.metric_decides
    assert list_pairs(nbrs) == brute_pairs(R, 0.9, side, True)


# --------------------------------------------------------------------------
# 7. Boxes that do not fit the positions, named as such.


@pytest.mark.parametrize("axis", [0, 1, 2])
@pytest.mark.parametrize("free", [False, True])
def test_box_with_a_nan_side_is_refused_naming_its_axis(axis, free):
    # Found: a NaN side dropped the whole box, so a periodic displacement
    # was refused as ambiguous on axis 0 (whatever axis held the NaN), and
    # a free one silently ran without it.
    box = np.full(3, 6.0)
    box[axis] = np.nan
    disp = space.free()[0] if free else space.periodic(jnp.asarray(box))[0]
    R = jax.random.uniform(jax.random.PRNGKey(23), (40, 3)) * 6.0
    with pytest.raises(ValueError, match=rf"box has a non-finite side on "
                                         rf"axis {axis} \(nan\)"):
        jaxrt.neighbor_list(disp, box, 1.0).allocate(R)


def test_triclinic_box_with_a_nan_entry_is_refused_naming_it():
    box = np.eye(3) * 6.0
    box[0, 2] = np.nan
    disp = space.free()[0]
    R = jax.random.uniform(jax.random.PRNGKey(24), (40, 3)) * 6.0
    with pytest.raises(ValueError, match=r"box has a non-finite entry at "
                                         r"\[0, 2\] \(nan\)"):
        jaxrt.neighbor_list(disp, box, 1.0).allocate(R)


@pytest.mark.parametrize("box", [(6.0, 6.0, 6.0), np.eye(3) * 6.0],
                         ids=["sides", "matrix"])
@pytest.mark.parametrize("made_for", [2, 3])
def test_2d_positions_with_a_3d_box_name_the_dimensions(box, made_for):
    # Found: with space.periodic of the same 3 sides the error blamed
    # displacement_or_metric ("incompatible shapes for broadcasting") and
    # never said that positions and box disagree on the dimension.
    box = np.asarray(box)
    side = jnp.asarray(np.full(made_for, 6.0))
    disp, _ = space.periodic(side)
    R = jax.random.uniform(jax.random.PRNGKey(25), (40, 2)) * 6.0
    with pytest.raises(ValueError, match=r"positions are 2-D \(shape "
                                         r"\(N, 2\)\) but box has 3 sides"
                                         if box.ndim == 1 else
                                         r"positions are 2-D \(shape "
                                         r"\(N, 2\)\) but box is a \(3, 3\)"):
        jaxrt.neighbor_list(disp, box, 1.0).allocate(R)


def test_displacement_of_another_dimension_is_named_as_such():
    disp, _ = space.periodic(jnp.asarray([6.0, 6.0, 6.0]))
    R = jax.random.uniform(jax.random.PRNGKey(26), (40, 2)) * 6.0
    with pytest.raises(TypeError, match=r"positions are 2-D.*made for "
                                        r"another dimension"):
        jaxrt.neighbor_list(disp, 6.0, 1.0).allocate(R)
