"""Sweep the cell list's stencil reach and block width (module constants
`jaxrt.cell_list._REACH`, `_BLOCK`) on a uniform scene; prints ms per update.

    python benchmarks/tune_cell_list.py
"""
import os, time, itertools, numpy as np, jax, jax.numpy as jnp
from jax_md import space
import jaxrt, jaxrt.cell_list as cl
for N in (100000, 1000000):
    L = N ** (1 / 3)
    R = jax.random.uniform(jax.random.PRNGKey(0), (N, 3)) * L
    disp, _ = space.periodic(L)
    for reach, block in [(1, 32), (1, 128), (1, 600), (2, 64), (2, 256), (2, 400)]:
        cl._REACH, cl._BLOCK = reach, block
        jax.clear_caches()
        fns = jaxrt.neighbor_list(disp, L, 2.5)
        nb = fns.allocate(R)
        up = jax.jit(fns.update)
        xs = [R + 1e-3 * i for i in range(3)]
        for x in xs: up(x, nb).idx.block_until_ready()
        ts = []
        for i in range(10):
            t = time.perf_counter(); up(xs[i % 3], nb).idx.block_until_ready(); ts.append(time.perf_counter() - t)
        print(N, reach, block, dict(nb.cell_list_capacity.internal), f"{np.median(ts)*1e3:.2f} ms", flush=True)
