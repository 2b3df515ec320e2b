"""The seed study's worker: one (configuration, method) job, measured in a
`_harness` worker process (``_harness.run_jobs("seed_rt.worker:run_job",
...)``). The methods of one configuration share a worker and its scene on
the device; a new configuration, or any failure, gets a fresh worker."""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import _harness
from seed_rt.plan import METHODS

INPUT_SETS = 3


def make_scene(scene: str, param: int, p: int):
    """float32 input sets (3 of (N, 3)), cutoff, box side.

    The seed's boxes: the unit box for the uniform scene; for the sphere the
    box that just holds it, side ``2 + 2C``, the points shifted by ``1 + C``.
    Every method gets that box (jax-md's grid is sized by it)."""
    import numpy as np
    from jaxrt import seed_distributions as scenes
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


def lj_forces(R, idx, sigma):
    """LJ-like pair forces summed over each Dense row (padding idx = N)."""
    import jax.numpy as jnp
    n = R.shape[0]
    mask = idx < n
    dr = R[:, None, :] - R[jnp.minimum(idx, n - 1)]
    r2 = jnp.maximum(jnp.sum(dr * dr, axis=-1), (0.1 * sigma) ** 2)
    s6 = (sigma * sigma / r2) ** 3
    fmag = jnp.where(mask, 24.0 * (2.0 * s6 * s6 - s6) / r2, 0.0)
    return jnp.sum(fmag[..., None] * dr, axis=1)


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
    the kept BVHs (`jaxrt.rt.ffi.forget_trees`) and the last scene of the
    spheres / squares methods (their ``_scene``, held by the method objects
    that `jaxrt.rt.ffi` keeps per options value; an internal, looked up
    defensively)."""
    import gc
    try:
        from jaxrt.rt import ffi
    except ImportError:  # no Warp: nothing kept
        gc.collect()
        return
    ffi.forget_trees()
    for entry in list(getattr(ffi, "_METHOD_CALLABLES", {}).values()):
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


def run_job(job: dict) -> dict:
    """Measure one method on one configuration (init, compute, search)."""
    import jax
    import jax.numpy as jnp
    from jax_md import partition, space

    scene, param, p, method = job["scene"], job["param"], job["p"], job["method"]
    release_memory()
    inputs, cutoff, box = scene_inputs(scene, param, p)
    n = inputs[0].shape[0]
    row = {"N": n, "cutoff": cutoff, "box": box}
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

    sigma = 0.5 * cutoff

    @jax.jit
    def compute(x, nb):
        nb = fns.update(x, nb)
        return nb.did_buffer_overflow, lj_forces(x, nb.idx, sigma)

    search = jax.jit(lambda x, nb: fns.update(x, nb).idx)
    # Trace here, compile both programs at once (XLA releases the GIL).
    lowered = [compute.lower(inputs[0], nbrs)]
    if job.get("search", True):
        lowered.append(search.lower(inputs[0], nbrs))
    with ThreadPoolExecutor(len(lowered)) as pool:
        compiled = [f.result() for f in [pool.submit(lw.compile) for lw in lowered]]
    del lowered, compute, search

    flags = []
    _put(row, "compute", _timed(lambda x: compiled[0](x, nbrs), inputs, job,
                                keep=lambda out: flags.append(out[0])))
    row["overflow"] = bool(any(bool(f) for f in flags))
    if len(compiled) > 1:
        if row["compute_ms"] <= job.get("search_limit_ms", float("inf")):
            _put(row, "search", _timed(lambda x: compiled[1](x, nbrs), inputs,
                                       job))
        else:
            row["search_reps"] = 0  # compute too slow: not worth the budget
    row["total_ms"] = row["init_ms"] + row["compute_ms"]
    return row
