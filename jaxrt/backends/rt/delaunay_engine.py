"""The host side of the Warp Delaunay engine: launches the kernels of
`jaxrt.backends.rt.delaunay_kernels` until the flips converge, maintains a
triangulation through a move (local repair, with the poster's displacement
splitting), and searches it. Warp and NumPy only (no JAX); the triangulation
from scratch is the caller's (``rebuild``, e.g.
`jaxrt.backends.delaunay.host_triangulate`).

Each flip round reads one counter back to the host (the number of flips)
to decide whether to go on; everything else stays on the device.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import warp as wp

from jaxrt.backends.rt import delaunay_kernels as k


@dataclasses.dataclass
class Mesh:
    """A triangulation on a Warp device (layout of
    `jaxrt.backends.delaunay.Triangulation`).

    Attributes:
      position: vec2d ``(V, 2)``, the positions it is Delaunay for (``V``:
        the ``n`` particles, then 4 frame vertices in free space).
      tri, twin: int32 ``(T, 3)``; shift: vec2i ``(T, 3)``.
      side: float64 ``(2,)`` box sides on a torus, zeros in free space.
      safe: float64 ``(2, 2)``, free space: the box the particles must
        stay in for the frame to hold them.
      n: the number of particles; periodic: a torus.
    """

    position: wp.array
    tri: wp.array
    twin: wp.array
    shift: wp.array
    side: np.ndarray
    safe: np.ndarray
    n: int
    periodic: bool

    @property
    def device(self):
        return self.tri.device

    @property
    def L(self):
        return wp.vec2d(*(float(x) for x in self.side))

    def numpy(self) -> dict:
        """Host copies: position (V, 2), tri, twin (T, 3), shift (T, 3, 2)."""
        return {"position": self.position.numpy(), "tri": self.tri.numpy(),
                "twin": self.twin.numpy(), "shift": self.shift.numpy()}


def mesh(position, tri, twin, shift, *, n: int, side=None, safe=None,
         device="cpu") -> Mesh:
    """A `Mesh` on ``device`` from host arrays (``position`` float64
    ``(V, 2)``, ``tri``/``twin`` int32 ``(T, 3)``, ``shift`` int32
    ``(T, 3, 2)``; ``side`` ``(2,)`` for a torus, None in free space)."""
    periodic = side is not None
    side = np.zeros(2) if side is None else np.asarray(side, np.float64)
    return Mesh(
        wp.array(np.asarray(position, np.float64), dtype=wp.vec2d, device=device),
        wp.array(np.asarray(tri, np.int32), dtype=wp.int32, device=device),
        wp.array(np.asarray(twin, np.int32), dtype=wp.int32, device=device),
        wp.array(np.asarray(shift, np.int32), dtype=wp.vec2i, device=device),
        side, np.zeros((2, 2)) if safe is None else np.asarray(safe), n,
        periodic)


class _Scratch:
    """Per-mesh-size work arrays, made once."""

    def __init__(self, m: Mesh):
        t, v, dev = m.tri.shape[0], m.position.shape[0], m.device
        self.want = wp.zeros(3 * t, dtype=wp.int32, device=dev)
        self.claim = wp.zeros(t, dtype=wp.int32, device=dev)
        self.twin_new = wp.zeros((t, 3), dtype=wp.int32, device=dev)
        self.counter = wp.zeros(1, dtype=wp.int32, device=dev)
        self.bad_vertex = wp.zeros(v, dtype=wp.int32, device=dev)
        self.delta = wp.zeros(v, dtype=wp.vec2d, device=dev)
        self.P = wp.zeros(v, dtype=wp.vec2d, device=dev)
        self.done_part = wp.zeros(v, dtype=wp.float64, device=dev)
        self.fraction = wp.zeros(v, dtype=wp.float64, device=dev)
        self.periods = wp.zeros(v, dtype=wp.vec2i, device=dev)
        self.degree = wp.zeros(m.n + 1, dtype=wp.int32, device=dev)
        self.start = wp.zeros(m.n + 1, dtype=wp.int32, device=dev)
        self.fill = wp.zeros(m.n, dtype=wp.int32, device=dev)
        self.neighbours = wp.zeros(6 * t, dtype=wp.int32, device=dev)


_SCRATCH: dict = {}


def scratch(m: Mesh) -> _Scratch:
    key = (m.tri.shape[0], m.position.shape[0], m.n, str(m.device))
    if key not in _SCRATCH:
        _SCRATCH.clear()  # one size at a time: benchmarks sweep N
        _SCRATCH[key] = _Scratch(m)
    return _SCRATCH[key]


def flip_round(m: Mesh, P: wp.array) -> int:
    """One round of conflict-free flips at positions ``P``; returns the
    number of flips (read back to the host)."""
    s = scratch(m)
    t = m.tri.shape[0]
    s.claim.fill_(k.UNCLAIMED)
    s.counter.zero_()
    wp.launch(k.flip_mark, dim=3 * t, device=m.device,
              inputs=[m.tri, m.twin, m.shift, P, m.L, s.want, s.claim])
    wp.copy(s.twin_new, m.twin)
    wp.launch(k.flip_apply, dim=3 * t, device=m.device,
              inputs=[m.tri, m.twin, m.shift, s.want, s.claim, s.twin_new,
                      s.counter])
    # Copied back, not swapped: the mesh's arrays may be a caller's
    # buffers (an XLA call's outputs), which must end up holding the result.
    wp.copy(m.twin, s.twin_new)
    return int(s.counter.numpy()[0])


def bad_triangles(m: Mesh, P: wp.array) -> int:
    """Triangles not certainly positive at ``P`` (their vertices marked in
    the scratch's ``bad_vertex``)."""
    s = scratch(m)
    s.bad_vertex.zero_()
    s.counter.zero_()
    wp.launch(k.check_triangles, dim=m.tri.shape[0], device=m.device,
              inputs=[m.tri, m.shift, P, m.L, s.bad_vertex, s.counter])
    return int(s.counter.numpy()[0])


def flip_to_delaunay(m: Mesh, P: wp.array | None = None,
                     max_rounds: int = 64) -> tuple[int, bool]:
    """Flip rounds at ``P`` (default: the mesh's positions) until none is
    wanted. Returns ``(flips, done)``: ``done`` when the rounds ended with
    nothing to flip and every triangle positive (a Delaunay triangulation
    of ``P``)."""
    P = m.position if P is None else P
    flips = 0
    for _ in range(max_rounds):
        f = flip_round(m, P)
        flips += f
        if f == 0:
            return flips, bad_triangles(m, P) == 0
    return flips, False


@dataclasses.dataclass
class Maintenance:
    """What one `maintain` did: ``ok`` (False: the caller must rebuild;
    the mesh's positions are then unchanged, its triangles valid for part
    of the move only), ``flips``, ``splits`` (failed tries)."""

    ok: bool
    flips: int
    splits: int


def _save(m: Mesh, kept=None):
    """Copies of the mesh's connectivity (into ``kept`` if given)."""
    if kept is None:
        return wp.clone(m.tri), wp.clone(m.twin), wp.clone(m.shift)
    for dst, src in zip(kept, (m.tri, m.twin, m.shift)):
        wp.copy(dst, src)
    return kept


def _restore(m: Mesh, kept) -> None:
    for dst, src in zip((m.tri, m.twin, m.shift), kept):
        wp.copy(dst, src)


def maintain(m: Mesh, target: wp.array, *, max_flip_rounds: int = 64,
             max_splits: int = 32) -> Maintenance:
    """Local repair: move the vertices from ``m.position`` to ``target``
    (vec2d ``(V, 2)``; frame vertices unmoved) and restore the Delaunay
    condition by flips from the current triangulation, splitting the
    displacement where a try fails (as `jaxrt.backends.delaunay.maintain`).
    """
    s = scratch(m)
    v = m.position.shape[0]
    dev = m.device
    if not m.periodic:
        s.counter.zero_()
        lo, hi = m.safe
        wp.launch(k.count_outside, dim=m.n, device=dev,
                  inputs=[target, wp.vec2d(*lo), wp.vec2d(*hi), s.counter])
        if int(s.counter.numpy()[0]):
            return Maintenance(False, 0, 0)
    wp.launch(k.move_delta, dim=v, device=dev,
              inputs=[m.position, target, m.L, int(m.periodic), s.delta])
    s.done_part.zero_()
    s.fraction.fill_(1.0)
    whole, flips, splits = True, 0, 0
    kept = _save(m)
    while True:
        wp.launch(k.move_part, dim=v, device=dev,
                  inputs=[m.position, s.delta, s.fraction, s.P])
        f, done = flip_to_delaunay(m, s.P, max_flip_rounds)
        if done:
            flips += f
            if whole:
                break
            wp.copy(s.done_part, s.fraction)
            s.fraction.fill_(1.0)
            whole = True
            _save(m, kept)
            continue
        any_bad = bad_triangles(m, s.P)  # marks the vertices to split
        _restore(m, kept)
        splits += 1
        if splits >= max_splits:
            return Maintenance(False, flips, splits)
        wp.launch(k.split_move, dim=v, device=dev,
                  inputs=[s.done_part, s.fraction, s.bad_vertex, any_bad])
        whole = False
    if m.periodic:
        wp.launch(k.wrap, dim=v, device=dev,
                  inputs=[m.position, s.delta, m.L, s.P, s.periods])
        wp.launch(k.add_periods, dim=m.tri.shape, device=dev,
                  inputs=[m.tri, s.periods, m.shift])
    wp.copy(m.position, s.P)
    return Maintenance(True, flips, splits)


def adjacency(m: Mesh) -> tuple[wp.array, wp.array]:
    """CSR adjacency of the particles: int32 ``start (n + 1,)`` and
    ``neighbours`` (each row in no particular order)."""
    s = scratch(m)
    s.degree.zero_()
    s.fill.zero_()
    wp.launch(k.degree_count, dim=m.tri.shape, device=m.device,
              inputs=[m.tri, m.n, s.degree])
    wp.utils.array_scan(s.degree, s.start, inclusive=False)
    wp.launch(k.degree_fill, dim=m.tri.shape, device=m.device,
              inputs=[m.tri, m.n, s.start, s.fill, s.neighbours])
    return s.start, s.neighbours


def max_degree(m: Mesh) -> int:
    s = scratch(m)
    adjacency(m)
    return int(s.degree.numpy()[:m.n].max(initial=0))


@dataclasses.dataclass
class Search:
    """A radius search's output (Warp arrays on the mesh's device).

    Attributes:
      found: int32 ``(n, width)``: each vertex, then its neighbours within
        the cutoff, padded with ``n``.
      count: int32 ``(n,)``: entries of each row, the vertex included (a
        lower bound past ``width``).
      pairs: int32 ``(capacity, 2)`` (i, j) pairs, both orders, in no
        particular order; pair_count: int32 ``(1,)``, the pairs found
        (past ``capacity``: overflow).
    """

    found: wp.array
    count: wp.array
    pairs: wp.array
    pair_count: wp.array

    def overflow(self) -> bool:
        width = self.found.shape[1]
        return bool(self.count.numpy().max(initial=0) > width
                    or self.pair_count.numpy()[0] > self.pairs.shape[0])

    def pair_set(self) -> set[tuple[int, int]]:
        p = self.pairs.numpy()[:min(int(self.pair_count.numpy()[0]),
                                    self.pairs.shape[0])]
        return set(map(tuple, p.tolist()))


def radius_search(m: Mesh, cutoff: float, *, width: int,
                  pair_capacity: int = 0, points: wp.array | None = None,
                  out: Search | None = None) -> Search:
    """The BFS of every particle (`delaunay_kernels.radius_bfs`).

    ``points``: vec2d ``(n,)`` positions that decide the pairs (default:
    the mesh's); ``width``: row size, the vertex included;
    ``pair_capacity``: 0 writes no pair buffer. ``out`` reuses arrays.
    """
    dev = m.device
    n = m.n
    if out is None:
        out = Search(wp.zeros((n, width), dtype=wp.int32, device=dev),
                     wp.zeros(n, dtype=wp.int32, device=dev),
                     wp.zeros((max(pair_capacity, 1), 2), dtype=wp.int32,
                              device=dev),
                     wp.zeros(1, dtype=wp.int32, device=dev))
    out.pair_count.zero_()
    start, neighbours = adjacency(m)
    points = m.position if points is None else points
    wp.launch(k.radius_bfs, dim=n, device=dev,
              inputs=[points, m.position, start, neighbours, m.L,
                      int(m.periodic), float(cutoff) ** 2, n, out.found,
                      out.count, int(pair_capacity > 0), out.pairs,
                      out.pair_count])
    return out


def load_host(m: Mesh, position, tri, twin, shift, safe) -> None:
    """Overwrite the mesh with host arrays of the same shapes (a rebuild)."""
    dev = m.device
    for dst, src, dtype in ((m.position, position, wp.vec2d),
                            (m.tri, tri, wp.int32), (m.twin, twin, wp.int32),
                            (m.shift, shift, wp.vec2i)):
        wp.copy(dst, wp.array(np.asarray(src), dtype=dtype, device=dev))
    m.safe = np.asarray(safe, np.float64)


@dataclasses.dataclass
class Step:
    """What one `step` did: ``rebuilt`` from scratch, ``failed`` (the
    rebuild failed too: the list is not valid), ``flips``, ``splits``."""

    rebuilt: bool
    failed: bool
    flips: int
    splits: int


def step(m: Mesh, target: wp.array, rebuild, *, local_repair: bool = True,
         max_flip_rounds: int = 64, max_splits: int = 32) -> Step:
    """Bring the mesh to ``target`` (vec2d ``(V,)``, frame vertices
    included): local repair by `maintain`, or (``local_repair=False``, or
    where repair fails) a rebuild from scratch by ``rebuild(points)``
    (float64 ``(n, 2)`` -> ``(position, tri, twin, shift, safe, ok)``, as
    `jaxrt.backends.delaunay.host_triangulate`) finished by flips."""
    flips = splits = 0
    if local_repair:
        r = maintain(m, target, max_flip_rounds=max_flip_rounds,
                     max_splits=max_splits)
        if r.ok:
            return Step(False, False, r.flips, r.splits)
        flips, splits = r.flips, r.splits
    out = rebuild(target.numpy()[:m.n])
    if not out[-1]:
        return Step(True, True, flips, splits)
    load_host(m, *out[:-1])
    f, done = flip_to_delaunay(m, max_rounds=max_flip_rounds)
    return Step(True, not done, flips + f, splits)
