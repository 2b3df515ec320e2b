"""Train a tiny machine-learned potential whose graph `jaxrt.pairs` builds
inside the jitted loss.

The data: periodic silicon snapshots of three sizes, padded to one batch
(``mask`` marks the real atoms): the 2-atom primitive cell (heights 3.1 Å,
so a 5 Å cutoff reaches two images of every atom along each axis: the case
an index-only list cannot hold), the 8-atom cubic cell and a 16-atom 2×1×1
supercell, each rattled and randomly strained (triclinic). Their energies
and forces come from a reference embedded-atom potential (a Morse pair term
plus ``-sqrt`` of a density) evaluated on ASE's ``neighbor_list("ijS")``
graph, so the reference shares no code with the model's graph.

The model: a message-passing step in plain JAX. Each pair sends a message
``g(r_ij)`` (radial basis times a smooth cutoff) that is summed per atom
into a density; each atom's energy is a small MLP of its density, plus a
pair term expanded in the same basis:

    E = sum_i mlp(rho_i) + 1/2 sum_(i, j, S) phi(r_ij),
    rho_i = sum_(j, S) g(r_ij),   r_ij = |R[j] - R[i] + S @ cell|

The loss (energies per atom and forces, forces by ``jax.grad``) is
``jax.jit``-compiled with ``jax.vmap`` over the batch; inside it,
``jaxrt.pairs(R, 5.0, cell=cell, mask=mask, **sizes.kwargs)`` builds every
system's graph with the static sizes `jaxrt.pairs_sizes` measured on the
data set. The gradient reaches the model's parameters through
``pairs.distances`` (positions and cell stay differentiable: stress would
come the same way). After training the host checks that no graph
overflowed.

    python examples/graph_energy.py            # about 15 s on 2 CPU cores
    python examples/graph_energy.py --steps 2000
"""
from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

import jaxrt

CUTOFF = 5.0
N_BASIS = 8


# --- reference data -------------------------------------------------------------

def _cutoff_fn(r):
    """Smooth cutoff, 1 at r = 0 and 0 with two derivatives at CUTOFF."""
    x = jnp.clip(r / CUTOFF, 0, 1)
    return (1 - x) ** 3 * (1 + 3 * x + 6 * x * x)


def reference_energy(vectors, valid, i, mask):
    """The reference EAM energy of one system from its pair vectors (full
    list: both directions; ``valid`` marks the real ones, ``i`` their
    centres) and its real atoms ``mask``."""
    r = jnp.where(valid, jnp.linalg.norm(jnp.where(valid[:, None], vectors,
                                                   1.0), axis=1), CUTOFF)
    fc = _cutoff_fn(r)
    morse = 0.6 * (jnp.exp(-2.6 * (r - 2.35)) - 2 * jnp.exp(-1.3 * (r - 2.35)))
    rho = jax.ops.segment_sum(jnp.exp(-1.5 * (r - 2.35)) * fc, i,
                              mask.shape[0])
    return 0.5 * jnp.sum(morse * fc) - 2.0 * jnp.sum(
        jnp.where(mask, jnp.sqrt(rho + 1e-12), 0))


def snapshots(count: int, seed: int = 0):
    """ASE Atoms: rattled, strained Si cells of 2, 8 and 16 atoms."""
    from ase.build import bulk
    rng = np.random.default_rng(seed)
    kinds = [bulk("Si", "diamond", a=5.43),
             bulk("Si", "diamond", a=5.43, cubic=True),
             bulk("Si", "diamond", a=5.43, cubic=True).repeat((2, 1, 1))]
    out = []
    for s in range(count):
        atoms = kinds[s % len(kinds)].copy()
        strain = np.eye(3) + rng.uniform(-0.04, 0.04, (3, 3))
        atoms.set_cell(atoms.cell.array @ strain, scale_atoms=True)
        atoms.rattle(0.08, seed=int(rng.integers(1 << 30)))
        out.append(atoms)
    return out


def label(atoms_list):
    """Energies (B,) and forces (B, N, 3) of the reference on ASE's graphs
    (float64), padded to the largest system and graph: one program."""
    from ase.neighborlist import neighbor_list
    graphs = [neighbor_list("ijS", a, CUTOFF) for a in atoms_list]
    p = max(len(g[0]) for g in graphs)
    pos, cells, mask, _, _ = batch(atoms_list)
    i, j = (np.zeros((len(graphs), p), int) for _ in range(2))
    s = np.zeros((len(graphs), p, 3))
    valid = np.zeros((len(graphs), p), bool)
    for k, (gi, gj, gs) in enumerate(graphs):
        i[k, :len(gi)], j[k, :len(gi)], s[k, :len(gi)] = gi, gj, gs
        valid[k, :len(gi)] = True

    def energy(r, cell, i, j, s, valid, mask):
        return reference_energy(r[j] - r[i] + s @ cell, valid, i, mask)

    both = jax.jit(jax.vmap(jax.value_and_grad(energy)))
    energies, grad = both(pos, cells, i, j, s, valid, mask)
    return np.asarray(energies), -np.asarray(grad)


def batch(atoms_list):
    """Padded arrays: positions (B, N, 3), cells (B, 3, 3), mask (B, N),
    atoms per system (B,), and N."""
    n = max(len(a) for a in atoms_list)
    pos = np.zeros((len(atoms_list), n, 3))
    mask = np.zeros((len(atoms_list), n), bool)
    for k, a in enumerate(atoms_list):
        pos[k, :len(a)] = a.positions
        pos[k, len(a):] = a.positions[0]  # padding: anywhere finite
        mask[k, :len(a)] = True
    cells = np.stack([a.cell.array for a in atoms_list])
    return pos, cells, mask, mask.sum(1), n


# --- the model --------------------------------------------------------------------

def init(key):
    k1, k2, k3 = jax.random.split(key, 3)
    return {"g": 0.1 * jax.random.normal(k1, (N_BASIS,)),
            "phi": 0.1 * jax.random.normal(k2, (N_BASIS,)),
            "w1": jax.random.normal(k3, (1, 16)) / 4, "b1": jnp.zeros(16),
            "w2": jnp.zeros((16, 1)), "b2": jnp.zeros(1)}


def _basis(r):
    centres = jnp.linspace(1.5, CUTOFF, N_BASIS)
    return jnp.exp(-2.0 * (r[:, None] - centres) ** 2) * _cutoff_fn(r)[:, None]


def model_energy(params, positions, cell, mask, sizes):
    """One system: ``positions`` (N, 3) float, ``cell`` (3, 3), ``mask``
    (N,); the graph built here, inside whatever jit / vmap / grad calls it."""
    graph = jaxrt.pairs(jax.lax.stop_gradient(positions), CUTOFF, cell=cell,
                        mask=mask, **sizes.kwargs)
    r = graph.distances(positions, cell)
    basis = _basis(r) * graph.valid[:, None]
    n = positions.shape[0]
    # Messages summed per atom; padding entries (i = N) go to a segment
    # that is dropped.
    rho = jax.ops.segment_sum(basis @ params["g"], graph.i, n + 1)[:n]
    hidden = jnp.tanh(rho[:, None] @ params["w1"] + params["b1"])
    atom_e = (hidden @ params["w2"] + params["b2"])[:, 0]
    energy = jnp.sum(jnp.where(mask, atom_e, 0)) + 0.5 * jnp.sum(
        basis @ params["phi"])
    return energy, graph.overflow


def make_loss(sizes, force_weight=1.0):
    def one(params, pos, cell, mask, e_ref, f_ref, n_atoms):
        (energy, overflow), grad = jax.value_and_grad(
            model_energy, argnums=1, has_aux=True)(params, pos, cell, mask,
                                                   sizes)
        f_err = jnp.sum(jnp.where(mask[:, None], -grad - f_ref, 0) ** 2) / (
            3 * n_atoms)
        return ((energy - e_ref) / n_atoms) ** 2, f_err, overflow

    def loss(params, data):
        e_err, f_err, overflow = jax.vmap(one, (None, 0, 0, 0, 0, 0, 0))(
            params, *data)
        return jnp.mean(e_err) + force_weight * jnp.mean(f_err), (
            jnp.mean(e_err), jnp.mean(f_err), jnp.any(overflow))
    return loss


def train(steps: int = 300, n_train: int = 24, seed: int = 0,
          learning_rate: float = 0.02, log_every: int = 50):
    """Returns the history [(step, loss, energy MSE, force MSE)], the
    parameters and the static sizes. Run with x64 on (`main` turns it on):
    the reference labels are float64."""
    atoms = snapshots(n_train, seed)
    energies, frc = label(atoms)
    pos, cells, mask, n_atoms, _ = batch(atoms)
    # Energies are fitted relative to the mean energy per atom.
    mean = float(np.mean(energies / n_atoms))
    data = tuple(jnp.asarray(x) for x in (
        pos, cells, mask, energies - mean * n_atoms, frc, n_atoms))
    sizes = jaxrt.pairs_sizes(pos, CUTOFF, cell=cells, mask=mask)
    loss = make_loss(sizes)
    opt = optax.adam(learning_rate)
    params = init(jax.random.PRNGKey(seed))
    state = opt.init(params)

    @jax.jit
    def step(params, state):
        (value, aux), grads = jax.value_and_grad(loss, has_aux=True)(
            params, data)
        updates, state = opt.update(grads, state)
        return optax.apply_updates(params, updates), state, value, aux

    history = []
    for k in range(steps + 1):
        params, state, value, (e_mse, f_mse, overflow) = step(params, state)
        if k % log_every == 0 or k == steps:
            history.append((k, float(value), float(e_mse), float(f_mse)))
            if bool(overflow):  # never silent: sizes were measured on data
                raise jaxrt.PairsError("a graph overflowed during training")
    return history, params, sizes


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--snapshots", type=int, default=24)
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    t = time.perf_counter()
    history, _, sizes = train(args.steps, args.snapshots)
    print(f"graphs: capacity {sizes.capacity} pairs per system, "
          f"max_shift {sizes.max_shift} (2-atom cells reach 2 images)")
    print(f"{'step':>6} {'loss':>10} {'E/atom MSE':>12} {'F MSE':>10}")
    for k, value, e, f in history:
        print(f"{k:6d} {value:10.4g} {e:12.4g} {f:10.4g}")
    print(f"{time.perf_counter() - t:.1f} s; loss {history[0][1]:.3g} -> "
          f"{history[-1][1]:.3g}")


if __name__ == "__main__":
    main()
