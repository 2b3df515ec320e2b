"""Warp kernels of seed 004's Delaunay search (2D, float64): edge flips
with atomically claimed triangles, the validity check, the moves of
maintenance, the adjacency and the radius BFS. Pure Warp: they know
nothing of JAX (`jaxrt.backends.rt.ffi` wraps them; the host loop that
drives them is `jaxrt.backends.rt.delaunay_engine`).

The triangulation's layout is `jaxrt.backends.delaunay.Triangulation`'s:
``tri`` int32 ``(T, 3)`` counter-clockwise vertex ids, ``twin`` int32
``(T, 3)`` the half-edge ``3 u + m`` across the edge opposite local vertex
``e`` of triangle ``t`` (half-edge ``3 t + e``; -1 on the frame's hull),
``shift`` vec2i ``(T, 3)`` the image shift of each triangle vertex (vertex
``v`` of triangle ``t`` sits at ``P[v] + shift * L``; ``L`` is zero in
free space).

Predicates are float64 with Shewchuk's static error bounds, as the XLA
engine's (`jaxrt.backends.delaunay.orient`, ``incircle``): an undecided
in-circle test (cocircular points) means "no flip", an undecided
orientation means "not a valid triangle".

A flip round is three launches. `flip_mark` tests edges (all of them
in the first round after a move; later, only the edges of the triangles on
the round's worklist, in a grid-stride loop, so a round costs the tangle
and not the mesh); an edge wants a flip where one of its triangles is
inverted or the in-circle test fails, provided both new triangles are
positive, and then claims both triangles by an atomic min of its id and
appends them (once, by a flag) to the next worklist. `flip_apply`, over
that worklist: the edges that won both their triangles flip; no two flips
of one round touch one triangle. Twins are written to a second buffer
(``twin_new``, equal to ``twin`` between rounds), and each winner finds
the new id of an outer half-edge with `_remap`, which reads only the
round's claims and the old twins: so a flip next to another flip of the
same round links to the other's new half-edges without any ordering
between the threads. `finish_round` copies the rewritten rows back,
resets the claims and recycles the worklists.

The BFS (`radius_bfs`, one thread per vertex) is the XLA engine's: from
``v``, a neighbour ``w`` of a found vertex ``x`` is taken when it is within
the radius and ``x`` is w's parent (the neighbour of w closest to v, ties
to the lower id); in a Delaunay triangulation every point within the
radius is then found exactly once, cocircular lattices included.
"""
import warp as wp

# No FMA contraction: the predicates' error bounds are for rounded products,
# and the cutoff test matches jax-md's ``dx*dx + dy*dy`` bit for bit.
wp.set_module_options({"fuse_fp": False})

EPS = 2.0 ** -53
CCW_BOUND = wp.constant(wp.float64((3.0 + 16.0 * EPS) * EPS))
ICC_BOUND = wp.constant(wp.float64((10.0 + 96.0 * EPS) * EPS))
UNCLAIMED = wp.constant(2 ** 31 - 1)
"""Claim of a triangle no edge wants."""


@wp.func
def filtered_sign(det: wp.float64, bound: wp.float64) -> int:
    """The sign of ``det`` where its rounding error bound ``bound`` cannot
    flip it; 0 where it could (the predicate is undecided)."""
    if det > bound:
        return 1
    if det < -bound:
        return -1
    return 0


@wp.func
def orient_sign(a: wp.vec2d, b: wp.vec2d, c: wp.vec2d) -> int:
    """1: ``(a, b, c)`` counter-clockwise for certain; -1 clockwise for
    certain; 0 undecided."""
    acx = a[0] - c[0]
    acy = a[1] - c[1]
    bcx = b[0] - c[0]
    bcy = b[1] - c[1]
    left = acx * bcy
    right = acy * bcx
    det = left - right
    return filtered_sign(det, CCW_BOUND * (wp.abs(left) + wp.abs(right)))


@wp.func
def incircle_sign(a: wp.vec2d, b: wp.vec2d, c: wp.vec2d, d: wp.vec2d) -> int:
    """1: ``d`` inside the circle through counter-clockwise ``a, b, c`` for
    certain; -1 outside for certain; 0 undecided (cocircular)."""
    adx = a[0] - d[0]
    ady = a[1] - d[1]
    bdx = b[0] - d[0]
    bdy = b[1] - d[1]
    cdx = c[0] - d[0]
    cdy = c[1] - d[1]
    bc = bdx * cdy
    cb = cdx * bdy
    ca = cdx * ady
    ac = adx * cdy
    ab = adx * bdy
    ba = bdx * ady
    alift = adx * adx + ady * ady
    blift = bdx * bdx + bdy * bdy
    clift = cdx * cdx + cdy * cdy
    det = alift * (bc - cb) + blift * (ca - ac) + clift * (ab - ba)
    permanent = ((wp.abs(bc) + wp.abs(cb)) * alift
                 + (wp.abs(ca) + wp.abs(ac)) * blift
                 + (wp.abs(ab) + wp.abs(ba)) * clift)
    return filtered_sign(det, ICC_BOUND * permanent)


@wp.func
def at(P: wp.array(dtype=wp.vec2d), v: int, s: wp.vec2i, L: wp.vec2d):
    """Vertex ``v`` at image shift ``s``."""
    return P[v] + wp.vec2d(wp.float64(s[0]) * L[0], wp.float64(s[1]) * L[1])


@wp.func
def _outside(x: int, t: int, u: int) -> bool:
    """Half-edge ``x`` is a hull edge or lies in neither t nor u."""
    return x < 0 or (x // 3 != t and x // 3 != u)


@wp.func
def _append(t: int, flag: wp.array2d(dtype=wp.int32), lists: wp.array2d(dtype=wp.int32),
            sizes: wp.array(dtype=wp.int32), k: int):
    """Put triangle ``t`` on worklist ``k`` once (its flag deduplicates)."""
    if wp.atomic_max(flag, k, t, 1) == 0:
        slot = wp.atomic_add(sizes, k, 1)
        lists[k, slot] = t


@wp.func
def _mark_edge(h: int, tri: wp.array2d(dtype=wp.int32),
               twin: wp.array2d(dtype=wp.int32),
               shift: wp.array2d(dtype=wp.vec2i), P: wp.array(dtype=wp.vec2d),
               L: wp.vec2d, want: wp.array(dtype=wp.int32),
               claim: wp.array(dtype=wp.int32),
               flag: wp.array2d(dtype=wp.int32), lists: wp.array2d(dtype=wp.int32),
               sizes: wp.array(dtype=wp.int32), cur: int, nxt: int, fresh: int):
    t = h // 3
    e = h - 3 * t
    want[h] = 0
    tw = int(twin[t, e])
    if tw < 0:
        return
    u = tw // 3
    if tw <= h and (fresh != 0 or flag[cur, u] != 0):
        return  # the twin's thread tests this edge
    m = tw - 3 * u
    e1 = (e + 1) % 3
    e2 = (e + 2) % 3
    m1 = (m + 1) % 3
    m2 = (m + 2) % 3
    # An edge whose two triangles share another edge (tiny tori) is left.
    if u == t:
        return
    if not (_outside(int(twin[t, e1]), t, u) and _outside(int(twin[t, e2]), t, u)
            and _outside(int(twin[u, m1]), t, u)
            and _outside(int(twin[u, m2]), t, u)):
        return
    # t = (p, b, c), u = (q, c, b); q is put into t's frame.
    s_q = shift[u, m] + shift[t, e1] - shift[u, m2]
    p = at(P, int(tri[t, e]), shift[t, e], L)
    b = at(P, int(tri[t, e1]), shift[t, e1], L)
    c = at(P, int(tri[t, e2]), shift[t, e2], L)
    q = at(P, int(tri[u, m]), s_q, L)
    old_ok = orient_sign(p, b, c) == 1 and orient_sign(q, c, b) == 1
    new_ok = orient_sign(p, b, q) == 1 and orient_sign(q, c, p) == 1
    if new_ok and ((not old_ok) or incircle_sign(p, b, c, q) == 1):
        want[h] = 1
        wp.atomic_min(claim, t, h)
        wp.atomic_min(claim, u, h)
        _append(t, flag, lists, sizes, nxt)
        _append(u, flag, lists, sizes, nxt)


@wp.kernel
def flip_mark(tri: wp.array2d(dtype=wp.int32), twin: wp.array2d(dtype=wp.int32),
              shift: wp.array2d(dtype=wp.vec2i), P: wp.array(dtype=wp.vec2d),
              L: wp.vec2d, want: wp.array(dtype=wp.int32),
              claim: wp.array(dtype=wp.int32),
              flag: wp.array2d(dtype=wp.int32), lists: wp.array2d(dtype=wp.int32),
              sizes: wp.array(dtype=wp.int32),
              status: wp.array(dtype=wp.int32), r: int, cur: int, fresh: int,
              stride: int):
    """Does an edge want a flip (``want[h]``), and if so claim both its
    triangles (``claim``: atomic min of ``h``; every claim is `UNCLAIMED`
    between rounds, see `finish_round`).

    ``fresh`` (the first round after a move): one thread per half-edge
    ``h`` with ``h < twin[h]``, every edge once. Otherwise a grid-stride
    loop over the edges of the triangles of worklist ``cur`` (those of the
    last round's wanting edges: flipped, or lost a claim and must be tested
    again); an edge between two listed triangles is tested from its lower
    half-edge, an edge of two unlisted triangles kept its verdict. So a
    round costs the tangle, not the mesh. The wanting edges put both their
    triangles on worklist ``(cur + 1) % 3``.

    Round ``r`` of a batch launched without host reads: ``status[1 + r]``
    counts its flips, and where round ``r - 1`` flipped nothing
    (``status[r] == 0``) the round is a no-op (the device-side done flag).
    """
    tid = wp.tid()
    if r > 0 and status[r] == 0:
        return
    nxt = (cur + 1) % 3
    if tid == 0:
        sizes[3] = 0  # the rows this round's flips rewrite (flip_apply)
    total = 3 * tri.shape[0]
    if fresh == 0:
        total = 3 * sizes[cur]
    j = tid
    while j < total:
        h = j
        if fresh == 0:
            h = 3 * lists[cur, j // 3] + j % 3
        _mark_edge(h, tri, twin, shift, P, L, want, claim, flag, lists, sizes,
                   cur, nxt, fresh)
        j += stride


@wp.func
def _won(h: int, twin: wp.array2d(dtype=wp.int32),
         want: wp.array(dtype=wp.int32), claim: wp.array(dtype=wp.int32)):
    if h == UNCLAIMED:
        return False
    if want[h] == 0:
        return False
    t = h // 3
    u = int(twin[t, h - 3 * t]) // 3
    return claim[t] == h and claim[u] == h


@wp.func
def _remap(y: int, twin: wp.array2d(dtype=wp.int32),
           want: wp.array(dtype=wp.int32), claim: wp.array(dtype=wp.int32)):
    """The id after this round's flips of old outer half-edge ``y``."""
    h = int(claim[y // 3])
    if not _won(h, twin, want, claim):
        return y
    t = h // 3
    e = h - 3 * t
    tw = int(twin[t, e])
    u = tw // 3
    m = tw - 3 * u
    # New t = (p, b, q), new u = (q, c, p) (see flip_apply).
    if y == 3 * t + (e + 1) % 3:
        return 3 * u
    if y == 3 * t + (e + 2) % 3:
        return 3 * t + 2
    if y == 3 * u + (m + 1) % 3:
        return 3 * t
    return 3 * u + 2  # 3 u + m2


@wp.func
def _link(twin_new: wp.array2d(dtype=wp.int32), slot: int, outer: int,
          twin: wp.array2d(dtype=wp.int32), want: wp.array(dtype=wp.int32),
          claim: wp.array(dtype=wp.int32), sizes: wp.array(dtype=wp.int32),
          written: wp.array(dtype=wp.int32)):
    """Join new half-edge ``slot`` and old outer half-edge ``outer``."""
    if outer < 0:
        twin_new[slot // 3, slot % 3] = -1
        return
    o = _remap(outer, twin, want, claim)
    twin_new[slot // 3, slot % 3] = o
    twin_new[o // 3, o % 3] = slot
    written[wp.atomic_add(sizes, 3, 1)] = o // 3


@wp.func
def _flip(h: int, tri: wp.array2d(dtype=wp.int32), twin: wp.array2d(dtype=wp.int32),
          shift: wp.array2d(dtype=wp.vec2i), want: wp.array(dtype=wp.int32),
          claim: wp.array(dtype=wp.int32), twin_new: wp.array2d(dtype=wp.int32),
          sizes: wp.array(dtype=wp.int32), written: wp.array(dtype=wp.int32),
          status: wp.array(dtype=wp.int32), r: int):
    t = h // 3
    e = h - 3 * t
    tw = int(twin[t, e])
    u = tw // 3
    m = tw - 3 * u
    e1 = (e + 1) % 3
    e2 = (e + 2) % 3
    m1 = (m + 1) % 3
    m2 = (m + 2) % 3
    i_p = tri[t, e]
    i_b = tri[t, e1]
    i_c = tri[t, e2]
    i_q = tri[u, m]
    s_p = shift[t, e]
    s_b = shift[t, e1]
    s_c = shift[t, e2]
    s_q = shift[u, m] + s_b - shift[u, m2]
    A = int(twin[t, e1])
    B = int(twin[t, e2])
    C = int(twin[u, m1])
    D = int(twin[u, m2])
    tri[t, 0] = i_p
    tri[t, 1] = i_b
    tri[t, 2] = i_q
    tri[u, 0] = i_q
    tri[u, 1] = i_c
    tri[u, 2] = i_p
    shift[t, 0] = s_p
    shift[t, 1] = s_b
    shift[t, 2] = s_q
    shift[u, 0] = s_q
    shift[u, 1] = s_c
    shift[u, 2] = s_p
    # New t = (p, b, q): edge 0 (b-q) was u's m1 (outside C), edge 2 (p-b)
    # t's e2 (outside B). New u = (q, c, p): edge 0 (c-p) was t's e1
    # (outside A), edge 2 (q-c) u's m2 (outside D). Edges 1: the diagonal.
    _link(twin_new, 3 * t, C, twin, want, claim, sizes, written)
    _link(twin_new, 3 * t + 2, B, twin, want, claim, sizes, written)
    _link(twin_new, 3 * u, A, twin, want, claim, sizes, written)
    _link(twin_new, 3 * u + 2, D, twin, want, claim, sizes, written)
    twin_new[t, 1] = 3 * u + 1
    twin_new[u, 1] = 3 * t + 1
    wp.atomic_add(status, 1 + r, 1)


@wp.kernel
def flip_apply(tri: wp.array2d(dtype=wp.int32), twin: wp.array2d(dtype=wp.int32),
               shift: wp.array2d(dtype=wp.vec2i), want: wp.array(dtype=wp.int32),
               claim: wp.array(dtype=wp.int32),
               twin_new: wp.array2d(dtype=wp.int32),
               lists: wp.array2d(dtype=wp.int32), sizes: wp.array(dtype=wp.int32),
               written: wp.array(dtype=wp.int32),
               status: wp.array(dtype=wp.int32), r: int, cur: int, stride: int):
    """Grid-stride over worklist ``(cur + 1) % 3`` (every claimed
    triangle): the edges that won both their triangles flip, each by the
    thread of the triangle holding its half-edge. ``tri`` and ``shift``
    are rewritten in place (each triangle by its one winner), the twins
    into ``twin_new`` (equal to ``twin`` between rounds); the rows of
    outer neighbours so rewritten go on ``written`` (``sizes[3]``) for
    `finish_round`. The flip is counted in ``status[1 + r]``."""
    tid = wp.tid()
    if r > 0 and status[r] == 0:
        return
    nxt = (cur + 1) % 3
    j = tid
    while j < sizes[nxt]:
        t = lists[nxt, j]
        j += stride
        h = int(claim[t])
        if h // 3 == t and _won(h, twin, want, claim):
            _flip(h, tri, twin, shift, want, claim, twin_new, sizes, written,
                  status, r)


@wp.func
def _touch(t: int, touched: wp.array2d(dtype=wp.int32),
           touched_size: wp.array(dtype=wp.int32)):
    if wp.atomic_max(touched, 0, t, 1) == 0:
        touched[1, wp.atomic_add(touched_size, 0, 1)] = t


@wp.kernel
def finish_round(twin_new: wp.array2d(dtype=wp.int32),
                 twin: wp.array2d(dtype=wp.int32),
                 claim: wp.array(dtype=wp.int32),
                 flag: wp.array2d(dtype=wp.int32), lists: wp.array2d(dtype=wp.int32),
                 sizes: wp.array(dtype=wp.int32), written: wp.array(dtype=wp.int32),
                 touched: wp.array2d(dtype=wp.int32),
                 touched_size: wp.array(dtype=wp.int32),
                 status: wp.array(dtype=wp.int32), r: int, cur: int, stride: int):
    """After round ``r`` (grid-stride, skipped once the batch is done):
    the rows it rewrote copied from ``twin_new`` to ``twin`` (worklist
    ``cur + 1``'s triangles and ``written``), the claims of worklist
    ``cur + 1`` back to `UNCLAIMED`, worklist ``cur``'s flags cleared, and
    worklist ``cur + 2`` (read two rounds ago) emptied for the next round
    to fill. Copied, not swapped: ``twin`` may be a caller's buffer (an
    XLA call's output), which must end up holding the result. Every row
    copied (the only rows whose ``tri``, ``shift`` or ``twin`` a flip
    changes) goes once on ``touched`` (row 0: flags, row 1: the list,
    ``touched_size[0]`` its length), so a try is undone or kept by
    copying those rows alone (`copy_rows`)."""
    tid = wp.tid()
    if r > 0 and status[r] == 0:
        return
    nxt = (cur + 1) % 3
    if tid == 0:
        sizes[(cur + 2) % 3] = 0
    n_cur = sizes[cur]
    n_nxt = sizes[nxt]
    n_w = sizes[3]
    j = tid
    while j < n_cur or j < n_nxt or j < n_w:
        if j < n_cur:
            flag[cur, lists[cur, j]] = 0
        if j < n_nxt:
            t = lists[nxt, j]
            claim[t] = UNCLAIMED
            for e in range(3):
                twin[t, e] = twin_new[t, e]
            _touch(t, touched, touched_size)
        if j < n_w:
            t = written[j]
            for e in range(3):
                twin[t, e] = twin_new[t, e]
            _touch(t, touched, touched_size)
        j += stride


@wp.kernel
def copy_rows(src_tri: wp.array2d(dtype=wp.int32),
              src_twin: wp.array2d(dtype=wp.int32),
              src_shift: wp.array2d(dtype=wp.vec2i),
              dst_tri: wp.array2d(dtype=wp.int32),
              dst_twin: wp.array2d(dtype=wp.int32),
              dst_shift: wp.array2d(dtype=wp.vec2i),
              touched: wp.array2d(dtype=wp.int32),
              touched_size: wp.array(dtype=wp.int32), stride: int):
    """Grid-stride over the touched rows (`finish_round`): copy them from
    ``src`` to ``dst`` (a try undone, or kept as the last valid
    triangulation) and clear their flags; every other row is the same in
    both. ``touched_size`` is reset by the caller after the launch."""
    j = wp.tid()
    while j < touched_size[0]:
        t = touched[1, j]
        for e in range(3):
            dst_tri[t, e] = src_tri[t, e]
            dst_twin[t, e] = src_twin[t, e]
            dst_shift[t, e] = src_shift[t, e]
        touched[0, t] = 0
        j += stride


@wp.func
def _check(t: int, tri: wp.array2d(dtype=wp.int32),
           shift: wp.array2d(dtype=wp.vec2i), P: wp.array(dtype=wp.vec2d),
           L: wp.vec2d, bad_vertex: wp.array(dtype=wp.int32),
           bad: wp.array(dtype=wp.int32)):
    a = at(P, int(tri[t, 0]), shift[t, 0], L)
    b = at(P, int(tri[t, 1]), shift[t, 1], L)
    c = at(P, int(tri[t, 2]), shift[t, 2], L)
    if orient_sign(a, b, c) != 1:
        wp.atomic_add(bad, 0, 1)
        for k in range(3):
            bad_vertex[tri[t, k]] = 1


@wp.kernel
def check_triangles(tri: wp.array2d(dtype=wp.int32),
                    shift: wp.array2d(dtype=wp.vec2i),
                    P: wp.array(dtype=wp.vec2d), L: wp.vec2d,
                    bad_vertex: wp.array(dtype=wp.int32),
                    bad: wp.array(dtype=wp.int32)):
    """One thread per triangle: count those not certainly positive
    (``bad[0]``) and mark their vertices (``bad_vertex``)."""
    _check(wp.tid(), tri, shift, P, L, bad_vertex, bad)


@wp.kernel
def check_seeds(tri: wp.array2d(dtype=wp.int32),
                shift: wp.array2d(dtype=wp.vec2i),
                P: wp.array(dtype=wp.vec2d), L: wp.vec2d,
                seeds: wp.array(dtype=wp.int32), sizes: wp.array(dtype=wp.int32),
                bad_vertex: wp.array(dtype=wp.int32),
                bad: wp.array(dtype=wp.int32), stride: int):
    """`check_triangles` over the seeded triangles only (grid-stride over
    ``seeds[:sizes[4]]``): after a seeded try every other triangle is
    either unchanged with unmoved vertices (positive, as in the verified
    triangulation the try started from) or made by a flip, which only
    makes certainly positive triangles."""
    j = wp.tid()
    while j < sizes[4]:
        _check(seeds[j], tri, shift, P, L, bad_vertex, bad)
        j += stride


@wp.kernel
def seed_moved(tri: wp.array2d(dtype=wp.int32), delta: wp.array(dtype=wp.vec2d),
               done_part: wp.array(dtype=wp.float64),
               fraction: wp.array(dtype=wp.float64),
               flag: wp.array2d(dtype=wp.int32), lists: wp.array2d(dtype=wp.int32),
               sizes: wp.array(dtype=wp.int32), seeds: wp.array(dtype=wp.int32),
               cur: int):
    """A try from a verified Delaunay triangulation (at the committed
    fractions): only the triangles with a vertex that moves in this try
    can lose the Delaunay condition or turn over, the others keep their
    verdict. They go on worklist ``cur`` (the first round's) and on
    ``seeds`` (``sizes[4]``, for `check_seeds`)."""
    t = wp.tid()
    moved = bool(False)
    for k in range(3):
        v = int(tri[t, k])
        d = delta[v]
        if fraction[v] != done_part[v] and (d[0] != wp.float64(0.0)
                                            or d[1] != wp.float64(0.0)):
            moved = True
    if moved:
        _append(t, flag, lists, sizes, cur)
        seeds[wp.atomic_add(sizes, 4, 1)] = t


@wp.kernel
def move_delta(start: wp.array(dtype=wp.vec2d), target: wp.array(dtype=wp.vec2d),
               L: wp.vec2d, periodic: int, delta: wp.array(dtype=wp.vec2d)):
    """The move of each vertex, by minimum image on a torus (a move
    between two calls is below half a side)."""
    v = wp.tid()
    d = target[v] - start[v]
    if periodic != 0:
        d = wp.vec2d(d[0] - L[0] * wp.round(d[0] / L[0]),
                     d[1] - L[1] * wp.round(d[1] / L[1]))
    delta[v] = d


@wp.kernel
def move_part(start: wp.array(dtype=wp.vec2d), delta: wp.array(dtype=wp.vec2d),
              fraction: wp.array(dtype=wp.float64),
              P: wp.array(dtype=wp.vec2d)):
    """Positions after ``fraction`` of each vertex's move."""
    v = wp.tid()
    P[v] = start[v] + fraction[v] * delta[v]


@wp.kernel
def try_fraction(done_part: wp.array(dtype=wp.float64),
                 step: wp.array(dtype=wp.float64),
                 fraction: wp.array(dtype=wp.float64)):
    """The fraction of its move each vertex tries next: its committed part
    plus its step, capped at the whole move."""
    v = wp.tid()
    fraction[v] = wp.min(done_part[v] + step[v], wp.float64(1.0))


@wp.kernel
def commit_try(done_part: wp.array(dtype=wp.float64),
               step: wp.array(dtype=wp.float64),
               fraction: wp.array(dtype=wp.float64),
               unfinished: wp.array(dtype=wp.int32), grow: wp.float64):
    """After a successful try: its fractions are committed, each step
    doubles (a vertex slowed down by a tangle speeds up again once past
    it), and the vertices still short of their whole move are counted."""
    v = wp.tid()
    done_part[v] = fraction[v]
    # Capped at what is left, so one halving always shortens the try.
    step[v] = wp.min(step[v] * grow, wp.float64(1.0) - fraction[v])
    if fraction[v] < wp.float64(1.0):
        wp.atomic_add(unfinished, 0, 1)


@wp.kernel
def halve_steps(step: wp.array(dtype=wp.float64),
                bad_vertex: wp.array(dtype=wp.int32), any_bad: int,
                shrink: wp.float64):
    """After a failed try: the vertices of the triangles left inverted
    scale their step by ``shrink`` (all of them if none is marked); the
    others keep theirs, so one try bisects every tangle of the mesh at
    once."""
    v = wp.tid()
    if any_bad == 0 or bad_vertex[v] != 0:
        step[v] = step[v] * shrink


@wp.kernel
def wrap(start: wp.array(dtype=wp.vec2d), delta: wp.array(dtype=wp.vec2d),
         L: wp.vec2d, P: wp.array(dtype=wp.vec2d),
         periods: wp.array(dtype=wp.vec2i)):
    """Torus: the moved vertices wrapped into ``[0, L)`` and the whole
    periods removed, which the triangles' shifts take up."""
    v = wp.tid()
    moved = start[v] + delta[v]
    out = wp.vec2d()
    k = wp.vec2i()
    for a in range(2):
        r = wp.mod(moved[a], L[a])
        if r < wp.float64(0.0):
            r = r + L[a]
        if r >= L[a]:
            r = wp.float64(0.0)
        out[a] = r
        k[a] = int(wp.round((moved[a] - r) / L[a]))
    P[v] = out
    periods[v] = k


@wp.kernel
def add_periods(tri: wp.array2d(dtype=wp.int32), periods: wp.array(dtype=wp.vec2i),
                shift: wp.array2d(dtype=wp.vec2i)):
    t, k = wp.tid()
    shift[t, k] = shift[t, k] + periods[tri[t, k]]


@wp.kernel
def count_outside(P: wp.array(dtype=wp.vec2d), low: wp.vec2d, high: wp.vec2d,
                  outside: wp.array(dtype=wp.int32)):
    """Free space: count the particles out of the frame's safe box."""
    v = wp.tid()
    x = P[v]
    if not (x[0] > low[0] and x[0] < high[0] and x[1] > low[1]
            and x[1] < high[1]):
        wp.atomic_add(outside, 0, 1)


# ---------------------------------------------------------------------------
# Adjacency and search


@wp.kernel
def degree_count(tri: wp.array2d(dtype=wp.int32), n: int,
                 degree: wp.array(dtype=wp.int32)):
    """Every interior edge v-w appears once as "w follows v" in a
    counter-clockwise triangle: count it for v (particles only; frame
    vertices, ids >= n, are never within the radius)."""
    t, e = wp.tid()
    v = int(tri[t, e])
    w = int(tri[t, (e + 1) % 3])
    if v < n and w < n:
        wp.atomic_add(degree, v, 1)


@wp.kernel
def degree_fill(tri: wp.array2d(dtype=wp.int32), n: int,
                start: wp.array(dtype=wp.int32), fill: wp.array(dtype=wp.int32),
                neighbours: wp.array(dtype=wp.int32)):
    t, e = wp.tid()
    v = int(tri[t, e])
    w = int(tri[t, (e + 1) % 3])
    if v < n and w < n:
        k = wp.atomic_add(fill, v, 1)
        neighbours[start[v] + k] = w


@wp.func
def displacement(xi: wp.vec2d, xj: wp.vec2d, L: wp.vec2d, periodic: int):
    """jax-md's ``periodic_displacement(side, xi - xj)`` on a torus
    (``xi - xj`` in free space), operation for operation (``jnp.mod`` is
    fmod with a sign fix). A float64 fmod is a slow loop on a GPU; for
    ``-L < s < 2L`` (``s = xi - xj + L / 2``, every pair of wrapped
    positions) its result is ``s``, ``s - L`` (exact: Sterbenz) or ``s``
    then fixed to ``s + L``, computed here without it, bit for bit."""
    d = xi - xj
    if periodic != 0:
        for a in range(2):
            side = L[a]
            half = side * wp.float64(0.5)
            s = d[a] + half
            r = s
            if s >= wp.float64(0.0) and s < side:
                r = s
            elif s >= side and s < side + side:
                r = s - side
            elif s < wp.float64(0.0) and s > -side:
                r = s + side
            else:
                r = wp.mod(s, side)
                if r != wp.float64(0.0) and r < wp.float64(0.0):
                    r = r + side
            d[a] = r - half
    return d


@wp.func
def square_distance(xi: wp.vec2d, xj: wp.vec2d, L: wp.vec2d, periodic: int):
    d = displacement(xi, xj, L, periodic)
    return d[0] * d[0] + d[1] * d[1]


@wp.func
def _is_parent(x: int, dx: wp.float64, w: int, xv: wp.vec2d,
               start: wp.array(dtype=wp.int32),
               neighbours: wp.array(dtype=wp.int32),
               grid: wp.array(dtype=wp.vec2d), L: wp.vec2d, periodic: int):
    """Is x, a neighbour of w at ``dx`` from v (``xv = grid[v]``), w's
    parent: the neighbour of w closest to v, ties to the lower id? Leaves
    at the first neighbour that beats x."""
    for k in range(start[w], start[w + 1]):
        y = neighbours[k]
        d = square_distance(grid[y], xv, L, periodic)
        if d < dx or (d == dx and y < x):
            return False
    return True


@wp.kernel
def radius_bfs(points: wp.array(dtype=wp.vec2d), grid: wp.array(dtype=wp.vec2d),
               start: wp.array(dtype=wp.int32), neighbours: wp.array(dtype=wp.int32),
               L: wp.vec2d, periodic: int, cutoff_sq: wp.float64, n: int,
               found: wp.array2d(dtype=wp.int32), count: wp.array(dtype=wp.int32),
               emit: int, pairs: wp.array2d(dtype=wp.int32),
               pair_count: wp.array(dtype=wp.int32)):
    """One thread per vertex v: its BFS (module docstring).

    ``points``: the caller's positions, which decide every pair;
    ``grid``: the triangulated positions, which decide the parents.
    ``found[v]``: v first, then its neighbours in BFS order (padded with
    ``n``); ``count[v]``: their number with v, a lower bound once it
    exceeds the row width (overflow). With ``emit``, every pair (v, w) also
    goes to ``pairs`` at an atomically counted slot; ``pair_count[0]``
    counts past the capacity (overflow)."""
    v = wp.tid()
    width = found.shape[1]
    capacity = pairs.shape[0]
    for j in range(width):
        found[v, j] = n
    found[v, 0] = v
    total = int(1)
    j = int(0)
    xv = points[v]
    gv = grid[v]
    while j < total and j < width:
        x = int(found[v, j])
        j += 1
        dx = square_distance(grid[x], gv, L, periodic)
        for k in range(start[x], start[x + 1]):
            w = neighbours[k]
            if w == v:
                continue
            if not (square_distance(xv, points[w], L, periodic) < cutoff_sq):
                continue
            # A repeated edge (a multi-edge of a tiny torus) is visited once.
            repeated = bool(False)
            for k2 in range(start[x], k):
                if neighbours[k2] == w:
                    repeated = True
            if repeated:
                continue
            if not _is_parent(x, dx, w, gv, start, neighbours, grid, L,
                              periodic):
                continue
            if total < width:
                found[v, total] = w
            total += 1
            if emit != 0:
                slot = wp.atomic_add(pair_count, 0, 1)
                if slot < capacity:
                    pairs[slot, 0] = v
                    pairs[slot, 1] = w
    count[v] = total


def load(device) -> None:
    """Compile/load the kernels on ``device`` now."""
    wp.load_module(module=__name__, device=device)
