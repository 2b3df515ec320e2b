"""Does a Dense list step's time per particle grow with N because of the
particles' numbering? (memory locality of the ``R[idx]`` gathers)

System: `md_step`'s LJ fluid start (simple-cubic lattice at density 0.8,
r_onset 2.0, r_cutoff 2.5, skin 0.3, float32, jaxrt's `cell` list, Dense,
jaxrt's row-summed LJ), numbered by ``--orders`` (`md_step.ORDERS`:
``lattice`` x-major as md_step, ``random`` shuffled, ``hilbert`` /
``morton`` the shuffle sorted by `jaxrt.lists.order.spatial_order`).

Rows (``stage``), each jitted and timed alone:

* ``forces``: ``jax_md.quantity.force`` of the energy on the fixed list;
* ``rebuild``: ``nbrs.update`` forced to search (one particle moved past
  half the skin from the list's reference positions);
* ``gather``: the neighbours' positions alone, ``sum_c R[idx[i, c]]``
  (what the forces read through the list, with no arithmetic: on a CPU
  the forces' arithmetic can hide what the gathers cost);

``--stages`` picks them. One worker per N builds every numbering's system,
then times each stage's calls in turn, repeat after repeat (on a shared
machine a change of load then falls on every numbering alike).
The whole step with a numbering: ``md_step.py --order``.

Each row also gives ``ns_per_particle`` (median / N) and ``gap``, the
median over the list's entries of ``|i - j|`` (how far in memory a row's
gathers reach; a lattice numbering gives a few planes of N^(2/3)).

    python benchmarks/list_order.py                          # CPU sweep
    python benchmarks/list_order.py --sizes 10000 100000 --repeats 3
"""
from __future__ import annotations

import sys

if __package__:  # run as -m, or imported: the package's modules
    from benchmarks import _harness, md_step
else:  # run as a file: its folder is sys.path[0]
    import _harness
    import md_step

COLUMNS = ["order", "stage", "N", "k", "gap", "median_ms", "ns_per_particle",
           "min_ns_per_particle", "min_ms", "max_ms"]


def _gap(idx, n: int) -> float:
    import numpy as np
    idx = np.asarray(idx)
    rows = np.broadcast_to(np.arange(n)[:, None], idx.shape)
    real = idx < n
    return float(np.median(np.abs(idx[real] - rows[real])))


def _calls(stage: str, n: int, R, nbrs, neighbor_fn, energy_fn):
    """A no-argument call of one stage on one numbering's system."""
    import jax
    import jax.numpy as jnp
    from jax_md import quantity
    del neighbor_fn
    if stage == "forces":
        force = jax.jit(quantity.force(energy_fn))
        return lambda: force(R, neighbor=nbrs)
    if stage == "gather":
        padded = jnp.concatenate([R, jnp.zeros((1, 3), R.dtype)])
        gather = jax.jit(lambda r, idx: jnp.sum(r[idx], axis=1))
        return lambda: gather(padded, nbrs.idx)
    # rebuild: a list whose reference is R with particle 0 moved by 0.2 >
    # skin / 2, so every update from it searches.
    stale = nbrs.set(reference_position=R.at[0, 0].add(0.2))
    update = jax.jit(lambda r, nb: nb.update(r).idx)
    return lambda: update(R, stale)


def _interleaved(calls: dict, repeats: int, warmup: int) -> dict:
    """Median / min / max ms of each call, the calls taken in turn each
    repeat, so that a change in the shared machine's load falls on all."""
    import time
    import jax
    for fn in calls.values():
        for _ in range(max(1, warmup)):
            jax.block_until_ready(fn())
    samples = {key: [] for key in calls}
    for _ in range(repeats):
        for key, fn in calls.items():
            t = time.perf_counter()
            jax.block_until_ready(fn())
            samples[key].append((time.perf_counter() - t) * 1e3)
    return {key: _harness.summarize(v, max(1, warmup))
            for key, v in samples.items()}


def run_row(job: dict) -> list[dict]:
    """Every (order, stage) of one N, in one worker: the orders' systems
    built first, then each stage's calls timed in turn."""
    import jaxrt
    from jax_md import space
    from jaxrt.energy import lennard_jones_neighbor_list
    stages = job["stages"].split()
    systems = {}
    for order in job["orders"].split():
        n, box, R = md_step.lj_system(job["N"], order)
        disp, _ = space.periodic(box)
        neighbor_fn, energy_fn = lennard_jones_neighbor_list(
            disp, box, r_onset=2.0, r_cutoff=2.5, dr_threshold=0.3,
            format=jaxrt.Dense, neighbor_list_fn=jaxrt.neighbor_list)
        nbrs = neighbor_fn.allocate(R)
        systems[order] = (R, nbrs, neighbor_fn, energy_fn)
    rows = []
    for stage in stages:
        calls = {order: _calls(stage, n, *system)
                 for order, system in systems.items()}
        timings = _interleaved(calls, job["repeats"], job["warmup"])
        for order, timing in timings.items():
            nbrs = systems[order][1]
            rows.append({"order": order, "stage": stage, "N": n,
                         "k": round(float(md_step.mean_neighbours(nbrs, n)),
                                    2),
                         "gap": _gap(nbrs.idx, n), **timing.columns(),
                         "ns_per_particle": round(
                             timing.median_ms * 1e6 / n, 1),
                         "min_ns_per_particle": round(
                             timing.min_ms * 1e6 / n, 1)})
        del calls
    return rows


def main(argv=None) -> None:
    parser = _harness.make_parser(__doc__)
    parser.add_argument("--sizes", type=int, nargs="+",
                        default=[10_000, 100_000, 300_000, 1_000_000,
                                 2_000_000],
                        help="particles (rounded to a cube)")
    parser.add_argument("--orders", nargs="+", default=list(md_step.ORDERS),
                        choices=md_step.ORDERS)
    parser.add_argument("--stages", nargs="+",
                        default=["forces", "rebuild", "gather"],
                        choices=["forces", "rebuild", "gather"])
    _harness.add_common_args(parser, name="list_order.csv", repeats=5,
                             warmup=1, timeout=900)
    args = parser.parse_args(argv)
    jobs = [{"N": n, "orders": " ".join(args.orders),
             "stages": " ".join(args.stages), "repeats": args.repeats,
             "warmup": args.warmup} for n in args.sizes]
    _harness.run_jobs("list_order:run_row", jobs, columns=COLUMNS,
                      **_harness.run_options(args))


if __name__ == "__main__":
    sys.exit(main())
