"""The seed study's worker: one (configuration, method) job, measured in a
`_harness` worker process (``_harness.run_jobs("seed_rt.worker:run_job",
...)``). The methods of one configuration share a worker and its scene on
the device; a new configuration, or any failure, gets a fresh worker."""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

if __package__ == "benchmarks.seed_rt":  # the package's module
    from benchmarks import _harness
    from benchmarks.seed_rt.plan import FUSED, METHODS, WARP_METHODS
else:  # a worker of seed_rt_study.py run as a file
    import _harness
    from seed_rt.plan import FUSED, METHODS, WARP_METHODS

INPUT_SETS = 3


def make_scene(scene: str, param: int, p: int):
    """float32 input sets (3 of (N, 3)), cutoff, box side.

    The seed's boxes: the unit box for the uniform scene; for the sphere the
    box that just holds it, side ``2 + 2C``, the points shifted by ``1 + C``.
    Every method gets that box (jax-md's grid is sized by it)."""
    import numpy as np
    from jaxrt.sim import distributions as scenes
    if scene == "uniform":
        pos, cutoff = scenes.uniform(param, p, seed=0)
        box = 1.0
    else:
        pos, cutoff = scenes.sphere_surface(param, p, seed=0)
        pos = pos + (1.0 + cutoff)
        box = 2.0 + 2.0 * cutoff
    rng = np.random.default_rng(1)
    sets = [pos.astype(np.float32)]
    for _ in range(INPUT_SETS - 1):
        moved = pos + rng.normal(0.0, 1e-3 * cutoff, pos.shape)
        sets.append(np.clip(moved, 0.0, np.nextafter(box, 0.0)).astype(np.float32))
    return sets, float(cutoff), float(box)


def lj_energy(R, idx, sigma, epsilon=1.0):
    """Per-particle LJ energy summed over each Dense row (padding idx = N):
    ``E_i = sum_j 4 eps [(sigma^2/r2)^6 - (sigma^2/r2)^3]`` with r2 clamped
    at ``(sigma/10)^2``; the quantity the fused kernels sum during the
    traversal (`jaxrt.backends.rt.seed_energy`, same arithmetic), so the list and
    fused rows of a configuration can be compared (``energy_sum``)."""
    import jax.numpy as jnp
    n = R.shape[0]
    mask = idx < n
    dr = R[:, None, :] - R[jnp.minimum(idx, n - 1)]
    r2 = jnp.maximum(jnp.sum(dr * dr, axis=-1), (0.1 * sigma) ** 2)
    s6 = (sigma * sigma / r2) ** 3
    return jnp.sum(jnp.where(mask, 4.0 * epsilon * (s6 * s6 - s6), 0.0), axis=1)


_SCENE: dict = {}


def scene_inputs(scene: str, param: int, p: int):
    """The configuration's inputs on the device, kept for the next method
    of the same configuration (a worker serves one configuration)."""
    import jax
    import jax.numpy as jnp
    key = (scene, param, p)
    if key not in _SCENE:
        _SCENE.clear()
        sets, cutoff, box = make_scene(scene, param, p)
        inputs = [jnp.asarray(s) for s in sets]
        jax.block_until_ready(inputs)
        _SCENE[key] = (inputs, cutoff, box)
    return _SCENE[key]


def release_memory() -> None:
    """Drop what jaxrt keeps between calls, before the next method runs:
    the kept BVHs (`jaxrt.backends.rt.ffi.forget_trees`) and the last scene of the
    spheres / squares methods (their ``_scene``, held by the method objects
    that `jaxrt.backends.rt.ffi` keeps per options value, for the lists and the
    fused mode; an internal, looked up defensively)."""
    import gc
    try:
        from jaxrt.backends.rt import ffi
    except ImportError:  # no Warp: nothing kept
        gc.collect()
        return
    ffi.forget_trees()
    for entry in [*getattr(ffi, "_METHOD_CALLABLES", {}).values(),
                  *getattr(ffi, "_FUSED_CALLABLES", {}).values()]:
        method = entry[0] if isinstance(entry, tuple) else entry
        if hasattr(method, "_scene"):
            method._scene = None
    gc.collect()


def _timed(fn, inputs, job, keep=None):
    """`_harness.time_calls` as the study runs it: one untimed call, then
    timed calls whose number the first sets (``--target-s``, clamped to
    ``--min-repeats`` .. ``--max-repeats``)."""
    return _harness.time_calls(fn, inputs, repeats=job["min_repeats"],
                               warmup=1, target_s=job["target_s"],
                               max_repeats=job["max_repeats"], keep=keep)


def _put(row: dict, name: str, t: _harness.Timing) -> None:
    row[f"{name}_ms"] = t.median_ms
    row[f"{name}_min_ms"] = t.min_ms
    row[f"{name}_max_ms"] = t.max_ms
    row[f"{name}_reps"] = t.repeats


def _sums(row: dict, energy, count) -> None:
    """``pairs`` (ordered, int64) and ``energy_sum`` (float64) of one
    evaluation on the first input set, for comparing methods."""
    import numpy as np
    row["pairs"] = int(np.sum(np.asarray(count), dtype=np.int64))
    row["energy_sum"] = float(np.sum(np.asarray(energy), dtype=np.float64))


def warp_split(method: str, inputs, cutoff: float, box: float, job: dict,
               capacity: int | None) -> dict:
    """Seed 001's timing split (SPECS §7.2) for a Warp method, outside JAX:
    ``build_ms`` = the structure alone (the paper's init: the custom AABB's
    extent, Morton sort and placement, boxes and a BVH rebuild; spheres /
    squares: the survey, the primitives' boxes and a new BVH); ``query_ms``
    = the rays alone on that structure (the paper's compute: launch,
    callbacks and, fused, the interactions; for a list method the Dense
    rows instead of the interactions, which ``interaction_ms`` times in
    JAX). Each sample ends with a device synchronise."""
    import time

    import warp as wp
    from jaxrt.backends.rt import aabb
    from jaxrt.backends.rt import seed_energy
    from jaxrt.backends.rt import policy as rt_policy
    from jaxrt.backends.rt.method import FindArguments
    from jaxrt.backends.rt.spheres import SpheresMethod
    from jaxrt.backends.rt.squares import SquaresMethod

    points = [wp.from_jax(x, dtype=wp.vec3) for x in inputs]
    device = points[0].device
    n = points[0].shape[0]
    fused = method in FUSED
    base = FUSED.get(method, method)
    with wp.ScopedDevice(device):
        params = wp.array(seed_energy.lj_params(sigma=0.5 * cutoff), dtype=wp.float32)
        energy = wp.zeros(n, dtype=wp.float32)
        count = wp.zeros(n, dtype=wp.int32)
        rows = None if fused else wp.empty((n, max(capacity, 1)), dtype=wp.int32)
        side = wp.array([(box, box, box)], dtype=wp.vec3)
    free = (False, False, False)
    if base.startswith("aabb"):
        search = aabb.AabbSearch(n, wp.vec3, device, sort=base == "aabb-sorted",
                                 policy=rt_policy.Rebuild())

        def build(p):
            search.update(p, side, free, cutoff)

        def query():
            if fused:
                search.energy(side, params, energy=energy, count=count)
            else:
                search.query_dense(side, mask_self=True, rows=rows, count=count)
    else:
        m = SpheresMethod() if base == "spheres" else SquaresMethod()
        args = FindArguments(cutoff, (0.0, 0.0, 0.0), free, True)
        scene = []

        def build(p):
            scene[:] = [m.build(p, args)]

        def query():
            if fused:
                energy.zero_()
                m.query(scene[0], params=params, out_energy=energy, out_count=count)
            else:
                m.query(scene[0], out_idx=rows, out_count=count)

    def timed(fn):
        def run(x):
            wp.synchronize_device(device)
            t = time.perf_counter()
            fn(x)
            wp.synchronize_device(device)
            return (time.perf_counter() - t) * 1e3
        return run

    reps = job["min_repeats"]
    t_build = _harness.time_self_timed(timed(build), points, repeats=reps, warmup=1)
    build(points[0])
    t_query = _harness.time_self_timed(timed(lambda _: query()), points,
                                       repeats=reps, warmup=1)
    out = {}
    for name, t in (("build", t_build), ("query", t_query)):
        out[f"{name}_ms"] = t.median_ms
        out[f"{name}_min_ms"] = t.min_ms
        out[f"{name}_max_ms"] = t.max_ms
        out[f"{name}_reps"] = t.repeats
    return out


def run_job(job: dict) -> dict:
    """Measure one method on one configuration: init, compute, search (list
    methods), the JAX interaction alone (list methods) and the Warp split
    (build_ms, query_ms; Warp methods)."""
    import jax
    import jax.numpy as jnp
    from jax_md import partition, space

    scene, param, p, method = job["scene"], job["param"], job["p"], job["method"]
    release_memory()
    inputs, cutoff, box = scene_inputs(scene, param, p)
    n = inputs[0].shape[0]
    row = {"N": n, "cutoff": cutoff, "box": box}
    sigma = 0.5 * cutoff
    if method in FUSED:
        _fused_job(row, method, inputs, cutoff, box, sigma, job)
    else:
        _list_job(row, method, inputs, cutoff, box, sigma, job, jax, jnp,
                  partition, space)
    row["total_ms"] = row["init_ms"] + row["compute_ms"]
    if row.get("build_ms") is not None:
        # The paper's split: init = the build; compute = rays + interactions
        # (a list method's rays write rows, its interactions are the JAX sum).
        row["paper_init_ms"] = row["build_ms"]
        row["paper_compute_ms"] = row["query_ms"] + row.get("interaction_ms", 0.0)
    return row


def _fused_job(row, method, inputs, cutoff, box, sigma, job) -> None:
    """A fused method: ``init_ms`` is its build-only time (there is no
    list to allocate), ``compute_ms`` one jitted `jaxrt.rt.FusedEnergy`
    call (custom AABB: refit of the kept tree + rays, as the list aabb's
    compute; spheres / squares: build + rays, as theirs)."""
    import jax
    from jaxrt.backends.rt import FusedEnergy

    fused = FusedEnergy(_harness.backend(METHODS[method]), cutoff=cutoff, sigma=sigma)
    call = jax.jit(fused)
    t = _timed(call, inputs, job)
    _put(row, "compute", t)
    energy, count = call(inputs[0])
    _sums(row, energy, count)
    row["k_mean"] = row["k"] = round(row["pairs"] / row["N"], 2)
    if job.get("split", True):
        row.update(warp_split(method, inputs, cutoff, box, job, None))
    else:  # init is the build: without the split, one build in the call
        row["build_ms"] = None
    row["init_ms"] = row.get("build_ms") if row.get("build_ms") is not None else float("nan")
    for suffix in ("min_ms", "max_ms", "reps"):
        row[f"init_{suffix}"] = row.get(f"build_{suffix}")


def _list_job(row, method, inputs, cutoff, box, sigma, job, jax, jnp,
              partition, space) -> None:
    n = inputs[0].shape[0]
    disp, _ = space.free()
    if METHODS[method] is None:
        fns = partition.neighbor_list(disp, box, cutoff, dr_threshold=0.0,
                                      format=partition.Dense)
    else:
        import jaxrt
        fns = jaxrt.neighbor_list(disp, box, cutoff, dr_threshold=0.0,
                                  format=partition.Dense,
                                  backend=_harness.backend(METHODS[method]))

    # init: allocate (eager). The first (untimed) call's list is kept.
    t = _timed(fns.allocate, inputs, job)
    _put(row, "init", t)
    nbrs = t.first
    row["k_mean"] = row["k"] = round(float(jnp.mean(jnp.sum(nbrs.idx < n, axis=1))), 2)
    row["capacity"] = int(nbrs.idx.shape[1])

    @jax.jit
    def compute(x, nb):
        nb = fns.update(x, nb)
        return nb.did_buffer_overflow, lj_energy(x, nb.idx, sigma)

    search = jax.jit(lambda x, nb: fns.update(x, nb).idx)
    interaction = jax.jit(lambda x, idx: lj_energy(x, idx, sigma))
    # Trace here, compile the programs at once (XLA releases the GIL).
    lowered = [compute.lower(inputs[0], nbrs), interaction.lower(inputs[0], nbrs.idx)]
    if job.get("search", True):
        lowered.append(search.lower(inputs[0], nbrs))
    with ThreadPoolExecutor(len(lowered)) as pool:
        compiled = [f.result() for f in [pool.submit(lw.compile) for lw in lowered]]
    del lowered, compute, search, interaction

    flags = []
    _put(row, "compute", _timed(lambda x: compiled[0](x, nbrs), inputs, job,
                                keep=lambda out: flags.append(out[0])))
    row["overflow"] = bool(any(bool(f) for f in flags))
    # nbrs is allocate's list at inputs[0] (its first, untimed call).
    _, energy = compiled[0](inputs[0], nbrs)
    _sums(row, energy, jnp.sum(nbrs.idx < n, axis=1))
    del energy
    # The interactions alone, on the allocate'd list (the paper's CUDA
    # compute step is its interaction kernel).
    _put(row, "interaction", _timed(lambda x: compiled[1](x, nbrs.idx), inputs, job))
    if len(compiled) > 2:
        if row["compute_ms"] <= job.get("search_limit_ms", float("inf")):
            _put(row, "search", _timed(lambda x: compiled[2](x, nbrs), inputs,
                                       job))
        else:
            row["search_reps"] = 0  # compute too slow: not worth the budget
    if method in WARP_METHODS and job.get("split", True):
        cap = row["capacity"]
        del nbrs, compiled
        release_memory()
        row.update(warp_split(method, inputs, cutoff, box, job, cap))
