"""Time one SPH step with and without a neighbour list, side by side (#18).

The system: a periodic box of water (2D by default, ``--dim 3``), a
jittered lattice at spacing dx = 0.01 with random velocities (0.1), cubic
spline h = 1.3 dx, Tait (rho0 = 1000, c0 = 10, gamma = 7), Monaghan
viscosity alpha = 0.05, symplectic Euler with dt = 0.2 h / c0. One step is
summation density, pressure and viscosity forces and the integrator, inside
one jitted ``lax.scan`` of ``--steps`` steps; ``--warmup`` untimed calls
(compilation), then ``--repeats`` timed calls, ms per step (median, min,
max). Every row runs in its own worker (`_harness`).

Setup labels (``--list`` prints the defaults):
  list:<backend>/<format>  jaxrt.neighbor_list (skin 0.3 dx, rebuilt when a
                           particle moved half of it; <backend> a label of
                           `_harness.parse_backend`: cell, cell[xla], bvh...)
                           + sph.density + sph.acceleration
  fused:<backend>          no list: energy.acceleration_fused, which sorts
                           once and walks the cell runs twice (densities,
                           then forces); <backend> cell (the Pallas kernel
                           on CUDA, array programs elsewhere), cell[xla]
                           (the arrays), cell[pallas] (the kernel; CUDA
                           only), cell[auto] (= cell), cell[warp] (the
                           Warp engine: one sort, a walk per pass; CPU or
                           CUDA), cell[warp-rXY-G] (its stencil's reach X
                           cells along x, Y across, default 42; G the
                           CUDA graph capture: none, jax or warp) or brute

``walk``: the program a fused row's cell walk ran (``pallas``, ``xla``
or ``warp``; ``brute``). The default rows compare, in one run, the list step
with the list-free step as the kernel and as array programs (on a CPU
``fused:cell`` is the arrays too).
``k``: mean list neighbours (support + skin), of the list after the
timing (list rows) or at the start (fused rows). A list that overflowed
during the timing is allocated again with a larger capacity multiplier,
from the start (``capacity_multiplier``: the one that held).
``speedup``: the fastest list row's median over the row's. A fused row
also checks itself against the list path at the first configuration
(``max_rel_diff``: largest acceleration difference over the largest
acceleration; ~1e-6 in float32).

    python benchmarks/sph_step.py                       # CPU, N = 10^4, 2D
    python benchmarks/sph_step.py --n 1000000           # a GPU
    python benchmarks/sph_step.py --n 100000 --dim 3 --only list:cell/Dense fused:cell
    python benchmarks/sph_step.py --n 1000000 --only list:cell/OrderedSparse \\
        fused:cell[xla] fused:cell[pallas]                  # a GPU, side by side
    python benchmarks/sph_step.py --quick               # CPU smoke
    python benchmarks/sph_step.py --n 1000000 --dim 3 --only \
        list:cell/Dense list:cell/OrderedSparse fused:cell fused:cell[warp]
"""
from __future__ import annotations

import os
import re
import sys
import warnings

if __package__:  # run as -m, or imported: the package's modules
    from benchmarks import _harness
else:  # run as a file: its folder is sys.path[0]
    import _harness

FORMATS = ("Dense", "OrderedSparse")
LIST_BACKENDS = ("cell",)
# fused:cell is Cell(kernel="auto"): the Pallas kernel on CUDA.
FUSED_BACKENDS = ("cell", "cell[xla]", "cell[pallas]", "cell[auto]",
                  "cell[warp]", "brute")
# fused:cell[warp-rXY-G]: the Warp engine with its stencil's reach X cells
# along x and Y across (cells support / reach wide) and G the CUDA graph's
# capture (none, jax, warp; ffi.cell_sph_step): CellSums(kernel="warp",
# reach=(X, Y), graph=G); cell[warp] takes the defaults.
_WARP = re.compile(r"cell\[warp(?:-r(\d)(\d))?(?:-(none|jax|warp))?\]")
DEFAULT = [f"list:{b}/{f}" for b in LIST_BACKENDS for f in FORMATS] + [
    "fused:cell", "fused:cell[xla]"]

DX = 0.01


def parse_label(label: str) -> tuple[str, str, str | None]:
    """``"list:cell/Dense"`` -> (``"list"``, ``"cell"``, ``"Dense"``);
    ``"fused:cell"`` -> (``"fused"``, ``"cell"``, None)."""
    kind, sep, rest = label.partition(":")
    if kind == "fused" and sep:
        if rest not in FUSED_BACKENDS and not _WARP.fullmatch(rest):
            raise ValueError(f"setup {label!r}: fused:<backend> takes "
                             f"{FUSED_BACKENDS}")
        return "fused", rest, None
    if kind == "list" and sep:
        backend, sep, fmt = rest.rpartition("/")
        if not sep or fmt not in FORMATS:
            raise ValueError(f"setup {label!r}: end it with /Dense or "
                             "/OrderedSparse")
        _harness.parse_backend(backend)
        return "list", backend, fmt
    raise ValueError(f"setup {label!r}: list:<backend>/<format> or "
                     "fused:<backend>")


def walk_of(backend: str) -> str:
    """The program a fused row's walk runs here: ``pallas``, ``xla``,
    ``interpret`` or ``brute``."""
    import jax
    if _WARP.fullmatch(backend):
        return "warp"
    name, opts = _harness.parse_backend(backend)
    if name == "brute":
        return "brute"
    kernel = opts.get("kernel", "auto")
    if kernel == "auto":
        return "pallas" if jax.default_backend() in ("gpu", "cuda") else "xla"
    return kernel


def fused_backend(backend: str):
    """``backend=`` of a fused row's label (``cell[warp-rXY]``: the Warp
    engine with that reach)."""
    m = _WARP.fullmatch(backend)
    if m:
        import jaxrt
        from jaxrt.energy.listfree.lj import CellSums
        if not m[1] and not m[3]:
            return jaxrt.backends.Cell(kernel="warp")
        reach = (int(m[1]), int(m[2])) if m[1] else CellSums.reach
        return CellSums(kernel="warp", reach=reach, graph=m[3] or "none")
    return _harness.backend(backend)


def fluid(n: int, dim: int, seed: int = 0):
    """(R, V float32 (N, dim), side, N): a jittered lattice of N rounded to
    a square / cube, random velocities."""
    import jax.numpy as jnp
    import numpy as np
    n_side = round(n ** (1 / dim))
    n = n_side ** dim
    side = n_side * DX
    rng = np.random.default_rng(seed)
    g = np.stack(np.meshgrid(*[np.arange(n_side)] * dim, indexing="ij"), -1)
    R = (g.reshape(-1, dim) * DX + rng.uniform(-0.05, 0.05, (n, dim)) * DX)
    R = jnp.asarray(R % side, jnp.float32)
    V = jnp.asarray(rng.normal(0, 0.1, (n, dim)), jnp.float32)
    return R, V, side, n


def model(dim: int):
    """(kernel, eos, mass, alpha, dt) of the water box."""
    from jaxrt.energy import sph
    kernel = sph.CubicSpline(1.3 * DX, dim=dim)
    eos = sph.Tait(rho0=1000.0, c0=10.0, gamma=7.0)
    return kernel, eos, 1000.0 * DX ** dim, 0.05, 0.2 * 1.3 * DX / 10.0


def list_fn(backend: str, fmt: str, disp, side, cutoff,
            capacity_multiplier: float = 1.25):
    import jaxrt
    from jax_md import partition
    return jaxrt.neighbor_list(disp, side, cutoff, dr_threshold=0.3 * DX,
                               format=getattr(partition, fmt),
                               backend=_harness.backend(backend),
                               capacity_multiplier=capacity_multiplier)


def mean_neighbours(nbrs, n: int) -> float:
    import numpy as np
    from jax_md import partition
    idx = np.asarray(nbrs.idx)
    valid = np.sum(idx[0] < n) if nbrs.format is not partition.Dense \
        else np.sum(idx < n)
    return float(valid / n * (2 if nbrs.format is partition.OrderedSparse
                              else 1))


def run_row(job: dict) -> dict:
    """One setup, in a worker."""
    warnings.filterwarnings("ignore", message="Explicitly requested dtype")
    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax import lax
    from jax_md import space
    from jaxrt.energy import acceleration_fused, sph
    kind, backend, fmt = parse_label(job["list"])
    dim = job["dim"]
    R, V, side, n = fluid(job["N"], dim)
    disp, shift = space.periodic(side)
    kernel, eos, mass, alpha, dt = model(dim)
    steps = job["steps"]
    row = {"N": n, "dim": dim}

    if kind == "list":
        density = sph.density(disp, kernel, mass=mass)
        accel = sph.acceleration(disp, kernel, eos, mass=mass, alpha=alpha)

        @jax.jit
        def run(carry):
            def step(carry, _):
                R, V, nbrs = carry
                rho = density(R, nbrs)
                V = V + dt * accel(R, V, nbrs, rho=rho).total
                R = shift(R, dt * V)
                return (R, V, nbrs.update(R)), None
            return lax.scan(step, carry, None, length=steps)[0]

        # The fluid's density fluctuations grow the rows: a list that
        # overflows is allocated again with more room, from the start
        # (a simulation would reallocate too), and the row says how much.
        for multiplier in (1.25, 1.5, 2.0, 3.0):
            nbrs = list_fn(backend, fmt, disp, side, float(kernel.cutoff),
                           multiplier).allocate(R)
            timing, (_, _, nbrs) = _harness.time_carry(
                run, (R, V, nbrs), repeats=job["repeats"],
                warmup=job["warmup"], per_call=steps)
            if not nbrs.did_buffer_overflow:
                break
        else:
            raise RuntimeError("SPH list overflowed during timing")
        row["k"] = round(mean_neighbours(nbrs, n), 2)
        row["capacity_multiplier"] = multiplier
        return {**row, **timing.columns()}

    fused = acceleration_fused(disp, side, kernel, eos, mass=mass,
                               alpha=alpha, backend=fused_backend(backend))
    row["walk"] = walk_of(backend)

    @jax.jit
    def run(carry):
        def step(carry, _):
            R, V = carry
            V = V + dt * fused(R, V).total
            return (shift(R, dt * V), V), None
        return lax.scan(step, carry, None, length=steps)[0]

    timing, _ = _harness.time_carry(run, (R, V), repeats=job["repeats"],
                                    warmup=job["warmup"], per_call=steps)
    row.update(timing.columns())
    if job.get("check", True):
        # The list path at the first configuration, after the timing (its
        # memory is not the fused step's).
        nbrs = list_fn("cell", "Dense", disp, side,
                       float(kernel.cutoff)).allocate(R)
        ref = jax.jit(sph.acceleration(disp, kernel, eos, mass=mass,
                                       alpha=alpha))(R, V, nbrs).total
        got = jax.jit(fused)(R, V).total
        scale = float(jnp.max(jnp.abs(ref)))
        row["max_rel_diff"] = float(jnp.max(jnp.abs(got - ref))) / scale
        row["k"] = round(mean_neighbours(nbrs, n), 2)
        if not np.isfinite(row["max_rel_diff"]):
            raise RuntimeError("fused accelerations are not finite")
    return row


COLUMNS = ["dim", "list", "walk", "N", "k", "median_ms", "min_ms", "max_ms",
           "repeats", "speedup", "capacity_multiplier", "max_rel_diff"]


def add_speedup(rows: list[dict]) -> None:
    """``speedup`` of every ok row: the fastest list row's median over its
    own (per dim and N)."""
    for row in rows:
        peers = [r["median_ms"] for r in rows
                 if r.get("status") == "ok" and r["list"].startswith("list:")
                 and r.get("dim") == row.get("dim") and r.get("N") == row.get("N")]
        if row.get("status") == "ok" and peers:
            row["speedup"] = round(min(peers) / row["median_ms"], 3)


def plan(args) -> list[dict]:
    labels = args.only or DEFAULT
    for label in labels:
        parse_label(label)  # a typo fails here, not in a worker
    return [{"list": label, "N": args.n, "dim": args.dim,
             "steps": args.steps, "repeats": args.repeats,
             "warmup": args.warmup, "check": not args.no_check}
            for label in labels]


def main(argv=None) -> None:
    parser = _harness.make_parser(__doc__)
    parser.add_argument("--n", type=int, default=10000,
                        help="particles (rounded to a square / cube)")
    parser.add_argument("--dim", type=int, default=2, choices=(2, 3))
    parser.add_argument("--steps", type=int, default=20,
                        help="steps per timed call (one lax.scan)")
    parser.add_argument("--only", nargs="*", default=None,
                        help="setup labels (default: "
                        + " ".join(DEFAULT) + ")")
    parser.add_argument("--no-check", action="store_true",
                        help="skip the fused rows' comparison with the list "
                        "path")
    parser.add_argument("--list", action="store_true",
                        help="print the default labels and exit")
    parser.add_argument("--quick", action="store_true",
                        help="CPU smoke: N = 1024, 2 repeats of 5 steps")
    _harness.add_common_args(parser, name="sph_step.csv", repeats=5,
                             warmup=2, timeout=600)
    args = parser.parse_args(argv)
    if args.list:
        print("\n".join(DEFAULT))
        return
    if args.quick:
        args.n, args.steps, args.repeats = 1024, 5, 2
    _harness.run_jobs("sph_step:run_row", plan(args), columns=COLUMNS,
                      finish=add_speedup, **_harness.run_options(args))


if __name__ == "__main__":
    main()
