"""Sweep the cell list's stencil reach (module constant
`jaxrt.cell_list._REACH` = (reach along x, reach across)) on a uniform
periodic scene (density 1, rc = 2.5); prints ms per Dense update (warm,
median of 7) and the internal buffer sizes.

    python benchmarks/tune_cell_list.py [N ...]
"""
import sys
import time

import jax
import numpy as np
from jax_md import space

import jaxrt
import jaxrt.cell_list as cl

sizes = [int(a) for a in sys.argv[1:]] or [100_000]
for n in sizes:
    side = n ** (1 / 3)
    R = jax.random.uniform(jax.random.PRNGKey(0), (n, 3)) * side
    disp, _ = space.periodic(side)
    for reach in [(1, 1), (2, 1), (4, 1), (8, 1)]:
        cl._REACH = reach
        jax.clear_caches()
        fns = jaxrt.neighbor_list(disp, side, 2.5, backend="cell")
        nbrs = fns.allocate(R)
        update = jax.jit(fns.update)
        inputs = [(R + 1e-3 * i) % side for i in range(3)]
        for x in inputs:
            update(x, nbrs).idx.block_until_ready()
        times = []
        for i in range(7):
            t = time.perf_counter()
            update(inputs[i % 3], nbrs).idx.block_until_ready()
            times.append(time.perf_counter() - t)
        print(n, reach, dict(nbrs.cell_list_capacity.internal),
              f"{np.median(times) * 1e3:.1f} ms", flush=True)
