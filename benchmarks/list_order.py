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
* ``step``: `md_step.lj_step`'s NVE step (``--steps`` steps in one
  ``lax.scan``, the update's skin rule deciding rebuilds), only with
  ``--step``.

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
           "min_ms", "max_ms"]


def _gap(idx, n: int) -> float:
    import numpy as np
    idx = np.asarray(idx)
    rows = np.broadcast_to(np.arange(n)[:, None], idx.shape)
    real = idx < n
    return float(np.median(np.abs(idx[real] - rows[real])))


def run_row(job: dict) -> list[dict]:
    """The stages of one (N, order), in a worker."""
    import jax
    import jax.numpy as jnp
    from jax_md import quantity, space
    import jaxrt
    from jaxrt.energy import lennard_jones_neighbor_list
    n, box, R = md_step.lj_system(job["N"], job["order"])
    disp, _ = space.periodic(box)
    neighbor_fn, energy_fn = lennard_jones_neighbor_list(
        disp, box, r_onset=2.0, r_cutoff=2.5, dr_threshold=0.3,
        format=jaxrt.Dense, neighbor_list_fn=jaxrt.neighbor_list)
    nbrs = neighbor_fn.allocate(R)
    k = round(float(md_step.mean_neighbours(nbrs, n)), 2)
    common = {"N": n, "k": k, "gap": _gap(nbrs.idx, n)}
    reps = dict(repeats=job["repeats"], warmup=job["warmup"])
    rows = []

    force = jax.jit(quantity.force(energy_fn))
    timing = _harness.time_calls(lambda r: force(r, neighbor=nbrs), [R],
                                 **reps)
    rows.append({"stage": "forces", **common, **timing.columns()})

    # A list whose reference is R with particle 0 moved by 0.2 > skin / 2:
    # every update from it searches.
    stale = nbrs.set(reference_position=R.at[0, 0].add(0.2))
    update = jax.jit(lambda r, nb: nb.update(r))
    timing = _harness.time_calls(lambda r: update(r, stale).idx, [R], **reps)
    rows.append({"stage": "rebuild", **common, **timing.columns()})
    del stale, nbrs, force, update

    if job["step"]:
        row = md_step.lj_step("jaxrt:cell/Dense", job["N"],
                              {**job, "steps": job["steps"]})
        rows.append({"stage": "step", **common, **{
            c: row[c] for c in ("median_ms", "min_ms", "max_ms", "repeats",
                                "warmup")}, "rebuilds_per_step":
            row["rebuilds_per_step"]})
    for row in rows:
        row["ns_per_particle"] = round(row["median_ms"] * 1e6 / n, 2)
    return rows


def main(argv=None) -> None:
    parser = _harness.make_parser(__doc__)
    parser.add_argument("--sizes", type=int, nargs="+",
                        default=[10_000, 100_000, 300_000, 1_000_000,
                                 2_000_000],
                        help="particles (rounded to a cube)")
    parser.add_argument("--orders", nargs="+", default=list(md_step.ORDERS),
                        choices=md_step.ORDERS)
    parser.add_argument("--step", action="store_true",
                        help="also the whole NVE step (md_step's)")
    parser.add_argument("--steps", type=int, default=10,
                        help="steps per timed call of the step row")
    _harness.add_common_args(parser, name="list_order.csv", repeats=5,
                             warmup=1, timeout=900)
    args = parser.parse_args(argv)
    jobs = [{"N": n, "order": order, "step": args.step, "steps": args.steps,
             "repeats": args.repeats, "warmup": args.warmup}
            for n in args.sizes for order in args.orders]
    _harness.run_jobs("list_order:run_row", jobs, columns=COLUMNS,
                      **_harness.run_options(args))


if __name__ == "__main__":
    sys.exit(main())
