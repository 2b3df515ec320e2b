"""Lists with per-particle radii: the cell list's radius classes against cells of the largest radius, and the BVH.

Seed 003's scenes (`jaxrt.sim.distributions`: Lattice, Disordered,
Cluster in a periodic 1000³ box) with its radius kinds U[1, 160] and
LN(1, 2) clipped to [1, 330]. Each row times one rebuild of the list
(``update`` through ``jax.jit`` with no skin, so every call searches),
median of ``--repeats`` after ``--warmup``, all rows of one run side by
side on one device. Backends (`_harness.parse_backend` labels):

  cell                       radius classes (`jaxrt.backends.cell.radius_classes`)
  cell[radius_classes=1]     one grid of cells of the largest radius
  bvh                        boxes of each particle's radius (§3)

The cell list builds Dense rows before a Sparse layout, so N x the
largest row must stay below 2**31 (the largest LN particle has ~ρ 4/3 π
330³ neighbours): n = 50 000 on the GPU, as in the paper's Table 2.

    python benchmarks/radii.py                    # CPU sizes (n = 10 000)
    python benchmarks/radii.py --n 50000          # the H200 run
"""
from __future__ import annotations

import os
import sys

if __package__:  # run as -m, or imported: the package's modules
    from benchmarks import _harness
else:  # run as a file: its folder is sys.path[0]
    import _harness

BACKENDS = ("cell", "cell[radius_classes=1]", "bvh")
COLUMNS = ["scene", "radii", "method", "N", "k", "median_ms", "min_ms",
           "max_ms", "speedup", "classes"]


def run_row(job: dict) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax_md import partition, space

    import jaxrt
    from jaxrt.sim import distributions as sd

    n, seed = job["N"], job["seed"]
    position = {"lattice": lambda: sd.lattice(n),
                "disordered": lambda: sd.disordered(n, seed),
                "cluster": lambda: sd.cluster(n, seed)}[job["scene"]]()
    radii = sd.radii(job["radii"], n, seed + 1)
    side = sd.BOX_SIDE
    displacement, _ = space.periodic(side)
    fn = jaxrt.neighbor_list(displacement, side, float(radii.max()), 0.0,
                             format=partition.Sparse, radii=radii,
                             backend=_harness.backend(job["method"]))
    R = jnp.asarray(position, jnp.float32)
    nbrs = fn.allocate(R)
    update = jax.jit(fn.update)
    # Rotate inputs: tiny moves, so no call only measures a cache.
    rng = np.random.default_rng(seed)
    inputs = [jnp.mod(R + jnp.asarray(rng.normal(0, 1e-3, R.shape),
                                      jnp.float32), side) for _ in range(3)]
    timing = _harness.time_calls(lambda r: update(r, nbrs).idx, inputs,
                                 repeats=job["repeats"], warmup=job["warmup"])
    out = update(inputs[0], nbrs)
    if bool(out.did_buffer_overflow):
        raise RuntimeError("list overflowed during timing")
    capacity = nbrs.cell_list_capacity
    return {**{k: v for k, v in job.items() if not k.startswith("_")},
            "k": round(float(jnp.sum(out.idx[0] < n)) / n, 2),
            "classes": dict(capacity.internal).get("classes", ""),
            "radius_rule": "LN clipped to [1, 330]",
            **timing.columns(), "status": "ok"}


def speedups(rows: list[dict]) -> None:
    """Each row's speed-up over cells of the largest radius (same scene)."""
    base = {(r["scene"], r["radii"]): r.get("median_ms") for r in rows
            if r.get("method") == "cell[radius_classes=1]"
            and r.get("status") == "ok"}
    for r in rows:
        b = base.get((r.get("scene"), r.get("radii")))
        if b and r.get("status") == "ok" and r.get("median_ms"):
            r["speedup"] = round(float(b) / float(r["median_ms"]), 2)


def main(argv=None) -> None:
    parser = _harness.make_parser(__doc__)
    parser.add_argument("--n", type=int, default=10_000)
    parser.add_argument("--scenes", nargs="+",
                        default=("disordered", "lattice", "cluster"))
    parser.add_argument("--radii", nargs="+", default=("LN[1,330]", "U[1,160]"))
    parser.add_argument("--backends", nargs="+", default=BACKENDS)
    parser.add_argument("--seed", type=int, default=0)
    _harness.add_common_args(parser, name="radii.csv", repeats=5, warmup=1)
    args = parser.parse_args(argv)
    jobs = [{"scene": s, "radii": r, "method": b, "N": args.n,
             "seed": args.seed, "repeats": args.repeats,
             "warmup": args.warmup, "_group": f"{s}/{r}"}
            for r in args.radii for s in args.scenes for b in args.backends]
    _harness.run_jobs("radii:run_row", jobs, columns=COLUMNS, finish=speedups,
                      **_harness.run_options(args))


if __name__ == "__main__":
    main()
