"""backend="delaunay" (seed 004, `jaxrt.backends.delaunay`) against the float64
brute force: random scenes in every layout, lattices with the radius on
lattice distances (cocircular and collinear points, ties at the cutoff),
many small moves in a ``lax.scan``, a move across several edges, the
rebuild fallbacks, overflow, and the errors of bad input."""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax_md import partition, space

import jaxrt
from jaxrt.backends import delaunay
from jaxrt.errors import ErrorCode
from jaxrt.lists.neighbors import StatefulNeighborList
from oracle import assert_layout, brute_pairs, expected_pairs, list_pairs

pytestmark = pytest.mark.usefixtures("x64")

FORMATS = [partition.Dense, partition.Sparse, partition.OrderedSparse]


@pytest.fixture
def x64():
    # The global flag, not the jax.enable_x64 context: the rebuild's host
    # callback runs in another thread, where a context would not hold.
    before = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)
    yield
    jax.config.update("jax_enable_x64", before)


@functools.lru_cache(maxsize=None)
def factory(periodic: bool, side: float, cutoff: float, fmt=partition.Dense,
            skin: float = 0.0, mask_self: bool = True,
            capacity_multiplier: float = 1.25, **options):
    """One list factory per configuration, shared by the tests: each
    factory compiles its own search."""
    disp, _ = space.periodic(side) if periodic else space.free()
    backend = jaxrt.backends.Delaunay(**options) if options else "delaunay"
    fns = jaxrt.neighbor_list(disp, side, cutoff - skin, dr_threshold=skin,
                              format=fmt, backend=backend,
                              capacity_multiplier=capacity_multiplier,
                              mask_self=mask_self, periodic=periodic)
    return fns, jax.jit(fns.update)


def assert_exact(nbrs, R, cutoff, side, periodic, fmt=partition.Dense,
                 mask_self=True):
    assert not nbrs.did_buffer_overflow
    assert_layout(nbrs)
    want = expected_pairs(fmt, brute_pairs(np.asarray(R), cutoff, side,
                                           periodic, mask_self))
    assert list_pairs(nbrs) == want


def uniform(n, side, seed):
    return jnp.asarray(np.random.default_rng(seed).uniform(0, side, (n, 2)))


SIDE, CUTOFF = 10.0, 1.5


def scene():
    """The shared random scene: 300 particles, side 10, cutoff 1.5 (about
    21 neighbours). Tests share it, so that their lists have the same
    capacities and reuse one compiled search per configuration."""
    return uniform(300, SIDE, 1)


# ---------------------------------------------------------------------------
# Predicates


def test_predicates_decide_clear_cases_and_leave_ties_undecided():
    a, b, c = (jnp.array(p, jnp.float64) for p in ([0., 0.], [1., 0.],
                                                     [0., 1.]))
    det, bound = delaunay.orient(a, b, c)
    assert det > bound
    det, bound = delaunay.orient(a, c, b)
    assert det < -bound
    # Collinear: exactly zero, undecided.
    det, bound = delaunay.orient(a, b, jnp.array([3., 0.]))
    assert abs(det) <= bound
    # Cocircular (the unit square's corners): undecided, so no flip.
    d = jnp.array([1., 1.])
    det, bound = delaunay.incircle(a, b, d, c)
    assert abs(det) <= bound
    det, _ = delaunay.incircle(a, b, c, jnp.array([0.4, 0.4]))
    assert det > 0
    det, bound = delaunay.incircle(a, b, c, jnp.array([2., 2.]))
    assert det < -bound
    # Nearly collinear at 1e8 scale: the bound grows with the inputs.
    big = jnp.array([1e8, 1e8])
    det, bound = delaunay.orient(a + big, b + big,
                                 jnp.array([2., 1e-9]) + big)
    assert abs(det) <= bound


# ---------------------------------------------------------------------------
# Exactness


@pytest.mark.parametrize("periodic,fmt", [
    (True, partition.Dense),
    pytest.param(True, partition.Sparse, marks=pytest.mark.slow),
    (False, partition.OrderedSparse)])
def test_random_scene_and_a_jitted_move_are_exact(periodic, fmt):
    side, cutoff = SIDE, CUTOFF
    R = scene()
    fns, update = factory(periodic, side, cutoff, fmt)
    nbrs = fns.allocate(R)
    assert isinstance(nbrs, partition.NeighborList)
    assert isinstance(nbrs, StatefulNeighborList)
    assert_exact(nbrs, R, cutoff, side, periodic, fmt)
    step = 0.05 * jnp.asarray(np.random.default_rng(2).normal(size=R.shape))
    R2 = jnp.mod(R + step, side) if periodic else R + step
    nbrs = update(R2, nbrs)
    assert_exact(nbrs, R2, cutoff, side, periodic, fmt)
    s = delaunay.stats(nbrs)
    assert s["flips"] > 0 and not s["failed"]


@pytest.mark.parametrize("periodic", [
    True, pytest.param(False, marks=pytest.mark.slow)])
def test_square_lattice_with_ties_at_the_cutoff(periodic):
    """Every square of the lattice is cocircular and every row collinear;
    the cutoffs sit exactly on lattice distances (2 is excluded, strict;
    sqrt(5)**2 rounds to 5 + 1 ulp, so d^2 = 5 is included, as brute force
    says). The move off the lattice brings the points at distance 2 inside
    the radius, so the buffers get head-room."""
    side = 12.0
    g = np.arange(12.0)
    R = jnp.asarray(np.stack(np.meshgrid(g, g, indexing="ij"),
                             -1).reshape(-1, 2))
    for cutoff in (2.0,) if periodic else (np.sqrt(5.0),):
        fns, update = factory(periodic, side, float(cutoff),
                              capacity_multiplier=2.0)
        nbrs = fns.allocate(R)
        assert_exact(nbrs, R, cutoff, side, periodic)
        # The lattice, then a tiny move off it: maintenance from ties.
        R2 = R + 1e-3 * jnp.asarray(
            np.random.default_rng(3).normal(size=R.shape))
        R2 = jnp.mod(R2, side) if periodic else R2
        nbrs = update(R2, nbrs)
        assert_exact(nbrs, R2, cutoff, side, periodic)


@pytest.mark.parametrize("periodic", [
    True, pytest.param(False, marks=pytest.mark.slow)])
def test_many_small_moves_in_a_scan(periodic):
    """A random walk of 60 steps inside one lax.scan (every step a
    rebuild: no skin); the triangulation travels with the list."""
    side, cutoff = SIDE, CUTOFF
    R = scene()
    fns, _ = factory(periodic, side, cutoff)
    nbrs = fns.allocate(R)
    keys = jax.random.split(jax.random.PRNGKey(0), 60)

    def body(carry, key):
        R, nbrs = carry
        R = R + 0.02 * jax.random.normal(key, R.shape, R.dtype)
        if periodic:
            R = jnp.mod(R, side)
        nbrs = nbrs.update(R)
        return (R, nbrs), delaunay.Triangulation(*nbrs.backend_state).flips

    (R, nbrs), flips = jax.jit(lambda c: jax.lax.scan(body, c, keys))(
        (R, nbrs))
    assert_exact(nbrs, R, cutoff, side, periodic)
    s = delaunay.stats(nbrs)
    assert s["flips_total"] == int(np.sum(flips)) + int(
        np.asarray(fns.allocate(scene()).backend_state.flips))
    assert s["rebuilds"] == 0  # small moves never need one
    assert int(np.sum(flips)) > 0


def test_a_move_across_several_edges_is_split():
    """One particle jumps 2.2 (about 4 spacings) across several triangles:
    the displacement is split (Fig 5), and the list is still exact."""
    side, cutoff = SIDE, CUTOFF
    R = scene()
    fns, update = factory(True, side, cutoff)
    nbrs = fns.allocate(R)
    R2 = R.at[7].set(jnp.mod(R[7] + jnp.array([2.0, 1.0]), side))
    nbrs = update(R2, nbrs)
    assert_exact(nbrs, R2, cutoff, side, True)
    s = delaunay.stats(nbrs)
    assert s["splits"] >= 1 and s["rebuilds"] == 0


@pytest.mark.slow
def test_skin_keeps_the_list_until_half_the_skin_then_maintains():
    side, cutoff, skin = SIDE, CUTOFF, 0.4
    R = scene()
    fns, update = factory(True, side, cutoff, skin=skin)
    nbrs = fns.allocate(R)
    small = jnp.mod(R + 0.05, side)
    kept = update(small, nbrs)
    assert np.array_equal(np.asarray(kept.reference_position), np.asarray(R))
    big = jnp.mod(R + 0.3 * jnp.asarray(
        np.random.default_rng(7).normal(size=R.shape)), side)
    moved = update(big, kept)
    assert_exact(moved, big, cutoff, side, True)


@pytest.mark.slow
def test_custom_mask_and_a_rectangular_torus():
    """custom_mask_function goes through the stateful search (Sparse after
    the mask); a rectangular torus (10 x 6) is exact too."""
    R = scene()

    def mask(idx):  # keep pairs of opposite parity only
        i = jnp.arange(idx.shape[0])[:, None]
        return jnp.where(idx % 2 == i % 2, idx.shape[0], idx)
    fns = jaxrt.neighbor_list(space.periodic(SIDE)[0], SIDE, CUTOFF,
                              backend="delaunay", custom_mask_function=mask,
                              format=partition.Sparse)
    nbrs = fns.allocate(R)
    R2 = jnp.mod(R + 0.03, SIDE)
    nbrs = jax.jit(fns.update)(R2, nbrs)
    want = {(i, j) for i, j in brute_pairs(np.asarray(R2), CUTOFF, SIDE, True)
            if i % 2 != j % 2}
    assert not nbrs.did_buffer_overflow and list_pairs(nbrs) == want
    box = np.array([10.0, 6.0])
    R3 = uniform(200, 1.0, 2) * box
    fns = jaxrt.neighbor_list(space.periodic(jnp.asarray(box))[0], box, 1.2,
                              backend="delaunay")
    assert_exact(fns.allocate(R3), R3, 1.2, box, True)


# ---------------------------------------------------------------------------
# Rebuilds, overflow, errors


def test_free_space_point_leaving_the_frame_rebuilds_and_counts():
    side, cutoff = SIDE, CUTOFF
    R = scene()
    fns, update = factory(False, side, cutoff, partition.Dense)
    nbrs = fns.allocate(R)
    safe = np.asarray(nbrs.backend_state.safe)
    far = R.at[3].set(jnp.asarray(safe[1] + 1.0))  # out of the safe box
    nbrs = update(far, nbrs)
    assert_exact(nbrs, far, cutoff, side, False)
    assert delaunay.stats(nbrs)["rebuilds"] == 1
    # The new frame holds the far particle; a small move is maintenance.
    near = far + 0.01
    nbrs = update(near, nbrs)
    assert_exact(nbrs, near, cutoff, side, False)
    assert delaunay.stats(nbrs)["rebuilds"] == 1


def test_no_convergence_within_the_split_cap_rebuilds():
    """max_splits=1: a move that needs a split cannot be maintained, so
    the triangulation is rebuilt from scratch (host round trip)."""
    side, cutoff = SIDE, CUTOFF
    R = scene()
    fns, update = factory(True, side, cutoff, max_splits=1)
    nbrs = fns.allocate(R)
    R2 = R.at[7].set(jnp.mod(R[7] + jnp.array([2.0, 1.0]), side))
    nbrs = update(R2, nbrs)
    assert_exact(nbrs, R2, cutoff, side, True)
    assert delaunay.stats(nbrs)["rebuilds"] == 1


def test_overflow_is_flagged():
    side, cutoff = SIDE, CUTOFF
    R = scene()
    fns, update = factory(True, side, cutoff)
    nbrs = fns.allocate(R)
    # Squeeze everything into a quarter of the box: 4x the neighbours.
    R2 = R / 2
    nbrs2 = update(R2, nbrs)
    assert nbrs2.did_buffer_overflow
    assert int(np.asarray(nbrs2.error.code)) & ErrorCode.NEIGHBOR_LIST_OVERFLOW


def test_coincident_points_are_refused_at_allocate_and_flagged_under_jit():
    side, cutoff = SIDE, CUTOFF
    R = scene()
    fns, update = factory(True, side, cutoff)
    with pytest.raises(ValueError, match="particles 4 and 11 are at the "
                       "same position"):
        fns.allocate(R.at[11].set(R[4]))
    nbrs = update(R.at[11].set(R[4]), fns.allocate(R))
    code = int(np.asarray(nbrs.error.code))
    assert code & ErrorCode.SEARCH_FAILED and nbrs.did_buffer_overflow
    with pytest.raises(jaxrt.NeighborListError, match="delaunay"):
        jaxrt.check(nbrs)


def test_bad_input_is_refused_naming_the_fix():
    disp, _ = space.free()
    R = uniform(50, 5.0, 11)
    fns = jaxrt.neighbor_list(disp, 5.0, 1.0, backend="delaunay")
    with pytest.raises(TypeError, match="float64"):
        fns.allocate(R.astype(jnp.float32))
    with pytest.raises(ValueError, match="2D"):
        fns.allocate(jnp.zeros((50, 3)) + jnp.arange(50.)[:, None])
    def slab(ra, rb):  # periodic along x only
        d = ra - rb
        return d.at[0].set(d[0] - 5.0 * jnp.round(d[0] / 5.0))
    mixed = jaxrt.neighbor_list(slab, 5.0, 1.0, backend="delaunay",
                                periodic=(True, False))
    with pytest.raises(ValueError, match="both axes periodic"):
        mixed.allocate(R)
    with pytest.raises(ValueError, match="max_splits"):
        jaxrt.backends.Delaunay(max_splits=0)
    other = jaxrt.neighbor_list(disp, 5.0, 1.0, backend="brute")
    with pytest.raises(TypeError, match="state"):
        fns.update(R, other.allocate(R))


# ---------------------------------------------------------------------------
# The Boids scene


def test_boids_scene_runs_with_lists_checked_against_brute_force(tmp_path):
    from jaxrt import sim
    from jaxrt.tools import cli
    scene = sim.builtin("boids", n=300)
    rule = scene.effect("boids")
    summary = cli.run(scene, steps=8, out=tmp_path, chunk=4, check_brute=True)
    assert summary["brute_checks"] == 3  # at the start and after each chunk
    assert summary["overflows"] == 0
    assert summary["triangulation"]["rebuilds"] == 0
    assert (tmp_path / "triangulation.png").stat().st_size > 0
    v = np.load(tmp_path / "snapshots.npz")["velocity"]
    speed = np.linalg.norm(v, axis=1)
    # Soft limits (the effect's docstring): within about 12%.
    assert speed.min() > 0.85 * rule.min_speed
    assert speed.max() < 1.15 * rule.max_speed


def test_boids_rules_on_two_boids():
    """Cohesion pulls together, alignment matches velocities, separation
    pushes apart below R_s; speeds inside the limits feel nothing else."""
    from jaxrt import sim
    rule = sim.Boids(cohesion=1.0, alignment=1.0, separation=0.0)
    pos = np.array([[1.0, 1.0], [1.5, 1.0], [4.0, 4.0]])
    vel = np.array([[0.6, 0.0], [0.0, 0.8], [0.7, 0.0]])
    scene = sim.Scene(
        particles=sim.make_particles(positions=pos, velocities=vel),
        box=sim.Box((8.0, 8.0), ("periodic", "periodic")),
        effects=(rule,), integrator=sim.Integrator(dt=0.01),
        neighbors=sim.Neighbors(backend="brute", skin=0.1, format="Dense"),
        dtype="float64")
    c = sim.compile_scene(scene)
    state, nbrs = c.init()
    a = np.asarray(state.accel)
    # Boid 0 sees boid 1 (0.5 away): cohesion +0.5 x, alignment (-0.6, 0.8).
    np.testing.assert_allclose(a[0], [0.5 - 0.6, 0.8], atol=1e-12)
    np.testing.assert_allclose(a[1], [-0.5 + 0.6, -0.8], atol=1e-12)
    np.testing.assert_allclose(a[2], [0.0, 0.0], atol=1e-12)  # alone
    sep = sim.Boids(cohesion=0.0, alignment=0.0, separation=0.01,
                    separation_radius=0.6)
    state, _ = sim.compile_scene(dataclasses_replace(scene, effects=(sep,))
                                 ).init()
    a = np.asarray(state.accel)
    np.testing.assert_allclose(a[0], [-0.01 / 0.5, 0.0], atol=1e-12)
    np.testing.assert_allclose(a[1], [0.01 / 0.5, 0.0], atol=1e-12)


def dataclasses_replace(obj, **kw):
    import dataclasses
    return dataclasses.replace(obj, **kw)
