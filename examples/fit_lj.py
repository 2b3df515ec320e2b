"""Recover the sigma and epsilon of a Lennard-Jones fluid by gradient descent.

What is differentiated: the energies and forces of reference snapshots
(force matching), not a simulation. The snapshots come from a short jax-md
Langevin run at the reference parameters (sigma = 1, epsilon = 1) on a jaxrt
neighbour list. The loss compares, for each snapshot, the model's forces
and energy per particle with the reference's:

    loss = mean_s [ mean_i |F_i - F_i^ref|^2 + ((E - E^ref) / N)^2 ]

and is a `lax.scan` over the snapshots with ``nbrs.update(R_s)`` inside the
scan, as in a simulation. One epoch (``--steps`` Adam steps) is one
jit-compiled `lax.scan`. The list's capacity is static, so overflow cannot be
repaired inside the compiled epoch: between epochs the host reads
``did_buffer_overflow`` and, if set, reallocates the list on the snapshot with
the most neighbours and runs the epoch again from the parameters it started
with. The parameters are fitted as logarithms, which keeps them positive.

The cutoff is fixed in absolute units (2.5 sigma_ref), so it does not move
as sigma changes.

    python examples/fit_lj.py            # 2D, N = 144, about 10 s on a CPU
    python examples/fit_lj.py --large    # 3D, N = 4000 (a GPU size)
"""
from __future__ import annotations

import argparse
import functools
import time
import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax import lax
from jax_md import partition, simulate, space

import jaxrt
from jaxrt.energy import lennard_jones_pair_neighbor_list

# jax-md's float64 accumulator warns once per trace when x64 is off.
warnings.filterwarnings("ignore", message="Explicitly requested dtype float64")

SIGMA_REF, EPSILON_REF = 1.0, 1.0
R_ONSET, R_CUTOFF = 2.0, 2.5


class Problem(NamedTuple):
    neighbor_fn: partition.NeighborListFns
    energy_fn: callable
    positions: jax.Array  # float (S, N, dim) snapshots
    energies: jax.Array   # float (S,)
    forces: jax.Array     # float (S, N, dim)


def lattice(n_side: int, dim: int, density: float):
    """Square / cubic lattice of n_side**dim particles; returns (R, box)."""
    box = (n_side ** dim / density) ** (1 / dim)
    g = np.stack(np.meshgrid(*[np.arange(n_side)] * dim, indexing="ij"), -1)
    return jnp.asarray(g.reshape(-1, dim) * box / n_side, jnp.float32), box


def make_reference(*, n_side: int = 12, dim: int = 2, density: float = 0.7,
                   kT: float = 1.0, snapshots: int = 8, every: int = 50,
                   burn_in: int = 300, backend: str = "auto",
                   capacity_multiplier: float = 1.25,
                   format: partition.NeighborListFormat = partition.Sparse,
                   seed: int = 0) -> Problem:
    """Snapshots, energies and forces of an LJ fluid at the reference
    parameters, from a Langevin run on a jaxrt list. The list settings
    (backend, capacity_multiplier, format) are also the fit's."""
    R, box = lattice(n_side, dim, density)
    displacement, shift = space.periodic(box)
    neighbor_fn = jaxrt.neighbor_list(
        displacement, box, R_CUTOFF, dr_threshold=0.4,
        capacity_multiplier=capacity_multiplier, format=format,
        backend=backend)
    # The reference run gets its own, roomier list: it is not under test.
    reference_fn = jaxrt.neighbor_list(
        displacement, box, R_CUTOFF, dr_threshold=0.4,
        capacity_multiplier=1.5, format=format, backend=backend)
    energy_fn = lennard_jones_pair_neighbor_list(
        displacement, sigma=SIGMA_REF, epsilon=EPSILON_REF, r_onset=R_ONSET,
        r_cutoff=R_CUTOFF)
    init, apply = simulate.nvt_langevin(energy_fn, shift, dt=0.005, kT=kT,
                                        gamma=1.0)
    nbrs = reference_fn.allocate(R)
    state = init(jax.random.PRNGKey(seed), R, neighbor=nbrs)

    @functools.partial(jax.jit, static_argnums=2)
    def run(state, nbrs, steps):
        def step(carry, _):
            state, nbrs = carry
            state = apply(state, neighbor=nbrs)
            return (state, nbrs.update(state.position)), None
        return lax.scan(step, (state, nbrs), None, length=steps)[0]

    out = []
    burn_chunks = -(-burn_in // every)  # one compiled chunk length only
    for k in range(burn_chunks + snapshots):
        for attempt in range(1, 6):  # overflow is read between chunks
            new_state, new_nbrs = run(state, nbrs, every)
            if not new_nbrs.did_buffer_overflow:
                break
            # Rerunning the chunk is deterministic: size the list on where it
            # overflowed, with growing slack, or it could overflow forever.
            nbrs = reference_fn.allocate(new_state.position,
                                         extra_capacity=4 * attempt)
        else:
            raise RuntimeError("the reference list keeps overflowing")
        state, nbrs = new_state, new_nbrs
        if k >= burn_chunks:
            out.append(state.position)
    positions = jnp.stack(out)

    @jax.jit
    def labels(R):
        def one(nbrs, R):
            nbrs = nbrs.update(R)
            e, g = jax.value_and_grad(energy_fn)(R, nbrs)
            return nbrs, (e, -g)
        return lax.scan(one, nbrs, R)
    nbrs, (energies, forces) = labels(positions)
    if nbrs.did_buffer_overflow:
        raise RuntimeError("the reference list overflowed while labelling; "
                           "raise capacity_multiplier")
    return Problem(neighbor_fn, energy_fn, positions, energies, forces)


def make_epoch(problem: Problem, optimizer: optax.GradientTransformation,
               steps: int):
    """One jit-compiled epoch: ``steps`` Adam steps, each on the full loss.

    Returns ``epoch(params, opt_state, nbrs) -> (params, opt_state, nbrs,
    losses)`` with params ``{"log_sigma", "log_epsilon"}`` (float scalars) and
    ``losses`` float ``(steps,)``.
    """
    n = problem.positions.shape[1]

    def loss_fn(params, nbrs):
        sigma = jnp.exp(params["log_sigma"])
        epsilon = jnp.exp(params["log_epsilon"])

        def one(nbrs, snapshot):
            R, e_ref, f_ref = snapshot
            nbrs = nbrs.update(R)
            e, g = jax.value_and_grad(problem.energy_fn)(
                R, nbrs, sigma=sigma, epsilon=epsilon)
            err = jnp.mean(jnp.sum((-g - f_ref) ** 2, -1)) + (
                (e - e_ref) / n) ** 2
            return nbrs, err

        nbrs, errs = lax.scan(one, nbrs, (problem.positions, problem.energies,
                                          problem.forces))
        return jnp.mean(errs), nbrs

    @jax.jit
    def epoch(params, opt_state, nbrs):
        def step(carry, _):
            params, opt_state, nbrs = carry
            (loss, nbrs), grads = jax.value_and_grad(loss_fn, has_aux=True)(
                params, nbrs)
            updates, opt_state = optimizer.update(grads, opt_state, params)
            return (optax.apply_updates(params, updates), opt_state,
                    nbrs), loss

        (params, opt_state, nbrs), losses = lax.scan(
            step, (params, opt_state, nbrs), None, length=steps)
        return params, opt_state, nbrs, losses

    return epoch


def fit(problem: Problem, *, sigma0: float = 0.85, epsilon0: float = 1.6,
        epochs: int = 10, steps: int = 20, learning_rate: float = 0.05,
        allocate_on: jax.Array | None = None, verbose: bool = False):
    """Fit log sigma and log epsilon; returns (history, reallocations).

    ``history`` is a list of (loss, sigma, epsilon): the starting point (with
    the first step's loss), then each epoch's end (with its mean loss).
    ``allocate_on``: float ``(N, dim)`` positions to size the first list on
    (default the first snapshot); the tests pass a lattice, whose list is too
    small for the fluid, to exercise the overflow path.
    """
    optimizer = optax.adam(learning_rate)
    params = {"log_sigma": jnp.log(jnp.float32(sigma0)),
              "log_epsilon": jnp.log(jnp.float32(epsilon0))}
    opt_state = optimizer.init(params)
    epoch = make_epoch(problem, optimizer, steps)
    nbrs = problem.neighbor_fn.allocate(
        problem.positions[0] if allocate_on is None else allocate_on)
    history = [(float("nan"), sigma0, epsilon0)]
    reallocations = 0
    for k in range(epochs):
        new = epoch(params, opt_state, nbrs)
        if new[2].did_buffer_overflow:
            # Discard the epoch: its losses used truncated lists.
            nbrs = max((problem.neighbor_fn.allocate(R)
                        for R in problem.positions),
                       key=lambda nb: nb.idx.shape[-1])
            reallocations += 1
            new = epoch(params, opt_state, nbrs)
            if new[2].did_buffer_overflow:
                raise RuntimeError("the list still overflows after "
                                   "reallocation")
        params, opt_state, nbrs, losses = new
        sigma = float(jnp.exp(params["log_sigma"]))
        epsilon = float(jnp.exp(params["log_epsilon"]))
        history.append((float(jnp.mean(losses)), sigma, epsilon))
        if k == 0:
            history[0] = (float(losses[0]), sigma0, epsilon0)
        if verbose:
            print(f"epoch {k:3d}  loss {history[-1][0]:.4e}  "
                  f"sigma {sigma:.4f}  epsilon {epsilon:.4f}")
    return history, reallocations


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=None,
                        help="particles per side (default 12 in 2D, "
                        "16 in 3D with --large)")
    parser.add_argument("--large", action="store_true",
                        help="3D, N = 16**3 = 4096: a GPU size")
    parser.add_argument("--epochs", type=int, default=10)
    parser.add_argument("--backend", default="auto",
                        help=f"one of {jaxrt.available_backends()}")
    args = parser.parse_args()
    dim = 3 if args.large else 2
    n_side = args.n or (16 if args.large else 12)
    t0 = time.perf_counter()
    problem = make_reference(n_side=n_side, dim=dim,
                             density=0.8 if dim == 3 else 0.7,
                             backend=args.backend)
    print(f"{problem.positions.shape[0]} reference snapshots of "
          f"{problem.positions.shape[1]} particles in {dim}D "
          f"({time.perf_counter() - t0:.1f} s)")
    history, reallocations = fit(problem, epochs=args.epochs, verbose=True)
    loss0, sigma0, eps0 = history[0]
    loss, sigma, eps = history[-1]
    print(f"loss {loss0:.3e} -> {loss:.3e}; sigma {sigma0} -> {sigma:.4f} "
          f"(true {SIGMA_REF}); epsilon {eps0} -> {eps:.4f} "
          f"(true {EPSILON_REF}); {reallocations} reallocation(s); "
          f"{time.perf_counter() - t0:.1f} s in all")


if __name__ == "__main__":
    main()
