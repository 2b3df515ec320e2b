"""How far the cell grid's rebuild and its list-free LJ sums are from the
device's limits (issue #18's roofline table).

Rows, each in its own worker (`_harness`), side by side in one run:

* ``copy``: ``y = a x + b`` over 2^28 float32 (1 GiB in, 1 GiB out): the
  memory bandwidth a JAX program reaches (bytes read + written / time).
* ``fma``: 512 dependent multiply-adds per element on 2^24 float32, one
  fused XLA loop: the FP32 rate it reaches (2 flops per multiply-add).
* ``rebuild``: a jitted `jaxrt.neighbor_list` update (``cell``, Dense,
  ``dr_threshold = 0``: every call searches) on md_step's LJ system
  (simple-cubic lattice at density 0.8, jittered by 0.1 of a spacing,
  cutoff 2.5).
* ``fused``: the forces of `jaxrt.energy.lennard_jones_fused`
  (``backend=Cell(kernel=...)``, ``jax.grad`` of the energy under jit, as
  an MD step takes them: energy, forces and the pair count, no parameter
  derivatives) on the same system; with ``--launches``, also the kernel
  at other launches (particles x warps per program, and the cluster
  layout's tile of candidates).
* ``grid`` and ``walk``: the two halves of ``fused`` (``--parts``): the
  cell grid it rebuilds at every call (`jaxrt.energy.listfree.lj.cell_runs`:
  keys, sort, runs and their periodic images) and the kernel alone on that grid
  (`jaxrt.backends.cell.kernel.pair_sums` with the LJ terms, as ``fused`` calls
  it: energy and pair count, no parameter derivatives).

For the two search rows the script also counts, on the device, what the
work is: ``candidates`` per particle (the stencil runs' total length: every
one is read and tested) and ``pairs`` per particle within the cutoff. The
roofline columns then say what the row would cost at the measured limits:

* ``bytes_min``: compulsory traffic per particle (positions and order in,
  the grid's cell coordinates, or the stored runs, in; forces and sums or
  the row out) / ``copy``'s bandwidth;
* ``bytes_l2``: every candidate's coordinates fetched from memory or L2
  (4 bytes x dim each) / the same bandwidth: the cost when nothing is
  staged in shared memory or registers;
* ``flops``: ``FLOP_PER_CANDIDATE`` x candidates (the SIMT lanes execute
  the whole pair term for every candidate, masked) / ``fma``'s rate.

    GIT_SHA=$(git rev-parse --short HEAD) python benchmarks/roofline.py --n 1000000
    python benchmarks/roofline.py --quick          # CPU: N = 8000
"""
from __future__ import annotations

import dataclasses
import os
import sys

if __package__:  # run as -m, or imported: the package's modules
    from benchmarks import _harness
else:  # run as a file: its folder is sys.path[0]
    import _harness

# Counted in `jaxrt.backends.cell.kernel._sum_walk` with the LJ terms of
# `jaxrt.energy.listfree.lj.lj_terms` (reciprocal, floor, compare and select as
# one each): distance 9, the smooth-switched LJ energy and force factor
# 35, the accumulation 5. The md_step box is large enough that each run's
# periodic image is added once per run (`fused.run_image_axes`): no
# per-candidate minimum image (3 more per axis, 58 in all).
FLOP_PER_CANDIDATE = 49
# The list kernel (`jaxrt.backends.cell.kernel._walk`): distance 18, the two
# threshold tests and the row and shell offsets 8.
FLOP_PER_CANDIDATE_LIST = 26
ROWS = ("copy", "fma", "rebuild", "fused", "grid", "walk")


def _system(n: int, dtype):
    import jax.numpy as jnp
    import numpy as np
    from jax_md import space
    n_side = round(n ** (1 / 3))
    n = n_side ** 3
    box = (n / 0.8) ** (1 / 3)
    a = box / n_side
    g = np.stack(np.meshgrid(*[np.arange(n_side)] * 3, indexing="ij"), -1)
    rng = np.random.default_rng(0)
    R = (g.reshape(-1, 3) + rng.uniform(-0.1, 0.1, (n, 3))) * a % box
    return jnp.asarray(R, dtype), box, space.periodic(box)[0]


def _grid(box):
    """The fused energy's static parameters for md_step's LJ system."""
    from jaxrt.energy.listfree import lj as fused
    return fused.Params(r_onset=2.0, r_cutoff=2.5, bound=2.5,
                         periodic=(True,) * 3, side=(box,) * 3)


def _work(R, box, across: int = 1):
    """Candidates per particle and runs per particle of the cell grid the
    fused energy walks (`jaxrt.energy.listfree.lj.cell_runs`)."""
    import numpy as np
    from jaxrt.energy.listfree import lj as fused
    _, runs, _ = fused.cell_runs(R, _grid(box), across=across)
    start1 = fused.kernel_runs(runs)[0]
    return (float(np.mean(np.sum(np.asarray(runs.length), axis=1))),
            int(start1.shape[1]))


def run_row(job: dict) -> dict:
    import jax
    import jax.numpy as jnp
    row, n = job["row"], job["N"]
    timing = dict(repeats=job["repeats"], warmup=job["warmup"])
    if row == "copy":
        x = jnp.ones((n,), jnp.float32)
        f = jax.jit(lambda x: 1.0001 * x + 0.5)
        t = _harness.time_calls(f, [x, x + 1], **timing)
        return {"N": n, "bytes": 8 * n,
                "rate": 8 * n / (t.median_ms * 1e-3) / 1e12,
                "rate_unit": "TB/s", **t.columns()}
    if row == "fma":
        depth = 512

        def chain(x):
            for i in range(depth):  # unrolled: one fused elementwise loop
                x = x * (1.0 - 1e-7 * (i % 3)) + 1e-6
            return x
        x = jnp.ones((n,), jnp.float32)
        f = jax.jit(chain)
        t = _harness.time_calls(f, [x, x + 1], **timing)
        return {"N": n, "flops": 2 * depth * n,
                "rate": 2 * depth * n / (t.median_ms * 1e-3) / 1e12,
                "rate_unit": "TFLOP/s", **t.columns()}
    import jaxrt
    from jax_md import partition
    from jaxrt.backends import Cell
    from jaxrt.energy import lennard_jones_fused
    R, box, disp = _system(n, jnp.float32)
    n = R.shape[0]
    from md_step import launched  # the fused backend of a launch label
    backend = launched(job["launch"]) if job.get("launch") else None
    across = backend.across if backend is not None else 1
    candidates, runs = _work(R, box, across)
    inputs = [R, (R + 1e-3) % box]
    if row in ("grid", "walk"):
        return _part_row(job, R, box, inputs, candidates, runs, backend,
                         timing)
    if row == "rebuild":
        nfn = jaxrt.neighbor_list(disp, box, 2.5, dr_threshold=0.0,
                                  format=partition.Dense,
                                  backend=Cell(kernel=job["kernel"]))
        nbrs = nfn.allocate(R)
        t = _harness.time_calls(jax.jit(lambda R: nbrs.update(R).idx), inputs,
                                **timing)
        pairs = float(jnp.sum(nbrs.idx < n)) / n
        # order, 3 coordinates, the grid (the kernel finds its runs) or
        # the runs' starts and lengths (the portable path) in; the row out
        source = "stored" if job["kernel"] == "xla" else "kernel"
        bytes_min = 4 * (1 + 3) + _run_bytes(source, runs, 2) + 4 * (
            nbrs.idx.shape[1])
        flops = FLOP_PER_CANDIDATE_LIST * candidates
    else:
        energy_fn = lennard_jones_fused(
            disp, box, r_onset=2.0, r_cutoff=2.5,
            backend=backend or Cell(kernel=job["kernel"]))
        forces = jax.jit(jax.grad(energy_fn))
        t = _harness.time_calls(forces, inputs, **timing)
        pairs = 2 * float(energy_fn.sums(R).count) / n
        # order, 3 coordinates, the grid or the runs and their images in; 3
        # forces, the energy and the pair count out (grad skips the sigma /
        # epsilon sums)
        bytes_min = 4 * (1 + 3) + _run_bytes(
            getattr(backend, "runs", "kernel"), runs, 3) + 4 * 5
        flops = FLOP_PER_CANDIDATE * candidates
    return {"N": n, "k": round(pairs, 2),
            "kernel": job["kernel"] + (f" {job['launch']}" if job.get("launch")
                                       else ""),
            "candidates": round(candidates, 1), "bytes_min": bytes_min,
            "bytes_l2": 12 * candidates, "flops": flops, **t.columns()}


def _run_bytes(source: str, runs: int, per_run: int) -> int:
    """Compulsory bytes per particle of what a kernel reads to find its
    candidates: ``"stored"``, ``runs`` runs of ``per_run`` int32 each
    (start, length and, for the fused walk, the image code); ``"kernel"``,
    the particle's 3 cell coordinates (the cell-start table it also reads
    is about a cell per particle, and its two loads per run mostly hit
    the cache)."""
    return 4 * per_run * runs if source == "stored" else 4 * 3


def _part_row(job, R, box, inputs, candidates, runs, backend, timing):
    """`grid` or `walk`: one half of the fused forces (module docstring)."""
    import jax
    import jax.numpy as jnp
    from jaxrt.energy.listfree import lj as fused
    params = _grid(box)
    cell = backend or fused.CellSums()
    interpret = jax.default_backend() not in ("gpu", "cuda")  # CPU smoke
    n = R.shape[0]
    def walk(R):
        order, grid, images = fused.cell_runs(R, params, across=cell.across)
        if cell.runs == "kernel":  # the kernel reads the grid, not the runs
            return order, dataclasses.replace(images, first=None,
                                              wrapped=None), None
        return order, images, fused.kernel_runs(grid)

    if job["row"] == "grid":  # what the walk reads of it, no more
        t = _harness.time_calls(jax.jit(walk), inputs, **timing)
        # positions in; keys, order, the grid or the runs with their
        # images, and the sorted wrapped positions out
        return {"N": n, "kernel": job["kernel"] + (
                    f" {job['launch']}" if job.get("launch") else ""),
                "candidates": round(candidates, 1),
                "bytes_min": (4 * 3 + 4 * 2 + _run_bytes(cell.runs, runs, 3)
                              + 4 * 3),
                **t.columns()}

    walks = [jax.jit(walk)(x) for x in inputs]
    one = jnp.ones((), R.dtype)

    @jax.jit
    def kernel(order, images, grid):
        return cell._kernel_walk(
            images, grid, jnp.asarray(params.side, R.dtype), one, one,
            None, order, params, interpret, False, False,
            run_source=cell.runs, newton=cell.newton, block=cell.block,
            warps=cell.warps, tile=cell.tile, unroll=cell.unroll)

    t = _harness.time_calls(lambda w: kernel(*w), walks, **timing)
    return {"N": n, "kernel": job["kernel"] + (f" {job['launch']}" if job.get("launch") else ""),
            "candidates": round(candidates, 1),
            "bytes_min": 4 * 3 + _run_bytes(cell.runs, runs, 3) + 4 * 5,
            "bytes_l2": 12 * candidates,
            "flops": FLOP_PER_CANDIDATE * candidates, **t.columns()}


COLUMNS = ["row", "kernel", "N", "k", "candidates", "median_ms", "rate",
           "rate_unit", "limit_ms", "bound", "of_limit"]


def _finish(rows: list[dict]) -> None:
    """The roofline columns of the search rows from the measured limits."""
    rate = {r["row"]: float(r["rate"]) for r in rows
            if r.get("status") == "ok" and r.get("rate") not in (None, "")}
    if "copy" not in rate or "fma" not in rate:
        return
    bandwidth, fp32 = rate["copy"] * 1e12, rate["fma"] * 1e12
    for r in rows:
        if r.get("status") != "ok" or r["row"] not in ("rebuild", "fused", "walk"):
            continue
        n = float(r["N"])
        limits = {"memory (compulsory)": n * float(r["bytes_min"]) / bandwidth,
                  "memory (candidates uncached)": n * float(r["bytes_l2"]) / bandwidth,
                  "fp32": n * float(r["flops"]) / fp32}
        r["limit_ms_min"] = round(limits["memory (compulsory)"] * 1e3, 4)
        r["limit_ms_l2"] = round(limits["memory (candidates uncached)"] * 1e3, 4)
        r["limit_ms_fp32"] = round(limits["fp32"] * 1e3, 4)
        bound = max(limits, key=limits.get)
        r["bound"], r["limit_ms"] = bound, round(limits[bound] * 1e3, 4)
        r["of_limit"] = round(limits[bound] * 1e3 / float(r["median_ms"]), 3)


def plan(args) -> list[dict]:
    sizes = {"copy": 2 ** 28, "fma": 2 ** 24}
    if args.quick:
        sizes = {"copy": 2 ** 24, "fma": 2 ** 20}
    jobs = [{"row": r, "N": sizes[r], "kernel": "", "repeats": args.repeats,
             "warmup": args.warmup} for r in ("copy", "fma")]
    for row in ("rebuild", "fused"):
        for kernel in args.kernels:
            jobs.append({"row": row, "N": args.n, "kernel": kernel,
                         "repeats": args.repeats, "warmup": args.warmup})
    if args.parts:  # the default launch's halves, then each launch's
        jobs += [{"row": r, "N": args.n, "kernel": "pallas",
                  "repeats": args.repeats, "warmup": args.warmup,
                  **({"launch": launch} if launch else {})}
                 for launch in [""] + list(args.launches)
                 for r in ("grid", "walk")]
    for launch in args.launches:
        jobs.append({"row": "fused", "N": args.n, "kernel": "pallas",
                     "launch": launch, "repeats": args.repeats,
                     "warmup": args.warmup})
    return jobs


def main(argv=None) -> None:
    parser = _harness.make_parser(__doc__)
    parser.add_argument("--n", type=int, default=1_000_000)
    parser.add_argument("--kernels", nargs="*", default=["auto", "xla"],
                        help="Cell(kernel=...) values of the search rows")
    parser.add_argument("--launches", nargs="*", default=[],
                        help="extra fused rows with other launches of the "
                        "kernel, BLOCKxWARPS[xTILE][uUNROLL][aACROSS] (e.g. "
                        "64x2, 32x1u2a2, 16x1x16: with a tile, the cluster "
                        "layout; s: the runs stored beforehand, not "
                        "found by the kernel, as Cell(runs=\"stored\"); n: "
                        "each pair met once, Cell(newton=True); the default "
                        "is 32x1, no tile); CUDA only")
    parser.add_argument("--parts", action="store_true",
                        help="also the fused forces' two halves, the grid "
                        "and the kernel's walk (rows grid, walk); CUDA only")
    parser.add_argument("--quick", action="store_true",
                        help="CPU smoke: N = 8000, small limit rows")
    _harness.add_common_args(parser, name="roofline.csv", repeats=10,
                             warmup=2, timeout=300)
    args = parser.parse_args(argv)
    if args.quick:
        args.n, args.repeats = 8000, 3
    _harness.run_jobs("roofline:run_row", plan(args), columns=COLUMNS,
                      finish=_finish, **_harness.run_options(args))


if __name__ == "__main__":
    main()
