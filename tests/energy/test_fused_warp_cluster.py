"""The Warp engine's cluster walk (``Cell(kernel="warp", walk="cluster")``,
`jaxrt.backends.cell.warp_cluster`) against the thread walk and
``backend="brute"`` in float64: energies, forces, pair counts, sigma /
epsilon gradients and radii; periodic, free and slab boxes, small periodic
boxes whose stencils alias, coincident particles, pairs at the cutoff and
cells of more particles than a cluster holds; the cluster table against
NumPy; every cluster size, with and without the bounding-box test.

Tolerances: against brute force as tests/energy/test_fused_warp.py
(float64: ``1e-12`` of the energy, ``1e-10`` of the largest force; float32
against the float64 reference: ``rtol = 1e-4`` on energies, ``2e-3`` of the
largest force). Against the thread walk: each particle adds the same terms
in the same order, so on the CPU (where both compile alike) every output is
equal bit for bit, in float32 too; elsewhere the float64 tolerance above
(a compiler may contract the two loops' arithmetic differently), and for
the Warp kernels launched alone on CUDA ``1e-5`` (float32) / ``1e-12``
(float64) of the largest entry. Pair
counts and cluster tables are integers and equal exactly.
"""
from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scenes import GEOMETRIES, fluid

wp = pytest.importorskip("warp")

from jaxrt.backends.cell import warp_cluster, warp_kernels as wk  # noqa: E402
from jaxrt.backends.cell import warp_cluster_native  # noqa: E402
from jaxrt.energy import lennard_jones_fused  # noqa: E402
from jaxrt.energy.listfree.lj import CellSums  # noqa: E402
from lj_cases import (check_descent_in_scan_2d, check_sums,  # noqa: E402
                      close)

E_RTOL, F_RTOL = 1e-12, 1e-10
REACHES = ((4, 2), (1, 1))
CPU = jax.default_backend() == "cpu"


# The Warp kernels alone run where Warp's walks are meant to: the GPU when
# there is one (a slim Warp build may also lack the CPU compiler there).
DEVICE = "cuda:0" if wp.get_cuda_device_count() > 0 else "cpu"
# Warp's CPU compiler (LLVM), absent from slim builds: without it no kernel
# not already in Warp's cache can be launched on "cpu".
CPU_COMPILER = wp.is_cpu_available()
# Float outputs of two walks on CUDA: the same terms in the same order, but
# NVCC may contract each loop's arithmetic into FMAs differently, a few
# rounding steps per pair over ~100 pairs a particle (of the largest entry).
KERNEL_RTOL = {np.dtype(np.float32): 1e-5, np.dtype(np.float64): 1e-12}


def same_outputs(a, b, err_msg="", device=DEVICE):
    """One walk's outputs (forces, energy, d_sigma, d_epsilon, count) ==
    another's: bit for bit on Warp's CPU; on CUDA the count exactly and
    floats to `KERNEL_RTOL` of the largest entry."""
    for x, y in zip(a, b):
        if device == "cpu" or x.dtype.kind == "i":
            np.testing.assert_array_equal(x, y, err_msg=err_msg)
        else:
            scale = max(float(np.max(np.abs(y), initial=0.0)), 1e-300)
            np.testing.assert_allclose(
                x, y, rtol=0, atol=KERNEL_RTOL[np.dtype(y.dtype)] * scale,
                err_msg=err_msg)


def same(a, b, rtol=E_RTOL):
    """Equal bit for bit on the CPU, else to ``rtol`` of the largest."""
    if CPU:
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    else:
        close(a, b, rtol)


def engines(geometry, side, reach, cluster_size=8, **kw):
    """(cluster, thread, brute) energies for one box."""
    displacement, box, periodic = GEOMETRIES[geometry](side)
    backends = (CellSums(kernel="warp", reach=reach, walk="cluster",
                         cluster_size=cluster_size),
                CellSums(kernel="warp", reach=reach), "brute")
    return tuple(lennard_jones_fused(displacement, box, backend=b,
                                     periodic=periodic, **kw)
                 for b in backends)


def check(R, geometry, side, reach, cluster_size=8, **kw):
    cluster, thread, brute = engines(geometry, side, reach, cluster_size,
                                     **kw)
    s, u, t = cluster.sums(R), thread.sums(R), brute.sums(R)
    assert int(s.count) == int(u.count)
    for name in ("energy", "forces", "d_sigma", "d_epsilon"):
        same(getattr(s, name), getattr(u, name))
    check_sums(s, t, E_RTOL, F_RTOL)
    return cluster, brute, s


@pytest.mark.parametrize("reach", REACHES)
@pytest.mark.parametrize("geometry", ["periodic", "free", "slab"])
def test_matches_thread_walk_and_brute_float64(x64, geometry, reach):
    R, side = fluid()
    R = jnp.asarray(R)
    cluster, brute, s = check(R, geometry, side, reach)
    assert int(s.count) > 0
    close(jax.grad(cluster)(R), -brute.sums(R).forces, F_RTOL)


@pytest.mark.parametrize("reach", REACHES)
@pytest.mark.parametrize("side_over_cutoff", [2.05, 2.6, 3.4, 7.0])
def test_small_periodic_boxes_alias_no_pair(x64, side_over_cutoff, reach):
    side = side_over_cutoff * 2.5
    n = max(8, int(0.5 * side ** 3))
    R = jnp.asarray(np.random.default_rng(3).uniform(0, side, (n, 3)))
    check(R, "periodic", side, reach)


@pytest.mark.parametrize("reach, cluster_size", [((4, 2), 8), ((1, 1), 8),
                                                 ((1, 1), 4), ((2, 1), 16)])
def test_crowded_cells_coincident_and_cutoff_pairs(x64, reach, cluster_size):
    """Cells of up to ~40 particles (clusters of 8 and a remainder), five
    copies of one point, a pair exactly at the cutoff, one inside the
    switch and one across the x face."""
    side = 10.0
    rng = np.random.default_rng(7)
    crowd = rng.uniform(3.0, 4.6, (60, 3))   # one to a few coarse cells
    fixed = np.asarray([[1.0, 1.0, 1.0]] * 5 +             # coincident
                       [[5.0, 8.0, 8.0], [7.5, 8.0, 8.0],  # exactly r_cutoff
                        [1.0, 8.0, 1.0], [2.2, 8.0, 1.0],  # in the switch
                        [9.9, 3.0, 8.0], [0.3, 3.0, 8.0]])  # across x
    R = jnp.asarray(np.concatenate([crowd, fixed]))
    _, brute, s = check(R, "periodic", side, reach, cluster_size)
    # The crowd's pairs, the 10 coincident ones, the switch and face pairs.
    d = crowd[:, None] - crowd[None]
    crowd_pairs = (np.sum((np.sum(d * d, -1) < 2.5 ** 2)) - 60) // 2
    assert int(s.count) == crowd_pairs + 10 + 2


@pytest.mark.parametrize("geometry", ["slab", "periodic"])
def test_radii_and_parameter_gradients(x64, geometry):
    R, side = fluid(n_side=5, density=0.4)
    R = jnp.asarray(R)
    radii = jnp.asarray(np.random.default_rng(1).uniform(0.8, 2.6, len(R)))
    cluster, brute, _ = check(R, geometry, side, (1, 1), radii=radii)
    check(R, geometry, side, (4, 2), radii=radii * 0.9)
    close(jax.grad(cluster)(R), jax.grad(brute)(R), F_RTOL)
    for name in ("sigma", "epsilon"):
        value = jnp.asarray(0.95 if name == "sigma" else 1.3)
        g = jax.grad(lambda v: cluster(R, **{name: v}))(value)
        close(g, jax.grad(lambda v: brute(R, **{name: v}))(value), E_RTOL)


def test_float32_within_tolerance_and_jit(x64):
    R, side = fluid(n_side=7)
    cluster, thread, brute = engines("periodic", side, (1, 1))
    R32 = jnp.asarray(R, jnp.float32)
    e, g = jax.jit(jax.value_and_grad(cluster))(R32)
    assert e.dtype == g.dtype == jnp.float32
    e_thread, g_thread = jax.value_and_grad(thread)(R32)
    if CPU:
        np.testing.assert_array_equal(np.asarray(g), np.asarray(g_thread))
        assert float(e) == float(e_thread)
    t = brute.sums(jnp.asarray(R))
    np.testing.assert_allclose(float(e), float(t.energy), rtol=1e-4)
    close(-g, t.forces, 2e-3)


@pytest.mark.parametrize("walk", ["cluster", "native"])
def test_jit_scan_and_2d(x64, walk):
    cluster, _, R_end, displacement, side = check_descent_in_scan_2d(
        CellSums(kernel="warp", reach=(1, 1), walk=walk), E_RTOL)
    thread = lennard_jones_fused(displacement, side, backend=CellSums(
        kernel="warp", reach=(1, 1)))
    same(jax.grad(cluster)(R_end), jax.grad(thread)(R_end), F_RTOL)


def test_walk_option_refused_off_the_warp_engine():
    with pytest.raises(ValueError, match="walk='cluster'"):
        CellSums(kernel="xla", walk="cluster")
    with pytest.raises(ValueError, match="walk='tiles'"):
        CellSums(kernel="warp", walk="tiles")
    with pytest.raises(ValueError, match="cluster_size=3"):
        CellSums(kernel="warp", walk="cluster", cluster_size=3)
    with pytest.raises(ValueError, match="size=3"):
        warp_cluster.cluster_kernel(wp.float32, 0, size=3)


# --- The Warp kernels alone (no JAX), on `DEVICE`. ------------------------

def test_cluster_table_matches_numpy():
    rng = np.random.default_rng(0)
    for size in warp_cluster.SIZES:
        per_cell = rng.choice([0, 1, 5, 8, 9, 13, 16, 17, 40], 50)
        start = np.concatenate([[0], np.cumsum(per_cell)]).astype(np.int32)
        n, table = int(start[-1]), len(per_cell)
        expected = [s + m * size for s, c in zip(start, per_cell)
                    for m in range(math.ceil(c / size))]
        assert len(expected) <= warp_cluster.bound(n, table, size)
        counts = wp.empty(table + 1, dtype=wp.int32, device=DEVICE)
        offsets = wp.empty(table + 1, dtype=wp.int32, device=DEVICE)
        clusters = wp.full(warp_cluster.bound(n, table, size) + 1, -7,
                           dtype=wp.int32, device=DEVICE)
        warp_cluster.build_clusters(wp.array(start, device=DEVICE), counts,
                                    offsets, clusters, n=n, size=size)
        total = int(offsets.numpy()[-1])
        assert total == len(expected)
        np.testing.assert_array_equal(clusters.numpy()[:total + 1],
                                      expected + [n])


def _direct(points, side, periodic, scalar, radii=None, specialize=True,
            device=DEVICE):
    """Both walks through `wk.lj_sums` / `warp_cluster.lj_sums` on cells a
    cutoff wide: outputs per cluster size and pruning, and the thread
    walk's."""
    n = len(points)
    cut = 2.5
    lo, hi = points.min(0), points.max(0)
    if periodic:
        m = np.full(3, max(1, int(side // cut)))
        grid = np.stack([np.zeros(3), side / m, np.full(3, side)])
    else:
        m = np.maximum(1, np.floor((hi - lo) / cut)).astype(int)
        grid = np.stack([lo, np.maximum((hi - lo) / m, cut), np.ones(3)])
    cells = np.concatenate([m, [1, 1, 1]]).astype(np.int32)
    table = int(np.prod(m))
    np_scalar = np.float32 if scalar == wp.float32 else np.float64
    v3 = wp.types.vector(3, scalar)
    flags = wk.COUNT | wk.DERIVATIVES
    if periodic:
        flags |= 7 * wk.PERIODIC
    if radii is not None:
        flags |= wk.HAS_RADII
    params = np.zeros(wk.N_PARAMS)
    params[[wk.SIGMA, wk.EPSILON, wk.R_ONSET, wk.R_CUTOFF]] = 1, 1, 2, cut
    arr = lambda a, t: wp.array(np.asarray(a, np_scalar) if t is not wp.int32  # noqa: E731
                                else a, dtype=t, device=device)
    inputs = (arr(points, v3), arr(np.ones(1) if radii is None else radii,
                                   scalar), arr(grid, v3),
              wp.array(cells, dtype=wp.int32, device=device),
              arr(params, scalar), flags)

    def outputs():
        e = lambda k, t: wp.empty(k, dtype=t, device=device)  # noqa: E731
        return dict(forces=e(n, v3), energy=e(n, scalar),
                    d_sigma=e(n, scalar), d_epsilon=e(n, scalar),
                    count=e(n, wp.int32), keys=e(2 * n, wp.int32),
                    values=e(2 * n, wp.int32), wrapped=e(n, v3),
                    start=e(table + 1, wp.int32), position=e(n, v3),
                    radius=e(n if radii is not None else 1, scalar))

    def result(o):
        return [o[k].numpy() for k in ("forces", "energy", "d_sigma",
                                       "d_epsilon", "count")]
    o = outputs()
    wk.lj_sums(*inputs, **o, specialize=specialize)
    runs = {"thread": result(o)}
    for size in warp_cluster.SIZES:
        for prune in (True, False):
            o = outputs()
            o.update(counts=wp.empty(table + 1, dtype=wp.int32,
                                     device=device),
                     offsets=wp.empty(table + 1, dtype=wp.int32,
                                      device=device),
                     clusters=wp.empty(warp_cluster.bound(n, table, size) + 1,
                                       dtype=wp.int32, device=device))
            warp_cluster.lj_sums(*inputs, **o, size=size, prune=prune,
                                 specialize=specialize)
            runs[(size, prune)] = result(o)
    return runs


@pytest.mark.parametrize("periodic", [True, False])
@pytest.mark.parametrize("scalar", [wp.float32, wp.float64])
def test_every_size_and_pruning_equal_the_thread_walk(periodic, scalar):
    """Each cluster size, pruned or not, in float32 and float64, equals
    the thread walk (`same_outputs`), and the counts equal a
    NumPy brute count."""
    side = 9.0  # 3 cells a side: the stencil covers every cell
    rng = np.random.default_rng(5)
    points = np.concatenate([rng.uniform(0, side, (300, 3)),
                             rng.uniform(1.0, 2.0, (30, 3))])  # a crowd
    runs = _direct(points, side, periodic, scalar)
    reference = runs.pop("thread")
    d = points[:, None] - points[None]
    if periodic:
        d = d - side * np.round(d / side)
    pairs = int(np.sum(np.sum(d * d, -1) < 2.5 ** 2)) - len(points)
    assert int(reference[4].sum()) == pairs
    for key, outputs in runs.items():
        same_outputs(outputs, reference, err_msg=str(key))


def test_radii_and_generic_flags_equal_the_thread_walk():
    rng = np.random.default_rng(2)
    points = rng.uniform(0, 12.0, (250, 3))
    radii = rng.uniform(0.8, 2.5, 250)
    runs = _direct(points, 12.0, True, wp.float64, radii=radii,
                   specialize=False)
    reference = runs.pop("thread")
    assert int(reference[4].sum()) > 0
    for key, outputs in runs.items():
        same_outputs(outputs, reference, err_msg=str(key))


# --- The warp-cooperative walk (walk="native"). ---------------------------

def _native_one_lane(points, side, scalar, radii=None):
    """The native kernel built for one lane (clusters of one) on Warp's
    CPU: its chunks, ballots and survivor loop with a lone lane's
    shuffles; outputs as `_direct`'s."""
    n = len(points)
    runs = _direct(points, side, True, scalar, radii=radii, device="cpu")
    m = max(1, int(side // 2.5))
    table = m ** 3
    np_scalar = np.float32 if scalar == wp.float32 else np.float64
    v3 = wp.types.vector(3, scalar)
    flags = wk.COUNT | wk.DERIVATIVES | 7 * wk.PERIODIC
    if radii is not None:
        flags |= wk.HAS_RADII
    params = np.zeros(wk.N_PARAMS)
    params[[wk.SIGMA, wk.EPSILON, wk.R_ONSET, wk.R_CUTOFF]] = 1, 1, 2, 2.5
    e = lambda k, t: wp.empty(k, dtype=t, device="cpu")  # noqa: E731
    a = lambda x: wp.array(np.asarray(x, np_scalar), device="cpu")  # noqa: E731
    o = dict(forces=e(n, v3), energy=e(n, scalar), d_sigma=e(n, scalar),
             d_epsilon=e(n, scalar), count=e(n, wp.int32),
             keys=e(2 * n, wp.int32), values=e(2 * n, wp.int32),
             wrapped=e(n, v3), start=e(table + 1, wp.int32),
             position=e(n, v3), radius=e(n if radii is not None else 1,
                                          scalar))
    points_w = wp.array(np.asarray(points, np_scalar), dtype=v3, device="cpu")
    radii_w = a(np.ones(1) if radii is None else radii)
    grid = wp.array(np.stack([np.zeros(3), np.full(3, side / m),
                              np.full(3, side)]).astype(np_scalar),
                    dtype=v3, device="cpu")
    cells = wp.array(np.asarray([m, m, m, 1, 1, 1], np.int32), device="cpu")
    params_w = a(params)
    wk.sort_cells(points_w, radii_w, grid, cells, flags,
                  **{k: o[k] for k in ("keys", "values", "wrapped", "start",
                                       "position", "radius")})
    counts, offsets = e(table + 1, wp.int32), e(table + 1, wp.int32)
    clusters = e(warp_cluster.bound(n, table, 1) + 1, wp.int32)
    warp_cluster.build_clusters(o["start"], counts, offsets, clusters, n=n,
                                size=1)
    walk = warp_cluster_native.native_kernel(scalar, flags, size=1, lanes=1)
    warp_cluster_native.launch(
        walk, size=1, lanes=1, offsets=offsets, clusters=clusters,
        grid=grid, cells=cells, params=params_w, flags=flags,
        **{k: o[k] for k in ("position", "keys", "values", "radius", "start",
                             "forces", "energy", "d_sigma", "d_epsilon",
                             "count")})
    native = [o[k].numpy() for k in ("forces", "energy", "d_sigma",
                                     "d_epsilon", "count")]
    return native, runs["thread"]


@pytest.mark.parametrize("scalar", [wp.float32, wp.float64])
def test_native_walk_on_one_lane_equals_the_thread_walk(scalar):
    """The warp-cooperative kernel on one lane, on Warp's CPU: every
    candidate in the thread walk's order, so its outputs equal the thread
    walk's bit for bit (its cross-lane shuffles are not exercised)."""
    # On CUDA the kernel's ballots and shuffles span the hardware warp
    # whatever ``lanes`` is (32 one-lane clusters would mix candidates), so
    # the one-lane build runs on Warp's CPU only.
    if not CPU_COMPILER:
        pytest.skip("Warp has no CPU compiler (a slim build): the one-lane "
                    "native kernel runs only on Warp's CPU device.")
    rng = np.random.default_rng(9)
    points = np.concatenate([rng.uniform(0, 9.0, (300, 3)),
                             rng.uniform(1.0, 2.0, (30, 3))])
    native, thread = _native_one_lane(points, 9.0, scalar)
    assert int(thread[4].sum()) > 0
    same_outputs(native, thread, device="cpu")
    rng = np.random.default_rng(4)
    radii = rng.uniform(0.8, 2.5, len(points))
    native, thread = _native_one_lane(points, 9.0, scalar, radii=radii)
    same_outputs(native, thread, device="cpu")


def test_native_walk_sizes_refused():
    with pytest.raises(ValueError, match="size=3"):
        warp_cluster_native.native_kernel(wp.float32, 0, size=3)
    with pytest.raises(ValueError, match="lanes=8"):
        warp_cluster_native.native_kernel(wp.float32, 0, size=1, lanes=8)


@pytest.mark.parametrize("reach", [(1, 1), (2, 1)])
def test_native_walk_matches_brute(x64, reach):
    """walk="native": on CUDA the warp-cooperative walk (the thread walk's
    terms in another order: float64 tolerances), on the CPU the cluster
    walk."""
    R, side = fluid()
    R = jnp.asarray(R)
    displacement, box, periodic = GEOMETRIES["periodic"](side)
    native = lennard_jones_fused(
        displacement, box, periodic=periodic,
        backend=CellSums(kernel="warp", reach=reach, walk="native"))
    brute = lennard_jones_fused(displacement, box, periodic=periodic,
                                backend="brute")
    s, t = native.sums(R), brute.sums(R)
    assert int(t.count) > 0
    check_sums(s, t, E_RTOL, F_RTOL)
    R32 = jnp.asarray(R, jnp.float32)
    e, g = jax.value_and_grad(native)(R32)
    np.testing.assert_allclose(float(e), float(t.energy), rtol=1e-4)
    close(-g, t.forces, 2e-3)
