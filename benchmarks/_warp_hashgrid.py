"""Warp's HashGrid as a peer of the "bvh" backend (`rt_neighbors.py`): a
hand-written query kernel writing the same Dense rows, periodic images by
the same gamma rays (`jaxrt.backends.rt.periodic`). Imported only in workers."""
import warp as wp

from jaxrt.backends.rt import periodic as gamma


@wp.kernel
def hash_grid_dense(grid: wp.uint64, points: wp.array(dtype=wp.vec3),
                    side: wp.array(dtype=wp.vec3), periodic: wp.vec3i,
                    cutoff: wp.float32, rows: wp.array2d(dtype=wp.int32),
                    count: wp.array(dtype=wp.int32)):
    """rows[i] = neighbours of i (d² < cutoff², minimum image), padded N."""
    tid = wp.tid()
    i = wp.hash_grid_point_id(grid, tid)
    xi = points[i]
    box = side[0]
    width = rows.shape[1]
    n = int(0)
    for ray in range(gamma.RAYS_PER_PARTICLE):
        shift = gamma.ray_shift(ray)
        if gamma.ray_is_cast(shift, xi, box, periodic, cutoff):
            origin = gamma.shifted(xi, shift, box)
            query = wp.hash_grid_query(grid, origin, cutoff)
            j = int(0)
            while wp.hash_grid_query_next(query, j):
                xj = points[j]
                if j != i and gamma.is_canonical_image(shift, xi, xj, box, periodic):
                    d = origin - xj
                    if wp.dot(d, d) < cutoff * cutoff:
                        if n < width:
                            rows[i, n] = j
                        n += 1
    count[i] = n
    for s in range(wp.min(n, width), width):
        rows[i, s] = points.shape[0]


def load(device) -> None:
    wp.load_module(module=__name__, device=device)
