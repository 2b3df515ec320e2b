"""Where an ``allocate`` goes: jaxrt's stages, timed on new structures.

``benchmarks/neighbors.py``'s scenes (uniform, sphere); per backend label
and N, one cold ``allocate`` (seed 0, untimed), then ``--repeats`` more on
new structures of the same scene and N (seeds 1, 2, ...), each split into
the stages of `jaxrt.lists.neighbors._Lists.allocate`, device-synchronised:

  model     the metric's model and its checks (`_model_at_allocate`)
  measure   the backend's exact sizes (`_measure`: counting passes)
  build     the list's build (compiled for `_Lists.compiled_capacity`)
  trim      the wider build cut to the list's capacity (`_trimmed`)
  rest      everything else (argument checks, the finiteness check, ...)

``compiled`` says how many builds the row compiled (``_cache_size`` of the
jitted build). Medians over the repeats; compiles included, as a training
set's next structure pays them. A diagnostic of private stages: the names
above follow `jaxrt/lists/neighbors.py` and move with it.

    python benchmarks/allocate_parts.py --sizes 16384 --backends cell bvh
    python benchmarks/allocate_parts.py --sizes 2000000 --scenes sphere \\
        --backends cell bvh squares        # the H200 (seed 001's init)
"""
from __future__ import annotations

import time

if __package__:  # run as -m, or imported: the package's modules
    from benchmarks import _harness
else:  # run as a file: its folder is sys.path[0]
    import _harness
from neighbors import scene

STAGES = ("model", "measure", "build", "trim")
COLUMNS = ["scene", "method", "N", "capacity", "allocate_ms",
           *(f"{s}_ms" for s in STAGES), "rest_ms", "compiled"]


def run_row(job: dict) -> dict:
    """One (scene, method, N) row, in a worker."""
    import jax
    import numpy as np
    from jax_md import space

    import jaxrt
    from jaxrt.lists import neighbors

    n, name = job["N"], job["scene"]
    _, side, cutoff, periodic = scene(name, n, 0)
    disp, _ = space.periodic(side) if periodic else space.free()
    fns = jaxrt.neighbor_list(disp, side, cutoff, dr_threshold=0.0,
                              backend=_harness.backend(job["method"]))
    lists = fns.allocate.__self__
    spent: dict[str, float] = {}

    def timed(stage, fn):
        def run(*args, **kwargs):
            t = time.perf_counter()
            out = jax.block_until_ready(fn(*args, **kwargs))
            spent[stage] = spent.get(stage, 0.0) + time.perf_counter() - t
            return out
        return run

    # Module functions the allocate looks up at call time, and the build.
    for stage, attr in (("model", "_model_at_allocate"),
                        ("measure", "_measure"), ("trim", "_trimmed")):
        setattr(neighbors, attr, timed(stage, getattr(neighbors, attr)))
    build = lists.build
    lists.build = timed("build", build)

    samples = []
    for seed in range(job["repeats"] + 1):
        position = jax.block_until_ready(jax.numpy.asarray(
            scene(name, n, seed)[0]))
        spent.clear()
        t = time.perf_counter()
        nbrs = fns.allocate(position)
        jax.block_until_ready(nbrs.idx)
        total = time.perf_counter() - t
        if seed:  # the cold first one is neighbors.py's allocate_s
            samples.append({"allocate": total, **spent,
                            "rest": total - sum(spent.values())})
        del position
    row = {"scene": name, "method": job["method"], "N": n,
           "capacity": int(nbrs.idx.shape[-1]), "compiled": build._cache_size()}
    for stage in ("allocate", *STAGES, "rest"):
        row[f"{stage}_ms"] = 1e3 * float(np.median(
            [s.get(stage, 0.0) for s in samples]))
    return row


def main(argv=None) -> None:
    parser = _harness.make_parser(__doc__)
    parser.add_argument("--sizes", type=int, nargs="+", default=[16_384])
    parser.add_argument("--scenes", nargs="+", default=["uniform", "sphere"],
                        choices=["uniform", "sphere"])
    parser.add_argument("--backends", nargs="+", default=["cell"],
                        help="jaxrt backend labels: cell, bvh, squares, ...")
    _harness.add_common_args(parser, name="allocate_parts.csv", repeats=3,
                             warmup=0, timeout=600)
    args = parser.parse_args(argv)
    for label in args.backends:
        _harness.parse_backend(label)  # a typo fails here, not in a worker
    jobs = [{"scene": s, "method": m, "N": n, "repeats": args.repeats}
            for s in args.scenes for n in args.sizes for m in args.backends]
    _harness.run_jobs("allocate_parts:run_row", jobs, columns=COLUMNS,
                      **_harness.run_options(args))


if __name__ == "__main__":
    main()
