"""Scaling of the domain-decomposed LJ step (`jaxrt.sim.domains`) over devices.

The LJ system of ``md_step.py``: a simple-cubic lattice at density 0.8
(melting), smooth cutoff 2.0-2.5, skin 0.3, dt 0.005, Maxwell-Boltzmann
velocities at kT = 1. The box is cut into ``D`` slabs along x, one per
device (`jax.shard_map` over a 1-D mesh, halos by `jax.lax.ppermute`,
NCCL underneath on GPUs); each device builds its own Dense list with the
``--backend`` (default ``cell``) on owned + halo particles, the forces
come from the owned particles' rows (``--forces rows``, default) or from
``-jax.grad`` of the decomposed energy (``--forces grad``), and a step is `jaxrt.sim.domains`'s
velocity Verlet step (halo refresh every step; migration, halos and lists
again when a particle moved more than skin / 2, decided over all devices).
``--steps`` steps run in one jitted ``lax.scan``; ms per step, median of
``--repeats`` calls after ``--warmup`` (compilation excluded). Every row
runs in its own worker process (`_harness`), on the first ``D`` devices.

* strong scaling: N fixed (``--strong``, default 1e6 and 1e7) on
  ``--devices`` (default 1 2 4 8); efficiency = T(1) / (D T(D)), T(1) the
  same code on one device;
* weak scaling: ``--weak`` particles per device (default 1e6) on D
  devices; efficiency = T(1) / T(D);
* plain: ``md_step.py``'s own LJ step (jax-md's ``simulate.nve``, the
  jaxrt list of ``--backend`` on Dense, the "rows" forces) on one device
  at each strong N, no decomposition: ``vs_plain`` = T_plain / (D T(D))
  is what the decomposition gains over the best single-device step.

Rows whose D exceeds the devices present are written as skipped; a row
whose halo is wider than its slab is written as an error (the refusal).
The NCCL variables are left as the machine sets them.

    python benchmarks/domains.py --quick         # CPU: 4 fake devices,
                                                 # N = 4096, 2 repeats
    # 8 GPUs, under 10 minutes (no row starts after 500 s, the running
    # one is killed at 570 s; rows not reached are written as skipped):
    XLA_PYTHON_CLIENT_PREALLOCATE=false python benchmarks/domains.py \
        --strong 1e6 1e7 --weak 1e6 --devices 1 2 4 8 --steps 20 \
        --repeats 3 --warmup 1 --timeout 240 --budget 500 --hard-stop 570
    # the 1e7 rows it skipped, in a second run of the same length: the
    # same with --strong 1e7 --weak 0
    # if the Pallas cell kernel fails inside shard_map there: add
    #   --backend "cell[xla]"
"""
from __future__ import annotations

import math
import os
import sys
import warnings

if __package__:  # run as -m, or imported: the package's modules
    from benchmarks import _harness
else:  # run as a file: its folder is sys.path[0]
    import _harness

COLUMNS = ["scaling", "N", "devices", "N_per_device", "k", "median_ms",
           "min_ms", "max_ms", "efficiency", "vs_plain", "rebuilds",
           "capacity", "halo_capacity"]


def lj_row(job: dict) -> dict:
    warnings.filterwarnings("ignore", message="Explicitly requested dtype")
    if job["scaling"] == "plain":  # md_step.py's own row, no domains
        import md_step
        return md_step.lj_step(f"jaxrt:{job['backend']}/Dense", job["N"],
                               job)
    import jax
    import numpy as np
    from jax import lax
    from jaxrt.sim import domains
    from jaxrt.energy import lennard_jones_pair_neighbor_list
    d = job["devices"]
    if len(jax.devices()) < d:
        raise RuntimeError(f"needs {d} devices, found {len(jax.devices())}")
    n_side = round(job["N"] ** (1 / 3))
    n = n_side ** 3
    box = (n / 0.8) ** (1 / 3)
    g = np.stack(np.meshgrid(*[np.arange(n_side)] * 3, indexing="ij"), -1)
    R = g.reshape(-1, 3) * box / n_side
    V = np.random.default_rng(0).standard_normal((n, 3))
    V -= V.mean(0)
    dom = domains.decompose(
        box_size=(box,) * 3, periodic=True, cutoff=2.5, skin=0.3,
        energy=lambda disp: lennard_jones_pair_neighbor_list(
            disp, r_onset=2.0, r_cutoff=2.5, per_particle=True),
        decomposition=domains.Decomposition(devices=d, slack=1.2),
        backend=_harness.backend(job["backend"]),
        row_energy=(None if job["forces"] == "grad" else
                    lambda disp: lennard_jones_pair_neighbor_list(
                        disp, r_onset=2.0, r_cutoff=2.5)))
    state = dom.distribute(R, V, dtype=np.float32)
    state = jax.jit(dom.forces_into)(state)
    steps = job["steps"]

    @jax.jit
    def run(s):
        # No energy pass: md_step.py's steps compute forces only.
        return lax.scan(lambda s, _: dom.verlet_step(s, 0.005, energy=False),
                        s, None, length=steps)[0]

    timing, state = _harness.time_carry(
        run, state, repeats=job["repeats"], warmup=job["warmup"],
        per_call=steps)
    dom.check(state)  # raises on any overflow: such a row is an error
    idx = np.asarray(state.nbrs.idx[0][:state.capacity])
    owned = np.asarray(state.gid[0]) >= 0
    k = float(np.sum(idx[owned] < idx.shape[0]) / max(owned.sum(), 1))
    return {"N": n, "N_per_device": n // d, "k": round(k, 2),
            "rebuilds": int(np.asarray(state.rebuilds)[0]),
            "capacity": state.capacity, "halo_capacity": state.halo_capacity,
            **timing.columns()}


def efficiency(rows: list[dict]) -> None:
    """Fill ``efficiency``: strong T1 / (D TD) at equal N, weak T1 / TD
    (T1: the one-device row of ``base_N``, the per-device size rounded
    to a cube)."""
    ok = [r for r in rows if r.get("status") == "ok"]
    one = {(r["N"]): r["median_ms"] for r in ok if r["devices"] == 1
           and r["scaling"] != "plain"}
    plain = {r["N"]: r["median_ms"] for r in ok if r["scaling"] == "plain"}
    for r in ok:
        if r["N"] in plain and r["scaling"] != "plain":
            r["vs_plain"] = round(plain[r["N"]] / (r["devices"]
                                                   * r["median_ms"]), 3)
        d = r["devices"]
        if r["scaling"] == "strong" and r["N"] in one:
            r["efficiency"] = round(one[r["N"]] / (d * r["median_ms"]), 3)
        if r["scaling"] == "weak":
            base = one.get(r["base_N"])
            if base is not None:
                r["efficiency"] = round(base / r["median_ms"], 3)


def plan(args) -> list[dict]:
    common = {"steps": args.steps, "repeats": args.repeats,
              "warmup": args.warmup, "backend": args.backend,
              "forces": args.forces}
    def strong(n):
        side = round(n ** (1 / 3))
        rows = [{"scaling": "strong", "N": side ** 3, "devices": d,
                 "N_per_device": side ** 3 // d, **common}
                for d in args.devices]
        if args.plain:
            rows.append({"scaling": "plain", "N": side ** 3, "devices": 1,
                         "N_per_device": side ** 3, **common})
        return rows
    weak = []
    if args.weak:
        base = round(args.weak ** (1 / 3)) ** 3
        for d in args.devices:
            side = round((args.weak * d) ** (1 / 3))
            if d == 1 and any(round(s ** (1 / 3)) == side
                              for s in args.strong):
                continue  # the strong row on one device is the same run
            weak.append({"scaling": "weak", "N": side ** 3, "devices": d,
                         "N_per_device": side ** 3 // d, "base_N": base,
                         **common})
    # The first strong N, then the weak rows, then the larger N (the
    # slowest rows last: a --budget cuts them first).
    first, rest = args.strong[:1], args.strong[1:]
    return ([j for n in first for j in strong(n)] + weak
            + [j for n in rest for j in strong(n)])


def main(argv=None) -> None:
    parser = _harness.make_parser(__doc__)
    parser.add_argument("--strong", type=float, nargs="*",
                        default=[1e6, 1e7], help="N of the strong scaling")
    parser.add_argument("--weak", type=float, default=1e6,
                        help="N per device of the weak scaling (0: none)")
    parser.add_argument("--devices", type=int, nargs="*",
                        default=[1, 2, 4, 8])
    parser.add_argument("--steps", type=int, default=20,
                        help="steps per timed call (one lax.scan)")
    parser.add_argument("--backend", default="cell",
                        help="list backend label (`_harness.parse_backend`)")
    parser.add_argument("--forces", choices=("rows", "grad"),
                        default="rows", help="rows: each owned particle's "
                        "force from its own row (no reverse halo exchange, "
                        "no scatter); grad: jax.grad of the decomposed "
                        "energy through shard_map and the halo")
    parser.add_argument("--no-plain", dest="plain", action="store_false",
                        help="leave out the plain single-device rows "
                        "(md_step.py's LJ step on a jaxrt Dense list, no "
                        "decomposition: vs_plain = T_plain / (D T_D))")
    parser.add_argument("--quick", action="store_true",
                        help="CPU smoke: 4 fake CPU devices, strong N = "
                        "4000 on 1 2 4, weak 2000 per device, 5 steps, "
                        "2 repeats")
    _harness.add_common_args(parser, name="domains.csv", repeats=5,
                             warmup=2, timeout=300)
    args = parser.parse_args(argv)
    if args.quick:
        args.strong, args.weak, args.devices = [4000], 2000, [1, 2, 4]
        args.steps, args.repeats, args.warmup = 5, 2, 1
        # The workers read it before JAX starts (the driver never starts
        # JAX's backends).
        flags = os.environ.get("XLA_FLAGS", "")
        if "xla_force_host_platform_device_count" not in flags:
            os.environ["XLA_FLAGS"] = (
                flags + " --xla_force_host_platform_device_count=4").strip()
    args.strong = [int(n) for n in args.strong]
    args.weak = int(args.weak)
    jobs = plan(args)
    _harness.run_jobs("domains:lj_row", jobs, columns=COLUMNS,
                      finish=efficiency, **_harness.run_options(args))


if __name__ == "__main__":
    main()
