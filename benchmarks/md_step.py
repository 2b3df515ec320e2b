"""Time one whole MD step: a Lennard-Jones NVE step and an SPH step.

Each step is what a simulation pays per step: the neighbour-list update
with its skin (rebuilt only when a particle moved more than half the skin)
plus the forces and the integrator, inside one jitted ``lax.scan`` of
``--steps`` steps. Every row (system, list setup) runs in its own worker
process (`_harness`): its own memory, and a setup that fails, runs out of
memory or time is written as such. Timings: ``--warmup`` untimed calls
(compilation), then ``--repeats`` timed calls; ms per step, median / min /
max.

* LJ: 3D fluid at density 0.8 (a simple-cubic lattice that melts), smooth
  cutoff 2.0-2.5, skin 0.3, `jax_md.simulate.nve`. The baseline is
  jax-md's own energy and list in its default layout (OrderedSparse);
  jaxrt's energy on Dense lists sums forces row by row (no scatter).
* SPH: 2D periodic box of water at spacing dx, cubic spline h = 1.3 dx,
  summation density + Tait + pressure + viscosity, symplectic Euler.

Setup labels (``--list`` prints them; <format> is Dense or OrderedSparse by
default, and ``--only`` takes Sparse as well):
  jax-md/<format>                   jax-md's list and jax-md's energy
  jax-md list + jaxrt energy/Dense  (LJ) the energy's share, separated
  jaxrt:<backend>/<format>          jaxrt's list and energy; <backend> is a
                                    label of `_harness.parse_backend`:
                                    cell, cell[xla], bvh, bvh[unsorted], ...
  fused:<backend>                   (LJ) no list: `energy.lennard_jones_fused`
                                    (backend cell, cell[xla], cell[pallas],
                                    bvh or brute; cell is the Pallas kernel
                                    on CUDA; cell[warp] or cell[kernel=warp]
                                    the Warp engine, cell[warp-rXY-cK-G]
                                    with its reach, cluster walk (nK: the
                                    warp-cooperative one) and graph
                                    capture), forces
                                    from its custom_vjp, the same NVE step
A label in ``--only`` without ``/`` selects both formats.

    python benchmarks/md_step.py                         # CPU sizes, all
    python benchmarks/md_step.py --n 1000000 --systems lj \\
        --only jax-md/OrderedSparse jax-md/Dense jaxrt:cell/Dense jaxrt:bvh/Dense
    python benchmarks/md_step.py --quick                 # CPU smoke
"""
from __future__ import annotations

import math
import os
import re
import sys
import warnings

if __package__:  # run as -m, or imported: the package's modules
    from benchmarks import _harness
else:  # run as a file: its folder is sys.path[0]
    import _harness

FORMATS = ("Dense", "OrderedSparse")
# Accepted in --only (jax-md's three layouts); the defaults are FORMATS.
ALL_FORMATS = ("Dense", "Sparse", "OrderedSparse")
DEFAULT_BACKENDS = ("cell", "bvh", "bvh-unsorted", "squares", "spheres",
                    "brute")
JAXMD_LIST_JAXRT_ENERGY = "jax-md list + jaxrt energy"
FUSED_BACKENDS = ("cell", "cell[xla]", "bvh")
# fused:cell is Cell(kernel="auto"): the Pallas kernel on CUDA.
FUSED_OPTIONS = {"cell[xla]": ("cell", "xla"), "cell[pallas]": ("cell", "pallas"),
                 "cell[auto]": ("cell", "auto"), "cell[warp]": ("cell", "warp"),
                 "cell[kernel=warp]": ("cell", "warp")}
# fused:cell[warp-rXY-cK-G]: the Warp engine (CellSums(kernel="warp")) with
# its stencil's reach X along x and Y across (cells bound / reach wide),
# cK its cluster walk with K particles per cluster (CellSums(walk=
# "cluster", cluster_size=K); nK the warp-cooperative one, walk="native";
# without either the thread walk) and G the CUDA graph's capture (none,
# jax, warp; ffi.cell_lj_sums).
_WARP = re.compile(r"cell\[warp(?:-r(\d)(\d))?(?:-([cn])(\d+))?"
                   r"(?:-(none|jax|warp))?\]")


# fused:cell[32x4x32]: the kernel with that launch: particles and warps per
# program, then optionally the cluster layout's tile (no tile: a thread per
# particle), uN the thread walk's unroll, aN cells per cutoff across x, s
# for runs stored beforehand (Cell(runs="stored")) instead of found by the
# kernel in the cell-start table, and n for each pair met once, the
# partner's force added by an atomic (Cell(newton=True)).
LAUNCH = r"(\d+)x(\d+)(?:x(\d+))?(?:u(\d+))?(?:a(\d+))?(s)?(n)?"
_LAUNCH = re.compile(r"cell\[" + LAUNCH + r"\]")


def launched(label: str):
    """The fused cell backend of
    ``cell[BLOCKxWARPS[xTILE][uUNROLL][aACROSS][s][n]]`` or of the bare launch
    (the kernel, compiled: CUDA only)."""
    from jaxrt.energy.listfree.lj import CellSums
    match = _LAUNCH.fullmatch(label) or re.fullmatch(LAUNCH, label)
    if match is None:
        raise ValueError(f"launch {label!r}: write BLOCKxWARPS[xTILE]"
                         "[uUNROLL][aACROSS][s][n], e.g. 32x1u2a2, 16x1x16, "
                         "32x1s or 32x1n")
    *numbers, stored, newton = match.groups()
    block, warps, tile, unroll, across = (int(v) if v else 0 for v in numbers)
    return CellSums(kernel="pallas", block=block, warps=warps, tile=tile,
                 unroll=unroll or 1, across=across or 1,
                 runs="stored" if stored else "kernel", newton=bool(newton))


def labels(system: str, backends=DEFAULT_BACKENDS) -> list[str]:
    lists = ["jax-md"] + [f"jaxrt:{b}" for b in backends]
    out = [f"{name}/{fmt}" for name in lists for fmt in FORMATS]
    if system == "lj":
        out.insert(2, f"{JAXMD_LIST_JAXRT_ENERGY}/Dense")
        out += [f"fused:{b}" for b in FUSED_BACKENDS]
    return out


def parse_label(label: str) -> tuple[str, str | None, str]:
    """``"jaxrt:cell[xla]/Dense"`` -> (``"jaxrt"``, ``"cell[xla]"``,
    ``"Dense"``); jax-md's rows have no backend."""
    if label.startswith("fused:"):
        backend = label[len("fused:"):]
        known = FUSED_BACKENDS + tuple(FUSED_OPTIONS) + ("brute",)
        if (backend not in known and not _LAUNCH.fullmatch(backend)
                and not _WARP.fullmatch(backend)):
            raise ValueError(f"setup {label!r}: fused:<backend> takes "
                             f"{known} or cell[BLOCKxWARPS[xTILE]] (the "
                             "kernel's launch)")
        return "fused", backend, None
    lists, sep, fmt = label.rpartition("/")
    if not sep or fmt not in ALL_FORMATS:
        raise ValueError(f"setup {label!r}: end it with /Dense, /Sparse or "
                         "/OrderedSparse")
    if lists.startswith("jaxrt:"):
        backend = lists[len("jaxrt:"):]
        _harness.parse_backend(backend)
        return "jaxrt", backend, fmt
    if lists in ("jax-md", JAXMD_LIST_JAXRT_ENERGY):
        return lists, None, fmt
    raise ValueError(f"setup {label!r}: the list is jax-md, "
                     f"'{JAXMD_LIST_JAXRT_ENERGY}' or jaxrt:<backend>")


def _list_and_energy(label: str):
    """(list factory, LJ energy factory, jax-md format) of a setup."""
    import functools
    from jax_md import energy as jmd_energy
    from jax_md import partition
    import jaxrt
    from jaxrt.energy import lennard_jones_neighbor_list
    kind, backend, fmt = parse_label(label)
    fmt = getattr(partition, fmt)
    if kind == "jax-md":
        return partition.neighbor_list, jmd_energy.lennard_jones_neighbor_list, fmt
    if kind == JAXMD_LIST_JAXRT_ENERGY:
        return partition.neighbor_list, lennard_jones_neighbor_list, fmt
    list_fn = functools.partial(jaxrt.neighbor_list,
                                backend=_harness.backend(backend))
    return list_fn, lennard_jones_neighbor_list, fmt


def mean_neighbours(nbrs, n):
    import numpy as np
    from jax_md import partition
    idx = np.asarray(nbrs.idx)
    valid = np.sum(idx[0] < n) if nbrs.format is not partition.Dense else \
        np.sum(idx < n)
    return valid / n * (2 if nbrs.format is partition.OrderedSparse else 1)


ORDERS = ("lattice", "random", "hilbert", "morton")
"""How the LJ system's particles are numbered: ``lattice`` x-major over
the simple-cubic lattice (its rows' gathers stay within a few lattice
planes), ``random`` a seeded shuffle, ``hilbert`` / ``morton`` the shuffle
put in that curve's order by `jaxrt.lists.order.spatial_order`."""


def lj_system(n: int, order: str = "lattice"):
    """(N, box, float32 ``(N, 3)`` positions) of the LJ fluid's start: a
    simple-cubic lattice at density 0.8 of ``round(n ** (1/3)) ** 3``
    particles, numbered by ``order`` (`ORDERS`)."""
    import jax.numpy as jnp
    import numpy as np
    if order not in ORDERS:
        raise ValueError(f"order={order!r}: pass one of {ORDERS}")
    n_side = round(n ** (1 / 3))
    n = n_side ** 3
    box = (n / 0.8) ** (1 / 3)
    g = np.stack(np.meshgrid(*[np.arange(n_side)] * 3, indexing="ij"), -1)
    R = g.reshape(-1, 3) * box / n_side
    if order != "lattice":
        R = R[np.random.default_rng(0).permutation(n)]
    R = jnp.asarray(R, jnp.float32)
    if order in ("hilbert", "morton"):
        from jaxrt.lists.order import spatial_order
        R = R[spatial_order(R, box, curve=order)]
    return n, box, R


def lj_step(label: str, n: int, job: dict) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax import lax
    from jax_md import energy as jmd_energy
    from jax_md import simulate, space
    n, box, R = lj_system(n, job.get("order", "lattice"))
    disp, shift = space.periodic(box)
    if label.startswith("fused:"):
        return _fused_lj_step(label, n, box, R, disp, shift, job)
    list_fn, energy_factory, fmt = _list_and_energy(label)
    # r_onset / r_cutoff in units of sigma = 1, as jax-md's factory takes
    # them. jax-md's factory builds its own list (and would silently
    # swallow a neighbor_list_fn keyword).
    extra = {} if energy_factory is jmd_energy.lennard_jones_neighbor_list \
        else dict(neighbor_list_fn=list_fn)
    neighbor_fn, energy_fn = energy_factory(
        disp, box, r_onset=2.0, r_cutoff=2.5, dr_threshold=0.3, format=fmt,
        **extra)
    init, apply = simulate.nve(energy_fn, shift, dt=0.005)
    nbrs = neighbor_fn.allocate(R)
    state = init(jax.random.PRNGKey(0), R, 1.0, neighbor=nbrs)
    steps = job["steps"]

    @jax.jit
    def run(carry):
        def step(carry, _):
            state, nbrs = carry
            state = apply(state, neighbor=nbrs)
            return (state, nbrs.update(state.position)), None
        return lax.scan(step, carry, None, length=steps)[0]

    timing, (state_after, nbrs) = _harness.time_carry(
        run, (state, nbrs), repeats=job["repeats"], warmup=job["warmup"],
        per_call=steps)
    if nbrs.did_buffer_overflow:
        raise RuntimeError("LJ list overflowed during timing")
    # How often the skin forced a search, from one more (untimed) call: the
    # largest displacement among more particles crosses half the skin
    # sooner, a cost that grows faster than N.
    @jax.jit
    def count(carry):
        def step(carry, _):
            state, nbrs = carry
            state = apply(state, neighbor=nbrs)
            new = nbrs.update(state.position)
            moved = jnp.any(new.reference_position != nbrs.reference_position)
            return (state, new), moved
        return jnp.sum(lax.scan(step, carry, None, length=steps)[1])

    rebuilds = int(count((state_after, nbrs)))
    return {"N": n, "k": round(float(mean_neighbours(nbrs, n)), 2),
            "rebuilds_per_step": round(rebuilds / steps, 3),
            **timing.columns()}


def _fused_lj_step(label, n, box, R, disp, shift, job) -> dict:
    """The LJ step of `lj_step` with no list: the fused energy's forces."""
    import jax
    from jax import lax
    from jax_md import simulate
    from jaxrt.energy import lennard_jones_fused
    _, backend, _ = parse_label(label)
    if backend in FUSED_OPTIONS:
        from jaxrt.backends import Cell
        backend = Cell(kernel=FUSED_OPTIONS[backend][1])
    elif _WARP.fullmatch(backend):
        from jaxrt.energy.listfree.lj import CellSums
        x, y, kind, size, graph = _WARP.fullmatch(backend).groups()
        reach = (int(x), int(y)) if x else CellSums.reach
        walk = dict(walk="cluster" if kind == "c" else "native",
                    cluster_size=int(size)) if size else {}
        backend = CellSums(kernel="warp", graph=graph or "none", reach=reach,
                           **walk)
    elif _LAUNCH.fullmatch(backend):
        backend = launched(backend)
    energy_fn = lennard_jones_fused(disp, box, r_onset=2.0, r_cutoff=2.5,
                                    backend=backend)
    init, apply = simulate.nve(energy_fn, shift, dt=0.005)
    state = init(jax.random.PRNGKey(0), R, 1.0)
    steps = job["steps"]

    @jax.jit
    def run(state):
        return lax.scan(lambda s, _: (apply(s), None), state, None,
                        length=steps)[0]

    timing, state = _harness.time_carry(run, state, repeats=job["repeats"],
                                        warmup=job["warmup"], per_call=steps)
    pairs = float(energy_fn.sums(state.position).count)
    return {"N": n, "k": round(2 * pairs / n, 2), **timing.columns()}


def sph_step(label: str, n: int, job: dict) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax import lax
    from jax_md import space
    from jaxrt.energy import sph
    n_side = round(math.sqrt(n))
    n = n_side ** 2
    dx = 0.01
    side = n_side * dx
    rng = np.random.default_rng(0)
    g = np.stack(np.meshgrid(*[np.arange(n_side)] * 2, indexing="ij"), -1)
    R = jnp.asarray((g.reshape(-1, 2) * dx
                     + rng.uniform(-0.05, 0.05, (n, 2)) * dx) % side,
                    jnp.float32)
    disp, shift = space.periodic(side)
    kernel = sph.CubicSpline(1.3 * dx, dim=2)
    eos = sph.Tait(rho0=1000.0, c0=10.0)
    mass = 1000.0 * dx * dx
    accel = sph.acceleration(disp, kernel, eos, mass=mass, alpha=0.05)
    list_fn, _, fmt = _list_and_energy(label)
    neighbor_fn = list_fn(disp, side, float(kernel.cutoff),
                          dr_threshold=0.3 * dx, format=fmt)
    nbrs = neighbor_fn.allocate(R)
    V = jnp.asarray(rng.normal(0, 0.1, (n, 2)), jnp.float32)
    dt = 0.2 * kernel.h / 10.0
    steps = job["steps"]

    @jax.jit
    def run(carry):
        def step(carry, _):
            R, V, nbrs = carry
            V = V + dt * accel(R, V, nbrs).total
            R = shift(R, dt * V)
            return (R, V, nbrs.update(R)), None
        return lax.scan(step, carry, None, length=steps)[0]

    timing, (_, _, nbrs) = _harness.time_carry(
        run, (R, V, nbrs), repeats=job["repeats"], warmup=job["warmup"],
        per_call=steps)
    if nbrs.did_buffer_overflow:
        raise RuntimeError("SPH list overflowed during timing")
    return {"N": n, "k": round(float(mean_neighbours(nbrs, n)), 2),
            **timing.columns()}


def run_row(job: dict) -> dict:
    """One (system, setup) row, in a worker."""
    warnings.filterwarnings("ignore", message="Explicitly requested dtype float64")
    fn = lj_step if job["system"] == "lj" else sph_step
    return fn(job["list"], job["N"], job)


COLUMNS = ["system", "list", "order", "N", "k", "median_ms", "min_ms", "max_ms",
           "repeats"]


def plan(args) -> list[dict]:
    jobs = []
    for system in args.systems:
        if args.only:
            chosen = []
            for sel in args.only:
                chosen += ([sel] if "/" in sel or sel.startswith("fused:")
                           else [f"{sel}/{f}" for f in FORMATS])
            chosen = [c for c in chosen if system == "lj" or not
                      c.startswith((JAXMD_LIST_JAXRT_ENERGY, "fused:"))]
        else:
            chosen = labels(system)
        for label in chosen:
            parse_label(label)  # a typo fails here, not in a worker
            for order in args.order:
                if order != "lattice" and system != "lj":
                    raise ValueError(f"--order {order}: the SPH system has "
                                     "one numbering (lattice)")
                jobs.append({"system": system, "list": label, "N": args.n,
                             "order": order, "steps": args.steps,
                             "repeats": args.repeats, "warmup": args.warmup})
    return jobs


def main(argv=None) -> None:
    parser = _harness.make_parser(__doc__)
    parser.add_argument("--n", type=int, default=4096,
                        help="particles (rounded to a cube / square)")
    parser.add_argument("--steps", type=int, default=20,
                        help="steps per timed call (one lax.scan)")
    parser.add_argument("--only", nargs="*", default=None,
                        help="setup labels to run (default all; see --list)")
    parser.add_argument("--systems", nargs="*", default=["lj", "sph"],
                        choices=["lj", "sph"])
    parser.add_argument("--order", nargs="+", default=["lattice"],
                        choices=ORDERS,
                        help="LJ particles' numbering, one row each "
                        "(lattice: x-major, the default; random: shuffled; "
                        "hilbert, morton: the shuffle sorted along that "
                        "curve by jaxrt's spatial_order)")
    parser.add_argument("--list", action="store_true",
                        help="print the default labels and exit")
    parser.add_argument("--quick", action="store_true",
                        help="CPU smoke: N = 1000, LJ, jax-md/Dense and "
                        "jaxrt:cell/Dense, 2 repeats of 5 steps")
    _harness.add_common_args(parser, name="md_step.csv", repeats=5,
                             warmup=2, timeout=600)
    args = parser.parse_args(argv)
    if args.list:
        for system in args.systems:
            print("\n".join(f"{system:4s} {label}" for label in labels(system)))
        return
    if args.quick:
        args.n, args.steps, args.repeats, args.systems = 1000, 5, 2, ["lj"]
        args.only = args.only or ["jax-md/Dense", "jaxrt:cell/Dense"]
    _harness.run_jobs("md_step:run_row", plan(args), columns=COLUMNS,
                      **_harness.run_options(args))


if __name__ == "__main__":
    main()
