"""Where a list step's time goes, per layout: the list update, the Dense to
Sparse conversion, and the forces, each jitted and timed alone (#17's open
question: at k ≈ 700 seed 003's list rows cost 330-600 ms per step on the
H200, and which part is the layout's is not known; #18's target: Sparse and
OrderedSparse rebuilds within 1.2x of Dense).

System: uniform random positions in a periodic cube at density 0.8,
float32, the cutoff chosen for ``--k`` neighbours per particle on average
(k = 0.8 · 4/3 π rc³), the `cell` backend, no skin (every update searches).
LJ with σ = rc / 2.5 and jaxrt's smooth cutoff
(`jaxrt.energy.lennard_jones_pair_neighbor_list`).

Rows (``stage``):

* ``update <layout>``: `neighbor_list(...).update` of a list of that layout;
* ``convert Sparse`` / ``convert OrderedSparse``: `_backend.dense_to_sparse`
  alone, on the Dense rows the update builds first (on CUDA the
  left-packed rows of Sparse are copied by `jaxrt.layouts.edge_kernel`);
  ``... xla``: XLA's scatters everywhere; ``... scan all``: the
  same as it was until 631d12d (one scan over all N x M entries; the two
  ways' edges are checked equal); ``convert OrderedSparse half rows
  auto`` / ``xla``: the rows of the neighbours j < i alone, as the cell
  list's OrderedSparse search now writes them (the kernel, and the
  scatters);
* ``forces <layout>``: ``jax.grad`` of the energy on that list (Dense:
  each row summed in place, no scatter; Sparse layouts: reverse mode
  through jax-md's pair map, a scatter-add over every edge);
  ``forces <layout> jax-md``: the same with jax-md's own
  ``energy.lennard_jones_neighbor_list`` (what a jax-md user's step runs);
* ``energy <layout>``: the energy alone, no gradient (is the forward pass
  or its transpose slow?); ``forces <layout> edges``, edge layouts only:
  the per-edge gradients of both ends taken on the gathered positions,
  then two `segment_sum`s (padding dropped by range): reverse mode with
  its scatter written out, to compare with ``reduce scatter``, and
  ``... edges barrier``, the per-edge gradients written to memory before
  the scatters (no producer fused into them): the pair of rows that showed
  XLA's fused scatters to be the edge layouts' cost (jaxrt.layouts.edges;
  benchmarks/RESULTS.md, "What does a list's layout cost?");
* ``reduce ...``: only the reduction of per-edge force vectors (E, 3) to
  per-particle forces on the OrderedSparse list's edges, four ways: two
  scatter-adds as reverse mode does (``scatter``), the sender side with
  ``indices_are_sorted=True`` (``scatter sorted senders``), a segmented
  scan over the sorted senders plus a scatter for the receivers
  (``segmented scan``), and the Dense rows' sum for comparison (``rows``:
  what the Dense layout needs instead, both directions present).

    GIT_SHA=$(git rev-parse --short HEAD) python benchmarks/list_forces.py --n 1000000 --k 52
    python benchmarks/list_forces.py --n 50000 --k 700     # seed 003's r = 160 density
    python benchmarks/list_forces.py --n 4000 --k 60 --repeats 3  # CPU smoke
"""
from __future__ import annotations

import argparse
import functools
import math
import os
import sys

if __package__:  # run as -m, or imported: the package's modules
    from benchmarks import _harness
else:  # run as a file: its folder is sys.path[0]
    import _harness

LAYOUTS = ("Dense", "Sparse", "OrderedSparse")
# LLVM's NVPTX backend lowers an f32 atomic add to a compare-and-swap loop
# unless the function flushes denormals (global atom.add.f32 flushes them);
# this hidden option makes it emit the native instruction anyway.
FTZ_ATOMICS = "-nvptx-allow-ftz-atomics"


def _scan_all_entries(dense, capacity: int, ordered: bool):
    """Dense rows to edges as `_backend.dense_to_sparse` did until 631d12d:
    each entry's slot from one scan over all N x M entries (the
    comparison row ``convert <layout> scan all``)."""
    import jax.numpy as jnp
    n = dense.shape[0]
    senders = jnp.broadcast_to(jnp.arange(n, dtype=jnp.int32)[:, None],
                               dense.shape).reshape(-1)
    receivers = dense.reshape(-1)
    keep = receivers < n
    if ordered:
        keep = keep & (receivers < senders)
    slot = jnp.where(keep, jnp.cumsum(keep, dtype=jnp.int32) - 1, capacity)
    out = jnp.full((2, capacity), n, jnp.int32)
    out = out.at[0, slot].set(receivers, mode="drop")
    return out.at[1, slot].set(senders, mode="drop"), jnp.sum(keep)


def _segmented_sum(values, segment):
    """Per-segment sums of float ``(E, 3)`` ``values`` whose int32 ``(E,)``
    ``segment`` ids are sorted: an inclusive segmented scan (no sums
    across segments, so no cancellation), then each segment's last entry."""
    import jax
    import jax.numpy as jnp
    starts = jnp.concatenate([jnp.ones((1,), bool), segment[1:] != segment[:-1]])

    def op(a, b):
        (av, af), (bv, bf) = a, b
        return jnp.where(bf[..., None], bv, av + bv), af | bf

    scanned, _ = jax.lax.associative_scan(op, (values, starts))
    last = jnp.concatenate([segment[1:] != segment[:-1], jnp.ones((1,), bool)])
    return scanned, last


def _edge_forces(pair, displacement, R, idx, ordered: bool,
                 barrier: bool = False):
    """dE/dR on an edge list (int32 ``(2, E)``, padding ``N``): the two
    ends' per-edge gradients, then one `segment_sum` per end. Sparse holds
    both directions of each pair (each edge's energy counts half). With
    ``barrier`` the per-edge gradients are written to memory first (XLA
    cannot fuse their computation into the scatters)."""
    import jax
    import jax.numpy as jnp
    from jax_md import space
    n = R.shape[0]
    i, j = idx
    real = i < n
    distance = space.map_bond(space.metric(displacement))

    def total(a, b):
        e = jnp.where(real, pair(distance(a, b)), 0.0)
        return jnp.sum(e) * (1.0 if ordered else 0.5)

    ga, gb = jax.grad(total, argnums=(0, 1))(R[i], R[j])
    if barrier:
        ga, gb = jax.lax.optimization_barrier((ga, gb))
    return (jax.ops.segment_sum(ga, i, n) + jax.ops.segment_sum(gb, j, n))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n")[0], epilog=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=1_000_000)
    parser.add_argument("--k", type=float, default=52.0,
                        help="mean neighbours per particle (sets the cutoff)")
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--stages", nargs="+", default=None,
                        help="only the stages whose name starts with one "
                        "of these words (update, convert, forces, reduce)")
    parser.add_argument("--xla-ftz-atomics", action="store_true",
                        help="let XLA:GPU's LLVM emit native float atomic "
                        "adds (--xla_backend_extra_options="
                        f"{FTZ_ATOMICS}): from jaxlib 0.10.2 it emits a "
                        "compare-and-swap loop for f32 scatter-adds, slow "
                        "under contention (jax-ml/jax#38806). CUDA only: "
                        "an XLA without the NVPTX backend (CPU-only "
                        "jaxlib) exits on the unknown option")
    parser.add_argument("--out", default=None, help="CSV path or folder")
    args = parser.parse_args(argv)
    if args.xla_ftz_atomics:  # before jax reads XLA_FLAGS
        flags = os.environ.get("XLA_FLAGS", "")
        os.environ["XLA_FLAGS"] = (
            f"{flags} --xla_backend_extra_options={FTZ_ATOMICS}".strip())

    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax_md import energy as jax_md_energy
    from jax_md import partition, space

    import jaxrt
    from jaxrt.backends import contract as _backend
    from jaxrt.energy import lennard_jones_pair_neighbor_list
    from jaxrt.energy.lj import lennard_jones_truncated

    n, density = args.n, 0.8
    side = (n / density) ** (1 / 3)
    cutoff = (3 * args.k / (4 * math.pi * density)) ** (1 / 3)
    rng = np.random.default_rng(0)
    base = rng.uniform(0, side, (n, 3))
    # Two position sets, so that repeated calls do not replay one input.
    inputs = [jnp.asarray(base, jnp.float32),
              jnp.asarray(np.mod(base + rng.uniform(-0.01, 0.01, base.shape),
                                 side), jnp.float32)]
    displacement, _ = space.periodic(side)
    energy = lennard_jones_pair_neighbor_list(
        displacement, sigma=cutoff / 2.5, epsilon=1.0,
        r_onset=0.8 * cutoff, r_cutoff=cutoff)
    pair = functools.partial(lennard_jones_truncated, truncation="smooth",
                             sigma=cutoff / 2.5, epsilon=1.0,
                             r_onset=0.8 * cutoff, r_cutoff=cutoff)
    device = _harness.device_provenance()
    tag = "_ftz_atomics" if args.xla_ftz_atomics else ""
    path = _harness.out_path(args.out,
                             f"list_forces_{n}_k{int(args.k)}{tag}.csv",
                             device.get("device_slug", "unknown"))
    rows = []

    def wanted(name):
        return args.stages is None or any(name.startswith(s)
                                          for s in args.stages)

    def stage(name, fn, xs, **extra):
        if not wanted(name):
            return
        t = _harness.time_calls(jax.jit(fn), xs, repeats=args.repeats,
                                warmup=args.warmup)
        rows.append({"stage": name, "N": n, "k": args.k,
                     "cutoff": round(cutoff, 5),
                     "ftz_atomics": args.xla_ftz_atomics, **extra,
                     **t.columns(),
                     "dtype": "float32", **device,
                     **_harness.host_provenance(),
                     "git_sha": _harness.git_sha()})
        print(f"{name:34s} {t.median_ms:10.3f} ms", flush=True)
        _harness.write_csv(rows, path)  # a run cut short keeps its rows

    lists = {}
    for layout in LAYOUTS:
        fmt = getattr(partition, layout)
        nfn = jaxrt.neighbor_list(displacement, side, cutoff, 0.0,
                                  format=fmt, backend="cell")
        nbrs = nfn.allocate(inputs[0])
        lists[layout] = nbrs
        edges = int(np.sum(np.asarray(nbrs.idx)[0] < n)) if layout != "Dense" \
            else int(np.sum(np.asarray(nbrs.idx) < n))
        stage(f"update {layout}", lambda R, nb=nbrs, f=nfn: f.update(R, nb),
              inputs, entries=edges, capacity=int(np.prod(nbrs.idx.shape)))
        stage(f"forces {layout}", lambda R, nb=nbrs: jax.grad(energy)(R, nb),
              inputs, entries=edges)
        stage(f"energy {layout}", lambda R, nb=nbrs: energy(R, nb), inputs,
              entries=edges)
        if layout != "Dense":
            def edge_fn(R, barrier=False, nb=nbrs,
                        ordered=layout == "OrderedSparse"):
                return _edge_forces(pair, displacement, R, nb.idx, ordered,
                                    barrier)
            stage(f"forces {layout} edges", edge_fn, inputs, entries=edges)
            stage(f"forces {layout} edges barrier",
                  functools.partial(edge_fn, barrier=True), inputs,
                  entries=edges)
            if wanted(f"forces {layout} edges"):
                a = np.asarray(jax.jit(edge_fn)(inputs[0]))
                b = np.asarray(jax.jit(jax.grad(energy))(inputs[0], nbrs))
                print(f"edges vs grad ({layout}): max |diff| "
                      f"{np.abs(a - b).max():.3g} (max |F| {np.abs(b).max():.3g})")
        # jax-md's cutoffs are in units of its sigma: the same potential.
        _, theirs = jax_md_energy.lennard_jones_neighbor_list(
            displacement, side, sigma=cutoff / 2.5, epsilon=1.0,
            r_onset=2.0, r_cutoff=2.5, format=fmt)
        stage(f"forces {layout} jax-md",
              lambda R, nb=nbrs, e=theirs: jax.grad(e)(R, nb), inputs,
              entries=edges)

    dense = lists["Dense"].idx
    for ordered in (False, True):
        layout = "OrderedSparse" if ordered else "Sparse"
        cap = lists[layout].idx.shape[1]
        stage(f"convert {layout}",
              lambda d, c=cap, o=ordered: _backend.dense_to_sparse(d, c, o),
              [dense, dense], capacity=cap)
        stage(f"convert {layout} xla",
              lambda d, c=cap, o=ordered: _backend.dense_to_sparse(
                  d, c, o, engine="xla"), [dense, dense], capacity=cap)
        stage(f"convert {layout} scan all",
              lambda d, c=cap, o=ordered: _scan_all_entries(d, c, o),
              [dense, dense], capacity=cap)
        if ordered and wanted("convert OrderedSparse half rows"):
            # What the cell list's OrderedSparse search now converts: rows
            # of the neighbours j < i alone, left-packed (cell_list's
            # _lower_only), with their counts from the search.
            half, half_counts = _backend.pack_rows(
                dense, dense < jnp.arange(n)[:, None],
                int(jnp.max(jnp.sum(dense < jnp.arange(n)[:, None], 1))))
            for engine in ("auto", "xla"):
                stage(f"convert OrderedSparse half rows {engine}",
                      lambda d, c=cap, e=engine, k=half_counts:
                      _backend.dense_to_sparse(d, c, False, counts=k,
                                               engine=e),
                      [half, half], capacity=cap)
            same = np.array_equal(
                np.asarray(_backend.dense_to_sparse(
                    half, cap, False, counts=half_counts)[0]),
                np.asarray(_backend.dense_to_sparse(dense, cap, True)[0]))
            print(f"convert OrderedSparse: half rows' edges equal: {same}")
        if wanted("convert"):
            ours = _backend.dense_to_sparse(dense, cap, ordered)
            old = _scan_all_entries(dense, cap, ordered)
            same = (np.array_equal(np.asarray(ours[0]), np.asarray(old[0]))
                    and int(ours[1]) == int(old[1]))
            print(f"convert {layout}: the two ways' edges equal: {same}")

    # The reductions alone, on per-edge vectors of the OrderedSparse list
    # (receivers j = idx[0], senders i = idx[1], the senders ascending as
    # jaxrt's conversion writes them).
    if wanted("reduce"):  # random edge vectors: host time, memory
        idx = lists["OrderedSparse"].idx
        receivers, senders = idx[0], idx[1]
        e = idx.shape[1]
        force = [jnp.asarray(rng.normal(size=(e, 3)), jnp.float32)
                 for _ in range(2)]

        def scatter(f):
            return (jax.ops.segment_sum(f, senders, n)
                    - jax.ops.segment_sum(f, receivers, n))

        def scatter_sorted(f):
            return (jax.ops.segment_sum(f, senders, n, indices_are_sorted=True)
                    - jax.ops.segment_sum(f, receivers, n))

        def segmented(f):
            scanned, last = _segmented_sum(f, senders)
            # Every index distinct (the others out of range, dropped), as
            # unique_indices promises.
            at = jnp.where(last, senders, n + 1 + jnp.arange(e, dtype=jnp.int32))
            own = jnp.zeros((n, 3), f.dtype).at[at].set(
                scanned, mode="drop", unique_indices=True)
            return own - jax.ops.segment_sum(f, receivers, n)

        stage("reduce scatter", scatter, force, entries=e)
        stage("reduce scatter sorted senders", scatter_sorted, force, entries=e)
        stage("reduce segmented scan", segmented, force, entries=e)
        width = dense.shape[1]
        per_slot = [jnp.asarray(rng.normal(size=(n, width, 3)), jnp.float32)
                    for _ in range(2)]
        stage("reduce rows (Dense)", lambda f: jnp.sum(f, axis=1), per_slot,
              entries=int(np.sum(np.asarray(dense) < n)))
        a = np.asarray(jax.jit(scatter)(force[0]))
        b = np.asarray(jax.jit(segmented)(force[0]))
        print(f"segmented scan vs scatter: max |diff| {np.abs(a - b).max():.3g}"
              f" (max |F| {np.abs(a).max():.3g})")

    print(f"cutoff {cutoff:.4f}; wrote {path}")


if __name__ == "__main__":
    main()
