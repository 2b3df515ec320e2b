"""The Warp Delaunay engine (`jaxrt.backends.rt.delaunay_kernels`,
`jaxrt.backends.rt.delaunay_engine`) on the GPU where one is visible,
else on Warp's CPU device, against float64 oracles: the empty-circumcircle property after the flips (every vertex
against every triangle), the pair set of the radius BFS against a float64
brute force (random, square lattices with cocircular points and ties at the
cutoff, clusters, Boids-like and random moves; torus and free space),
overflow, local repair against a fresh triangulation, and the warp engine
against the xla engine through `jaxrt.neighbor_list`."""
from __future__ import annotations

import numpy as np
import pytest

wp = pytest.importorskip("warp")

from jaxrt.backends.delaunay import FRAME, host_triangulate  # noqa: E402
from jaxrt.backends.rt import delaunay_engine as engine  # noqa: E402
from jaxrt.backends.rt import delaunay_kernels as kernels  # noqa: E402

# The engine runs where its users run it: on the GPU when one is visible.
DEVICE = "cuda:0" if wp.is_cuda_available() else "cpu"

wp.config.quiet = True
EPS = 2.0 ** -53


def brute(points, cutoff, side=None):
    """(i, j), i != j, with jax-md's periodic displacement, float64."""
    d = points[:, None, :] - points[None, :, :]
    if side is not None:
        d = np.mod(d + side / 2, side) - side / 2
    d2 = d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1]
    i, j = np.nonzero(d2 < cutoff * cutoff)
    return {(a, b) for a, b in zip(i.tolist(), j.tolist()) if a != b}


def triangulate(points, cutoff, side=None):
    pos, tri, twin, shift, safe, ok = host_triangulate(points, side, cutoff)
    assert ok
    return engine.mesh(pos, tri, twin, shift, n=len(points), side=side,
                       safe=safe, device=DEVICE)


def assert_delaunay(m: engine.Mesh):
    """Every triangle positive, and no vertex (nor any image of it within
    one period) certainly inside any triangle's circumcircle (float64
    in-circle with Shewchuk's bound: cocircular points are allowed)."""
    h = m.numpy()
    L = m.side
    c = h["position"][h["tri"]] + h["shift"] * L  # (T, 3, 2)
    a, b, cc = c[:, 0], c[:, 1], c[:, 2]
    det = (a[:, 0] - cc[:, 0]) * (b[:, 1] - cc[:, 1]) - \
        (a[:, 1] - cc[:, 1]) * (b[:, 0] - cc[:, 0])
    assert np.all(det > 0)
    images = [np.array([sx, sy]) for sx in (-1, 0, 1) for sy in (-1, 0, 1)] \
        if m.periodic else [np.zeros(2)]
    for s in images:
        d = (h["position"] + s * L)[None, :, :]  # (1, V, 2)
        ad, bd, cd = a[:, None] - d, b[:, None] - d, cc[:, None] - d
        lift = lambda x: x[..., 0] ** 2 + x[..., 1] ** 2  # noqa: E731
        cross = lambda x, y: x[..., 0] * y[..., 1] - y[..., 0] * x[..., 1]  # noqa: E731,E501
        terms = (lift(ad) * cross(bd, cd), lift(bd) * cross(cd, ad),
                 lift(cd) * cross(ad, bd))
        det = sum(terms)
        perm = sum(np.abs(t) for t in terms)
        # A generous bound (far above Shewchuk's 10 eps): only certain
        # violations count.
        assert not np.any(det > 64 * EPS * perm), "not Delaunay"


def pairs_of(m, cutoff, points=None, width=64, capacity=100_000):
    pts = (None if points is None
           else wp.array(points, dtype=wp.vec2d, device=DEVICE))
    s = engine.radius_search(m, cutoff, width=width, pair_capacity=capacity,
                             points=pts)
    assert not s.overflow()
    pairs = s.pair_set()
    found, count = s.found.numpy(), s.count.numpy()
    rows = {(v, int(w)) for v in range(m.n) for w in found[v, 1:count[v]]}
    assert rows == pairs  # the rows and the pair buffer agree
    assert int(s.pair_count.numpy()[0]) == len(pairs)  # each pair once
    return pairs


def lattice(k, spacing=1.0):
    x, y = np.meshgrid(np.arange(k), np.arange(k))
    return np.stack([x.ravel(), y.ravel()], 1).astype(np.float64) * spacing


def clusters(n, side, seed):
    rng = np.random.default_rng(seed)
    centres = rng.uniform(0.2 * side, 0.8 * side, (5, 2))
    return centres[rng.integers(0, 5, n)] + rng.normal(0, 0.05 * side, (n, 2))


SIDE = np.array([10.0, 10.0])


def test_stretched_triangulation_is_flipped_to_delaunay():
    # The Delaunay triangulation of the points stretched 4x along x is a
    # valid but far from Delaunay triangulation of the points themselves:
    # the flips must fix it (many rounds, many conflicts).
    rng = np.random.default_rng(3)
    pts = rng.uniform(0, 10, (250, 2))
    stretch = np.array([4.0, 1.0])
    pos, tri, twin, shift, safe, ok = host_triangulate(pts * stretch, None,
                                                       1.0)
    assert ok
    pos = pos / stretch  # frame included: orientation is kept
    m = engine.mesh(pos, tri, twin, shift, n=250, safe=safe, device=DEVICE)
    flips, done = engine.flip_to_delaunay(m, max_rounds=256,
                                          rounds_per_read=16)
    assert done and flips > 100
    assert_delaunay(m)
    assert pairs_of(m, 1.2) == brute(pts, 1.2)


@pytest.mark.parametrize("periodic", [True, False])
def test_random_scene_is_exact(periodic):
    pts = np.random.default_rng(1).uniform(0, 10, (300, 2))
    side = SIDE if periodic else None
    m = triangulate(pts, 1.5, side)
    assert engine.flip_to_delaunay(m)[1]
    assert_delaunay(m)
    assert pairs_of(m, 1.5) == brute(pts, 1.5, side)


@pytest.mark.parametrize("periodic", [True, False])
@pytest.mark.parametrize("cutoff", [1.0, np.sqrt(2.0), 2.0, np.sqrt(5.0)])
def test_square_lattice_with_cocircular_points_and_ties(periodic, cutoff):
    # Every unit square's corners are cocircular; the cutoffs sit exactly on
    # lattice distances (ties decided by < in float64, as brute force).
    pts = lattice(12)
    side = np.array([12.0, 12.0]) if periodic else None
    m = triangulate(pts, cutoff, side)
    assert engine.flip_to_delaunay(m)[1]
    assert_delaunay(m)
    assert pairs_of(m, cutoff) == brute(pts, cutoff, side)


def test_clusters_are_exact():
    pts = clusters(300, 10.0, 5)
    m = triangulate(pts, 0.6)
    assert engine.flip_to_delaunay(m)[1]
    assert_delaunay(m)
    assert pairs_of(m, 0.6, width=128) == brute(pts, 0.6)


def test_overflow_is_flagged():
    pts = np.random.default_rng(1).uniform(0, 10, (300, 2))
    m = triangulate(pts, 1.5, SIDE)
    want = brute(pts, 1.5, SIDE)
    rows = engine.radius_search(m, 1.5, width=4)
    assert rows.overflow()
    few = engine.radius_search(m, 1.5, width=64, pair_capacity=len(want) - 1)
    assert few.overflow()
    assert int(few.pair_count.numpy()[0]) == len(want)  # counted past it
    enough = engine.radius_search(m, 1.5, width=64,
                                  pair_capacity=len(want))
    assert not enough.overflow() and enough.pair_set() == want


def boids_move(pts, vel, side, rng, dt=0.05, radius=1.0):
    """A small Boids step (alignment, cohesion, separation), float64."""
    d = pts[None] - pts[:, None]
    d = np.mod(d + side / 2, side) - side / 2
    r2 = np.sum(d * d, -1)
    near = (r2 < radius ** 2) & (r2 > 0)
    cnt = np.maximum(near.sum(1, keepdims=True), 1)
    align = (near @ vel) / cnt - vel
    cohesion = np.sum(near[..., None] * d, 1) / cnt
    separate = -np.sum((near & (r2 < 0.09))[..., None] * d, 1)
    vel = vel + dt * (align + 0.5 * cohesion + 2 * separate) + \
        0.01 * rng.normal(size=vel.shape)
    speed = np.linalg.norm(vel, axis=1, keepdims=True)
    vel = vel / speed * np.clip(speed, 0.5, 1.0)
    return np.mod(pts + dt * vel, side), vel


@pytest.mark.parametrize("motion,per_read", [("boids", None), ("random", 5)])
def test_local_repair_matches_brute_force_and_a_fresh_triangulation(
        motion, per_read):
    # per_read=5: flip rounds batched without host reads (the GPU's way),
    # ending mid-batch and across batches.
    rng = np.random.default_rng(7)
    pts = rng.uniform(0, 10, (300, 2))
    vel = rng.normal(size=pts.shape)
    m = triangulate(pts, 1.0, SIDE)
    repairs = 0
    for _ in range(6):
        if motion == "boids":
            pts, vel = boids_move(pts, vel, SIDE, rng)
        else:
            pts = np.mod(pts + 0.05 * rng.normal(size=pts.shape), SIDE)
        r = engine.maintain(m, wp.array(pts, dtype=wp.vec2d, device=DEVICE),
                            rounds_per_read=per_read)
        assert r.ok
        repairs += r.flips
        assert_delaunay(m)
        got = pairs_of(m, 1.0, points=pts)
        assert got == brute(pts, 1.0, SIDE)
        fresh = triangulate(pts, 1.0, SIDE)
        assert engine.flip_to_delaunay(fresh)[1]
        assert got == pairs_of(fresh, 1.0, points=pts)
    assert repairs > 0  # the moves did need flips


def test_tangling_moves_are_repaired_on_the_device_by_split_steps():
    # Moves of half a spacing invert triangles that no flip can undo: the
    # repair must go back to the last valid triangulation and bisect the
    # tangled vertices' steps (splits > 0), with no rebuild, and end exact.
    rng = np.random.default_rng(11)
    pts = rng.uniform(0, 10, (300, 2))
    m = triangulate(pts, 1.0, SIDE)
    splits = 0
    for per_read in (None, 4):
        pts = np.mod(pts + 0.5 * rng.normal(size=pts.shape), SIDE)
        r = engine.maintain(m, wp.array(pts, dtype=wp.vec2d, device=DEVICE),
                            rounds_per_read=per_read)
        assert r.ok and r.tries > r.splits
        splits += r.splits
        assert_delaunay(m)
        assert pairs_of(m, 1.0, points=pts) == brute(pts, 1.0, SIDE)
    assert splits > 0


@pytest.mark.parametrize("periodic", [True, False])
def test_tries_after_a_success_test_only_the_moving_vertices(periodic):
    # Large moves: the first tries fail, one succeeds with the tangled
    # vertices short of their move, and the tries after it start from that
    # checked triangulation, testing and checking only the triangles of the
    # vertices still moving (seeded). The end must still be exact, on a
    # lattice with cocircular points moved off it partly.
    rng = np.random.default_rng(5)
    g = np.arange(16) * 0.625 + 0.3
    pts = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    side = SIDE if periodic else None
    m = triangulate(pts, 1.0, side)
    frame = m.position.numpy()[pts.shape[0]:]
    seeded = 0
    for _ in range(3):
        move = 0.35 * rng.normal(size=pts.shape)
        move[rng.random(len(pts)) < 0.3] = 0.0  # some stay on the lattice
        pts = pts + move
        pts = np.mod(pts, SIDE) if periodic else np.clip(pts, 0.05, 9.95)
        target = np.concatenate([pts, frame])
        r = engine.maintain(m, wp.array(target, dtype=wp.vec2d,
                                        device=DEVICE))
        assert r.ok
        seeded += r.seeded
        assert_delaunay(m)
        assert pairs_of(m, 1.0, points=pts) == brute(pts, 1.0, side)
    assert seeded > 0


def test_free_space_repair_and_a_point_leaving_the_frame_rebuilds():
    rng = np.random.default_rng(8)
    pts = rng.uniform(0, 10, (200, 2))
    m = triangulate(pts, 1.0)
    frame = m.position.numpy()[-FRAME:]
    for _ in range(3):
        pts = pts + 0.05 * rng.normal(size=pts.shape)
        target = wp.array(np.concatenate([pts, frame]), dtype=wp.vec2d,
                      device=DEVICE)
        st = engine.step(m, target, lambda p: host_triangulate(p, None, 1.0))
        assert not st.rebuilt and not st.failed
        assert pairs_of(m, 1.0, points=pts) == brute(pts, 1.0)
    pts[0] = [1e3, 1e3]  # far outside the safe box
    target = wp.array(np.concatenate([pts, frame]), dtype=wp.vec2d,
                      device=DEVICE)
    st = engine.step(m, target, lambda p: host_triangulate(p, None, 1.0))
    assert st.rebuilt and not st.failed
    assert_delaunay(m)
    assert pairs_of(m, 1.0, points=pts) == brute(pts, 1.0)


@pytest.fixture
def x64():
    jax = pytest.importorskip("jax")
    before = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)
    yield jax
    jax.config.update("jax_enable_x64", before)


def dense_pairs(nbrs, n):
    idx = np.asarray(nbrs.idx)
    i, k = np.nonzero(idx < n)
    return set(zip(i.tolist(), idx[i, k].tolist()))


def test_bad_engine_options_are_refused():
    import jaxrt
    with pytest.raises(ValueError, match="engine"):
        jaxrt.backends.Delaunay(engine="cuda")
    with pytest.raises(ValueError, match="local_repair"):
        jaxrt.backends.Delaunay(local_repair=1)


def test_warp_engine_without_local_repair_rebuilds_every_step(x64):
    jax = x64
    import jax.numpy as jnp
    from jax_md import partition, space
    import jaxrt
    rng = np.random.default_rng(4)
    R = jnp.asarray(rng.uniform(0, 10, (200, 2)))
    fns = jaxrt.neighbor_list(
        space.free()[0], 10.0, 1.2, format=partition.Dense, periodic=False,
        backend=jaxrt.backends.Delaunay(engine="warp", local_repair=False))
    nbrs = fns.allocate(R)
    before = jaxrt.backends.delaunay.stats(nbrs)["rebuilds"]
    update = jax.jit(fns.update)
    for _ in range(3):
        R = R + 0.05 * jnp.asarray(rng.normal(size=R.shape))
        nbrs = update(R, nbrs)
        assert not nbrs.did_buffer_overflow
        assert dense_pairs(nbrs, 200) == brute(np.asarray(R), 1.2)
    assert jaxrt.backends.delaunay.stats(nbrs)["rebuilds"] == before + 3


@pytest.mark.slow  # compiles the XLA engine (about 20 s on 2 CPU cores)
def test_warp_and_xla_engines_give_the_same_lists(x64):
    jax = x64
    from jax_md import partition, space
    import jaxrt
    import jax.numpy as jnp
    rng = np.random.default_rng(2)
    R = jnp.asarray(lattice(14, 10.0 / 14) + 1e-3 * rng.normal(
        size=(196, 2)))
    disp, _ = space.periodic(10.0)
    lists, updates = {}, {}
    for name in ("xla", "warp"):
        fns = jaxrt.neighbor_list(
            disp, 10.0, 1.1, format=partition.Dense, periodic=True,
            backend=jaxrt.backends.Delaunay(engine=name))
        lists[name] = fns.allocate(R)
        updates[name] = jax.jit(fns.update)
    for step in range(3):
        got = {}
        for name in lists:
            assert not lists[name].did_buffer_overflow
            got[name] = dense_pairs(lists[name], 196)
        assert got["xla"] == got["warp"] == brute(
            np.asarray(R), 1.1, SIDE)
        R = jnp.mod(R + 0.03 * jnp.asarray(rng.normal(size=R.shape)),
                    10.0)
        for name in lists:
            lists[name] = updates[name](R, lists[name])
    stats = jaxrt.backends.delaunay.stats(lists["warp"])
    assert stats["flips_total"] > 0 and not stats["failed"]
    assert stats == jaxrt.backends.delaunay.stats(lists["xla"])


@wp.kernel
def _displacements(xi: wp.array(dtype=wp.vec2d), xj: wp.array(dtype=wp.vec2d),
                   L: wp.vec2d, out: wp.array(dtype=wp.vec2d)):
    t = wp.tid()
    out[t] = kernels.displacement(xi[t], xj[t], L, 1)


def test_periodic_displacement_is_jax_mds_bit_for_bit():
    # The kernels' displacement skips the fmod where its result is known;
    # it must still equal jnp.mod(d + L/2, L) - L/2 (numpy's np.mod, the
    # same rounding) in every bit: wrapped positions, unwrapped ones (the
    # fmod fallback), and at and near the edges s = -L, 0, L, 2L of the
    # fast path.
    rng = np.random.default_rng(3)
    L = np.array([7.3, 10.0])
    xi = rng.uniform(-3, 4, (4000, 2)) * L
    xj = rng.uniform(0, 1, (4000, 2)) * L
    xi[:2000] = rng.uniform(0, 1, (2000, 2)) * L  # wrapped pairs
    edges = np.array([-1.0, 0.0, 1.0, 2.0])
    edges = np.concatenate([edges, np.nextafter(edges, 9),
                            np.nextafter(edges, -9)])
    xj[:len(edges)] = 0.0
    xi[:len(edges)] = edges[:, None] * L - L / 2  # s = d + L/2 at the edges
    got = wp.zeros(len(xi), dtype=wp.vec2d, device=DEVICE)
    wp.launch(_displacements, dim=len(xi), device=DEVICE,
              inputs=[wp.array(xi, dtype=wp.vec2d, device=DEVICE),
                      wp.array(xj, dtype=wp.vec2d, device=DEVICE),
                      wp.vec2d(*L), got])
    want = np.mod(xi - xj + L / 2, L) - L / 2
    assert np.array_equal(got.numpy().view(np.int64), want.view(np.int64))
