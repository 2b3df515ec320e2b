"""Where a Table 2 step's time goes on the host: the fixed per-step cost.

One row per (method, N): the step of `table2` (same scene, policy, jitter
and leapfrog), timed as Table 2 times it (each step synchronised), plus
what the host spends per step, measured by wrapping the functions a step
goes through (in the worker; the wrappers cost a few microseconds each):

* ``dispatch_us``: until the jitted step returns (before the wait);
* ``python_dispatches``: JAX executions through Python per step (0: the
  C++ fast path; an effectful program, e.g. an FFI call declared with side
  effects, takes the Python path);
* ``callback_us``, ``callbacks``: Warp's FFI callbacks (`wp.jax_callable`)
  per step, all inside them included;
* ``arg_arrays_us``: Warp building its ``wp.array`` views of the buffers;
* ``update_us`` / ``query_us``: `jaxrt.backends.rt.aabb.AabbSearch.update` (extent,
  placement, drift read-back, boxes, refit or rebuild) and the query or
  ORCS launch after it;
* ``readback_us``, ``readbacks``: device-to-host reads (``wp.array.numpy``:
  the refit's drift flag, a host synchronisation);
* ``launches``, ``launch_us``: ``wp.launch`` calls and their host time;
* ``rebuilds``: BVH rebuilds per step (the policy's choice).

The µs columns are per step, medians' worth of the timed steps (totals
divided by steps). On a GPU the step's ``median_ms`` minus the kernels is
roughly ``dispatch_us + callback_us`` when the step is host-bound.

    python benchmarks/step_overhead.py --quick                 # CPU smoke
    python benchmarks/step_overhead.py --n 64 50000            # GPU, ~1 min
"""
from __future__ import annotations

import collections
import functools
import os
import statistics
import sys
import time

if __package__:  # run as -m, or imported: the package's modules
    from benchmarks import _harness
else:  # run as a file: its folder is sys.path[0]
    import _harness
import table2  # noqa: E402

METHODS = ("RT-REF", "ORCS-forces", "ORCS-persé", "GPU-CELL", "GPU-CELL-fused")
COLUMNS = ["method", "N", "scene", "boundary", "median_ms", "min_ms",
           "dispatch_us", "python_dispatches", "callbacks", "callback_us",
           "arg_arrays_us", "update_us", "query_us", "readbacks",
           "readback_us", "launches", "launch_us", "rebuilds"]


class _Meter:
    """Wraps ``owner.name`` so that each call adds its host time to
    ``totals[label]`` and one to ``counts[label]``."""

    def __init__(self):
        self.totals: collections.Counter = collections.Counter()
        self.counts: collections.Counter = collections.Counter()

    def wrap(self, owner, name: str, label: str) -> None:
        inner = getattr(owner, name)

        @functools.wraps(inner)
        def timed(*args, **kwargs):
            t = time.perf_counter()
            try:
                return inner(*args, **kwargs)
            finally:
                self.totals[label] += time.perf_counter() - t
                self.counts[label] += 1

        setattr(owner, name, timed)

    def reset(self) -> None:
        self.totals.clear()
        self.counts.clear()


def _instrument(meter: _Meter) -> None:
    """Wrap what a step calls on the host (before any callable is made)."""
    from jax._src.interpreters import pxla
    meter.wrap(pxla.ExecuteReplicated, "__call__", "python_dispatch")
    try:
        import warp as wp
        from warp._src.jax import ffi as warp_ffi
    except ImportError:  # no Warp: the cell methods only
        return
    from jaxrt.backends.rt import aabb
    from jaxrt.backends.rt import orcs
    meter.wrap(warp_ffi.FfiCallable, "ffi_callback", "callback")
    meter.wrap(warp_ffi.FfiCallable, "_build_arg_list", "arg_arrays")
    meter.wrap(aabb.AabbSearch, "update", "update")
    meter.wrap(aabb.AabbSearch, "query", "query")
    meter.wrap(aabb.AabbSearch, "energy", "query")
    meter.wrap(orcs, "forces", "query")
    meter.wrap(orcs, "perse_step", "query")
    meter.wrap(wp.array, "numpy", "readback")
    meter.wrap(wp, "launch", "launch")
    meter.wrap(wp.Bvh, "rebuild", "rebuild")


def run_row(job: dict) -> dict:
    """One method at one N: the step's times and its host pieces."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    meter = _Meter()
    _instrument(meter)
    position, radii = table2._scene(job["scene"], "r=1", job["N"], 0)
    rng = np.random.default_rng(7)
    side = job["dynamics"]["box"]
    snapshots = [np.clip(position + rng.uniform(-0.01, 0.01, position.shape),
                         0.0, side * (1 - 1e-7)) for _ in range(3)]
    R = [jnp.asarray(s, jnp.float32) for s in snapshots]
    step, state, _, _ = table2._step_fns(job, R[0], radii)
    states = [(r,) + tuple(state[1:]) for r in R]
    for i in range(job["warmup"]):
        jax.block_until_ready(step(states[i % 3]))
    meter.reset()
    total, dispatch = [], []
    for i in range(job["repeats"]):
        t = time.perf_counter()
        out = step(states[i % 3])
        dispatch.append(time.perf_counter() - t)
        jax.block_until_ready(out)
        total.append(time.perf_counter() - t)
    steps = job["repeats"]

    def per_step_us(label):
        return round(1e6 * meter.totals[label] / steps, 1)

    def per_step(label):
        return round(meter.counts[label] / steps, 2)

    return {"median_ms": 1e3 * statistics.median(total),
            "min_ms": 1e3 * min(total),
            "dispatch_us": round(1e6 * statistics.median(dispatch), 1),
            "python_dispatches": per_step("python_dispatch"),
            "callbacks": per_step("callback"),
            "callback_us": per_step_us("callback"),
            "arg_arrays_us": per_step_us("arg_arrays"),
            "update_us": per_step_us("update"),
            "query_us": per_step_us("query"),
            "readbacks": per_step("readback"),
            "readback_us": per_step_us("readback"),
            "launches": per_step("launch"),
            "launch_us": per_step_us("launch"),
            "rebuilds": per_step("rebuild"), "status": "ok",
            "dtype": "float32"}


def main(argv=None) -> None:
    parser = _harness.make_parser(__doc__)
    parser.add_argument("--n", type=int, nargs="+", default=[64, 50_000])
    parser.add_argument("--methods", nargs="+", default=list(METHODS),
                        choices=list(METHODS))
    parser.add_argument("--scene", default="lattice", choices=table2.SCENES)
    parser.add_argument("--boundary", default="wall",
                        choices=table2.BOUNDARIES)
    parser.add_argument("--policy", default="gradient")
    parser.add_argument("--quick", action="store_true",
                        help="CPU smoke: n = 64 and 2000, 50 steps")
    _harness.add_common_args(parser, name="step_overhead.csv", repeats=300,
                             warmup=5, timeout=300.0)
    args = parser.parse_args(argv)
    if args.quick:
        args.n, args.repeats = [64, 2000], 50
    jobs = [{"method": m, "N": n, "scene": args.scene, "radii": "r=1",
             "boundary": args.boundary, "seed": 0, "policy": args.policy,
             "repeats": args.repeats, "warmup": args.warmup,
             "dynamics": table2.DYNAMICS}
            for n in args.n for m in args.methods]
    # A fresh worker per row: the wrappers and the kept trees stay its own.
    _harness.run_jobs("step_overhead:run_row", jobs, columns=COLUMNS,
                      **_harness.run_options(args))


if __name__ == "__main__":
    main()
