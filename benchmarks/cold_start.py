"""Cold start: a newcomer's first neighbour list, jaxrt beside jax-md.

Each (library, N) runs in a fresh Python process, so that nothing is
compiled or imported before it: the process CPU time and the wall time of
``import``, ``neighbor_list`` + ``allocate``, the first ``update`` (eager,
as the README's "Use" snippet calls it), the median of 5 more eager
``update`` calls, and the median of 5 calls of ``jax.jit(update)`` after
its first (its compile is reported as ``jit_first``). Then, in the same
process (warm: imported, earlier programs compiled), a second
``neighbor_list`` with the same arguments: ``allocate`` and its first
``update`` again.

The system: uniform random positions at density 0.8 in a periodic cube,
``space.periodic``, r_cutoff 1.5, dr_threshold 0.5, the default format
(Dense) and the default backend, called as a user would:
``jaxrt.neighbor_list(displacement, box, r_cutoff, dr_threshold)`` against
``jax_md.partition.neighbor_list`` with the same arguments.

    PYTHONPATH=$PWD JAX_PLATFORMS=cpu python3 benchmarks/cold_start.py \
        --n 100 1000 10000 --out benchmarks/results/cpu-2core/cold_start.csv
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

PHASES = ("import", "allocate", "first_update", "eager_update",
          "jit_first", "jit_update", "warm_allocate", "warm_first_update")


def _child(library: str, n: int, fmt: str) -> None:
    """One cold run; prints a JSON object of {phase: [cpu_s, wall_s]}."""
    out = {}
    clock = [time.process_time(), time.perf_counter()]

    def lap(name):
        t, w = time.process_time(), time.perf_counter()
        out[name] = [t - clock[0], w - clock[1]]
        clock[:] = [t, w]

    import jax
    import jax.numpy as jnp
    from jax_md import partition, space
    if library == "jaxrt":
        import jaxrt
        neighbor_list = jaxrt.neighbor_list
    else:
        neighbor_list = partition.neighbor_list
    jnp.zeros(()).block_until_ready()  # the backend started: import's
    lap("import")

    side = (n / 0.8) ** (1 / 3)
    position = jax.random.uniform(jax.random.PRNGKey(0), (n, 3)) * side
    moved = [position + 0.02 * k for k in range(1, 7)]
    jax.block_until_ready(moved)
    displacement, _ = space.periodic(side)
    layout = getattr(partition.NeighborListFormat, fmt)
    clock[:] = [time.process_time(), time.perf_counter()]

    def allocate_and_update(prefix):
        """A new factory's ``allocate`` and first eager ``update``, timed."""
        fns = neighbor_list(displacement, side, 1.5, 0.5, format=layout)
        nbrs = fns.allocate(position)
        nbrs.idx.block_until_ready()
        lap(prefix + "allocate")
        nbrs.update(moved[0]).idx.block_until_ready()
        lap(prefix + "first_update")
        return nbrs

    nbrs = allocate_and_update("")
    def median_lap(name, call):
        """The median (CPU, wall) seconds of ``call`` over the later moves."""
        laps = []
        for r in moved[1:]:
            call(r).idx.block_until_ready()
            lap("_")
            laps.append(out.pop("_"))
        out[name] = [statistics.median(c) for c in zip(*laps)]

    median_lap("eager_update", nbrs.update)
    update = jax.jit(lambda r, nb: nb.update(r))
    update(moved[0], nbrs).idx.block_until_ready()
    lap("jit_first")
    median_lap("jit_update", lambda r: update(r, nbrs))
    nbrs = allocate_and_update("warm_")
    out["capacity"] = [int(nbrs.idx.shape[-1]), 0]
    print("RESULT " + json.dumps(out), flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, nargs="+", default=[100, 1000, 10000])
    parser.add_argument("--format", default="Dense",
                        choices=("Dense", "Sparse", "OrderedSparse"))
    parser.add_argument("--libraries", nargs="+", default=["jaxrt", "jax-md"])
    parser.add_argument("--out", type=Path, default=Path(
        "benchmarks/results/cpu-2core/cold_start.csv"))
    parser.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        _child(args.child[0], int(args.child[1]), args.child[2])
        return
    from benchmarks._harness import git_sha, host_provenance, write_csv
    host = host_provenance()
    rows = []
    for n in args.n:
        for library in args.libraries:
            env = dict(os.environ)
            env.setdefault("JAX_PLATFORMS", "cpu")
            proc = subprocess.run(
                [sys.executable, __file__, "--child", library, str(n),
                 args.format], capture_output=True, text=True, env=env)
            line = [s for s in proc.stdout.splitlines()
                    if s.startswith("RESULT ")]
            if proc.returncode or not line:
                print(proc.stderr[-3000:], file=sys.stderr)
                raise SystemExit(f"{library} N={n} failed")
            result = json.loads(line[0][len("RESULT "):])
            for phase in PHASES:
                cpu, wall = result[phase]
                rows.append({**host, "device": "cpu", "device_slug": "cpu-2core",
                             "git_sha": git_sha(),
                             "library": library, "n": n,
                             "format": args.format, "phase": phase,
                             "cpu_s": round(cpu, 4), "wall_s": round(wall, 4),
                             "capacity": result["capacity"][0]})
            print(library, n, {p: round(result[p][0], 2) for p in PHASES},
                  flush=True)
    write_csv(rows, args.out)
    print("wrote", args.out)


if __name__ == "__main__":
    main()
