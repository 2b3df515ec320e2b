"""Graphs for machine-learned potentials: jaxrt.pairs and jaxrt.pairs_batch
against vesin and matscipy (and ASE on small systems), side by side.

Every structure (or flat batch) is one worker process that times all the
methods interleaved (call of method 1, of method 2, ..., repeated), so
that a busy machine slows them alike; times are medians of the timed
calls, warm-up (compilation) excluded, float64 everywhere (vesin,
matscipy and ASE compute in float64; ``jaxrt[f32]`` is jaxrt in float32).
``pairs`` is the number of pairs of the first call; ``same_as_vesin``
whether it equals vesin's. ``vs_vesin`` is the time over vesin's.

Structures (the issue's): primitive Si (2 atoms, 5 Å: shifts up to 2), a
1-atom Cu cell (shifts up to 3), Cu and hcp Mg supercells, a sheared
triclinic cell needing shifts of 3, an Al(111) slab, C60 in free space, a
2 000-atom random box, and (``--large``) 10⁵-atom fcc Cu. Batches: the
five-structure mixed batch (molecule, slab, bulk, 1-atom cell, triclinic:
2-256 atoms), 64 small periodic cells (2-32 atoms) and 16 cells of 16-128
atoms; vesin and matscipy run system by system (they have no batch call),
jaxrt as one flat batch (`jaxrt.pairs_batch`, jraph's layout).

Methods:
  jaxrt          jax.jit of jaxrt.pairs / pairs_batch with static sizes
                 (what a training step runs)
  jaxrt[f32]     the same in float32
  jaxrt[dense]   jaxrt with max_nodes forced to the largest system's size
                 bucket: dense blocks (unless the blocks are too many)
  jaxrt[cells]   jaxrt with max_nodes=0 forced: the cell search
  jaxrt[static]  batches: jaxrt with every system searched at the batch's
                 static reach (``program.OWN_REACH`` off when traced), not
                 at its own
  jaxrt[eager]   jaxrt.pairs / pairs_batch(..., capacity=None): sizing,
                 bucketed programs and the cut to size included
  vesin          vesin.NeighborList(cutoff, full_list=True).compute
  matscipy       matscipy.neighbours.neighbour_list("ijS"), if installed
  ase            ase.neighborlist.neighbor_list("ijS"), up to --ase-max atoms

``--compiles`` adds the compile table (its own CSV, ``graphs_compiles``):
eager calls over a data set of 50 atom counts (random atoms at a solid's
density, 20-69 atoms, cutoff 5 Å) and over 20 flat batches of it: programs
compiled, the first pass's time (compiles included) and a second pass's
time per call.

    python benchmarks/graphs.py                  # CPU: every structure
    python benchmarks/graphs.py --large          # and 10^5 atoms
    python benchmarks/graphs.py --compiles       # and the compile table
    python benchmarks/graphs.py --quick          # smoke: 3 structures

``--structures batch_cu16_XYZ`` (any digits X, Y, Z) is a batch of 16
rattled copies of cubic fcc Cu repeated (X, Y, Z), and ``batch_si16_1``
16 primitive Si cells (reach 3): with ``jaxrt[dense]`` and ``jaxrt[cells]``
they calibrate `jaxrt.pairs_batch_sizes`'s choice between the two.
"""
from __future__ import annotations

import os
import sys
import time

if __package__:
    from benchmarks import _harness
else:
    import _harness

CUTOFF = 5.0
STRUCTURES = ["si2", "cu1", "cu_108", "mg_hcp_96", "triclinic_7", "slab_36",
              "c60", "random_2000"]
LARGE = ["cu_1e5"]
BATCHES = ["batch_mixed_5", "batch_small_64", "batch_medium_16"]
METHODS = ["jaxrt", "jaxrt[f32]", "jaxrt[eager]", "vesin", "matscipy", "ase",
           "jaxrt[dense]", "jaxrt[cells]", "jaxrt[static]"]


def structure(name: str):
    """An ``ase.Atoms`` by name (module docstring)."""
    import numpy as np
    from ase import Atoms
    from ase.build import bulk, fcc111, molecule
    if name == "si2":
        return bulk("Si", "diamond", a=5.43)
    if name == "cu1":
        return bulk("Cu", "fcc", a=3.61)
    if name == "cu_108":
        atoms = bulk("Cu", "fcc", a=3.61, cubic=True).repeat((3, 3, 3))
    elif name == "mg_hcp_96":
        atoms = bulk("Mg", "hcp", a=3.21, c=5.21).repeat((4, 4, 3))
    elif name == "triclinic_7":
        rng = np.random.default_rng(0)
        cell = np.array([[4.0, 0, 0], [3.1, 3.5, 0], [-2.7, 1.9, 3.2]])
        return Atoms("H7", positions=rng.uniform(0, 1, (7, 3)) @ cell,
                     cell=cell, pbc=True)
    elif name == "slab_36":
        atoms = fcc111("Al", size=(3, 3, 4), vacuum=6.0)
    elif name == "c60":
        return molecule("C60")
    elif name == "random_2000":
        side = (2000 / 0.05) ** (1 / 3)
        rng = np.random.default_rng(1)
        return Atoms("Si2000", positions=rng.uniform(0, side, (2000, 3)),
                     cell=[side] * 3, pbc=True)
    elif name == "cu_1e5":
        atoms = bulk("Cu", "fcc", a=3.61, cubic=True).repeat((29, 29, 29))
    else:
        raise ValueError(name)
    atoms.rattle(0.05, seed=2)
    return atoms


def batch(name: str) -> list:
    """The systems of a flat batch by name."""
    import numpy as np
    from ase.build import bulk
    rng = np.random.default_rng(3)
    if name.startswith("batch_cu16_") or name == "batch_si16_1":
        reps = tuple(int(c) for c in name[-3:]) if "cu16" in name else (1,)*3
        base = bulk("Cu", "fcc", a=3.61, cubic=True) if "cu16" in name \
            else bulk("Si", "diamond", a=5.43)
        out = []
        for k in range(16):
            atoms = base.repeat(reps)
            atoms.rattle(0.05, seed=k)
            out.append(atoms)
        return out
    if name == "batch_mixed_5":
        return [structure("c60"), structure("slab_36"),
                structure("cu_108"), structure("cu1"),
                structure("triclinic_7")]
    kinds = [bulk("Si", "diamond", a=5.43), bulk("Cu", "fcc", a=3.61),
             bulk("Cu", "fcc", a=3.61, cubic=True),
             bulk("Si", "diamond", a=5.43, cubic=True)]
    out = []
    if name == "batch_small_64":
        for k in range(64):
            atoms = kinds[k % 4].repeat((1 + k % 2, 1, 1 + (k // 2) % 2))
            atoms.rattle(0.05, seed=k)
            out.append(atoms)
    elif name == "batch_medium_16":
        for k in range(16):
            atoms = kinds[2 + k % 2].repeat((1 + k % 2, 2, 2 + (k // 4) % 2))
            atoms.rattle(0.05, seed=k)
            out.append(atoms)
    else:
        raise ValueError(name)
    del rng
    return out


def _arrays(atoms):
    import numpy as np
    return (np.asarray(atoms.positions, np.float64),
            np.asarray(atoms.cell.array, np.float64),
            tuple(bool(p) for p in atoms.pbc))


def _one_system_calls(atoms, methods):
    """{method: (call, count)} for one system."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    import jaxrt
    pos, cell, pbc = _arrays(atoms)
    h = cell if any(pbc) else None
    calls = {}
    for method in methods:
        if method in ("jaxrt", "jaxrt[f32]"):
            dtype = jnp.float64 if method == "jaxrt" else jnp.float32
            sizes = jaxrt.pairs_sizes(pos.astype(dtype), CUTOFF, cell=h,
                                      pbc=pbc)
            f = jax.jit(lambda r, c, sizes=sizes: jaxrt.pairs(
                r, CUTOFF, cell=c, pbc=pbc, **sizes.kwargs))
            r = jnp.asarray(pos, dtype)
            c = None if h is None else jnp.asarray(h, dtype)
            calls[method] = (lambda f=f, r=r, c=c: jax.block_until_ready(
                f(r, c)), lambda out: int(out.count))
        elif method == "jaxrt[eager]":
            calls[method] = (lambda: jaxrt.pairs(pos, CUTOFF, cell=h,
                                                 pbc=pbc),
                             lambda out: int(out.count))
        elif method == "vesin":
            from vesin import NeighborList
            nl = NeighborList(cutoff=CUTOFF, full_list=True)
            box = cell if any(pbc) else np.zeros((3, 3))
            calls[method] = (lambda: nl.compute(
                points=pos, box=box, periodic=list(pbc),
                quantities="ijS"), lambda out: len(out[0]))
        elif method == "matscipy":
            from matscipy.neighbours import neighbour_list
            calls[method] = (lambda: neighbour_list("ijS", atoms, CUTOFF),
                             lambda out: len(out[0]))
        elif method == "ase":
            from ase.neighborlist import neighbor_list
            calls[method] = (lambda: neighbor_list("ijS", atoms, CUTOFF),
                             lambda out: len(out[0]))
    return calls


def _batch_calls(systems, methods):
    """{method: (call, count)} for a flat batch (vesin and matscipy: a loop
    over the systems)."""
    import jax
    import jax.numpy as jnp
    import jaxrt
    from jaxrt.pairs.checks import bucket
    flat = jaxrt.batch_from_ase(systems)
    calls = {}
    for method in methods:
        if method in ("jaxrt", "jaxrt[f32]", "jaxrt[dense]", "jaxrt[cells]",
                      "jaxrt[static]"):
            dtype = jnp.float32 if method == "jaxrt[f32]" else jnp.float64
            sizes = jaxrt.pairs_batch_sizes(flat.positions.astype(dtype),
                                            flat.n_node, CUTOFF, **flat.kwargs)
            kwargs = sizes.kwargs
            if method == "jaxrt[dense]":
                kwargs = dict(kwargs, max_nodes=bucket(max(
                    len(a) for a in systems)))
            elif method == "jaxrt[cells]":
                kwargs = dict(kwargs, max_nodes=0)
            f = jax.jit(lambda r, n, c, p, m, kw=kwargs: jaxrt.pairs_batch(
                r, n, CUTOFF, cell=c, pbc=p, graph_mask=m, **kw))
            args = (jnp.asarray(flat.positions, dtype), flat.n_node,
                    jnp.asarray(flat.cell, dtype), flat.pbc, flat.graph_mask)
            if method == "jaxrt[static]":
                _traced_static(f, args)
            calls[method] = (lambda f=f, args=args: jax.block_until_ready(
                f(*args)), lambda out: int(out.count))
        elif method == "jaxrt[eager]":
            calls[method] = (lambda: jaxrt.pairs_batch(
                flat.positions, flat.n_node, CUTOFF, **flat.kwargs),
                lambda out: int(out.count))
        elif method in ("vesin", "matscipy", "ase"):
            one = [_one_system_calls(a, [method])[method][0]
                   for a in systems]
            calls[method] = (lambda one=one: [c() for c in one],
                             lambda out: sum(len(o[0]) for o in out))
    return calls


def _traced_static(f, args):
    """``f`` traced (and compiled) with each system at the batch's static
    reach: the switch is read when the program is traced."""
    import importlib
    program = importlib.import_module("jaxrt.pairs.program")
    before = program.OWN_REACH
    program.OWN_REACH = False
    try:
        f(*args)
    finally:
        program.OWN_REACH = before


def _available(methods, n_atoms: int, ase_max: int):
    out = []
    for m in methods:
        if m == "ase" and n_atoms > ase_max:
            continue
        if m in ("vesin", "matscipy"):
            try:
                __import__({"vesin": "vesin",
                            "matscipy": "matscipy.neighbours"}[m])
            except ImportError:
                continue
        out.append(m)
    return out


def _interleaved(calls: dict, repeats: int, warmup: int, target_s: float):
    """Median, min and max ms per method, calls interleaved."""
    import statistics
    firsts = {}
    for m, (call, _) in calls.items():
        for w in range(max(1, warmup)):
            out = call()
            if w == 0:
                firsts[m] = out
    samples = {m: [] for m in calls}
    t_start = time.perf_counter()
    rounds = 0
    while rounds < repeats or (time.perf_counter() - t_start < target_s
                               and rounds < 200):
        for m, (call, _) in calls.items():
            t = time.perf_counter()
            call()
            samples[m].append((time.perf_counter() - t) * 1e3)
        rounds += 1
    return {m: (statistics.median(s), min(s), max(s), len(s), firsts[m])
            for m, s in samples.items()}


def run_row(job: dict) -> list[dict]:
    """Every method on one structure or batch, in a worker."""
    import jax
    jax.config.update("jax_enable_x64", True)
    name = job["structure"]
    if name.startswith("batch_"):
        systems = batch(name)
        n_atoms = sum(len(a) for a in systems)
        methods = _available(job["methods"], n_atoms, job["ase_max"])
        calls = _batch_calls(systems, methods)
        label = f"{len(systems)} systems"
    else:
        atoms = structure(name)
        n_atoms = len(atoms)
        methods = _available(job["methods"], n_atoms, job["ase_max"])
        calls = _one_system_calls(atoms, methods)
        label = "pbc " + "".join("TF"[not p] for p in atoms.pbc)
    timed = _interleaved(calls, job["repeats"], job["warmup"],
                         job["target_s"])
    rows = []
    for m, (med, lo, hi, reps, first) in timed.items():
        count = calls[m][1](first)
        rows.append({"structure": name, "what": label, "method": m,
                     "N": n_atoms, "dtype": "float32" if m == "jaxrt[f32]"
                     else "float64", "k": round(count / n_atoms, 1),
                     "pairs": count, "time_ms": med, "median_ms": med,
                     "min_ms": lo, "max_ms": hi, "repeats": reps,
                     "warmup": job["warmup"]})
    vesin = next((r for r in rows if r["method"] == "vesin"), None)
    for r in rows:
        if vesin is not None:
            r["vs_vesin"] = r["time_ms"] / vesin["time_ms"]
            r["same_as_vesin"] = r["pairs"] == vesin["pairs"]
    return rows


def _gas(n: int, seed: int):
    import numpy as np
    from ase import Atoms
    side = (n / 0.085) ** (1 / 3)
    rng = np.random.default_rng(seed)
    return Atoms(f"Cu{n}", positions=rng.uniform(0, side, (n, 3)),
                 cell=[side] * 3, pbc=True)


def compile_row(job: dict) -> list[dict]:
    """Programs compiled and time over a data set of 50 atom counts."""
    import jax
    jax.config.update("jax_enable_x64", True)
    import importlib
    import jaxrt
    program = importlib.import_module("jaxrt.pairs.program")
    data = [_gas(n, n) for n in range(20, 70)]
    rows = []

    def passes(call, items, what, method):
        before = program.search._cache_size()
        t = time.perf_counter()
        for x in items:
            call(x)
        first = time.perf_counter() - t
        programs = program.search._cache_size() - before
        t = time.perf_counter()
        for x in items:
            call(x)
        warm = (time.perf_counter() - t) * 1e3 / len(items)
        rows.append({"structure": what, "method": method,
                     "N": f"{min(len(a) for a in data)}-"
                          f"{max(len(a) for a in data)}",
                     "calls": len(items), "programs": programs,
                     "first_pass_s": first, "warm_ms_per_call": warm,
                     "dtype": "float64"})

    passes(lambda a: jaxrt.pairs(a.positions, CUTOFF, cell=a.cell.array),
           data, "50 atom counts, one by one", "jaxrt[eager]")
    batches = [jaxrt.batch_from_ase(data[k::20]) for k in range(20)]
    passes(lambda b: jaxrt.pairs_batch(b.positions, b.n_node, CUTOFF,
                                       **b.kwargs),
           batches, "20 flat batches of 2-3 of them", "jaxrt[eager] batch")
    return rows


COLUMNS = ["structure", "what", "method", "N", "k", "pairs", "time_ms",
           "repeats", "vs_vesin", "same_as_vesin"]
COMPILE_COLUMNS = ["structure", "method", "N", "calls", "programs",
                   "first_pass_s", "warm_ms_per_call"]


def _structure_name(name: str) -> str:
    """A --structures name checked (the fixed ones or batch_cu16_XYZ)."""
    import argparse
    if name in STRUCTURES + LARGE + BATCHES + ["batch_si16_1"] or (
            name.startswith("batch_cu16_") and len(name) == 14
            and name[-3:].isdigit() and "0" not in name[-3:]):
        return name
    raise argparse.ArgumentTypeError(
        f"unknown structure {name!r}: choose from "
        f"{STRUCTURES + LARGE + BATCHES} or batch_cu16_XYZ, batch_si16_1")


def main(argv=None) -> None:
    parser = _harness.make_parser(__doc__)
    parser.add_argument("--structures", nargs="+", default=None,
                        metavar="NAME", type=_structure_name)
    parser.add_argument("--methods", nargs="+", default=METHODS,
                        choices=METHODS)
    parser.add_argument("--large", action="store_true",
                        help="also 10^5-atom fcc Cu")
    parser.add_argument("--compiles", action="store_true",
                        help="also the compile table (graphs_compiles CSV)")
    parser.add_argument("--ase-max", type=int, default=3000)
    parser.add_argument("--target-s", type=float, default=2.0,
                        help="timed seconds per structure (all methods)")
    parser.add_argument("--quick", action="store_true")
    _harness.add_common_args(parser, name="graphs.csv", repeats=20,
                             warmup=2, timeout=1800)
    args = parser.parse_args(argv)
    names = args.structures or (STRUCTURES + BATCHES
                                + (LARGE if args.large else []))
    if args.quick:
        names, args.repeats, args.target_s = ["si2", "cu_108",
                                              "batch_mixed_5"], 3, 0.2
    jobs = [{"structure": s, "methods": args.methods,
             "repeats": args.repeats, "warmup": args.warmup,
             "target_s": args.target_s, "ase_max": args.ase_max}
            for s in names]
    options = _harness.run_options(args)
    _harness.run_jobs("graphs:run_row", jobs, columns=COLUMNS, **options)
    if args.compiles:
        options["name"] = args.name.replace(".csv", "_compiles.csv") \
            if args.name.endswith(".csv") else args.name + "_compiles"
        _harness.run_jobs("graphs:compile_row", [{"what": "compiles"}],
                          columns=COMPILE_COLUMNS, **options)


if __name__ == "__main__":
    main()
