"""Where a jitted call's device time goes: the call traced with JAX's
profiler, its GPU kernels (and copies) summed by name per call, next to
the call's wall time; the gap between the two is launch, host-sync and
idle time (a ``while_loop`` on a GPU reads its predicate back every trip).

Cases (``--cases``, each ``NAME:N``):

* ``pairs:N``: `jaxrt.pairs` jitted with `jaxrt.pairs_sizes`' sizes, on
  pairs.py's diamond scene (float32, its cutoff); ``pairs-looped:N``
  with the short runs' loop kept a loop on the GPU
  (``jaxrt.pairs.cells.UNROLL_SLOTS_ON_CUDA`` off); ``pairs-half:N``
  with the unsorted list searched from the half stencil on the GPU too
  (``jaxrt.pairs.program.FULL_STENCIL_UNSORTED_ON_CUDA`` off), as the
  CPU searches it.
* ``rows:N``: `jaxrt.backends.rt.ffi.cell_candidate_rows` jitted alone, on
  warp_rebuild_stages.py's uniform scene (its grid, row width ``--width``),
  Warp's graphs on (``rows-none``, ``rows-jax``: the other graph modes).
* ``update:N``: the ``cell[warp]`` Dense list's jitted update on the same
  scene; ``update-pallas``: ``cell[pallas]``; ``update-warp-G``:
  ``cell[warp]`` with ``warp_graph=G`` (none, warp, jax).
* ``step:N``: md_step.py's LJ NVE step on the default Dense list, ten
  steps in one ``lax.scan`` per call (so per step: a tenth).

One CSV row per (case, kernel): calls per traced call, device time per
traced call (summed over the kernel's launches), and per case a
``(wall)`` row and a ``(device busy)`` row.

    python benchmarks/kernel_profile.py --cases pairs:1000 rows:1000000 \
        update:1000000 --out $OUT
"""
from __future__ import annotations

import argparse
import collections
import glob
import os
import statistics
import sys
import tempfile
import time

if __package__:
    from benchmarks import _harness
else:
    import _harness


def _pairs_case(n, unroll=True, full_stencil=True):
    import jax
    import jax.numpy as jnp
    import numpy as np
    import jaxrt
    import pairs as pairs_bench
    from jaxrt.pairs import cells, program
    cells.UNROLL_SLOTS_ON_CUDA = unroll
    program.FULL_STENCIL_UNSORTED_ON_CUDA = full_stencil
    jax.clear_caches()
    pos, cell = pairs_bench.scene(n)
    x = jnp.asarray(pos, jnp.float32)
    c = jnp.asarray(cell, jnp.float32)
    sizes = jaxrt.pairs_sizes(x[None], pairs_bench.CUTOFF,
                              cell=np.asarray(cell))
    f = jax.jit(lambda x, c: jaxrt.pairs(x, pairs_bench.CUTOFF, cell=c,
                                         **sizes.kwargs))
    return lambda: f(x, c), int(x.shape[0])


def _uniform(n):
    import jax.numpy as jnp
    import numpy as np
    side = n ** (1 / 3)
    return jnp.asarray(np.random.default_rng(0).uniform(0, side, (n, 3))
                       .astype(np.float32)), side


def _rows_case(n, width, graph=None):
    import jax
    import warp_rebuild_stages as stages_bench
    R, side = _uniform(n)

    class Quiet:
        def time(self, *a, **k):
            pass
    grid, cells, table, thresholds, flags = stages_bench.jax_stages(
        Quiet(), [R], side, n, width, False)
    from jaxrt.backends.rt import ffi
    if jax.default_backend() not in ("gpu", "cuda"):
        graph = "none"
    graph = graph or "warp"
    f = jax.jit(lambda p, g, c, t: ffi.cell_candidate_rows(
        p, g, c, t, flags=flags, table=table, row_width=width,
        shell=stages_bench.SHELL, graph=graph))
    return lambda: f(R, grid, cells, thresholds), n


def _update_case(n, backend):
    import jax
    import jaxrt
    from jax_md import space
    R, side = _uniform(n)
    disp, _ = space.periodic(side)
    fns = jaxrt.neighbor_list(disp, side, 2.5,
                              backend=_harness.backend(backend))
    nbrs = fns.allocate(R)
    update = jax.jit(fns.update)
    return lambda: update(R, nbrs).idx, n


UPDATES = {"update": "cell[warp]", "update-pallas": "cell[pallas]",
           "update-warp-none": "cell[kernel=warp,warp_graph=none]",
           "update-warp-warp": "cell[kernel=warp,warp_graph=warp]",
           "update-warp-jax": "cell[kernel=warp,warp_graph=jax]"}


def _step_case(n, steps=10):
    """md_step.py's LJ NVE step with the default Dense list (its lattice
    numbering): ``steps`` steps in one ``lax.scan`` per call."""
    import jax
    import md_step
    job = {"steps": steps, "repeats": 1, "warmup": 0}
    captured = {}
    original = md_step._harness.time_carry

    def keep(run, carry, **kwargs):
        captured["call"] = lambda: run(carry)
        return original(run, carry, **kwargs)
    md_step._harness.time_carry = keep
    try:
        row = md_step.lj_step("jaxrt:cell/Dense", n, job)
    finally:
        md_step._harness.time_carry = original
    print(f"  step:{n}: k {row.get('k')}, rebuilds per step "
          f"{row.get('rebuilds_per_step')}", flush=True)
    return (lambda: jax.tree_util.tree_leaves(captured["call"]())[0],
            int(row["N"]))


def _device_events(path):
    """(line name, event name, duration ns) of every device event."""
    from jax.profiler import ProfileData
    data = ProfileData.from_file(path)
    out = []
    for plane in data.planes:
        if "GPU" not in plane.name and "gpu" not in plane.name:
            continue
        for line in plane.lines:
            for e in line.events:
                out.append((line.name, e.name, e.duration_ns))
    return out


def profile(case, fn, repeats, common):
    import jax
    for _ in range(3):
        jax.block_until_ready(fn())
    walls = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        walls.append((time.perf_counter() - t) * 1e3)
    folder = tempfile.mkdtemp()
    with jax.profiler.trace(folder):
        for _ in range(repeats):
            jax.block_until_ready(fn())
    paths = glob.glob(os.path.join(folder, "**", "*.xplane.pb"),
                      recursive=True)
    events = _device_events(paths[0]) if paths else []
    lines = collections.Counter(line for line, _, _ in events)
    # Kernels are on the streams' lines; the others summarise them again.
    stream = [e for e in events if e[0].lower().startswith("stream")]
    if not stream and lines:
        busiest = lines.most_common(1)[0][0]
        stream = [e for e in events if e[0] == busiest]
    per_name = collections.defaultdict(lambda: [0, 0.0])
    for _, name, ns in stream:
        per_name[name][0] += 1
        per_name[name][1] += ns
    rows = [{"case": case, "kernel": "(wall)", "calls": 1,
             "us_per_call": statistics.median(walls) * 1e3, **common}]
    busy = sum(v[1] for v in per_name.values()) / repeats / 1e3
    rows.append({"case": case, "kernel": "(device busy)",
                 "calls": sum(v[0] for v in per_name.values()) / repeats,
                 "us_per_call": busy, **common})
    for name, (count, ns) in sorted(per_name.items(),
                                    key=lambda kv: -kv[1][1]):
        rows.append({"case": case, "kernel": name[:120],
                     "calls": count / repeats,
                     "us_per_call": ns / repeats / 1e3, **common})
    print(f"== {case}: wall {rows[0]['us_per_call']:.1f} us, device busy "
          f"{busy:.1f} us, lines {dict(lines)}", flush=True)
    for r in rows[2:14]:
        print(f"  {r['us_per_call']:10.1f} us  x{r['calls']:<6g} "
              f"{r['kernel'][:90]}", flush=True)
    return rows


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cases", nargs="+", default=["pairs:1000"])
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--width", type=int, default=137)
    parser.add_argument("--out", default=None, help="CSV path or folder")
    args = parser.parse_args(argv)
    os.environ.setdefault("XLA_PYTHON_CLIENT_MEM_FRACTION", "0.5")
    device_columns = _harness.device_provenance()
    path = _harness.out_path(args.out, "kernel_profile.csv",
                             device_columns["device_slug"])
    common = {"dtype": "float32", **device_columns,
              **_harness.host_provenance(), "git_sha": _harness.git_sha(),
              "repeats": args.repeats}
    rows = []
    for case in args.cases:
        name, _, size = case.partition(":")
        n = int(size or 1000)
        try:
            if name in ("pairs", "pairs-looped", "pairs-half"):
                fn, n = _pairs_case(n, unroll=name != "pairs-looped",
                                    full_stencil=name != "pairs-half")
            elif name.startswith("rows"):
                fn, n = _rows_case(n, args.width, name.partition("-")[2])
            elif name == "step":
                fn, n = _step_case(n)
            elif name in UPDATES:
                fn, n = _update_case(n, UPDATES[name])
            else:
                raise ValueError(f"--cases: unknown case {name!r} (pairs, "
                                 f"pairs-looped, pairs-half, rows, "
                                 f"rows-GRAPH, step, {', '.join(UPDATES)})")
            rows += profile(case, fn, args.repeats, {"N": n, **common})
        except Exception as e:  # noqa: BLE001 - report and go on
            import traceback
            traceback.print_exc(limit=4)
            rows.append({"case": case, "kernel": "(error)",
                         "status": f"{type(e).__name__}: {e}"[:300],
                         **common})
        _harness.write_csv(rows, path)
    print(f"wrote {path}")


if __name__ == "__main__":
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    main()
