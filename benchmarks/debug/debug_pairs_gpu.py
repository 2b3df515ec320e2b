"""Debug of a GPU-only failure (tests/pairs/test_pairs.py::
test_vmap_over_padded_batch_of_different_systems, H200, 2bf10b5): where do
jaxrt.pairs and ASE differ, and does an XLA flag change it?

    PYTHONPATH=$PWD python3 benchmarks/debug/debug_pairs_gpu.py           # every flag set, in subprocesses
    PYTHONPATH=$PWD python3 benchmarks/debug/debug_pairs_gpu.py float64   # this process's XLA_FLAGS only

Needs ASE (the systems and the oracle are tests/pairs/test_pairs.py's). On the
H200 at 2bf10b5 (results/h200/debug_pairs_2bf10b5/) every variant matched
ASE except level 0's vmapped brute force.
"""
import os, subprocess, sys
import numpy as np

FLAGS = ["", "--xla_backend_optimization_level=0",
         "--xla_gpu_autotune_level=0", "--xla_gpu_enable_command_buffer="]


def one(dtype):
    import jax
    jax.config.update("jax_enable_x64", True)
    sys.path.insert(0, "tests")
    import jaxrt
    import importlib
    P = importlib.import_module("jaxrt.pairs.search")
    from test_pairs import si2, triclinic, fe_bcc_rattled, cu_primitive, as_set, ase_set
    systems = [si2(), triclinic(3, 6), fe_bcc_rattled(), cu_primitive()]
    cutoff = 4.5
    n_max = max(len(a) for a in systems)
    pos = np.zeros((len(systems), n_max, 3), dtype)
    mask = np.zeros((len(systems), n_max), bool)
    cells = np.stack([np.asarray(a.cell) for a in systems]).astype(dtype)
    for b, a in enumerate(systems):
        pos[b, :len(a)] = a.positions; pos[b, len(a):] = a.positions[0]
        mask[b, :len(a)] = True
    sizes = jaxrt.pairs_sizes(pos, cutoff, cell=cells, mask=mask)

    def dist(a, p):
        i, j, *s = p
        return np.linalg.norm(a.positions[j] - a.positions[i] + np.array(s) @ np.asarray(a.cell))

    def report(tag, got, a, detail=False):
        want = ase_set(a, cutoff)
        got = {p for p in got if p[0] != "pad"}
        extra, missing = got - want, want - got
        print(f"  {tag}: got {len(got)} want {len(want)} extra {len(extra)} missing {len(missing)}")
        if detail:
            for p in sorted(extra)[:4]: print("     extra", p, round(dist(a, p), 4))
            for p in sorted(missing)[:4]: print("     missing", p, round(dist(a, p), 4))

    for backend in ("brute", "cell"):
        f = jax.jit(jax.vmap(lambda r, c, m: jaxrt.pairs(
            r, cutoff, cell=c, mask=m, backend=backend, **sizes.kwargs)))
        batch = f(pos, cells, mask)
        for b, a in enumerate(systems):
            o = jax.tree_util.tree_map(lambda x: x[b], batch)
            report(f"vmap {backend} b={b} count={int(o.count)} err={int(o.error)}", as_set(o), a, detail=b == 0)
        g = jax.jit(lambda r, c, m: jaxrt.pairs(r, cutoff, cell=c, mask=m, backend=backend, **sizes.kwargs))
        for b, a in enumerate(systems):
            report(f"jit padded {backend} b={b}", as_set(g(pos[b], cells[b], mask[b])), a)
        o = jax.tree_util.tree_map(lambda x: x[0], f(pos[:1], cells[:1], mask[:1]))
        report(f"vmap-of-one {backend} b=0", as_set(o), systems[0])
        o = jax.tree_util.tree_map(lambda x: x[0], f(pos[:2], cells[:2], mask[:2]))
        report(f"vmap-of-two {backend} b=0", as_set(o), systems[0])
    # The same vmapped _search on the GPU and on the CPU, row for row.
    brute, reach, chunk = P._plan(n_max, (True,) * 3, sizes.kwargs["max_shift"], "brute")
    search = lambda dev: jax.jit(jax.vmap(lambda r, c, m: P._search(
        r, c, m, cutoff, pbc=(True,) * 3, reach=reach, capacity=sizes.capacity,
        brute=brute, chunk=chunk)), device=dev)
    outs = [search(d)(pos, cells, mask) for d in (jax.devices()[0], jax.devices("cpu")[0])]
    (og, tg, eg), (oc, tc, ec) = [[np.asarray(x) for x in o] for o in outs]
    print(f"  _search gpu/cpu: totals {tg} / {tc}, errors {eg} / {ec}, rows equal per system "
          f"{[bool((og[b] == oc[b]).all()) for b in range(len(systems))]}")
    bad = np.nonzero((og[0] != oc[0]).any(axis=1))[0]
    for k in bad[:6]:
        print("     row", k, "gpu", og[0, k].tolist(), "cpu", oc[0, k].tolist())
    print(f"  plan: brute={brute} reach={reach} chunk={chunk}")


if __name__ == "__main__":
    if len(sys.argv) > 1:
        one(np.dtype(sys.argv[1]))
        sys.exit(0)
    for flags in FLAGS:
        for dtype in ("float64", "float32") if not flags else ("float64",):
            env = dict(os.environ, XLA_FLAGS=flags)
            print(f"== XLA_FLAGS={flags!r} {dtype}", flush=True)
            r = subprocess.run([sys.executable, __file__, dtype], env=env,
                               capture_output=True, text=True, timeout=150)
            print(r.stdout[-6000:], r.stderr[-1500:] if r.returncode else "", flush=True)
