"""NVE molecular dynamics of a Lennard-Jones fluid with a jaxrt neighbour list.

jax-md does the physics (`simulate.nve`, velocity Verlet); jaxrt builds the
list (`jaxrt.neighbor_list`, passed as ``neighbor_list_fn``) and
`jaxrt.energy.lennard_jones_neighbor_list` gives the energy, smoothly
truncated between r_onset = 2.0 and r_cutoff = 2.5 (so forces are continuous
and energy is conserved to the integrator's accuracy). The run is chunks of
``lax.scan`` with ``nbrs.update`` at every step; between chunks the host
checks for overflow and, if the list overflowed, reallocates it and redoes
the chunk.

Printed: total energy per particle along the run, and its drift: the
largest |E(t) - E(0)| / N and the slope of a straight-line fit.

    python examples/lj_md.py                 # N = 512, 2000 steps, CPU
    python examples/lj_md.py --large         # N = 32**3 = 32768 (a GPU size)
    python examples/lj_md.py --n 12 --steps 5000 --backend cell
"""
from __future__ import annotations

import argparse
import functools
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax_md import partition, quantity, simulate, space

import jaxrt
from jaxrt.energy import lennard_jones_neighbor_list

# jax-md's float64 accumulator warns once per trace when x64 is off.
warnings.filterwarnings("ignore", message="Explicitly requested dtype float64")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=None,
                        help="particles per side of the initial cubic "
                        "lattice (default 8: N = 512)")
    parser.add_argument("--large", action="store_true",
                        help="n = 32 (N = 32768) unless --n is given")
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--chunk", type=int, default=100,
                        help="steps per compiled chunk (overflow is checked "
                        "between chunks)")
    parser.add_argument("--dt", type=float, default=0.005)
    parser.add_argument("--density", type=float, default=0.8)
    parser.add_argument("--kT", type=float, default=1.0,
                        help="initial temperature")
    parser.add_argument("--backend", default="auto",
                        help=f"one of {jaxrt.available_backends()}")
    parser.add_argument("--format", default="OrderedSparse",
                        choices=["Dense", "Sparse", "OrderedSparse"])
    args = parser.parse_args()

    n_side = args.n or (32 if args.large else 8)
    n = n_side ** 3
    box = (n / args.density) ** (1 / 3)
    g = np.stack(np.meshgrid(*[np.arange(n_side)] * 3, indexing="ij"), -1)
    R = jnp.asarray(g.reshape(-1, 3) * box / n_side + 0.25, jnp.float32)

    displacement, shift = space.periodic(box)
    neighbor_fn, energy_fn = lennard_jones_neighbor_list(
        displacement, box, r_onset=2.0, r_cutoff=2.5, dr_threshold=0.3,
        format=getattr(partition, args.format),
        neighbor_list_fn=functools.partial(jaxrt.neighbor_list,
                                           backend=args.backend))
    init, apply = simulate.nve(energy_fn, shift, dt=args.dt)

    t0 = time.perf_counter()
    nbrs = neighbor_fn.allocate(R)
    state = init(jax.random.PRNGKey(0), R, args.kT, neighbor=nbrs)

    def total_energy(state, nbrs):
        return (energy_fn(state.position, nbrs)
                + quantity.kinetic_energy(momentum=state.momentum,
                                          mass=state.mass))

    @jax.jit
    def chunk(state, nbrs):
        def step(carry, _):
            state, nbrs = carry
            state = apply(state, neighbor=nbrs)
            nbrs = nbrs.update(state.position)
            return (state, nbrs), None
        (state, nbrs), _ = lax.scan(step, (state, nbrs), None,
                                    length=args.chunk)
        return state, nbrs, total_energy(state, nbrs)

    energies = [float(jax.jit(total_energy)(state, nbrs))]
    reallocations = 0
    n_chunks = max(1, args.steps // args.chunk)
    for k in range(n_chunks):
        new_state, new_nbrs, e = chunk(state, nbrs)
        if new_nbrs.did_buffer_overflow:
            # The chunk ran on a truncated list: grow the list, redo it.
            nbrs = neighbor_fn.allocate(state.position)
            reallocations += 1
            new_state, new_nbrs, e = chunk(state, nbrs)
            if new_nbrs.did_buffer_overflow:
                raise RuntimeError("the list overflowed twice in one chunk; "
                                   "raise capacity_multiplier")
        state, nbrs = new_state, new_nbrs
        energies.append(float(e))
        if k % max(1, n_chunks // 10) == 0 or k == n_chunks - 1:
            kT = float(quantity.temperature(momentum=state.momentum,
                                            mass=state.mass))
            print(f"step {(k + 1) * args.chunk:6d}  "
                  f"E/N {energies[-1] / n:+.6f}  kT {kT:.4f}")
    elapsed = time.perf_counter() - t0
    jaxrt.check(nbrs)  # any other error bit (e.g. a non-finite position)

    e = np.asarray(energies) / n
    t = np.arange(len(e)) * args.chunk * args.dt
    slope = np.polyfit(t, e, 1)[0]
    print(f"N = {n}, {n_chunks * args.chunk} steps of dt = {args.dt} on "
          f"backend {args.backend!r}, {reallocations} reallocation(s), "
          f"{elapsed:.1f} s")
    print(f"energy drift: max |E(t) - E(0)| / N = {np.abs(e - e[0]).max():.2e}"
          f", slope {slope:+.2e} per particle per time unit")


if __name__ == "__main__":
    main()
