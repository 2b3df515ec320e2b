"""The host side of the Warp Delaunay engine: launches the kernels of
`jaxrt.backends.rt.delaunay_kernels` until the flips converge, maintains a
triangulation through a move (local repair, with the poster's displacement
splitting), and searches it. Warp and NumPy only (no JAX); the triangulation
from scratch is the caller's (``rebuild``, e.g.
`jaxrt.backends.delaunay.host_triangulate`).

Flip rounds run in batches of ``ROUNDS_PER_READ`` launches with no host
read in between: each round counts its flips on the device, a round after
one that flipped nothing is a no-op (the device-side done flag), and only
the triangles of the previous round's wanting edges are re-tested, from a
compacted worklist (grid-stride launches of at most `STRIDE_THREADS`).
The host reads one small status array per batch (the rounds' flips and
the inverted triangles left), so a converged try costs one read whatever
its number of rounds. Launches are recorded once and replayed.
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
        self.claim = wp.full(t, k.UNCLAIMED, dtype=wp.int32, device=dev)
        self.twin_new = wp.zeros((t, 3), dtype=wp.int32, device=dev)
        self.counter = wp.zeros(1, dtype=wp.int32, device=dev)
        # status[0]: inverted triangles; status[1 + r]: flips of round r.
        self.status = wp.zeros(2 + ROUNDS_PER_READ, dtype=wp.int32, device=dev)
        # Three worklists of triangles (read, being filled, emptied) with
        # their membership flags; sizes[3]: rows rewritten this round.
        self.lists = wp.zeros((3, t), dtype=wp.int32, device=dev)
        self.flag = wp.zeros((3, t), dtype=wp.int32, device=dev)
        self.sizes = wp.zeros(5, dtype=wp.int32, device=dev)
        self.seeds = wp.zeros(t, dtype=wp.int32, device=dev)
        self.written = wp.zeros(2 * t + 4, dtype=wp.int32, device=dev)
        self.ring = 0  # the worklist the next round reads
        self.launches: dict = {}  # `_round_launches`
        self.commands: dict = {}  # `_launch`
        # Rows a flip changed since the last save (flags, list); size.
        self.touched = wp.zeros((2, t), dtype=wp.int32, device=dev)
        self.touched_size = wp.zeros(1, dtype=wp.int32, device=dev)
        self.step = wp.zeros(v, dtype=wp.float64, device=dev)
        self.kept = (wp.zeros_like(m.tri), wp.zeros_like(m.twin),
                     wp.zeros_like(m.shift))  # the last valid connectivity
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


ROUNDS_PER_READ = 16
"""Flip rounds launched between two host reads on a GPU. On the CPU a
launch runs to completion before the next, so a read costs nothing and
each round is read (a no-op round would cost a full pass there)."""
STRIDE_THREADS = 1 << 17
"""Threads of a worklist launch (grid-stride): a round after the first
costs its worklist (the tangle) plus one launch of this size, whatever the
mesh's size; 2^17 threads keep an H200's SMs busy on a long list."""


GROW, SHRINK = 2.0, 0.5
"""A step's factor after a successful try, and a tangled vertex's after a
failed one (measured on Boids and random walks: 4 and 1/4 in either place
did not cut the tries)."""


def _threads(work: int) -> int:
    return max(1, min(work, STRIDE_THREADS))


def rounds_per_read(m: Mesh, rounds: int | None = None) -> int:
    """``rounds`` (1 to `ROUNDS_PER_READ`) or the device's default."""
    if rounds is None:
        return ROUNDS_PER_READ if m.device.is_cuda else 1
    if not 1 <= rounds <= ROUNDS_PER_READ:
        raise ValueError(f"rounds_per_read={rounds}: pass 1 to "
                         f"{ROUNDS_PER_READ}.")
    return int(rounds)


def _key(x):
    if isinstance(x, wp.array):
        return (x.ptr, x.shape)
    if isinstance(x, (int, float, str)):
        return x
    return tuple(float(c) for c in x)  # a Warp vector


def _launch(s: _Scratch, kernel, dim, device, inputs: list) -> None:
    """``wp.launch`` of a maintenance kernel from a launch recorded once
    per (kernel, dim, arguments): the tries of a step repeat the same
    launches, and a recorded one costs the host a few microseconds
    instead of packing every argument again."""
    key = (kernel.key, dim, str(device), tuple(_key(x) for x in inputs))
    cmd = s.commands.get(key)
    if cmd is None:
        if len(s.commands) >= 256:  # a caller's buffers changed: forget
            s.commands.clear()
        cmd = wp.launch(kernel, dim=dim, device=device, inputs=inputs,
                        record_cmd=True)
        s.commands[key] = cmd
    cmd.launch()


def _round_launches(m: Mesh, P: wp.array, s: _Scratch) -> tuple:
    """The launches of a flip round (`flip_mark` over every edge, over a
    worklist, `flip_apply`, `finish_round`), recorded once per set of
    arrays: a round then costs the host a few microseconds per launch
    instead of packing every argument again (the rounds of a try are
    launched whether or not the device finds them no-ops)."""
    key = (m.tri.ptr, m.twin.ptr, m.shift.ptr, P.ptr, tuple(m.side),
           str(m.device))
    if key not in s.launches:
        if len(s.launches) >= 8:  # a caller's buffers changed: forget
            s.launches.clear()
        t, dev = m.tri.shape[0], m.device
        edges, tris = _threads(3 * t), _threads(t)

        def mark(dim, first):
            return wp.launch(
                k.flip_mark, dim=dim, device=dev, record_cmd=True,
                inputs=[m.tri, m.twin, m.shift, P, m.L, s.want, s.claim,
                        s.flag, s.lists, s.sizes, s.status, 0, 0, first,
                        dim])
        s.launches[key] = (
            mark(3 * t, 1), mark(edges, 0),
            wp.launch(k.flip_apply, dim=tris, device=dev, record_cmd=True,
                      inputs=[m.tri, m.twin, m.shift, s.want, s.claim,
                              s.twin_new, s.lists, s.sizes, s.written,
                              s.status, 0, 0, tris]),
            wp.launch(k.finish_round, dim=tris, device=dev, record_cmd=True,
                      inputs=[s.twin_new, m.twin, s.claim, s.flag, s.lists,
                              s.sizes, s.written, s.touched, s.touched_size,
                              s.status, 0, 0, tris]))
    return s.launches[key]


def flip_batch(m: Mesh, P: wp.array, rounds: int, *,
               fresh: bool, seeded: bool = False) -> tuple[int, int, int]:
    """Up to ``rounds`` (at most `ROUNDS_PER_READ`) flip rounds at ``P``,
    then the validity check, with one host read at the end. ``fresh``: all
    triangles are tested in the first round (after a move); otherwise only
    those the last batch's final round marked (its wanting edges').
    ``seeded`` (maintenance from a verified Delaunay triangulation at the
    committed fractions, `maintain`): a fresh batch tests only the
    triangles of the vertices that move (`delaunay_kernels.seed_moved`),
    and every batch of the try checks only those. Returns ``(flips, last,
    bad)``: the flips, those of the last round run (0: converged), and the
    triangles not certainly positive (their vertices marked in the
    scratch's ``bad_vertex``)."""
    s = scratch(m)
    t = m.tri.shape[0]
    dev = m.device
    s.status.zero_()
    if fresh:
        s.flag.zero_()
        s.sizes.zero_()
        s.ring = 0
        if seeded:
            _launch(s, k.seed_moved, t, dev,
                    [m.tri, s.delta, s.done_part, s.fraction, s.flag,
                     s.lists, s.sizes, s.seeds, s.ring])
    wp.copy(s.twin_new, m.twin)
    tris = _threads(t)
    mark_all, mark, apply, finish = _round_launches(m, P, s)
    for r in range(rounds):
        first = fresh and not seeded and r == 0  # all edges, no worklist
        for cmd, at in ((mark_all if first else mark, 11), (apply, 10),
                        (finish, 10)):
            cmd.set_param_at_index(at, r)
            cmd.set_param_at_index(at + 1, s.ring)
            cmd.launch()
        s.ring = (s.ring + 1) % 3  # the worklist this round filled
    s.bad_vertex.zero_()
    if seeded:
        _launch(s, k.check_seeds, tris, dev,
                [m.tri, m.shift, P, m.L, s.seeds, s.sizes, s.bad_vertex,
                 s.status, tris])
    else:
        _launch(s, k.check_triangles, t, dev,
                [m.tri, m.shift, P, m.L, s.bad_vertex, s.status])
    st = s.status.numpy()
    per_round = st[1:1 + rounds]
    return int(per_round.sum()), int(per_round[-1]), int(st[0])


def flip_to_delaunay(m: Mesh, P: wp.array | None = None,
                     max_rounds: int = 64, rounds_per_read: int | None = None
                     ) -> tuple[int, bool]:
    """Flip rounds at ``P`` (default: the mesh's positions) until none is
    wanted. Returns ``(flips, done)``: ``done`` when the rounds ended with
    nothing to flip and every triangle positive (a Delaunay triangulation
    of ``P``). ``rounds_per_read``: see `rounds_per_read`."""
    flips, _, done, _ = _flip_rounds(m, m.position if P is None else P,
                                     max_rounds, rounds_per_read)
    return flips, done


def _flip_rounds(m: Mesh, P: wp.array, max_rounds: int,
                 per_read: int | None = None, seeded: bool = False
                 ) -> tuple[int, int, bool, int]:
    """`flip_to_delaunay`: ``(flips, host reads, done, triangles not
    certainly positive after the last batch)``; ``seeded``: see
    `flip_batch`."""
    per_read = rounds_per_read(m, per_read)
    flips = reads = 0
    left, fresh = max_rounds, True
    while left > 0:
        rounds = min(left, per_read)
        f, last, bad = flip_batch(m, P, rounds, fresh=fresh, seeded=seeded)
        flips += f
        reads += 1
        left -= rounds
        fresh = False
        if last == 0:
            return flips, reads, bad == 0, bad
    return flips, reads, False, bad


@dataclasses.dataclass
class Maintenance:
    """What one `maintain` did: ``ok`` (False: the caller must rebuild;
    the mesh's positions are then unchanged, its triangles valid for part
    of the move only), ``flips``, ``splits`` (failed tries), ``tries``,
    ``reads`` (host reads of device results) and ``seeded`` (tries that
    tested only the triangles of their moving vertices)."""

    ok: bool
    flips: int
    splits: int
    tries: int = 0
    reads: int = 0
    seeded: int = 0


def _save(m: Mesh, kept) -> None:
    """The whole mesh becomes the last valid triangulation; no row is
    touched since."""
    s = scratch(m)
    for dst, src in zip(kept, (m.tri, m.twin, m.shift)):
        wp.copy(dst, src)
    s.touched[0].zero_()
    s.touched_size.zero_()


def _copy_touched(m: Mesh, kept, *, keep: bool) -> None:
    """``keep``: the rows the flips touched since the last save become the
    last valid triangulation; else they go back to it (a try undone).
    Every other row is the same in both: the cost is the tangle's."""
    s = scratch(m)
    t = m.tri.shape[0]
    mesh = (m.tri, m.twin, m.shift)
    src, dst = (mesh, kept) if keep else (kept, mesh)
    _launch(s, k.copy_rows, _threads(t), m.device,
            [*src, *dst, s.touched, s.touched_size, _threads(t)])
    s.touched_size.zero_()


def maintain(m: Mesh, target: wp.array, *, max_flip_rounds: int = 64,
             max_splits: int = 64, rounds_per_read: int | None = None
             ) -> Maintenance:
    """Local repair: move the vertices from ``m.position`` to ``target``
    (vec2d ``(V, 2)``; frame vertices unmoved) and restore the Delaunay
    condition by flips from the current triangulation.

    Where a try leaves inverted triangles (a tangle flips cannot undo),
    the mesh goes back to its last valid triangulation (only the rows
    the try's flips touched are copied back) and the vertices of
    those triangles halve their step along their move while every other
    vertex keeps its own; after a successful try the steps double again.
    So each try bisects every tangle of the mesh at once, and the
    vertices away from tangles finish their move in the first successful
    try; the tries after it start from that checked triangulation and
    test only the triangles of the vertices still moving (a tangle's
    neighbourhood), so they cost the tangle, not the mesh.
    ``max_splits`` caps the failed tries; past it ``ok`` is False.
    ``rounds_per_read``: see `rounds_per_read`.
    """
    s = scratch(m)
    v = m.position.shape[0]
    dev = m.device
    reads = 0
    if not m.periodic:
        s.counter.zero_()
        lo, hi = m.safe
        wp.launch(k.count_outside, dim=m.n, device=dev,
                  inputs=[target, wp.vec2d(*lo), wp.vec2d(*hi), s.counter])
        reads += 1
        if int(s.counter.numpy()[0]):
            return Maintenance(False, 0, 0, 0, reads)
    wp.launch(k.move_delta, dim=v, device=dev,
              inputs=[m.position, target, m.L, int(m.periodic), s.delta])
    s.done_part.zero_()
    s.step.fill_(1.0)
    flips = splits = tries = seeded = 0
    # Set once a try has succeeded: the kept triangulation is then a
    # checked Delaunay one (at the committed fractions), and later tries
    # test only the triangles of the vertices they move.
    verified = False
    _save(m, s.kept)
    while True:
        tries += 1
        seeded += verified
        _launch(s, k.try_fraction, v, dev, [s.done_part, s.step, s.fraction])
        _launch(s, k.move_part, v, dev, [m.position, s.delta, s.fraction, s.P])
        f, r, done, any_bad = _flip_rounds(m, s.P, max_flip_rounds,
                                           rounds_per_read, seeded=verified)
        reads += r
        if done:
            flips += f
            if splits == 0:  # no step was ever halved: every move is whole
                break
            s.counter.zero_()
            _launch(s, k.commit_try, v, dev,
                    [s.done_part, s.step, s.fraction, s.counter, GROW])
            reads += 1
            if int(s.counter.numpy()[0]) == 0:
                break
            _copy_touched(m, s.kept, keep=True)
            verified = True
            continue
        # bad_vertex marks the vertices of the triangles left inverted;
        # none (the rounds ran out) halves every step.
        _copy_touched(m, s.kept, keep=False)
        splits += 1
        if splits >= max_splits:
            return Maintenance(False, flips, splits, tries, reads, seeded)
        _launch(s, k.halve_steps, v, dev,
                [s.step, s.bad_vertex, any_bad, SHRINK])
    if m.periodic:
        wp.launch(k.wrap, dim=v, device=dev,
                  inputs=[m.position, s.delta, m.L, s.P, s.periods])
        wp.launch(k.add_periods, dim=m.tri.shape, device=dev,
                  inputs=[m.tri, s.periods, m.shift])
    wp.copy(m.position, s.P)
    return Maintenance(True, flips, splits, tries, reads, seeded)


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
         max_flip_rounds: int = 64, max_splits: int = 64) -> Step:
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
