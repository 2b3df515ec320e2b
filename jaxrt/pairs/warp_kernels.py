"""The cell walk of `jaxrt.pairs` in Warp: each atom reads its stencil of
cells, decides every candidate ``(j, S)`` as `jaxrt.pairs.cells` does and
counts or writes its pairs, ``i``-major. No JAX here: the JAX call is
`jaxrt.backends.rt.ffi.pair_walk`, the arrays it reads are made by
`jaxrt.pairs.warp_search`.

The walk runs once, counting each atom's pairs (``degree``, its self pair
included) and keeping the first ``width`` of them (none by default) (``j`` and ``S``, one
16-byte store each) in a scratch row of its own; an exclusive scan of the
degrees gives each atom the first row it owns; `copy_rows` moves the kept
pairs there, and the walk runs again only for the atoms with more than
``width`` pairs, writing them all. An atom's rows are its self pair
(when asked for), then its pairs offset by offset (the stencil of
`jaxrt.pairs.cells.offsets`, the first axis slowest) and, within an
offset's cell, in the cell's sorted order: the order of the program's full
stencil, so the two agree row for row.

One thread per sorted slot: neighbouring threads hold atoms of one cell,
which read the same runs of partners.
"""
import warp as wp

# Columns of a row: i, j and the lattice shift S.
ROW = 5
# No adjoints (pairs are integers), loops kept as loops (compile time), and
# no fast math: every decision is the program's, in the positions' dtype.
MODULE_OPTIONS = {"enable_backward": False, "max_unroll": 1,
                  "fast_math": False}
wp.set_module_options(MODULE_OPTIONS)

_WALKS: dict = {}


@wp.func
def floor_div(t: int, c: int):
    """``floor(t / c)`` for ``c > 0``, whatever the sign of ``t``."""
    q = t / c
    if q * c > t:
        q = q - 1
    return q


@wp.func
def lex_positive(s: wp.vec3i):
    """``s`` lexicographically greater than zero."""
    if s[0] != 0:
        return s[0] > 0
    if s[1] != 0:
        return s[1] > 0
    return s[2] > 0


@wp.func
def image_of(t: int, cells: int, periodic: int):
    """The image of cell coordinate ``t`` on an axis of ``cells`` cells:
    ``floor(t / cells)`` where periodic, 0 where not."""
    m = int(0)
    if periodic != 0:
        m = floor_div(t, cells)
    return m


@wp.kernel
def fill_padding(total: wp.array(dtype=wp.int32), pad: int, capacity: int,
                 rows: wp.array(dtype=wp.int32)):
    """Rows from the count to the capacity set to ``(pad, pad, 0, 0, 0)``."""
    r = wp.tid()
    if r < total[0] or r >= capacity:
        return
    rows[r * 5 + 0] = pad
    rows[r * 5 + 1] = pad
    rows[r * 5 + 2] = 0
    rows[r * 5 + 3] = 0
    rows[r * 5 + 4] = 0


@wp.kernel
def copy_rows(degree: wp.array(dtype=wp.int32),
              selfs: wp.array(dtype=wp.int32),
              offset: wp.array(dtype=wp.int32), width: int, capacity: int,
              scratch: wp.array(dtype=wp.vec4i),
              rows: wp.array(dtype=wp.int32)):
    """One row per thread (``N * (width + 1)`` threads; neighbouring
    threads write neighbouring rows): slot 0 of atom ``i`` its self pair,
    slot ``k`` its ``k``-th kept pair, unless it has more than ``width``
    pairs (the walk writes those)."""
    t = wp.tid()
    i = t / (width + 1)
    k = t - i * (width + 1)
    own = selfs[i]
    kept = degree[i] - own
    if kept > width:
        return
    if k == 0:
        if own == 0:
            return
        e = wp.vec4i(i, 0, 0, 0)
    else:
        if k > kept:
            return
        e = scratch[i * width + k - 1]
    at = offset[i] + own + k - 1
    if at >= capacity:
        return
    r = at * 5
    rows[r + 0] = i
    rows[r + 1] = e[0]
    rows[r + 2] = e[1]
    rows[r + 3] = e[2]
    rows[r + 4] = e[3]


@wp.kernel
def last_total(degree: wp.array(dtype=wp.int32),
               offset: wp.array(dtype=wp.int32), n: int,
               total: wp.array(dtype=wp.int32)):
    """The rows in all: the last atom's first row plus its degree."""
    total[0] = offset[n - 1] + degree[n - 1]


def walk_kernel(scalar):
    """The walk for positions of ``scalar`` (``wp.float32`` or
    ``wp.float64``), built on first use. ``write`` 0: count each atom's
    pairs into ``degree``, keeping the first ``width`` in ``scratch``
    (``(N * width,)``); 1: write the rows of the atoms with more than
    ``width`` pairs at ``offset``."""
    if scalar not in _WALKS:
        _WALKS[scalar] = _walk_kernel(scalar)
    return _WALKS[scalar]


def _walk_kernel(scalar):
    vector = wp.types.vector(3, scalar)
    matrix = wp.types.matrix((3, 3), scalar)

    @wp.kernel(module="unique", module_options=MODULE_OPTIONS)
    def pair_walk(position: wp.array(dtype=vector),
                  sorted_position: wp.array(dtype=vector),
                  sorted_wrap: wp.array(dtype=wp.vec3i),
                  sorted_species: wp.array(dtype=wp.int32),
                  order: wp.array(dtype=wp.int32),
                  coord: wp.array(dtype=wp.vec3i),
                  wrap: wp.array(dtype=wp.vec3i),
                  graph: wp.array(dtype=wp.int32),
                  real: wp.array(dtype=wp.int32),
                  selfs: wp.array(dtype=wp.int32),
                  species: wp.array(dtype=wp.int32),
                  cells: wp.array(dtype=wp.vec3i),
                  base: wp.array(dtype=wp.int32),
                  pbc: wp.array(dtype=wp.vec3i),
                  lattice: wp.array(dtype=matrix),
                  runs: wp.array(dtype=wp.vec2i),
                  limit: wp.array(dtype=scalar), n_species: int,
                  reach: wp.vec3i, half: int, write: int, capacity: int,
                  width: int, offset: wp.array(dtype=wp.int32),
                  degree: wp.array(dtype=wp.int32),
                  scratch: wp.array(dtype=wp.vec4i),
                  rows: wp.array(dtype=wp.int32)):
        slot = wp.tid()
        i = order[slot]
        if real[i] == 0:
            if write == 0:
                degree[i] = 0
            return
        if write != 0 and degree[i] - selfs[i] <= width:
            return  # its rows are copied from its scratch row
        g = graph[i]
        c = cells[g]
        b = base[g]
        periodic = pbc[g]
        h = lattice[g]
        at = int(0)
        found = int(0)
        if write != 0:
            at = offset[i]
            if selfs[i] != 0:
                if at < capacity:
                    rows[at * 5 + 0] = i
                    rows[at * 5 + 1] = i
                    rows[at * 5 + 2] = 0
                    rows[at * 5 + 3] = 0
                    rows[at * 5 + 4] = 0
                at = at + 1
        ci = coord[i]
        wi = wrap[i]
        ri = position[i]
        row_limit = species[i] * n_species
        for ox in range(-reach[0], reach[0] + 1):
            tx = ci[0] + ox
            mx = image_of(tx, c[0], periodic[0])
            tx = tx - mx * c[0]
            if tx < 0 or tx >= c[0]:
                continue
            for oy in range(-reach[1], reach[1] + 1):
                ty = ci[1] + oy
                my = image_of(ty, c[1], periodic[1])
                ty = ty - my * c[1]
                if ty < 0 or ty >= c[1]:
                    continue
                for oz in range(-reach[2], reach[2] + 1):
                    tz = ci[2] + oz
                    mz = image_of(tz, c[2], periodic[2])
                    tz = tz - mz * c[2]
                    if tz < 0 or tz >= c[2]:
                        continue
                    own = ox == 0 and oy == 0 and oz == 0
                    run = runs[b + (tz * c[1] + ty) * c[0] + tx]
                    for p in range(run[0], run[0] + run[1]):
                        j = order[p]
                        wj = sorted_wrap[p]
                        s = wp.vec3i(mx + wi[0] - wj[0], my + wi[1] - wj[1],
                                     mz + wi[2] - wj[2])
                        sx = scalar(s[0])
                        sy = scalar(s[1])
                        sz = scalar(s[2])
                        rj = sorted_position[p]
                        # As the program's decision: the shift's three
                        # products summed in order, then added.
                        dx = (rj[0] - ri[0]) + (sx * h[0, 0] + sy * h[1, 0]
                                                + sz * h[2, 0])
                        dy = (rj[1] - ri[1]) + (sx * h[0, 1] + sy * h[1, 1]
                                                + sz * h[2, 1])
                        dz = (rj[2] - ri[2]) + (sx * h[0, 2] + sy * h[1, 2]
                                                + sz * h[2, 2])
                        d2 = dx * dx + dy * dy + dz * dz
                        keep = d2 <= limit[row_limit + sorted_species[p]]
                        if own and j == i:
                            keep = False
                        if half != 0 and keep:
                            keep = i < j or (i == j and lex_positive(s))
                        if keep:
                            if write != 0:
                                if at < capacity:
                                    rows[at * 5 + 0] = i
                                    rows[at * 5 + 1] = j
                                    rows[at * 5 + 2] = s[0]
                                    rows[at * 5 + 3] = s[1]
                                    rows[at * 5 + 4] = s[2]
                                at = at + 1
                            else:
                                if found < width:
                                    scratch[i * width + found] = wp.vec4i(
                                        j, s[0], s[1], s[2])
                                found = found + 1
        if write == 0:
            degree[i] = found + selfs[i]

    return pair_walk
