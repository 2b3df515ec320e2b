"""Train a message-passing potential on EMT energies and forces, its graphs
built by `jaxrt.pairs_batch` (jraph's flat batches) inside the jitted step.

The data (generated here, no download): rattled and strained Cu, Au, Pt and
Ni structures, some of them random alloys of the four, of three kinds that
share every batch:

* bulk: fcc cubic cells of 4 to 32 atoms, periodic on every axis;
* slabs: fcc(111) and fcc(100), 12 atoms, periodic in-plane only, vacuum
  along z;
* clusters: 13-atom icosahedra and 38-atom truncated octahedra in free
  space (ASE's all-zero cell, completed by jaxrt).

ASE's EMT calculator labels them (energies and forces, float64).

The batches: ``batch_size`` structures at a time, concatenated by
`jaxrt.batch_from_ase` (positions ``(N, 3)``, ``n_node``, one cell and
``pbc`` per system, a padding system as jraph's ``pad_with_graphs``), with
the atoms and systems rounded up to size buckets. The edge capacity is a
function of the atom bucket (the densest structure's edges per atom times
the bucket, rounded up to a bucket), so the training step compiles once per
atom bucket, however the structures are shuffled: a handful of programs
for the whole run (the count is printed).

The model (flax): species embeddings, ``layers`` continuous-filter
interaction blocks (a message ``W(r_ij) * h_j`` from a radial basis with a
smooth cutoff, summed on the centre ``i``: the edges come sorted by ``i``),
an MLP readout to an energy per atom plus a learned energy per species:

    E_G = sum_(i in G) e(h_i),   F = -dE/dR  (jax.grad in the positions)

Inside the jitted step, ``jaxrt.pairs_batch(stop_gradient(R), n_node, rc,
cell=, pbc=, graph_mask=, capacity=, max_shift=)`` builds the graph; the
gradient reaches the positions (the forces) and the parameters through
``graph.vectors(R, cell)``. The loss is the energy per atom and the force
errors, squared; optax's Adam. After each step the host checks the
overflow flag (never silent: the capacity was sized on the data). At the
end the force error on held-out structures is printed beside the error of
predicting zero forces.

    python examples/emt_potential.py          # (--quick) ~45 s, 2 CPU cores
    python examples/emt_potential.py --full   # 300 structures, minutes
"""
from __future__ import annotations

import argparse
import time
from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax

import jaxrt
from jaxrt.pairs.checks import bucket

CUTOFF = 5.0
ELEMENTS = ("Cu", "Au", "Pt", "Ni")


# --- data ----------------------------------------------------------------------

def structures(count: int, seed: int = 0):
    """``count`` ASE Atoms, bulk, slabs and clusters in turn (module
    docstring), rattled (0.03 to 0.12 Å) and, where periodic, strained
    (up to 3 %)."""
    from ase.build import bulk, fcc100, fcc111
    from ase.cluster import Icosahedron, Octahedron
    from ase.data import atomic_numbers, reference_states

    rng = np.random.default_rng(seed)
    out = []
    for k in range(count):
        element = ELEMENTS[rng.integers(len(ELEMENTS))]
        a = reference_states[atomic_numbers[element]]["a"]
        kind = k % 3
        if kind == 0:
            reps = [(1, 1, 1), (2, 1, 1), (2, 2, 1), (2, 2, 2)][
                rng.integers(4)]
            atoms = bulk(element, "fcc", a=a, cubic=True).repeat(reps)
        elif kind == 1:
            build = (fcc111, fcc100)[rng.integers(2)]
            atoms = build(element, size=(2, 2, 3), a=a, vacuum=5.0)
        else:
            atoms = (Icosahedron(element, 2, latticeconstant=a)
                     if rng.integers(2) else
                     Octahedron(element, 4, 1, latticeconstant=a))
        if rng.random() < 0.3:  # a random alloy of the four
            atoms.numbers = [atomic_numbers[e] for e in rng.choice(
                ELEMENTS, len(atoms))]
        if atoms.pbc.any():
            strain = np.eye(3) + rng.uniform(-0.03, 0.03, (3, 3))
            strain[:, ~atoms.pbc] = np.eye(3)[:, ~atoms.pbc]
            atoms.set_cell(atoms.cell.array @ strain, scale_atoms=True)
        atoms.rattle(rng.uniform(0.03, 0.12),
                     seed=int(rng.integers(1 << 30)))
        out.append(atoms)
    return out


def label(atoms_list):
    """EMT energies (float64 ``(S,)``) and forces (list of ``(n, 3)``)."""
    from ase.calculators.emt import EMT
    energies, forces = [], []
    for atoms in atoms_list:
        atoms.calc = EMT()
        energies.append(atoms.get_potential_energy())
        forces.append(atoms.get_forces())
        atoms.calc = None
    return np.array(energies), forces


class Batch(NamedTuple):
    """One padded flat batch (arrays; see `make_batch`)."""

    positions: np.ndarray   # float32 (N, 3)
    species: np.ndarray     # int32 (N,), 0 for padding atoms
    n_node: np.ndarray      # int32 (G,)
    cell: np.ndarray        # float32 (G, 3, 3)
    pbc: np.ndarray         # bool (G, 3)
    graph_mask: np.ndarray  # bool (G,)
    energy: np.ndarray      # float32 (G,), 0 for padding systems
    forces: np.ndarray      # float32 (N, 3), 0 for padding atoms


def make_batch(atoms_list, energies, forces, n_graph: int) -> Batch:
    """``atoms_list`` as a flat batch of ``n_graph`` systems (a padding
    system included), its atoms rounded up to a size bucket."""
    from ase.data import atomic_numbers
    flat = jaxrt.batch_from_ase(atoms_list, n_graph=n_graph)
    n = flat.positions.shape[0]
    species = np.zeros(n, np.int32)  # 0: padding, then ELEMENTS' order
    for s, element in enumerate(ELEMENTS, start=1):
        species[flat.numbers == atomic_numbers[element]] = s
    f = np.zeros((n, 3), np.float32)
    count = sum(len(a) for a in atoms_list)
    f[:count] = np.concatenate(forces)
    e = np.zeros(n_graph, np.float32)
    e[:len(atoms_list)] = energies
    return Batch(flat.positions.astype(np.float32), species, flat.n_node,
                 flat.cell.astype(np.float32), flat.pbc, flat.graph_mask, e,
                 f)


def graph_sizes(atoms_list):
    """The densest structure's edges per atom, the stencil reach every
    cell needs, and the graphs themselves (`jaxrt.BatchPairs`, numpy):
    one eager `jaxrt.pairs_batch` over all the structures, float64."""
    with jax.enable_x64(True):
        flat = jaxrt.batch_from_ase(atoms_list, pad=False)
        graphs = jaxrt.pairs_batch(flat.positions, flat.n_node, CUTOFF,
                                   **flat.kwargs)
        sizes = jaxrt.pairs_batch_sizes(flat.positions, flat.n_node, CUTOFF,
                                        **flat.kwargs)
    per_atom = float(np.max(graphs.n_edge / flat.n_node))
    return per_atom, sizes.max_shift, graphs


# --- the model -------------------------------------------------------------------

def _envelope(r):
    """1 at r = 0, 0 with two derivatives at CUTOFF."""
    x = jnp.clip(r / CUTOFF, 0, 1)
    return (1 - x) ** 3 * (1 + 3 * x + 6 * x * x)


class Potential(nn.Module):
    """Energy per atom of a flat batch's atoms."""

    features: int = 32
    n_basis: int = 12
    layers: int = 2

    @nn.compact
    def __call__(self, species, senders, receivers, distances, edge_mask):
        n = species.shape[0]
        centres = jnp.linspace(0.0, CUTOFF, self.n_basis)
        width = CUTOFF / self.n_basis
        basis = jnp.exp(-((distances[:, None] - centres) / width) ** 2) * (
            _envelope(distances) * edge_mask)[:, None]
        h = nn.Embed(len(ELEMENTS) + 1, self.features)(species)
        for _ in range(self.layers):
            filt = nn.Dense(self.features)(
                nn.silu(nn.Dense(self.features)(basis)))
            # Padding edges have a zero basis, but the filter's biases
            # would still give them a message: mask the messages.
            msg = filt * nn.Dense(self.features, use_bias=False)(h)[
                receivers] * edge_mask[:, None]
            agg = jax.ops.segment_sum(msg, senders, n + 1,
                                      indices_are_sorted=True)[:n]
            h = h + nn.Dense(self.features)(nn.silu(agg))
        e = nn.Dense(1)(nn.silu(nn.Dense(self.features)(h)))[:, 0]
        return e + nn.Embed(len(ELEMENTS) + 1, 1)(species)[:, 0]


def _atoms_of(batch: Batch):
    """Each atom's system (int ``(N,)``, ``G`` past the systems) and
    whether it is a real atom (bool ``(N,)``)."""
    n, g = batch.positions.shape[0], batch.n_node.shape[0]
    node_graph = jnp.repeat(jnp.arange(g), batch.n_node,
                            total_repeat_length=n)
    node_graph = jnp.where(jnp.arange(n) < jnp.sum(batch.n_node),
                           node_graph, g)
    real = (node_graph < g) & batch.graph_mask[jnp.minimum(node_graph,
                                                            g - 1)]
    return node_graph, real


def energies_and_forces(model, params, batch: Batch, capacity: int,
                        max_shift):
    """Energies per system (G,), forces (N, 3), the graph's error bits."""
    g = batch.n_node.shape[0]
    node_graph, real_atom = _atoms_of(batch)
    graph = jaxrt.pairs_batch(
        jax.lax.stop_gradient(batch.positions), batch.n_node, CUTOFF,
        cell=batch.cell, pbc=batch.pbc, graph_mask=batch.graph_mask,
        capacity=capacity, max_shift=max_shift)

    def total(positions):
        d = graph.distances(positions, batch.cell)
        atom_e = model.apply(params, batch.species, graph.senders,
                             graph.receivers, d, graph.valid)
        per_graph = jax.ops.segment_sum(
            jnp.where(real_atom, atom_e, 0), node_graph, g)
        return jnp.sum(per_graph), per_graph

    (_, per_graph), grad = jax.value_and_grad(total, has_aux=True)(
        batch.positions)
    return per_graph, -grad, graph.error


def make_loss(model, capacity, max_shift, force_weight=4.0):
    def loss(params, batch: Batch):
        energy, forces, error = energies_and_forces(model, params, batch,
                                                    capacity, max_shift)
        _, real_atom = _atoms_of(batch)
        atoms = jnp.maximum(batch.n_node, 1)
        e_err = jnp.where(batch.graph_mask,
                          ((energy - batch.energy) / atoms) ** 2, 0)
        f_err = jnp.where(real_atom[:, None], forces - batch.forces, 0) ** 2
        e_mse = jnp.sum(e_err) / jnp.sum(batch.graph_mask)
        f_mse = jnp.sum(f_err) / (3 * jnp.sum(real_atom))
        return e_mse + force_weight * f_mse, (e_mse, f_mse, error)
    return loss


# --- training ----------------------------------------------------------------------

class Run(NamedTuple):
    history: list        # [(epoch, train loss, energy/atom MSE, force MSE)]
    programs: int        # training-step programs compiled (traces)
    buckets: set         # (atoms, edge capacity) of the training batches
    steps: int           # training steps taken
    test_force_rmse: float  # eV/Å, held-out structures
    zero_force_rmse: float  # predicting zero forces on the same atoms
    params: dict
    predict: callable    # predict(params, batch) -> energies, forces, error
    test_batch: Batch    # the held-out structures, one batch
    data: tuple          # (atoms, energies, forces, graphs, max_shift)


def train(n_structures: int = 60, epochs: int = 30, batch_size: int = 6,
          test_fraction: float = 0.2, learning_rate: float = 3e-3,
          seed: int = 0, log=print) -> Run:
    """Generate, label, train and evaluate (module docstring)."""
    t = time.perf_counter()
    atoms = structures(n_structures, seed)
    energies, forces = label(atoms)
    per_atom, reach, graphs = graph_sizes(atoms)
    n_test = max(1, int(round(test_fraction * n_structures)))
    train_ids = np.arange(n_structures - n_test)
    test_ids = np.arange(n_structures - n_test, n_structures)
    log(f"{n_structures} structures ({len(train_ids)} train, {n_test} "
        f"held out), {sum(len(a) for a in atoms)} atoms, labelled and "
        f"sized in {time.perf_counter() - t:.1f} s; up to {per_atom:.0f} "
        f"edges per atom, max_shift {reach}")

    def capacity_for(n_atoms):
        # Every real atom has at most `per_atom` edges: the capacity is a
        # function of the atom bucket, so one program per atom bucket.
        return bucket(int(np.ceil(per_atom * n_atoms)))

    def batch_of(ids):
        return make_batch([atoms[k] for k in ids], energies[ids],
                          [forces[k] for k in ids], bucket(batch_size + 1))

    model = Potential()
    params = model.init(jax.random.PRNGKey(seed), np.zeros(4, np.int32),
                        np.zeros(4, np.int32), np.zeros(4, np.int32),
                        np.ones(4, np.float32), np.ones(4, bool))
    opt = optax.adam(learning_rate)
    opt_state = opt.init(params)
    traces = [0]

    def step(params, opt_state, batch, capacity):
        traces[0] += 1  # runs once per trace: counts the programs
        loss = make_loss(model, capacity, reach)
        (value, aux), grads = jax.value_and_grad(loss, has_aux=True)(
            params, batch)
        updates, opt_state = opt.update(grads, opt_state)
        return optax.apply_updates(params, updates), opt_state, value, aux

    step = jax.jit(step, static_argnames="capacity")
    predict = jax.jit(energies_and_forces, static_argnums=(0, 3, 4))

    def predict_batch(params, batch):
        return predict(model, params, batch,
                       capacity_for(batch.positions.shape[0]), reach)

    rng = np.random.default_rng(seed + 1)
    history, buckets, taken = [], set(), 0
    for epoch in range(epochs):
        sums = np.zeros(3)
        order = rng.permutation(train_ids)
        chunks = [order[s:s + batch_size]
                  for s in range(0, len(order), batch_size)]
        for ids in chunks:
            batch = batch_of(ids)
            capacity = capacity_for(batch.positions.shape[0])
            buckets.add((batch.positions.shape[0], capacity))
            params, opt_state, value, (e_mse, f_mse, error) = step(
                params, opt_state, batch, capacity=capacity)
            if int(error):  # never silent (the capacity was sized on data)
                raise jaxrt.PairsError(f"a batch's graph overflowed: error "
                                       f"bits {int(error)}")
            sums += (float(value), float(e_mse), float(f_mse))
            taken += 1
        history.append((epoch, *(sums / len(chunks))))
        log(f"epoch {epoch:3d}  loss {history[-1][1]:9.4g}  E/atom MSE "
            f"{history[-1][2]:9.4g}  F MSE {history[-1][3]:9.4g}  "
            f"({traces[0]} programs, {time.perf_counter() - t:.0f} s)")

    # The held-out structures in one batch: one more program.
    test = make_batch([atoms[k] for k in test_ids], energies[test_ids],
                      [forces[k] for k in test_ids], bucket(n_test + 1))
    _, f, error = predict_batch(params, test)
    if int(error):
        raise jaxrt.PairsError("the held-out graph overflowed")
    real = int(np.sum(test.n_node[test.graph_mask]))
    f, ref = np.asarray(f)[:real], test.forces[:real]
    return Run(history, traces[0], buckets, taken,
               float(np.sqrt(np.mean((f - ref) ** 2))),
               float(np.sqrt(np.mean(ref ** 2))), params, predict_batch,
               test, (atoms, energies, forces, graphs, reach))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--full", action="store_true",
                        help="300 structures, 60 epochs (minutes on a CPU)")
    parser.add_argument("--quick", action="store_true",
                        help="the default: 60 structures, 30 epochs")
    parser.add_argument("--structures", type=int, default=None)
    parser.add_argument("--epochs", type=int, default=None)
    args = parser.parse_args(argv)
    n, epochs = (300, 60) if args.full else (60, 30)
    t = time.perf_counter()
    run = train(args.structures or n, args.epochs or epochs)
    print(f"{run.steps} steps, {run.programs} training programs compiled "
          f"for {len(run.buckets)} (atoms, edges) buckets: "
          f"{sorted(run.buckets)}")
    print(f"loss {run.history[0][1]:.4g} -> {run.history[-1][1]:.4g}; "
          f"held-out force RMSE {run.test_force_rmse:.3f} eV/Å (zero forces: "
          f"{run.zero_force_rmse:.3f}); {time.perf_counter() - t:.0f} s")


if __name__ == "__main__":
    main()
