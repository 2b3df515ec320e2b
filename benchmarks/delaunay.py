"""Seed 004: update time per step of Delaunay lists against grids, in 2D.

The poster's claim: its Delaunay method (a triangulation kept by edge flips,
searched by BFS) "is faster than grid based methods in various situations"
for slowly moving particles (2D Boids, float64). Here, per step of a
trajectory, every method updates its list with dr_threshold = 0 (every
step searches again, as the poster does each time step):

  delaunay   jaxrt's backend="delaunay" (maintenance by flips, then BFS),
             its XLA engine
  delaunay[engine=warp]
             the same backend on its Warp engine: flips with atomically
             claimed triangles and the BFS as Warp kernels, one custom
             call per step (`jaxrt.backends.rt.delaunay_kernels`)
  cell       jaxrt's cell list (the uniform grid; the poster's baseline is
             the GPU uniform grid of Green 2010)
  jax-md     jax_md.partition.neighbor_list (its cell list)

Motions (positions precomputed, then replayed forward and backward so that
repeated timing loops join smoothly; float64):

  boids      the built-in Boids scene (`jaxrt.sim.builtin.boids`: R = 1,
             speeds 0.5 to 1, dt = 0.05), a periodic square sized for k
             neighbours within R on average; simulated with the cell list
  random     a periodic random walk from uniform positions: each step
             every particle moves by a Gaussian of 0.05 mean spacings per
             axis; cutoff sized for k neighbours

Columns: ``update_ms`` (median per step over ``--repeats`` loops of
2 ``--steps`` steps, compilation excluded), ``k`` the measured mean
neighbours, for delaunay ``flips_per_step``, ``rebuilds`` (from scratch,
during the timed loops) and ``splits_last``; for the Warp engine
``maintain_ms`` and ``bfs_ms``, its two phases timed apart (median over
10 steps, outside JAX), with the maintenance's mean ``tries_per_step``,
``reads_per_step`` (host reads of device results), ``splits_per_step``
(failed tries), ``seeded_per_step`` (tries after a successful one, which
test only the triangles of the vertices still moving) and ``maintain_failed`` (steps whose repair gave up, each
then rebuilt on the host); ``overflow`` if any list
overflowed during the loops (the row is then not valid).

    python benchmarks/delaunay.py --sizes 10000                   # CPU
    python benchmarks/delaunay.py --sizes 10000 100000 1000000    # GPU
    python benchmarks/delaunay.py --quick                         # smoke
    python benchmarks/delaunay.py --smoke       # tiny N, end to end on CPU
"""
from __future__ import annotations

import math
import os
import sys
import tempfile
import time

if __package__:  # run as -m, or imported: the package's modules
    from benchmarks import _harness
else:  # run as a file: its folder is sys.path[0]
    import _harness

METHODS = ("delaunay", "delaunay[engine=warp]", "cell", "jax-md")
MOTIONS = ("boids", "random")
CACHE = os.path.join(tempfile.gettempdir(), "jaxrt-delaunay-bench")


def trajectory(motion: str, n: int, k: float, steps: int):
    """float64 ``(2 steps, N, 2)`` positions (forward, then back), the box
    side and the cutoff; cached on disk per (motion, N, k, steps)."""
    import numpy as np
    os.makedirs(CACHE, exist_ok=True)
    path = os.path.join(CACHE, f"{motion}_{n}_{k:g}_{steps}.npz")
    if os.path.exists(path):
        z = np.load(path)
        return z["traj"], float(z["side"]), float(z["cutoff"])
    if motion == "boids":
        traj, side, cutoff = _boids(n, k, steps)
    else:
        rng = np.random.default_rng(0)
        side = math.sqrt(n)  # unit density
        cutoff = math.sqrt(k / math.pi)  # k = pi rc^2 density
        step = 0.05 * rng.normal(size=(steps, n, 2))  # spacing = 1
        start = rng.uniform(0, side, (n, 2))
        traj = np.mod(start + np.cumsum(step, axis=0), side)
    traj = np.concatenate([traj, traj[::-1]])
    np.savez(path, traj=traj, side=side, cutoff=cutoff)
    return traj, side, cutoff


def _boids(n: int, k: float, steps: int):
    import jax
    import numpy as np
    from jaxrt import sim
    scene = sim.builtin("boids", n=n, neighbours=k, backend="cell")
    c = sim.compile_scene(scene)
    state, nbrs = c.init()
    step = jax.jit(c.step)
    out = []
    for _ in range(steps):
        state, nbrs, _ = step(state, nbrs)
        if nbrs.did_buffer_overflow:
            nbrs = c.neighbor_fn.allocate(state.position)
        out.append(np.asarray(state.position))
    return np.stack(out), float(scene.box.size[0]), scene.cutoff


def _list_fns(method: str, side: float, cutoff: float):
    from jax_md import partition, space
    disp, _ = space.periodic(side)
    if method == "jax-md":
        return partition.neighbor_list(disp, side, cutoff, 0.0,
                                       capacity_multiplier=1.5)
    import jaxrt
    return jaxrt.neighbor_list(disp, side, cutoff, 0.0,
                               capacity_multiplier=1.5,
                               backend=_harness.backend(method),
                               periodic=True)


def warp_phases(traj, side: float, cutoff: float, width: int,
                initial=None) -> dict:
    """The Warp engine's phases timed apart, outside JAX, on JAX's device:
    median ms per step of the maintenance (flips, with the flip counter
    read back each round) and of the adjacency and BFS. ``initial``:
    numpy ``(position, tri, twin, shift)`` of a Delaunay triangulation at
    ``traj[0]`` (the list's ``allocate`` made one: at 10^6 points a second
    host triangulation costs many seconds), else one is made here."""
    import numpy as np
    import warp as wp
    import jax
    from jaxrt.backends.delaunay import host_triangulate
    from jaxrt.backends.rt import delaunay_engine as engine
    device = "cuda" if jax.default_backend() in ("gpu", "cuda") else "cpu"
    L = np.array([side, side])
    if initial is None or not np.array_equal(initial[0], traj[0]):
        initial = host_triangulate(traj[0], L, cutoff)[:4]
    m = engine.mesh(*initial, n=traj.shape[1], side=L, device=device)
    engine.flip_to_delaunay(m)
    maintain, search, tries, reads, splits, failed = [], [], [], [], [], 0
    seeded = []
    result = None
    for R in traj[1:]:
        target = wp.array(R, dtype=wp.vec2d, device=device)
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        r = engine.maintain(m, target)
        wp.synchronize_device(device)
        t1 = time.perf_counter()
        if not r.ok:  # the timed call then rebuilds from scratch
            failed += 1
            engine.step(m, target, lambda p: host_triangulate(p, L, cutoff),
                        local_repair=False)
        tries.append(r.tries)
        reads.append(r.reads)
        splits.append(r.splits)
        seeded.append(r.seeded)
        result = engine.radius_search(m, cutoff, width=width, points=target,
                                      out=result)
        wp.synchronize_device(device)
        t2 = time.perf_counter()
        maintain.append(t1 - t0)
        search.append(t2 - t1)
    return {"maintain_ms": 1e3 * float(np.median(maintain)),
            "bfs_ms": 1e3 * float(np.median(search)),
            "tries_per_step": float(np.mean(tries)),
            "reads_per_step": float(np.mean(reads)),
            "splits_per_step": float(np.mean(splits)),
            "seeded_per_step": float(np.mean(seeded)),
            "maintain_failed": failed}


def run_row(job: dict) -> dict:
    """One (motion, method, N, k) row, in a worker."""
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    traj, side, cutoff = trajectory(job["motion"], job["N"],
                                    job["k_target"], job["steps"])
    path = jnp.asarray(traj)
    fns = _list_fns(job["method"], side, cutoff)
    t = time.perf_counter()
    nbrs = fns.allocate(path[0])
    jax.block_until_ready(nbrs.idx)
    allocate_s = time.perf_counter() - t
    idx = np.asarray(nbrs.idx)
    initial = None
    if "engine=warp" in job["method"]:
        st = nbrs.backend_state
        initial = tuple(np.asarray(a) for a in (st.position, st.tri,
                                                 st.twin, st.shift))
    k_measured = float(np.mean(np.sum(idx < job["N"], axis=1)))
    update = fns.update

    @jax.jit
    def loop(carry):
        nbrs, overflow = carry

        def body(c, R):
            nb, bad = c
            nb = update(R, nb)
            return (nb, bad | (nb.did_buffer_overflow != 0)), None
        (nbrs, overflow), _ = jax.lax.scan(body, (nbrs, overflow), path)
        return nbrs, overflow

    delaunay = job["method"].startswith("delaunay")
    carry = (nbrs, jnp.bool_(False))
    carry = jax.block_until_ready(loop(carry))  # warm: compiled
    before = (np.asarray(carry[0].backend_state.flips_total),
              np.asarray(carry[0].backend_state.rebuilds)) if delaunay \
        else None
    timing, carry = _harness.time_carry(
        loop, carry, repeats=job["repeats"], warmup=job["warmup"],
        per_call=len(traj))
    row = {"motion": job["motion"], "method": job["method"], "N": job["N"],
           "k_target": job["k_target"], "k": round(k_measured, 1),
           "cutoff": round(cutoff, 4), "box": round(side, 3),
           "dtype": "float64", "steps_per_loop": len(traj),
           "allocate_s": allocate_s, "update_ms": timing.median_ms,
           **timing.columns(), "overflow": bool(carry[1])}
    if delaunay:
        state = carry[0].backend_state
        loops = timing.repeats + timing.warmup
        row["flips_per_step"] = float(
            (np.asarray(state.flips_total) - before[0])
            / (loops * len(traj)))
        row["rebuilds"] = int(np.asarray(state.rebuilds) - before[1])
        row["splits_last"] = int(np.asarray(state.splits))
    if "engine=warp" in job["method"]:
        width = min(job["N"], 1 + int(np.max(np.sum(idx < job["N"], axis=1)))
                    + 16)
        row.update(warp_phases(traj[:min(len(traj), 11)], side, cutoff,
                               width, initial))
    return row


def add_ratios(rows: list[dict]) -> None:
    """Each row's speed-up over the cell list and over jax-md, same motion,
    N and k (> 1: this row is faster)."""
    for r in rows:
        for ref_name, col in (("cell", "vs_cell"), ("jax-md", "vs_jax_md")):
            ref = next((x for x in rows if x["motion"] == r["motion"]
                        and x["N"] == r["N"]
                        and x.get("k_target") == r.get("k_target")
                        and x["method"] == ref_name and x["status"] == "ok"),
                       None)
            if ref is not None and r["status"] == "ok" and r is not ref:
                r[col] = ref["update_ms"] / r["update_ms"]


COLUMNS = ["motion", "method", "N", "k_target", "k", "update_ms", "min_ms",
           "max_ms", "vs_cell", "vs_jax_md", "flips_per_step", "rebuilds",
           "splits_last", "maintain_ms", "bfs_ms", "tries_per_step",
           "reads_per_step", "splits_per_step", "seeded_per_step",
           "maintain_failed", "overflow", "allocate_s"]


def main(argv=None) -> None:
    parser = _harness.make_parser(__doc__)
    parser.add_argument("--sizes", type=int, nargs="+", default=[10_000],
                        help="N")
    parser.add_argument("--neighbours", type=float, nargs="+",
                        default=[8, 16, 32, 64],
                        help="mean neighbours k the box (boids) or the "
                        "cutoff (random) is scaled for")
    parser.add_argument("--motions", nargs="+", default=list(MOTIONS),
                        choices=MOTIONS)
    parser.add_argument("--methods", nargs="+", default=list(METHODS),
                        help="delaunay, delaunay[max_splits=8], cell, "
                        "cell[xla], jax-md, ...")
    parser.add_argument("--steps", type=int, default=20,
                        help="steps of the trajectory (replayed forward and "
                        "back: 2 steps per timed loop)")
    parser.add_argument("--quick", action="store_true",
                        help="smoke: N = 2000, k = 8, 2 repeats")
    _harness.add_common_args(parser, name="delaunay.csv", repeats=5,
                             warmup=1, timeout=900)
    parser.add_argument("--smoke", action="store_true",
                        help="end-to-end check: N = 400, k = 8, 3 steps, "
                        "1 repeat")
    parser.add_argument("--reuse-worker", action="store_true",
                        help="one worker for the rows while they succeed "
                        "(its start-up paid once)")
    args = parser.parse_args(argv)
    if args.smoke:
        args.sizes, args.neighbours, args.repeats = [400], [8], 1
        args.steps, args.warmup = 3, 0
    if args.quick:
        args.sizes, args.neighbours, args.repeats = [2000], [8], 2
    for label in args.methods:
        if label != "jax-md":
            _harness.parse_backend(label)  # a typo fails here
    jobs = [{"motion": m, "method": meth, "N": n, "k_target": k,
             "steps": args.steps, "repeats": args.repeats,
             "warmup": args.warmup}
            for n in args.sizes for k in args.neighbours
            for m in args.motions for meth in args.methods]
    _harness.run_jobs("delaunay:run_row", jobs, columns=COLUMNS,
                      finish=add_ratios, reuse_worker=args.reuse_worker,
                      **_harness.run_options(args))


if __name__ == "__main__":
    main()
