"""Sweep the cell list's stencil reach on a uniform periodic scene.

The reach is the module constant `jaxrt.backends.cell.search._REACH` = (reach along x,
reach across): cells are cutoff / reach wide along those axes. Each row
(N, reach) runs in its own worker process (`_harness`), which sets the
constant (and `_RUN_SPAN`, derived from it at import) before building the
list, so no row sees another's setting. Scene: density 1, rc = 2.5; times
are the jitted Dense ``update`` (every call searches again), warm-up
excluded, median / min / max over three rotating input sets. ``internal``
holds the list's internal buffer sizes; ``same_list`` says whether a row's
list (rows sorted) equals the first row's of the same N.

    python benchmarks/tune_cell_list.py [N ...]          # default 100000
    python benchmarks/tune_cell_list.py 2000 --reaches 4,1 8,1 --repeats 3
"""
from __future__ import annotations

import hashlib
import os
import sys

if __package__:  # run as -m, or imported: the package's modules
    from benchmarks import _harness
else:  # run as a file: its folder is sys.path[0]
    import _harness


def run_row(job: dict) -> dict:
    """One (N, reach) row, in a worker."""
    import jax
    import numpy as np
    from jax_md import space

    import jaxrt
    import jaxrt.backends.cell.search as cl

    n, reach = job["N"], tuple(int(v) for v in job["reach"].split(","))
    cl._REACH = reach
    cl._RUN_SPAN = 2 * reach[0] + 2  # as cell_list derives it at import
    side = n ** (1 / 3)
    R = jax.random.uniform(jax.random.PRNGKey(0), (n, 3)) * side
    disp, _ = space.periodic(side)
    fns = jaxrt.neighbor_list(disp, side, 2.5,
                              backend=_harness.backend(job["backend"]))
    nbrs = fns.allocate(R)
    update = jax.jit(fns.update)
    inputs = [(R + 1e-3 * i) % side for i in range(3)]
    timing = _harness.time_calls(lambda x: update(x, nbrs).idx, inputs,
                                 repeats=job["repeats"], warmup=job["warmup"])
    idx = np.sort(np.asarray(update(inputs[0], nbrs).idx), axis=1)
    return {"N": n, "k": round(float(np.mean(np.sum(idx < n, axis=1))), 1),
            "internal": " ".join(f"{k}:{v}" for k, v in
                                 nbrs.cell_list_capacity.internal),
            "update_ms": timing.median_ms, **timing.columns(),
            "list_sha1": hashlib.sha1(idx.tobytes()).hexdigest()[:12]}


def same_lists(rows: list[dict]) -> None:
    for r in rows:
        ref = next((x for x in rows if x["N"] == r["N"] and x.get("list_sha1")),
                   None)
        if r.get("list_sha1") and ref is not None:
            r["same_list"] = r["list_sha1"] == ref["list_sha1"]


COLUMNS = ["N", "reach", "backend", "k", "update_ms", "min_ms", "max_ms",
           "internal", "same_list"]


def main(argv=None) -> None:
    parser = _harness.make_parser(__doc__)
    parser.add_argument("sizes", type=int, nargs="*", default=[100_000])
    parser.add_argument("--reaches", nargs="+", default=["1,1", "2,1", "4,1",
                                                         "8,1"],
                        help="reach along x,reach across")
    parser.add_argument("--backend", default="cell",
                        help="backend label: cell, cell[xla], cell[pallas]")
    _harness.add_common_args(parser, name="tune_cell_list.csv", repeats=7,
                             warmup=3, timeout=600)
    args = parser.parse_args(argv)
    _harness.parse_backend(args.backend)
    reaches = [",".join(str(int(v)) for v in r.split(",")) for r in args.reaches]
    jobs = [{"N": n, "reach": r, "backend": args.backend,
             "repeats": args.repeats, "warmup": args.warmup}
            for n in args.sizes for r in reaches]
    _harness.run_jobs("tune_cell_list:run_row", jobs, columns=COLUMNS,
                      finish=same_lists, **_harness.run_options(args))


if __name__ == "__main__":
    main()
