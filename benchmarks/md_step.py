"""Time one whole MD step: a Lennard-Jones NVE step and an SPH step.

Each step is what a simulation pays per step: the neighbour-list update
with its skin (rebuilt only when a particle moved more than half the skin)
plus the forces and the integrator. Run for jax-md's own list and for each
jaxrt backend, on the same particles, jit-compiled; warm-up calls are
excluded from the timings.

* LJ: 3D fluid at density 0.8, smooth cutoff 2.0-2.5, skin 0.3,
  `jax_md.simulate.nve`. The baseline is jax-md's own energy and list in
  its default layout (OrderedSparse); jaxrt runs Dense (forces summed row
  by row, no scatter) and OrderedSparse for every backend (`--list`).
* SPH: 2D periodic box of water at spacing dx, cubic spline h = 1.3 dx,
  summation density + Tait + pressure + viscosity, symplectic Euler.

Prints a table and writes a CSV (device, jax version, jax-md version, git
sha, N, k = mean neighbours per particle, median_ms, repeats, ...) to
``benchmarks/results/<device>/md_step.csv``, through the lead's
``benchmarks/_provenance.py`` when it provides ``write_csv(path, rows)``.

    python benchmarks/md_step.py                      # CPU sizes
    python benchmarks/md_step.py --n 100000 --repeats 50   # a GPU size
"""
from __future__ import annotations

import argparse
import functools
import math
import pathlib
import sys
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax_md import energy as jmd_energy
from jax_md import partition, simulate, space

import jaxrt
from jaxrt.energy import lennard_jones_neighbor_list, sph

warnings.filterwarnings("ignore", message="Explicitly requested dtype float64")

HERE = pathlib.Path(__file__).resolve().parent


def lj_setups():
    """label -> (list factory, energy factory, format) for the LJ step.

    ``jax-md`` rows are jax-md's own energy on jax-md's own list (the
    baseline is its default, OrderedSparse). ``jaxrt:<backend>`` rows use
    jaxrt's energy on jaxrt's list; on Dense lists that energy takes its
    forces row by row (`jaxrt.energy._rows`: no scatter), on OrderedSparse
    it is jax-md's pair sum. ``jax-md list + jaxrt energy`` separates the
    energy's share from the list's.
    """
    setups = {
        "jax-md/OrderedSparse": (partition.neighbor_list,
                                 jmd_energy.lennard_jones_neighbor_list,
                                 partition.OrderedSparse),
        "jax-md/Dense": (partition.neighbor_list,
                         jmd_energy.lennard_jones_neighbor_list,
                         partition.Dense),
        "jax-md list + jaxrt energy/Dense": (partition.neighbor_list,
                                             lennard_jones_neighbor_list,
                                             partition.Dense),
    }
    for b in jaxrt.available_backends():
        list_fn = functools.partial(jaxrt.neighbor_list, backend=b)
        for fmt in (partition.Dense, partition.OrderedSparse):
            setups[f"jaxrt:{b}/{fmt.name}"] = (list_fn,
                                              lennard_jones_neighbor_list, fmt)
    return setups


def sph_setups():
    """label -> (list factory, format) for the SPH step (jaxrt's SPH)."""
    fns = {"jax-md": partition.neighbor_list}
    for b in jaxrt.available_backends():
        fns[f"jaxrt:{b}"] = functools.partial(jaxrt.neighbor_list, backend=b)
    return {f"{name}/{fmt.name}": (fn, fmt) for name, fn in fns.items()
            for fmt in (partition.Dense, partition.OrderedSparse)}


def median_ms(fn, carry, repeats, steps_per_call):
    """Median wall time of one step in ms, and the final carry."""
    carry = jax.block_until_ready(fn(carry))  # warm-up (compile)
    carry = jax.block_until_ready(fn(carry))
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        carry = jax.block_until_ready(fn(carry))
        times.append((time.perf_counter() - t) * 1e3 / steps_per_call)
    return float(np.median(times)), carry


def mean_neighbours(nbrs, n):
    idx = np.asarray(nbrs.idx)
    valid = np.sum(idx[0] < n) if nbrs.format is not partition.Dense else \
        np.sum(idx < n)
    return valid / n * (2 if nbrs.format is partition.OrderedSparse else 1)


def lj_step(setup, n, repeats, steps):
    n_side = round(n ** (1 / 3))
    n = n_side ** 3
    box = (n / 0.8) ** (1 / 3)
    g = np.stack(np.meshgrid(*[np.arange(n_side)] * 3, indexing="ij"), -1)
    R = jnp.asarray(g.reshape(-1, 3) * box / n_side, jnp.float32)
    disp, shift = space.periodic(box)
    list_fn, energy_factory, fmt = setup
    # r_onset / r_cutoff in units of sigma = 1, as jax-md's factory takes them.
    # jax-md's factory builds its own list (and would silently swallow a
    # neighbor_list_fn keyword).
    extra = {} if energy_factory is jmd_energy.lennard_jones_neighbor_list \
        else dict(neighbor_list_fn=list_fn)
    neighbor_fn, energy_fn = energy_factory(
        disp, box, r_onset=2.0, r_cutoff=2.5, dr_threshold=0.3, format=fmt,
        **extra)
    init, apply = simulate.nve(energy_fn, shift, dt=0.005)
    nbrs = neighbor_fn.allocate(R)
    state = init(jax.random.PRNGKey(0), R, 1.0, neighbor=nbrs)

    @jax.jit
    def run(carry):
        def step(carry, _):
            state, nbrs = carry
            state = apply(state, neighbor=nbrs)
            return (state, nbrs.update(state.position)), None
        return lax.scan(step, carry, None, length=steps)[0]

    ms, (_, nbrs) = median_ms(run, (state, nbrs), repeats, steps)
    if nbrs.did_buffer_overflow:
        raise RuntimeError("LJ list overflowed during timing")
    return n, mean_neighbours(nbrs, n), ms


def sph_step(setup, n, repeats, steps):
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
    list_fn, fmt = setup
    neighbor_fn = list_fn(disp, side, float(kernel.cutoff),
                          dr_threshold=0.3 * dx, format=fmt)
    nbrs = neighbor_fn.allocate(R)
    V = jnp.asarray(rng.normal(0, 0.1, (n, 2)), jnp.float32)
    dt = 0.2 * kernel.h / 10.0

    @jax.jit
    def run(carry):
        def step(carry, _):
            R, V, nbrs = carry
            V = V + dt * accel(R, V, nbrs).total
            R = shift(R, dt * V)
            return (R, V, nbrs.update(R)), None
        return lax.scan(step, carry, None, length=steps)[0]

    ms, (_, _, nbrs) = median_ms(run, (R, V, nbrs), repeats, steps)
    if nbrs.did_buffer_overflow:
        raise RuntimeError("SPH list overflowed during timing")
    return n, mean_neighbours(nbrs, n), ms


def write(rows, device, path=None):
    """CSV with provenance columns, via benchmarks/_provenance.py."""
    sys.path.insert(0, str(HERE))
    from _provenance import write_csv
    if path is None:
        return write_csv(rows, "md_step.csv")
    path = pathlib.Path(path)
    return write_csv(rows, path.name, str(path.parent))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=4096,
                        help="particles (rounded to a cube / square)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--steps", type=int, default=20,
                        help="steps per timed call (one lax.scan)")
    parser.add_argument("--only", nargs="*", default=None,
                        help="labels to run (default all; see --list): "
                        "setups like 'jaxrt:bvh/Dense'; a label without '/' "
                        "selects every format of that list")
    parser.add_argument("--systems", nargs="*", default=["lj", "sph"],
                        choices=["lj", "sph"])
    parser.add_argument("--list", action="store_true",
                        help="print the labels and exit")
    parser.add_argument("--out", default=None,
                        help="CSV path (default results/<device>/md_step.csv)")
    args = parser.parse_args()
    device = jax.devices()[0].device_kind
    # device, versions and git sha are added by _provenance.write_csv
    common = dict(repeats=args.repeats)
    jobs = [("lj", label, setup) for label, setup in lj_setups().items()]
    jobs += [("sph", label, setup) for label, setup in sph_setups().items()]
    if args.list:
        print("\n".join(f"{system:4s} {label}" for system, label, _ in jobs))
        return

    def selected(label):
        return not args.only or label in args.only or \
            label.split("/")[0] in args.only

    rows = []
    print(f"{'system':6s} {'setup':36s} {'N':>8s} {'k':>6s} {'ms/step':>9s}")
    for system, label, setup in jobs:
        if system not in args.systems or not selected(label):
            continue
        fn = lj_step if system == "lj" else sph_step
        # jax-md's jitted integrators cache on the list's static fields, and
        # comparing two jax-md lists there fails (their cell_size is an
        # array): start every setup with empty caches.
        jax.clear_caches()
        try:
            n, k, ms = fn(setup, args.n, args.repeats, args.steps)
        except Exception as e:  # noqa: BLE001 - one failure, one row
            print(f"{system:6s} {label:36s} failed: {str(e)[:200]}")
            rows.append(dict(common, system=system, list=label, N=args.n,
                             failed=str(e)[:200]))
            continue
        print(f"{system:6s} {label:36s} {n:8d} {k:6.1f} {ms:9.3f}")
        rows.append(dict(common, system=system, list=label, N=n,
                         k=round(k, 2), median_ms=round(ms, 4)))
    if rows:
        print("wrote", write(rows, device, args.out))


if __name__ == "__main__":
    main()
