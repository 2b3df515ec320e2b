"""Seed 004: neighbours from a Delaunay triangulation kept by edge flips (2D).

The backend ``"delaunay"`` (`Delaunay`). It follows the poster (seed 004,
``../shared/seeds/004_*.txt``; our spec is ``SPECS.md`` §6): a Delaunay
triangulation (DT) of the particles is built once on the host and then kept
on the device from one ``update`` to the next by edge flips; the
neighbours of each vertex are found by a breadth-first search (BFS) over
the triangulation's edges that expands only vertices within the radius.

Two engines run the same algorithm (``Delaunay(engine=...)``): ``"xla"``,
the pure-JAX pieces below, and ``"warp"``, Warp kernels
(`jaxrt.backends.rt.delaunay_kernels`: one thread per edge for the flips,
triangles claimed by atomic min; one thread per vertex for the BFS) driven
by `jaxrt.backends.rt.delaunay_engine` inside one XLA custom call per step
(`jaxrt.backends.rt.ffi.delaunay_step`). Both keep the same
`Triangulation` and make the same flips; rebuilds from scratch go to the
host (Qhull) in both.

Pieces (each a pure-JAX kernel that knows nothing of `neighbor_list`):

* **Predicates** (§6 "Predicates"): `orient` and `incircle` in float64 with
  Shewchuk's static error bounds. A result whose magnitude is not above its
  bound is *undecided*: an undecided in-circle test (cocircular points, as
  on a lattice) means "no flip" (the DT of cocircular points is not
  unique, and the search below is exact on any of them); an undecided
  orientation (collinear points) means the triangulation is not valid,
  which ends in a rebuild.
* **Triangulation** (`Triangulation`): fixed-size arrays, T triangles of
  three counter-clockwise vertex ids, the twin of each half-edge (the
  poster's half-edge structure, indexed ``3 t + e`` for the edge opposite
  local vertex ``e``), and per triangle vertex an integer image shift (a
  torus triangulation: vertex ``v`` of triangle ``t`` sits at
  ``position[v] + shift[t, k] * L``). Flips keep T constant: T = 2N on a
  torus; in free space four fixed frame vertices far outside the points
  are added (§6 "Rebuild triggers": "add fixed frame vertices"), so the
  hull never changes and T = 2(N + 4) - 6.
* **Maintenance** (poster Figs 4-5, §6 "Validity", "Delaunay repair",
  "Displacement splitting"): the vertices move from the positions the DT
  was made for to the new ones. Flip rounds run at the target positions:
  an edge flips where one of its two triangles is inverted (a point went
  through the edge, Fig 4) or the in-circle test fails, provided both new
  triangles are positive. Each wanting edge claims its two triangles by a
  scatter-min of its half-edge id; only edges that won both flip, so no
  two flips in a round touch one triangle. Rounds repeat until none is
  wanted (Lawson's algorithm). If that does not end with every triangle
  positive within ``max_flip_rounds`` rounds, the displacement is split
  (Fig 5), point by point: each point keeps the fraction of its move that
  last worked; the points of the triangles left inverted retry half their
  remaining way, the others their whole move, and then all try the rest.
  After ``max_splits`` failed tries the triangulation is rebuilt from
  scratch. The Warp engine (`jaxrt.backends.rt.delaunay_engine.maintain`)
  keeps a step per point instead: the points of the triangles left
  inverted halve theirs, and after a successful try every step doubles
  (capped at the rest of the move); its flip rounds run in batches with
  one host read each on a GPU, re-testing only the triangles of the last
  round's wanting edges.
* **Rebuilds** from scratch (scipy's Qhull, on the host, through
  `jax.pure_callback` under ``jit``: a host round trip) where maintenance
  cannot succeed: a point left the frame's safe region (free space),
  splitting did not converge, a predicate stayed undecided. They are
  counted in `Triangulation.rebuilds`.
* **Search** (poster Fig 6, §6 "BFS correctness"): from each vertex v, a
  frontier array of the vertices found so far; the next vertex of the
  frontier is expanded by its 1-ring. A neighbour w of x enters v's
  frontier when it is within the radius and x is w's *parent*: the vertex
  adjacent to w closest to v (ties to the lower id). In a DT every p != v
  has a neighbour strictly closer to v (leave Vor(p) along pv; at a
  degenerate Voronoi vertex, p is the farthest point of the cocircle from
  v, so both its cocircle neighbours are closer), so every w within r of v
  is reached through its parent chain, each exactly once: no "visited"
  scan is needed and the list is exact, ties and lattices included
  (tests/backends/test_delaunay.py checks it against brute force). Frontier and
  degree buffers are static; their overflow is flagged, never silent.

State: the triangulation travels with the list: `jaxrt.neighbor_list`
returns a `jaxrt.lists.neighbors.StatefulNeighborList` (a subclass of jax-md's
``NeighborList``) whose ``backend_state`` is the `Triangulation`, so a
``lax.scan`` over ``nbrs.update(R)`` carries it. Maintenance runs when the
list is rebuilt (past half the skin), moving the DT from the last
rebuild's positions to the new ones.

Requirements: 2D, float64 positions (``jax_enable_x64``; the poster runs in
double precision, and the predicates' bounds are for float64), free space
or a rectangular box periodic on both axes, no coincident points.

One module past 800 lines on purpose: the triangulation, its flips, the
search and the backend share the state's layout.
"""
from __future__ import annotations

import dataclasses
import functools
from typing import ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from jaxrt.backends import contract as _backend
from jaxrt.backends.contract import (Capacity, Geometry, MetricSq, Query,
                                     SearchResult)
from jaxrt.errors import ErrorCode

Array = jax.Array

FRAME = 4
"""Frame vertices added in free space (the corners of a square)."""

# Shewchuk's static error-bound coefficients for float64 (eps = 2**-53):
# |det| above bound * permanent decides the sign of the exact determinant
# of the (double) inputs.
_EPS = 2.0 ** -53
_CCW_BOUND = (3.0 + 16.0 * _EPS) * _EPS
_ICC_BOUND = (10.0 + 96.0 * _EPS) * _EPS


# ---------------------------------------------------------------------------
# Predicates


def orient(a: Array, b: Array, c: Array) -> tuple[Array, Array]:
    """Orientation of triangles ``(a, b, c)`` (float64 ``(..., 2)``).

    Returns ``(det, bound)``, float64 ``(...)``: ``det > bound`` is
    counter-clockwise for certain, ``det < -bound`` clockwise; otherwise
    undecided (collinear up to rounding).
    """
    acx, acy = a[..., 0] - c[..., 0], a[..., 1] - c[..., 1]
    bcx, bcy = b[..., 0] - c[..., 0], b[..., 1] - c[..., 1]
    left, right = acx * bcy, acy * bcx
    return left - right, _CCW_BOUND * (jnp.abs(left) + jnp.abs(right))


def incircle(a: Array, b: Array, c: Array, d: Array) -> tuple[Array, Array]:
    """In-circle test: ``det > bound`` means ``d`` lies inside the circle
    through the counter-clockwise ``a, b, c`` for certain (float64
    ``(..., 2)`` each). Returns ``(det, bound)``, float64 ``(...)``."""
    adx, ady = a[..., 0] - d[..., 0], a[..., 1] - d[..., 1]
    bdx, bdy = b[..., 0] - d[..., 0], b[..., 1] - d[..., 1]
    cdx, cdy = c[..., 0] - d[..., 0], c[..., 1] - d[..., 1]
    bc, cb = bdx * cdy, cdx * bdy
    ca, ac = cdx * ady, adx * cdy
    ab, ba = adx * bdy, bdx * ady
    alift = adx * adx + ady * ady
    blift = bdx * bdx + bdy * bdy
    clift = cdx * cdx + cdy * cdy
    det = alift * (bc - cb) + blift * (ca - ac) + clift * (ab - ba)
    permanent = ((jnp.abs(bc) + jnp.abs(cb)) * alift
                 + (jnp.abs(ca) + jnp.abs(ac)) * blift
                 + (jnp.abs(ab) + jnp.abs(ba)) * clift)
    return det, _ICC_BOUND * permanent


# ---------------------------------------------------------------------------
# The triangulation


class Triangulation(NamedTuple):
    """A 2D triangulation in fixed-size arrays (a pytree; ``V`` vertices:
    the ``N`` particles, then `FRAME` frame vertices in free space).

    Attributes:
      position: float64 ``(V, 2)``, the vertex positions (grid Cartesian
        coordinates) the triangulation is Delaunay for; in ``[0, L)`` on a
        torus.
      tri: int32 ``(T, 3)``, vertex ids, counter-clockwise.
      twin: int32 ``(T, 3)``, for the edge opposite local vertex ``e`` of
        triangle ``t`` (half-edge ``3 t + e``), the half-edge id of the
        same edge in the neighbouring triangle; -1 on the frame's hull.
      shift: int32 ``(T, 3, 2)``, image shift of each triangle vertex (in
        box sides; zeros in free space).
      safe: float64 ``(2, 2)``, free space: the box (low, high corners) in
        which the points must stay for the frame to hold them; unused on a
        torus.
      rebuilds: int32 ``()``, rebuilds from scratch since ``allocate``.
      flips: int32 ``()``, flips of the last maintenance.
      flips_total: int32 ``()``, flips since ``allocate``.
      splits: int32 ``()``, halvings of the displacement at the last
        maintenance.
      failed: bool ``()``, the last rebuild failed (coincident points or a
        degenerate input): the list is wrong and carries an error bit.
    """

    position: Array
    tri: Array
    twin: Array
    shift: Array
    safe: Array
    rebuilds: Array
    flips: Array
    flips_total: Array
    splits: Array
    failed: Array


def triangle_count(n: int, periodic: bool) -> int:
    """T for ``n`` particles: 2n on a torus, 2(n + 4) - 6 with the frame."""
    return 2 * n if periodic else 2 * (n + FRAME) - 2 - FRAME


# ---------------------------------------------------------------------------
# Host side: the initial triangulation and rebuilds (scipy's Qhull)


def coincident_pair(points: np.ndarray) -> tuple[int, int] | None:
    """The first pair of particles at identical positions (float64
    ``(N, 2)``), or None."""
    order = np.lexsort(points.T[::-1])
    same = np.all(points[order[1:]] == points[order[:-1]], axis=1)
    if not same.any():
        return None
    k = int(np.argmax(same))
    i, j = sorted((int(order[k]), int(order[k + 1])))
    return i, j


def _orient_np(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a, b, cc = c[:, 0], c[:, 1], c[:, 2]
    left = (a[:, 0] - cc[:, 0]) * (b[:, 1] - cc[:, 1])
    right = (a[:, 1] - cc[:, 1]) * (b[:, 0] - cc[:, 0])
    return left - right, _CCW_BOUND * (np.abs(left) + np.abs(right))


def _twins(tri: np.ndarray, shift: np.ndarray, v: int) -> np.ndarray | None:
    """Half-edge twins of a triangulation, -1 where an edge has none;
    None if an edge is shared by more than two triangles (or twice in one
    direction): not a triangulation."""
    t_count = tri.shape[0]
    e = np.arange(3)
    a = tri[:, (e + 1) % 3].ravel().astype(np.int64)
    b = tri[:, (e + 2) % 3].ravel().astype(np.int64)
    ds = (shift[:, (e + 2) % 3] - shift[:, (e + 1) % 3]).reshape(-1, 2)
    if np.abs(ds).max(initial=0) > 3:
        return None

    def code(x, y, d):
        return ((x * v + y) * 7 + (d[:, 0] + 3)) * 7 + (d[:, 1] + 3)
    key = code(a, b, ds)
    want = code(b, a, -ds)
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    if np.any(sorted_key[1:] == sorted_key[:-1]):
        return None
    pos = np.searchsorted(sorted_key, want)
    pos = np.minimum(pos, len(sorted_key) - 1)
    found = sorted_key[pos] == want
    twin = np.where(found, order[pos], -1).astype(np.int32)
    return twin.reshape(t_count, 3)


def _ccw(tri: np.ndarray, coords: np.ndarray, shift: np.ndarray):
    """Make every triangle counter-clockwise (Qhull does not orient)."""
    det, _ = _orient_np(coords)
    flip = det < 0
    tri[flip] = tri[flip][:, [0, 2, 1]]
    shift[flip] = shift[flip][:, [0, 2, 1]]
    coords[flip] = coords[flip][:, [0, 2, 1]]
    return tri, coords, shift


def _jitter(points: np.ndarray, scale: float, seed: int) -> np.ndarray:
    """Points moved by ~1e-9 of the spacing: Qhull then sees no cocircular
    or collinear sets (a lattice), so every image copy of a torus region is
    triangulated alike. The device's flips then make the result Delaunay
    for the true points (`maintain` with no move)."""
    rng = np.random.default_rng(seed)
    return points + rng.uniform(-1e-9, 1e-9, points.shape) * scale


def _torus(points: np.ndarray, side: np.ndarray, seed: int):
    """(tri, shift) of a torus triangulation, or None: Qhull on the points
    and their image copies within a margin, keeping the one copy of each
    triangle whose centroid lies in ``[0, L)^2``."""
    from scipy.spatial import Delaunay as Qhull
    n = len(points)
    spacing = float(np.sqrt(side[0] * side[1] / n))
    # Not wrapped again: a jittered copy of a point at 0 stays next to it,
    # so the image shifts below refer to the true (canonical) points.
    jittered = _jitter(points, spacing, seed)
    for factor in (4.0, 8.0, 16.0, np.inf):
        margin = np.minimum(factor * spacing, side)
        ext, ids, shifts = [], [], []
        for sx in (-1, 0, 1):
            for sy in (-1, 0, 1):
                s = np.array([sx, sy])
                q = jittered + s * side
                keep = np.all((q >= -margin) & (q < side + margin), axis=1)
                ext.append(q[keep])
                ids.append(np.flatnonzero(keep))
                shifts.append(np.broadcast_to(s, (keep.sum(), 2)))
        ext, ids, shifts = (np.concatenate(x) for x in (ext, ids, shifts))
        simplices = Qhull(ext).simplices
        centroid = ext[simplices].mean(axis=1)
        own = np.all((centroid >= 0) & (centroid < side), axis=1)
        simplices = simplices[own]
        tri = ids[simplices].astype(np.int32)
        shift = shifts[simplices].astype(np.int32)
        coords = points[tri] + shift * side
        tri, coords, shift = _ccw(tri, coords, shift)
        if len(tri) == 2 * n:
            twin = _twins(tri, shift, n)
            if twin is not None and np.all(twin >= 0):
                return tri, shift, twin
        if not np.isfinite(factor) or np.all(margin >= side):
            break
    return None


def frame_of(points: np.ndarray, cutoff: float):
    """The frame vertices (float64 ``(4, 2)``) around ``points`` and the
    safe box (``(2, 2)``: low, high) the points must stay in.

    The frame's corners lie at least ``2 cutoff`` beyond the safe box, so a
    frame vertex is never within the radius of a particle there and the
    BFS never expands one: the search stays exact with the frame added.
    """
    lo, hi = points.min(axis=0), points.max(axis=0)
    centre = (lo + hi) / 2
    half = float(np.max(hi - lo)) / 2
    reach = 2 * half + 2 * cutoff + 1e-6 * max(half, cutoff)
    safe = np.stack([centre - reach, centre + reach])
    corner = 2 * reach
    frame = centre + corner * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]])
    return frame, safe


def _free(points: np.ndarray, cutoff: float, seed: int):
    from scipy.spatial import Delaunay as Qhull
    n = len(points)
    frame, safe = frame_of(points, cutoff)
    vertices = np.concatenate([points, frame])
    spacing = float(np.max(np.ptp(points, axis=0))) / np.sqrt(n) if n > 1 \
        else cutoff
    simplices = Qhull(_jitter(vertices, max(spacing, 1e-300), seed)).simplices
    tri = simplices.astype(np.int32)
    shift = np.zeros(tri.shape + (2,), np.int32)
    tri, _, shift = _ccw(tri, vertices[tri], shift)
    if len(tri) != triangle_count(n, False):
        return None
    twin = _twins(tri, shift, n + FRAME)
    if twin is None or np.sum(twin < 0) != FRAME:
        return None
    return vertices, tri, shift, twin, safe


def host_triangulate(points: np.ndarray, side: np.ndarray | None,
                     cutoff: float, seed: int = 0):
    """A triangulation of ``points`` (float64 ``(N, 2)``, grid Cartesian
    coordinates) on the host.

    Returns ``(position (V, 2), tri (T, 3), twin (T, 3), shift (T, 3, 2),
    safe (2, 2), ok)`` as numpy arrays (``ok``: bool; on failure the other
    arrays are zeros of the right shapes). ``side``: float64 ``(2,)`` for
    a torus, None for free space. Delaunay up to the jitter of `_jitter`;
    the caller's flips finish it.
    """
    points = np.asarray(points, np.float64)
    n = len(points)
    periodic = side is not None
    t_count = triangle_count(n, periodic)
    v = n if periodic else n + FRAME
    fail = (np.zeros((v, 2)), np.zeros((t_count, 3), np.int32),
            np.full((t_count, 3), -1, np.int32),
            np.zeros((t_count, 3, 2), np.int32), np.zeros((2, 2)), False)
    if periodic:
        points = np.mod(points, side)
        points = np.where(points >= side, 0.0, points)  # mod rounding to L
    if not np.all(np.isfinite(points)) or coincident_pair(points) is not None:
        return fail
    for attempt in range(3):
        try:
            if periodic:
                out = _torus(points, np.asarray(side, np.float64),
                             seed + attempt)
                if out is None:
                    continue
                tri, shift, twin = out
                vertices, safe = points, np.zeros((2, 2))
            else:
                out = _free(points, cutoff, seed + attempt)
                if out is None:
                    continue
                vertices, tri, shift, twin, safe = out
        except Exception:  # noqa: BLE001 - Qhull errors: try another jitter
            continue
        scale = np.asarray(side if periodic else np.zeros(2))
        det, bound = _orient_np(vertices[tri] + shift * scale)
        if np.all(det > bound):
            return vertices, tri, twin, shift, safe, True
    return fail


# ---------------------------------------------------------------------------
# Device side: flips and maintenance


def _coords(tri_state: Triangulation, P: Array, L: Array) -> Array:
    """float64 ``(T, 3, 2)``: each triangle's vertices at positions ``P``."""
    return P[tri_state.tri] + tri_state.shift.astype(P.dtype) * L


def _flip_round(tri: Array, twin: Array, shift: Array, P: Array, L: Array):
    """One round of parallel flips at vertex positions ``P`` (float64
    ``(V, 2)``). Returns the new ``(tri, twin, shift)`` and the int32
    number of flips."""
    t_count = tri.shape[0]
    h = jnp.arange(3 * t_count, dtype=jnp.int32)
    t, e = h // 3, h % 3
    e1, e2 = (e + 1) % 3, (e + 2) % 3
    tw = twin.reshape(-1)
    has = tw >= 0
    tw0 = jnp.where(has, tw, 0)
    u, m = tw0 // 3, tw0 % 3
    m1, m2 = (m + 1) % 3, (m + 2) % 3
    Lf = L.astype(P.dtype)
    # Triangle t = (p, b, c), its neighbour across bc is u = (q, c, b).
    # q is put into t's frame: the shift of b in t minus that in u.
    off = shift[t, e1] - shift[u, m2]
    s_p, s_b, s_c = shift[t, e], shift[t, e1], shift[t, e2]
    s_q = shift[u, m] + off
    i_p, i_b, i_c, i_q = tri[t, e], tri[t, e1], tri[t, e2], tri[u, m]
    f = lambda i, s: P[i] + s.astype(P.dtype) * Lf  # noqa: E731
    p, b, c, q = f(i_p, s_p), f(i_b, s_b), f(i_c, s_c), f(i_q, s_q)
    det_t, bnd_t = orient(p, b, c)
    det_u, bnd_u = orient(q, c, b)
    det_1, bnd_1 = orient(p, b, q)
    det_2, bnd_2 = orient(q, c, p)
    det_i, bnd_i = incircle(p, b, c, q)
    old_ok = (det_t > bnd_t) & (det_u > bnd_u)
    inverted = ~old_ok
    violated = det_i > bnd_i  # undecided (cocircular): no flip
    new_ok = (det_1 > bnd_1) & (det_2 > bnd_2)
    A, B = twin[t, e1], twin[t, e2]
    C, D = twin[u, m1], twin[u, m2]
    # An edge whose two triangles share another edge (tiny tori) is left.
    simple = u != t
    for x in (A, B, C, D):
        simple &= (x < 0) | ((x // 3 != t) & (x // 3 != u))
    want = has & (h < tw) & simple & new_ok & (inverted | violated)
    # Claims: each wanting edge writes its id onto both its triangles; the
    # lowest id wins a triangle, and an edge flips only if it won both.
    none = jnp.int32(3 * t_count)
    key = jnp.where(want, h, none)
    claim = jnp.full((t_count,), none, jnp.int32)
    claim = claim.at[t].min(key).at[u].min(key)
    win = want & (claim[t] == h) & (claim[u] == h)
    drop = jnp.int32(t_count)  # an out-of-range row: scatter drops it
    wt, wu = jnp.where(win, t, drop), jnp.where(win, u, drop)
    tri = tri.at[wt].set(jnp.stack([i_p, i_b, i_q], -1), mode="drop")
    tri = tri.at[wu].set(jnp.stack([i_q, i_c, i_p], -1), mode="drop")
    shift = shift.at[wt].set(jnp.stack([s_p, s_b, s_q], 1), mode="drop")
    shift = shift.at[wu].set(jnp.stack([s_q, s_c, s_p], 1), mode="drop")
    # New t = (p, b, q): edge 0 (b-q) was u's edge m1 (outside C), edge 2
    # (p-b) was t's e2 (outside B). New u = (q, c, p): edge 0 (c-p) was
    # t's e1 (outside A), edge 2 (q-c) was u's m2 (outside D). Edges 1 of
    # both are the new diagonal. ``remap`` sends each old half-edge to its
    # new id, so that twins pointing into any flipped pair (this one or
    # another flipped in the same round) are redirected without conflicts.
    n_h = 3 * t_count
    drop_h = jnp.int32(n_h)
    remap = jnp.arange(n_h, dtype=jnp.int32)
    for old, new in ((3 * t + e1, 3 * u), (3 * t + e2, 3 * t + 2),
                     (3 * u + m1, 3 * t), (3 * u + m2, 3 * u + 2)):
        remap = remap.at[jnp.where(win, old, drop_h)].set(new, mode="drop")
    flat = twin.reshape(-1)
    for slot, outer in ((3 * t, C), (3 * t + 2, B), (3 * u, A),
                        (3 * u + 2, D)):
        flat = flat.at[jnp.where(win, slot, drop_h)].set(outer, mode="drop")
    flat = jnp.where(flat >= 0, remap[jnp.maximum(flat, 0)], -1)
    flat = flat.at[jnp.where(win, 3 * t + 1, drop_h)].set(3 * u + 1,
                                                          mode="drop")
    flat = flat.at[jnp.where(win, 3 * u + 1, drop_h)].set(3 * t + 1,
                                                          mode="drop")
    return tri, flat.reshape(t_count, 3), shift, jnp.sum(win, dtype=jnp.int32)


def _all_positive(tri: Array, shift: Array, P: Array, L: Array) -> Array:
    c = P[tri] + shift.astype(P.dtype) * L.astype(P.dtype)
    det, bound = orient(c[:, 0], c[:, 1], c[:, 2])
    return jnp.all(det > bound)


def flip_to_delaunay(tri: Array, twin: Array, shift: Array, P: Array,
                     L: Array, max_rounds: int):
    """Flip rounds at positions ``P`` until no edge wants a flip, at most
    ``max_rounds`` (an int, or a traced int32). Returns ``(tri, twin, shift, flips, done)``: ``done``
    (bool) when the rounds ended with every triangle positive and nothing
    to flip, i.e. a Delaunay triangulation of ``P``."""

    def cond(c):
        return (c[4] < max_rounds) & c[5]

    def body(c):
        tri, twin, shift, flips, rounds, _ = c
        tri, twin, shift, k = _flip_round(tri, twin, shift, P, L)
        return tri, twin, shift, flips + k, rounds + 1, k > 0

    tri, twin, shift, flips, _, again = lax.while_loop(
        cond, body, (tri, twin, shift, jnp.int32(0), jnp.int32(0),
                     jnp.bool_(True)))
    done = ~again & _all_positive(tri, shift, P, L)
    return tri, twin, shift, flips, done


def maintain(state: Triangulation, target: Array, L: Array, *,
             periodic: bool, max_flip_rounds: int, max_splits: int
             ) -> tuple[Triangulation, Array]:
    """Move the triangulation's vertices to ``target`` (float64 ``(V, 2)``)
    and restore the Delaunay condition by flips, splitting the
    displacement where needed (module docstring).

    ``L``: float64 ``(2,)`` box sides (torus) or zeros (free space).
    Returns the new state (``position = target``, wrapped into ``[0, L)``
    on a torus) and a bool: True if maintenance failed and the caller must
    rebuild (then the returned state is the old one).
    """
    X0 = state.position
    d = target - X0
    if periodic:  # minimum image: a move between rebuilds is below L/2
        delta = d - L * jnp.round(d / L)
    else:
        delta = d

    # Every success short of the end is followed by a try at the end, so
    # capping the failures (splits) caps the loop at 2 max_splits + 1.
    def cond(c):
        return jnp.any(c[3] < 1.0) & (c[6] < max_splits)

    def body(c):
        tri, twin, shift, s, f, flips, splits = c
        P = X0 + f[:, None] * delta
        t2, w2, s2, k, done = flip_to_delaunay(tri, twin, shift, P, L,
                                               max_flip_rounds)
        # On failure, split the moves (Fig 5) of the vertices of the
        # triangles the flips left inverted or flat: the points that went
        # through more than one edge are among them. They go half their
        # remaining way; the other points keep their whole step. If no
        # triangle is bad (the rounds ran out), every point halves.
        c2 = P[t2] + s2.astype(P.dtype) * L
        det, bound = orient(c2[:, 0], c2[:, 1], c2[:, 2])
        bad = ~(det > bound)
        bad_v = jnp.zeros(f.shape, bool).at[t2].max(
            jnp.broadcast_to(bad[:, None], t2.shape))
        shrink = jnp.where(jnp.any(bad), bad_v, True)
        retry = jnp.where(shrink, s + (f - s) / 2, f)
        tri, twin, shift = (jnp.where(done, x2, x) for x2, x in
                            ((t2, tri), (w2, twin), (s2, shift)))
        new_s = jnp.where(done, f, s)
        new_f = jnp.where(done, jnp.ones_like(f), retry)
        return (tri, twin, shift, new_s, new_f,
                flips + jnp.where(done, k, 0), splits + ~done)

    ones = jnp.ones((X0.shape[0],), X0.dtype)
    tri, twin, shift, s, _, flips, splits = lax.while_loop(
        cond, body, (state.tri, state.twin, state.shift, 0 * ones, ones,
                     jnp.int32(0), jnp.int32(0)))
    failed = jnp.any(s < 1.0)
    if periodic:
        new_pos = jnp.mod(target, L)
        new_pos = jnp.where(new_pos >= L, 0.0, new_pos)
        # The triangles saw X0 + delta; re-express them at the wrapped
        # positions: the image shift absorbs the whole periods.
        k = jnp.round((X0 + delta - new_pos) / L).astype(jnp.int32)
        shift = shift + k[tri]
    else:
        new_pos = target
        real = target[:-FRAME]
        failed |= ~jnp.all((real > state.safe[0]) & (real < state.safe[1]))
    moved = state._replace(position=new_pos, tri=tri, twin=twin, shift=shift,
                           flips=flips, flips_total=state.flips_total + flips,
                           splits=splits)
    keep = jax.tree.map(lambda a, b: jnp.where(failed, a, b), state, moved)
    return keep, failed


def _device_rebuild(state: Triangulation, points: Array, L: Array, *,
                    periodic: bool, cutoff: float) -> Triangulation:
    """Rebuild from scratch on the host (`jax.pure_callback`, a host round
    trip); the caller flips the result to Delaunay at the true positions
    (`_finish_rebuild`). A failed rebuild keeps the old triangulation with
    ``failed`` set."""
    n = points.shape[0]
    t_count = triangle_count(n, periodic)
    v = n if periodic else n + FRAME
    shapes = (jax.ShapeDtypeStruct((v, 2), points.dtype),
              jax.ShapeDtypeStruct((t_count, 3), jnp.int32),
              jax.ShapeDtypeStruct((t_count, 3), jnp.int32),
              jax.ShapeDtypeStruct((t_count, 3, 2), jnp.int32),
              jax.ShapeDtypeStruct((2, 2), points.dtype),
              jax.ShapeDtypeStruct((), jnp.bool_))

    def host(p, side):
        out = host_triangulate(np.asarray(p), np.asarray(side) if periodic
                               else None, cutoff)
        return tuple(np.asarray(x, s.dtype) for x, s in zip(out, shapes))

    pos, tri, twin, shift, safe, ok = jax.pure_callback(
        host, shapes, points, L, vmap_method="sequential")
    new = state._replace(position=pos, tri=tri, twin=twin, shift=shift,
                         safe=safe, rebuilds=state.rebuilds + 1,
                         flips=jnp.int32(0), splits=jnp.int32(0),
                         failed=~ok)
    return jax.tree.map(lambda a, b: jnp.where(ok, a, b), new,
                        state._replace(failed=jnp.bool_(True)))


def _finish_rebuild(state: Triangulation, rebuilt: Array, L: Array,
                    max_flip_rounds: int) -> Triangulation:
    """Flip a fresh (jittered, `host_triangulate`) triangulation to
    Delaunay at the true positions; no rounds when nothing was rebuilt.
    One flip loop serves both branches, so it is compiled once."""
    rounds = jnp.where(rebuilt & ~state.failed, max_flip_rounds, 0)
    tri, twin, shift, flips, done = flip_to_delaunay(
        state.tri, state.twin, state.shift, state.position, L, rounds)
    bad = rebuilt & ~state.failed & ~done
    return state._replace(tri=tri, twin=twin, shift=shift,
                          flips=state.flips + flips,
                          flips_total=state.flips_total + flips,
                          failed=state.failed | bad)


# ---------------------------------------------------------------------------
# Device side: the search


def adjacency(tri: Array, n: int, degree: int) -> tuple[Array, Array, Array]:
    """Vertex -> neighbour rows from the triangles (particles only: frame
    vertices, ids >= n, are never within the radius and are left out).

    Every interior edge v-w appears once as "w follows v" in a
    counter-clockwise triangle, so each row lists each neighbour once.

    Returns int32 ``(n, degree)`` rows padded with ``n``, int32 ``(n,)``
    exact degrees, and bool: some vertex has a neighbour twice (a
    multi-edge of a tiny torus, which would list a pair twice).
    """
    v = tri.reshape(-1)
    w = tri[:, (1, 2, 0)].reshape(-1)
    real = (v < n) & (w < n)
    big = jnp.int64(n + FRAME)
    key = jnp.where(real, v.astype(jnp.int64) * big + w, big * big)
    key = jnp.sort(key)
    valid = key < big * big
    src = jnp.where(valid, key // big, n).astype(jnp.int32)
    dst = jnp.where(valid, key % big, n).astype(jnp.int32)
    counts = jnp.zeros((n + 1,), jnp.int32).at[src].add(1)[:n]
    starts = jnp.cumsum(counts) - counts
    rank = jnp.arange(key.shape[0], dtype=jnp.int32) - jnp.where(
        valid, starts[jnp.minimum(src, n - 1)], 0)
    rows = jnp.full((n, degree), n, jnp.int32)
    rows = rows.at[jnp.where(valid, src, n), rank].set(dst, mode="drop")
    repeated = jnp.any(valid[1:] & (key[1:] == key[:-1]))
    return rows, counts, repeated


def bfs(position: Array, rows: Array, metric_sq: MetricSq, cutoff: float,
        width: int, grid: Array, L: Array | None) -> tuple[Array, Array]:
    """Breadth-first search from every vertex (module docstring).

    Args:
      position: float ``(N, 2)``, the caller's positions (the caller's
        metric decides every pair, bit for bit as jax-md does).
      rows: int32 ``(N, D)`` adjacency padded with ``N`` (`adjacency`).
      width: frontier size per vertex, the vertex itself included.
      grid: float ``(N, 2)``, the positions in grid Cartesian coordinates;
        L: float ``(2,)`` box sides on a torus, None in free space. The
        parent rule compares Euclidean (minimum-image) distances on them:
        it only has to pick, among a vertex's neighbours, one closer to v,
        and the parent is closer than the candidate by far more than
        rounding wherever the candidate is in the radius.
    Returns:
      int32 ``(N, width)`` frontiers (the vertex itself first, then its
      neighbours in BFS order, padded with ``N``) and int32 ``(N,)``
      counts, exact unless they exceed ``width`` (then a lower bound; the
      caller flags overflow).
    """
    n = position.shape[0]
    cut2 = jnp.asarray(cutoff ** 2, position.dtype)
    me = jnp.arange(n, dtype=jnp.int32)
    metric = jax.vmap(jax.vmap(metric_sq, (None, 0)), (0, 0))
    far = jnp.asarray(jnp.inf, position.dtype)
    real = rows < n
    # Each vertex's neighbours' positions, gathered once: the parent test
    # below then reads whole rows (contiguous) instead of single vertices.
    nbr_grid = jnp.where(real[..., None], grid[jnp.minimum(rows, n - 1)], 0)

    def body(c):
        j, found, count = c
        active = j < jnp.minimum(count, width)
        x = found[:, j]
        cand = rows[jnp.minimum(x, n - 1)]  # (N, D)
        safe = jnp.minimum(cand, n - 1)
        d2 = jnp.where(cand < n, metric(position, position[safe]), far)
        inside = active[:, None] & (cand < n) & (cand != me[:, None]) & (
            d2 < cut2)
        # The parent of each candidate: its neighbour closest to v (ties to
        # the lower id).
        ids = rows[safe]  # (N, D, D)
        dv = nbr_grid[safe] - grid[:, None, None, :]
        if L is not None:
            dv = dv - L * jnp.round(dv / L)
        dy = jnp.where(real[safe], jnp.sum(dv * dv, axis=-1), far)
        best = jnp.min(dy, axis=-1, keepdims=True)
        parent = jnp.min(jnp.where(dy == best, ids, n), axis=-1)
        take = inside & (parent == x[:, None])
        slot = count[:, None] + jnp.cumsum(take, axis=1, dtype=jnp.int32) - 1
        slot = jnp.where(take, slot, width)
        found = found.at[me[:, None], slot].set(cand, mode="drop")
        return j + 1, found, count + jnp.sum(take, axis=1, dtype=jnp.int32)

    def cond(c):
        j, _, count = c
        return (j < width) & jnp.any(j < count)

    found = jnp.full((n, width), n, jnp.int32).at[:, 0].set(me)
    _, found, count = lax.while_loop(
        cond, body, (jnp.int32(0), found, jnp.ones((n,), jnp.int32)))
    return found, count


# ---------------------------------------------------------------------------
# The backend


def _targets(position: Array, geometry: Geometry, state: Triangulation,
             periodic: bool) -> tuple[Array, Array]:
    """Vertex targets (V, 2) in grid coordinates, and the sides L (2,)."""
    grid = geometry.grid_coordinates(position)
    if periodic:
        return grid, geometry.side.astype(grid.dtype)
    frame = state.position[-FRAME:]
    return (jnp.concatenate([grid, frame.astype(grid.dtype)]),
            jnp.zeros((2,), grid.dtype))


@dataclasses.dataclass(frozen=True)
class Delaunay:
    """The Delaunay backend (``"delaunay"``, seed 004) as a
    `jaxrt.backends.Backend` that keeps state (module docstring).

    Options (keyword-only, static):
      max_flip_rounds: flip rounds at one fraction of the move before the
        displacement is split (halved).
      max_splits: failed tries (each followed by a split of the move) of
        one maintenance before the triangulation is rebuilt from scratch.
      engine: ``"xla"`` (this module's JAX kernels) or ``"warp"`` (the
        Warp kernels of `jaxrt.backends.rt.delaunay_kernels`, one XLA
        custom call per step through `jaxrt.backends.rt.ffi.delaunay_step`;
        needs ``warp-lang``; pairs decided by jax-md's periodic
        displacement on the grid coordinates, not by the caller's metric;
        no ``vmap``).
      local_repair: keep the triangulation by flips from the last one
        (True), or rebuild it from scratch at every search (False; the
        reference the repair is checked against).
    """

    max_flip_rounds: int = 64
    max_splits: int = 64
    engine: str = "xla"
    local_repair: bool = True
    name: ClassVar[str] = "delaunay"
    stateful: ClassVar[bool] = True

    def __post_init__(self):
        if self.engine not in ("xla", "warp"):
            raise ValueError("Delaunay(engine=...) must be 'xla' or 'warp'; "
                             f"got {self.engine!r}.")
        if not isinstance(self.local_repair, bool):
            raise ValueError("Delaunay(local_repair=...) must be a bool; got "
                             f"{self.local_repair!r}.")
        for k in ("max_flip_rounds", "max_splits"):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) \
                    or v < 1:
                raise ValueError(f"Delaunay({k}=...) must be an int >= 1; "
                                 f"got {v!r}.")

    # -- checks and the initial triangulation (eager, at allocate)

    def _check(self, position, geometry: Geometry, query: Query) -> bool:
        if query.dim != 2:
            raise ValueError("backend='delaunay' triangulates 2D positions; "
                             f"got dim {query.dim}. Use backend='cell' in "
                             "other dimensions.")
        if position.dtype != jnp.float64:
            raise TypeError(
                "backend='delaunay' needs float64 positions (its predicates "
                "are float64, as the poster runs in double precision); got "
                f"{position.dtype}. Enable jax.config.update("
                "'jax_enable_x64', True) and pass float64 positions.")
        if geometry.transform is not None:
            raise ValueError("backend='delaunay' supports free space or a "
                             "rectangular periodic box, not a triclinic one.")
        if any(query.periodic) and not all(query.periodic):
            raise ValueError(
                "backend='delaunay' needs both axes periodic (a torus) or "
                f"both free; got periodic={list(query.periodic)}.")
        return all(query.periodic)

    def init_state(self, position, geometry: Geometry, query: Query
                   ) -> Triangulation:
        """The triangulation at ``allocate`` (eager): Qhull on the host,
        then flips to Delaunay at the true positions. Raises for coincident
        points and unsupported input."""
        periodic = self._check(position, geometry, query)
        grid = np.asarray(geometry.grid_coordinates(position), np.float64)
        side = np.asarray(geometry.side, np.float64) if periodic else None
        wrapped = np.mod(grid, side) if periodic else grid
        pair = coincident_pair(wrapped)
        if pair is not None:
            raise ValueError(
                f"backend='delaunay': particles {pair[0]} and {pair[1]} are "
                "at the same position; a triangulation needs distinct "
                "points. Move one of them (or use backend='cell').")
        if len(grid) < 3:
            raise ValueError("backend='delaunay' needs at least 3 particles; "
                             f"got {len(grid)}.")
        pos, tri, twin, shift, safe, ok = host_triangulate(
            grid, side, query.cutoff)
        if not ok:
            raise ValueError(
                "backend='delaunay' could not triangulate the positions "
                "(Qhull failed, or the points are degenerate, e.g. all "
                "collinear); use backend='cell'.")
        L = jnp.asarray(side if periodic else np.zeros(2), jnp.float64)
        if self.engine == "warp":
            from jaxrt.backends.rt import ffi
            tri, twin, shift, flips, done = ffi.delaunay_flip(
                pos, tri, twin, shift, np.asarray(L), periodic=periodic,
                max_rounds=self.max_flip_rounds)
            tri, twin, shift = (jnp.asarray(x) for x in (tri, twin, shift))
            flips = jnp.int32(flips)
        else:
            tri, twin, shift, flips, done = _flip_jit(
                tri, twin, shift, jnp.asarray(pos), L,
                max_rounds=self.max_flip_rounds)
        if not bool(done):
            raise ValueError(
                "backend='delaunay': the flips to Delaunay did not converge "
                f"in max_flip_rounds={self.max_flip_rounds} rounds at "
                "allocate; raise max_flip_rounds.")
        z = jnp.zeros((), jnp.int32)
        return Triangulation(jnp.asarray(pos), tri, twin, shift,
                             jnp.asarray(safe), z, flips, flips, z,
                             jnp.bool_(False))

    def measure(self, position, geometry, query, metric_sq, *, state):
        """Exact sizes: ``row``, ``edges``, the vertex ``degree`` and the
        BFS ``frontier`` (the vertex itself included)."""
        n = position.shape[0]
        degree = int(np.bincount(np.asarray(state.tri).ravel(),
                                 minlength=n + FRAME)[:n].max(initial=0))
        # In free space a vertex's row lacks the frame vertices; the count
        # above includes them: an upper bound, which is all sizing needs.
        width = min(n, 64)
        while True:
            cap = Capacity(0, (("degree", degree), ("frontier", width),
                               ("row", width)))
            if self.engine == "warp":
                found, count = _warp_frontiers(position, geometry, state,
                                               query, width)
            else:
                found, count = _frontiers_jit(position, geometry, state,
                                              metric_sq, query=query,
                                              capacity=cap)
            top = int(jnp.max(count))
            if top <= width or width >= n:
                break
            width = min(n, 2 * top)
        keep = np.asarray(found) < n
        if query.mask_self:
            keep[:, 0] = False
        i = np.arange(n)[:, None]
        rows = int(keep.sum(1).max(initial=0))
        ordered = query.format.name == "OrderedSparse"
        edges = int((keep & (np.asarray(found) < i)).sum() if ordered
                    else keep.sum())
        return {"row": rows, "edges": edges, "degree": degree,
                "frontier": top}

    def search(self, position, geometry, query, capacity: Capacity,
               metric_sq, *, state):
        """Maintain the triangulation at ``position`` (rebuilding it where
        that fails) and search it. Returns ``(SearchResult, state)``."""
        rows_of = _search_rows_warp if self.engine == "warp" else \
            _search_rows
        found, count, overflow, error, state = rows_of(
            self, position, geometry, query, capacity, metric_sq, state)
        start = 1 if query.mask_self else 0
        rows = found[:, start:]
        counts = count - start
        width = capacity["row"]
        if rows.shape[1] < width:
            pad = jnp.full((rows.shape[0], width - rows.shape[1]),
                           rows.shape[0], jnp.int32)
            rows = jnp.concatenate([rows, pad], axis=1)
        result = _backend.format_dense_rows(rows[:, :width], counts, query,
                                            capacity)
        return result._replace(overflow=result.overflow | overflow,
                               error=error), state


def _frontiers(position, geometry: Geometry, state: Triangulation,
               metric_sq: MetricSq, query: Query, capacity: Capacity):
    """Adjacency and BFS of ``state`` as it is (no maintenance): frontiers
    int32 ``(N, K)``, counts int32 ``(N,)``, overflow and repeated-edge
    flags (bool)."""
    n = position.shape[0]
    width = min(max(capacity["frontier"], capacity["row"] + 1), n)
    rows, degrees, repeated = adjacency(state.tri, n, capacity["degree"])
    periodic = all(query.periodic)
    found, count = bfs(position, rows, metric_sq, query.cutoff, width,
                       state.position[:n], geometry.side.astype(
                           position.dtype) if periodic else None)
    overflow = (jnp.any(degrees > capacity["degree"])
                | jnp.any(count > width))
    return found, count, overflow, repeated


def _search_rows(backend: Delaunay, position, geometry: Geometry,
                 query: Query, capacity: Capacity, metric_sq: MetricSq,
                 state: Triangulation):
    """Maintenance, adjacency and BFS. Returns the frontiers (int32
    ``(N, K)``), counts (int32 ``(N,)``), an overflow flag, error bits
    (uint8) and the new state."""
    periodic = all(query.periodic)
    n = position.shape[0]
    target, L = _targets(position, geometry, state, periodic)
    kept, failed = maintain(state, target, L, periodic=periodic,
                            max_flip_rounds=backend.max_flip_rounds,
                            max_splits=backend.max_splits)
    if not backend.local_repair:
        failed = jnp.bool_(True)
    rebuild = functools.partial(
        _device_rebuild, points=target[:n], L=L, periodic=periodic,
        cutoff=query.cutoff)
    state = lax.cond(failed, lambda s: rebuild(s), lambda s: s, kept)
    state = _finish_rebuild(state, failed, L, backend.max_flip_rounds)
    found, count, overflow, repeated = _frontiers(
        position, geometry, state, metric_sq, query, capacity)
    bad = state.failed | repeated
    error = jnp.where(bad, jnp.uint8(ErrorCode.SEARCH_FAILED
                                     | ErrorCode.NEIGHBOR_LIST_OVERFLOW),
                      jnp.uint8(0))
    return found, count, overflow | bad, error, state


def _warp_frontiers(position, geometry: Geometry, state: Triangulation,
                    query: Query, width: int):
    """`_frontiers` on the Warp engine (eager, at ``measure``)."""
    from jaxrt.backends.rt import ffi
    periodic = all(query.periodic)
    n = position.shape[0]
    return ffi.delaunay_counts(
        np.asarray(geometry.grid_coordinates(position), np.float64), state,
        np.asarray(geometry.side, np.float64), n=n, periodic=periodic,
        cutoff=query.cutoff, width=width)


def _search_rows_warp(backend: Delaunay, position, geometry: Geometry,
                      query: Query, capacity: Capacity, metric_sq: MetricSq,
                      state: Triangulation):
    """`_search_rows` on the Warp engine: maintenance (or rebuild) and
    BFS in one custom call."""
    from jaxrt.backends.rt import ffi
    del metric_sq  # the kernels decide pairs with jax-md's arithmetic
    periodic = all(query.periodic)
    n = position.shape[0]
    width = min(max(capacity["frontier"], capacity["row"] + 1), n)
    target, L = _targets(position, geometry, state, periodic)
    pos, tri, twin, shift, safe, found, count, stats = ffi.delaunay_step(
        target, target[:n], geometry.side.astype(target.dtype), state,
        cutoff=query.cutoff, periodic=periodic, width=width,
        local_repair=backend.local_repair,
        max_flip_rounds=backend.max_flip_rounds,
        max_splits=backend.max_splits)
    failed = stats[1] > 0
    state = state._replace(
        position=pos, tri=tri, twin=twin, shift=shift, safe=safe,
        rebuilds=state.rebuilds + stats[0], flips=stats[2],
        flips_total=state.flips_total + stats[2], splits=stats[3],
        failed=failed)
    overflow = jnp.any(count > width)
    error = jnp.where(failed, jnp.uint8(ErrorCode.SEARCH_FAILED
                                        | ErrorCode.NEIGHBOR_LIST_OVERFLOW),
                      jnp.uint8(0))
    return found, count, overflow | failed, error, state


_flip_jit = jax.jit(flip_to_delaunay, static_argnames="max_rounds")
_frontiers_jit = jax.jit(lambda p, g, s, m, *, query, capacity: _frontiers(
    p, g, s, m, query, capacity)[:2], static_argnames=("query", "capacity"))


def stats(neighbors) -> dict:
    """Host-side counters of a Delaunay list's triangulation: rebuilds
    from scratch since ``allocate``, flips of the last maintenance and in
    total, displacement halvings of the last maintenance, and whether the
    last rebuild failed."""
    s = neighbors.backend_state
    if not isinstance(s, Triangulation):
        raise TypeError("stats needs a list of backend='delaunay'.")
    return {k: (bool(np.asarray(v)) if k == "failed" else
                np.asarray(v).tolist())
            for k, v in s._asdict().items()
            if k in ("rebuilds", "flips", "flips_total", "splits", "failed")}
