"""Pairs with lattice shifts (i, j, S): jaxrt.pairs against ASE, matscipy,
vesin (CPU) and nvalchemiops (GPU), one call each, time per call.

Scene: a diamond silicon supercell (a = 5.43 Å, 8 atoms per cubic cell
repeated r×r×r, rattled by 0.05 Å), periodic, cutoff 5 Å (about 29
neighbours per atom, full lists), N from 10³ to 10⁶ (the nearest 8 r³).
Each row runs in its own worker process (`_harness`); times are the median
of the timed calls, warm-up (compilation) excluded, over three rotating
inputs (the scene and two copies jittered by 10⁻³ Å). ``pairs`` is the
number of pairs the method returned on the first input (every method must
agree with ASE's count where ASE ran: ``same_count``).

Methods:
  jaxrt          jax.jit(jaxrt.pairs) with static sizes from
                 jaxrt.pairs_sizes (what a training loop runs)
  jaxrt[eager]   jaxrt.pairs(..., capacity=None): sizing included
  ase            ase.neighborlist.neighbor_list("ijS", ...)
  matscipy       matscipy.neighbours.neighbour_list("ijS", ...)
  vesin          vesin.NeighborList(cutoff, full_list=True).compute(...)
  nvalchemiops   nvalchemiops' torch neighbor_list on CUDA (COO list with
                 shifts), if installed (nvalchemi-toolkit-ops and torch)
  nvalchemiops[jax]  its JAX binding's neighbor_list (eager dispatcher)

    python benchmarks/pairs.py                    # CPU: 1e3..1e5, all CPU methods
    python benchmarks/pairs.py --sizes 1000000 --methods jaxrt vesin matscipy
    python benchmarks/pairs.py --gpu              # CUDA: jaxrt, nvalchemiops (torch, jax), 1e3..1e6
    python benchmarks/pairs.py --quick            # smoke: N = 1000, 2 repeats
"""
from __future__ import annotations

import os
import sys

if __package__:  # run as -m, or imported: the package's modules
    from benchmarks import _harness
else:  # run as a file: its folder is sys.path[0]
    import _harness

CUTOFF = 5.0
LATTICE = 5.43
CPU_METHODS = ["jaxrt", "jaxrt[eager]", "ase", "matscipy", "vesin"]
GPU_METHODS = ["jaxrt", "jaxrt[eager]", "nvalchemiops", "nvalchemiops[jax]"]


def scene(n: int, seed: int = 0):
    """float64 positions (M, 3), cell (3, 3) (rows), M = 8 r³ nearest n."""
    import numpy as np
    r = max(1, round((n / 8) ** (1 / 3)))
    base = np.array([[0, 0, 0], [0, 2, 2], [2, 0, 2], [2, 2, 0],
                     [1, 1, 1], [1, 3, 3], [3, 1, 3], [3, 3, 1]]) / 4
    grid = np.stack(np.meshgrid(*[np.arange(r)] * 3, indexing="ij"),
                    -1).reshape(-1, 1, 3)
    frac = ((grid + base[None]) / r).reshape(-1, 3)
    cell = np.eye(3) * LATTICE * r
    rng = np.random.default_rng(seed)
    return frac @ cell + rng.normal(0, 0.05, frac.shape), cell


def _inputs(n: int):
    import numpy as np
    pos, cell = scene(n)
    jitter = np.random.default_rng(1)
    return [pos] + [pos + jitter.normal(0, 1e-3, pos.shape)
                    for _ in range(2)], cell


def _jaxrt(eager: bool, inputs, cell, dtype):
    import jax
    import jax.numpy as jnp
    import numpy as np
    import jaxrt
    xs = [jnp.asarray(x, dtype) for x in inputs]
    c = jnp.asarray(cell, dtype)
    if eager:
        def call(x):
            return jaxrt.pairs(x, CUTOFF, cell=c)
    else:
        sizes = jaxrt.pairs_sizes(jnp.stack(xs), CUTOFF, cell=np.asarray(cell))
        jitted = jax.jit(lambda x, c: jaxrt.pairs(x, CUTOFF, cell=c,
                                                  **sizes.kwargs))

        def call(x):
            return jitted(x, c)

    def count(out):
        out.check()
        return int(out.count)
    return call, xs, None, count


def _ase(inputs, cell):
    from ase import Atoms
    from ase.neighborlist import neighbor_list
    atoms = [Atoms(positions=x, cell=cell, pbc=True) for x in inputs]
    return (lambda a: neighbor_list("ijS", a, CUTOFF)), atoms, \
        (lambda out: out), (lambda out: len(out[0]))


def _matscipy(inputs, cell):
    from ase import Atoms
    from matscipy.neighbours import neighbour_list
    atoms = [Atoms(positions=x, cell=cell, pbc=True) for x in inputs]
    return (lambda a: neighbour_list("ijS", a, CUTOFF)), atoms, \
        (lambda out: out), (lambda out: len(out[0]))


def _vesin(inputs, cell):
    from vesin import NeighborList
    nl = NeighborList(cutoff=CUTOFF, full_list=True)
    return (lambda x: nl.compute(points=x, box=cell, periodic=True,
                                 quantities="ijS")), inputs, \
        (lambda out: out), (lambda out: len(out[0]))


def _probe(call, x, cell, pbc):
    """Call nvalchemiops with one cell and pbc ((3, 3), (3,)) or, where that
    release wants them per system, ((1, 3, 3), (1, 3)); returns the pair
    that worked."""
    try:
        call(x, cell, pbc)
        return cell, pbc
    except (TypeError, ValueError, RuntimeError, IndexError):
        cell, pbc = cell.reshape(1, 3, 3), pbc.reshape(1, 3)
        call(x, cell, pbc)
        return cell, pbc


def _count_pairs(out):
    """nvalchemiops' COO list (return_neighbor_list=True): (2, P) first."""
    first = out[0] if isinstance(out, (tuple, list)) else out
    return int(first.shape[-1])


def _nvalchemiops(inputs, cell, dtype):
    import torch
    try:  # the module moved between releases
        from nvalchemiops.torch.neighbors import neighbor_list
    except ImportError:
        from nvalchemiops.neighborlist import neighbor_list
    torch_dtype = getattr(torch, dtype)
    xs = [torch.as_tensor(x, dtype=torch_dtype, device="cuda")
          for x in inputs]

    def nl(x, c, p):
        return neighbor_list(x, CUTOFF, cell=c, pbc=p,
                             return_neighbor_list=True)

    c, p = _probe(nl, xs[0], torch.as_tensor(cell, dtype=torch_dtype,
                                             device="cuda"),
                  torch.ones(3, dtype=torch.bool, device="cuda"))

    def sync(out):
        torch.cuda.synchronize()
        return out
    return (lambda x: nl(x, c, p)), xs, sync, _count_pairs


def _nvalchemiops_jax(inputs, cell, dtype):
    """nvalchemiops' JAX binding (its eager dispatcher: the documented entry
    point; not a jit boundary)."""
    import jax.numpy as jnp
    from nvalchemiops.jax.neighbors import neighbor_list
    xs = [jnp.asarray(x, dtype) for x in inputs]

    def nl(x, c, p):
        return neighbor_list(x, CUTOFF, cell=c, pbc=p,
                             return_neighbor_list=True)

    c, p = _probe(nl, xs[0], jnp.asarray(cell, dtype), jnp.ones(3, bool))
    return (lambda x: nl(x, c, p)), xs, None, _count_pairs


def run_row(job: dict) -> dict:
    """One (method, N) row, in a worker."""
    method, n, dtype = job["method"], job["N"], job["dtype"]
    inputs, cell = _inputs(n)
    if method.startswith("jaxrt"):
        import jax
        if dtype == "float64":
            jax.config.update("jax_enable_x64", True)
        call, xs, sync, count = _jaxrt(method == "jaxrt[eager]", inputs, cell,
                                       dtype)
    elif method == "nvalchemiops":
        call, xs, sync, count = _nvalchemiops(inputs, cell, dtype)
    elif method == "nvalchemiops[jax]":
        import jax
        if dtype == "float64":
            jax.config.update("jax_enable_x64", True)
        call, xs, sync, count = _nvalchemiops_jax(inputs, cell, dtype)
    else:
        call, xs, sync, count = {"ase": _ase, "matscipy": _matscipy,
                                 "vesin": _vesin}[method](inputs, cell)
    timing = _harness.time_calls(call, xs, repeats=job["repeats"],
                                 warmup=job["warmup"], sync=sync,
                                 target_s=job["target_s"],
                                 max_repeats=job["max_repeats"])
    pairs = count(timing.first)
    return {"N": len(inputs[0]), "k": round(pairs / len(inputs[0]), 1),
            "pairs": pairs, "time_ms": timing.median_ms, **timing.columns()}


def add_ratios(rows: list[dict]) -> None:
    """Time relative to the fastest and count agreement with ASE, per N."""
    for r in rows:
        same_n = [x for x in rows if x["N"] == r["N"] and x["status"] == "ok"]
        ase = next((x for x in same_n if x["method"] == "ase"), None)
        if r["status"] != "ok":
            continue
        r["vs_fastest"] = r["time_ms"] / min(x["time_ms"] for x in same_n)
        if ase is not None:
            r["same_count"] = r["pairs"] == ase["pairs"]


COLUMNS = ["method", "N", "k", "pairs", "time_ms", "min_ms", "max_ms",
           "repeats", "vs_fastest", "same_count"]


def main(argv=None) -> None:
    parser = _harness.make_parser(__doc__)
    parser.add_argument("--sizes", type=int, nargs="+",
                        default=[1_000, 10_000, 100_000])
    parser.add_argument("--methods", nargs="+", default=None,
                        choices=CPU_METHODS + GPU_METHODS[2:])
    parser.add_argument("--dtype", default="float64",
                        choices=["float32", "float64"],
                        help="jaxrt's and nvalchemiops' dtype (ASE, matscipy "
                        "and vesin are float64)")
    parser.add_argument("--gpu", action="store_true",
                        help="CUDA rows: jaxrt, jaxrt[eager], nvalchemiops "
                        "at 1e3..1e6, float32")
    parser.add_argument("--ase-max", type=int, default=200_000,
                        help="skip ASE above this N (minutes per call)")
    parser.add_argument("--target-s", type=float, default=3.0,
                        help="timed seconds per row (repeats raised to it)")
    parser.add_argument("--quick", action="store_true")
    _harness.add_common_args(parser, name="pairs.csv", repeats=3, warmup=1,
                             timeout=1200)
    args = parser.parse_args(argv)
    if args.gpu:
        args.methods = args.methods or GPU_METHODS
        if args.sizes == parser.get_default("sizes"):
            args.sizes = [1_000, 10_000, 100_000, 1_000_000]
        if args.dtype == parser.get_default("dtype"):
            args.dtype = "float32"
    methods = args.methods or CPU_METHODS
    if args.quick:
        args.sizes, args.repeats, args.target_s = [1000], 2, 0.2
    jobs = [{"method": m, "N": n, "dtype": args.dtype,
             "repeats": args.repeats, "warmup": args.warmup,
             "target_s": args.target_s, "max_repeats": 50}
            for n in args.sizes for m in methods
            if not (m == "ase" and n > args.ase_max)]
    _harness.run_jobs("pairs:run_row", jobs, columns=COLUMNS,
                      finish=add_ratios, **_harness.run_options(args))


if __name__ == "__main__":
    main()
