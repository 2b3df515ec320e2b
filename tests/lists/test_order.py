"""Spatial orderings (`jaxrt.spatial_order`, `reorder`, `inverse_order`).

Oracles: a permutation is checked as integers (sorted equals arange); the
Hilbert curve by its defining property on a grid (consecutive cells are
face neighbours); physics by float64 LJ on a jaxrt Dense list, where the
reordered system's energy must equal the original's and its forces the
original's permuted (the sums differ only in order: 1e-12 relative, far
above float64's rounding of a few hundred terms and far below any wrong
pair); pairs as exact sets against a fresh list.
"""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax_md import quantity, space

import jaxrt
from oracle import list_pairs

CURVES = ("hilbert", "morton")


def grid(n_side: int, dim: int, seed: int = 0) -> np.ndarray:
    """Integer cells of an ``n_side**dim`` grid, shuffled."""
    g = np.stack(np.meshgrid(*[np.arange(n_side)] * dim, indexing="ij"), -1)
    g = g.reshape(-1, dim)
    return g[np.random.default_rng(seed).permutation(len(g))]


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("curve", CURVES + ("cells",))
@pytest.mark.parametrize("box", ["periodic", "free", "triclinic"])
def test_is_a_permutation_and_idempotent(dim, curve, box):
    rng = np.random.default_rng(1)
    R = jnp.asarray(rng.uniform(0, 5.0, (777, dim)), jnp.float32)
    kwargs = {"cell_size": 1.0} if curve == "cells" else {}
    if box == "free":
        b = None
    elif box == "triclinic":
        b = 5.0 * np.eye(dim) + np.triu(np.full((dim, dim), 0.7), 1)
    else:
        b = 5.0
    if curve == "cells" and box != "periodic":
        with pytest.raises(ValueError, match="curve='cells'"):
            jaxrt.spatial_order(R, b, curve=curve, **kwargs)
        return
    perm = np.asarray(jaxrt.spatial_order(R, b, curve=curve, **kwargs))
    assert perm.dtype == np.int32
    np.testing.assert_array_equal(np.sort(perm), np.arange(len(R)))
    again = jaxrt.spatial_order(R[perm], b, curve=curve, **kwargs)
    np.testing.assert_array_equal(np.asarray(again), np.arange(len(R)))


@pytest.mark.parametrize("dim", [2, 3])
def test_hilbert_visits_face_neighbours(dim):
    # Cell centres of an 8^dim grid: at its finer resolution the curve
    # visits the coarse cells in the coarse curve's order, one face step
    # at a time; Morton's jumps are the contrast.
    g = grid(8, dim)
    R = jnp.asarray((g + 0.5) / 8)
    steps = {}
    for curve in CURVES:
        perm = np.asarray(jaxrt.spatial_order(R, 1.0, curve=curve))
        steps[curve] = np.abs(np.diff(g[perm], axis=0)).sum(1)
    assert steps["hilbert"].min() == 1 and steps["hilbert"].max() == 1
    assert steps["morton"].max() > 1


def test_cells_number_bins_x_major():
    g = grid(6, 3)
    R = jnp.asarray((g + 0.5) * 2.0)
    perm = np.asarray(jaxrt.spatial_order(R, 12.0, curve="cells",
                                          cell_size=2.0))
    key = (g[perm] * [36, 6, 1]).sum(1)
    np.testing.assert_array_equal(key, np.arange(216))


def test_jit_matches_eager_and_wraps_the_box():
    rng = np.random.default_rng(2)
    R = jnp.asarray(rng.uniform(0, 4.0, (500, 3)), jnp.float32)
    eager = jaxrt.spatial_order(R, 4.0)
    jitted = jax.jit(lambda r, b: jaxrt.spatial_order(r, b))(R, 4.0)
    np.testing.assert_array_equal(np.asarray(eager), np.asarray(jitted))
    # Periodic images order as the particles they are images of.
    shifted = R + 4.0 * jnp.asarray(rng.integers(-2, 3, R.shape), R.dtype)
    np.testing.assert_array_equal(
        np.asarray(jaxrt.spatial_order(shifted, 4.0)), np.asarray(eager))


def lj_system(n_side=9, seed=3):
    """A jittered simple-cubic LJ fluid (density 0.8), shuffled: numpy
    float64 positions (the caller picks the JAX dtype) and the box side."""
    rng = np.random.default_rng(seed)
    n = n_side ** 3
    box = (n / 0.8) ** (1 / 3)
    g = grid(n_side, 3, seed)
    R = (g + 0.5 + rng.uniform(-0.2, 0.2, g.shape)) * box / n_side
    return R, box


@pytest.mark.parametrize("curve", CURVES)
def test_energy_and_forces_follow_the_permutation(x64, curve):
    R, box = lj_system()
    R = jnp.asarray(R, jnp.float64)
    disp, _ = space.periodic(box)
    neighbor_fn, energy_fn = jaxrt.energy.lennard_jones_neighbor_list(
        disp, box, r_onset=2.0, r_cutoff=2.5, dr_threshold=0.3,
        format=jaxrt.Dense, neighbor_list_fn=jaxrt.neighbor_list)
    force_fn = quantity.force(energy_fn)
    perm = jaxrt.spatial_order(R, box, curve=curve)
    P = jaxrt.reorder(perm, R)
    nbrs, nbrs_p = neighbor_fn.allocate(R), neighbor_fn.allocate(P)
    e, e_p = energy_fn(R, neighbor=nbrs), energy_fn(P, neighbor=nbrs_p)
    f, f_p = force_fn(R, neighbor=nbrs), force_fn(P, neighbor=nbrs_p)
    assert e.dtype == jnp.float64
    np.testing.assert_allclose(float(e_p), float(e), rtol=1e-12)
    scale = float(jnp.max(jnp.abs(f)))
    np.testing.assert_allclose(np.asarray(f_p), np.asarray(f)[np.asarray(perm)],
                               rtol=0, atol=1e-12 * scale)
    inv = jaxrt.inverse_order(perm)
    np.testing.assert_array_equal(np.asarray(P[inv]), np.asarray(R))


def median_gap(nbrs) -> float:
    idx = np.asarray(nbrs.idx)
    n = idx.shape[0]
    i, c = np.nonzero(idx < n)
    return float(np.median(np.abs(idx[i, c] - i)))


@pytest.mark.parametrize("curve", CURVES)
def test_locality_improves(curve):
    R, box = lj_system(n_side=16)
    R = jnp.asarray(R, jnp.float32)
    disp, _ = space.periodic(box)
    neighbor_fn = jaxrt.neighbor_list(disp, box, 2.5, format=jaxrt.Dense)
    before = median_gap(neighbor_fn.allocate(R))
    P = jaxrt.reorder(jaxrt.spatial_order(R, box, curve=curve), R)
    after = median_gap(neighbor_fn.allocate(P))
    # Shuffled, a gap is about N/3 (4096 particles); along a curve a
    # particle's neighbours lie within a few of its cells' populations.
    assert before > 1000
    assert after < before / 5


def test_list_stays_right_across_a_reorder():
    R, box = lj_system()
    R = jnp.asarray(R, jnp.float32)
    disp, _ = space.periodic(box)
    neighbor_fn = jaxrt.neighbor_list(disp, box, 2.5, dr_threshold=0.3,
                                      format=jaxrt.Dense)
    nbrs = neighbor_fn.allocate(R)
    P = jaxrt.reorder(jaxrt.spatial_order(R, box), R)
    updated = jax.jit(lambda r, nb: nb.update(r))(P, nbrs)
    assert not updated.did_buffer_overflow
    assert list_pairs(updated) == list_pairs(neighbor_fn.allocate(P))


def test_reorder_takes_per_particle_leaves_only():
    perm = jnp.asarray([2, 0, 1])
    state = {"R": jnp.arange(6.0).reshape(3, 2), "species": jnp.asarray(
        [7, 8, 9]), "mass": 1.5, "pair": jnp.ones((4, 4)), "dt": jnp.asarray(
            0.1)}
    out = jaxrt.reorder(perm, state)
    np.testing.assert_array_equal(np.asarray(out["R"]), [[4, 5], [0, 1],
                                                         [2, 3]])
    np.testing.assert_array_equal(np.asarray(out["species"]), [9, 7, 8])
    assert out["mass"] == 1.5 and out["pair"].shape == (4, 4)
    assert float(out["dt"]) == pytest.approx(0.1)


@pytest.mark.parametrize("call, match", [
    (lambda R: jaxrt.spatial_order(R, 1.0, curve="peano"), "curve='peano'"),
    (lambda R: jaxrt.spatial_order(R[:, :1], 1.0), r"shape \(10, 1\)"),
    (lambda R: jaxrt.spatial_order(R.astype(jnp.int32), 1.0), "float"),
    (lambda R: jaxrt.spatial_order(R, jnp.ones(2)), r"box of shape \(2,\)"),
    (lambda R: jaxrt.spatial_order(R, 1.0, curve="cells"), "cell_size="),
    (lambda R: jaxrt.spatial_order(R, 1.0, cell_size=0.5), "drop cell_size"),
    (lambda R: jaxrt.spatial_order(R, 1.0, curve="cells", cell_size=0.0),
     "positive"),
    (lambda R: jaxrt.spatial_order(R, 1.0, curve="cells", cell_size=1e-4),
     "overflow int32"),
    (lambda R: jaxrt.reorder(jnp.ones((2, 2), jnp.int32), R), "perm"),
])
def test_bad_input_names_the_argument(call, match):
    R = jnp.asarray(np.random.default_rng(4).uniform(0, 1, (10, 3)),
                    jnp.float32)
    with pytest.raises(ValueError, match=match):
        call(R)


def test_cells_need_a_concrete_box():
    R = jnp.full((5, 3), 0.3, jnp.float32)
    order = jax.jit(lambda r, b: jaxrt.spatial_order(r, b, curve="cells",
                                                     cell_size=0.5))
    with pytest.raises(ValueError, match="traced box"):
        order(R, 1.0)
