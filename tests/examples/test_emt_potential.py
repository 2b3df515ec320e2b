"""examples/emt_potential.py at a tiny size: its flat batches' graphs are
ASE's, the loss falls, the training step compiles one program per atom
bucket, and the forces it trains on are minus the gradient of its energy."""
from __future__ import annotations

import importlib.util
import pathlib
import sys

import numpy as np
import pytest
from ase.neighborlist import neighbor_list

_PATH = (pathlib.Path(__file__).resolve().parents[2] / "examples"
         / "emt_potential.py")


def load_example():
    """The example as a module (imported here, not at collection: flax)."""
    spec = importlib.util.spec_from_file_location("emt_potential", _PATH)
    module = importlib.util.module_from_spec(spec)
    # flax's modules are dataclasses, which look their module up by name.
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


# Compiling the model's training step dominates (about 20 s on 2 cores);
# tests/pairs/test_batch.py keeps the flat batches against ASE by default.
@pytest.mark.slow
def test_emt_potential_trains_on_ase_graphs_with_one_program_per_bucket():
    example = load_example()
    # 10 structures: 8 train (one batch), 2 held out (a cluster, a bulk).
    run = example.train(n_structures=10, epochs=10, batch_size=8,
                        learning_rate=1e-2, log=lambda *_: None)
    atoms, _, _, graphs, reach = run.data

    # The graphs the capacity was sized on are ASE's, system by system,
    # clusters (zero cell) and slabs (pbc on x, y) included.
    ends = np.cumsum([len(a) for a in atoms])
    edge_ends = np.cumsum(graphs.n_edge)
    for k, a in enumerate(atoms):
        lo, e0 = ends[k] - len(a), edge_ends[k] - graphs.n_edge[k]
        got = {(int(i) - lo, int(j) - lo, *map(int, s)) for i, j, s in zip(
            graphs.i[e0:edge_ends[k]], graphs.j[e0:edge_ends[k]],
            graphs.shift[e0:edge_ends[k]])}
        i, j, s = neighbor_list("ijS", a, example.CUTOFF)
        assert got == {(int(x), int(y), *map(int, z))
                       for x, y, z in zip(i, j, s)}, k
    assert reach == (2, 2, 2)  # 4-atom cubic cells need two images

    # One training program per (atoms, edges) bucket, however shuffled.
    assert run.programs == len(run.buckets) == 1, run.buckets
    assert run.steps == 10
    loss0, loss = run.history[0][1], run.history[-1][1]
    assert np.isfinite(loss) and loss < 0.5 * loss0, run.history
    assert run.test_force_rmse < run.zero_force_rmse

    # Forces are -dE/dR: central differences of the total energy, on the
    # first atom of the held-out cluster and of the held-out bulk cell (its
    # images through the lattice shifts). float32: h = 1e-2 Å keeps the
    # rounding (~1e-6 eV * |E| / h) and the h^2 term under 1e-2 eV/Å.
    batch = run.test_batch
    _, forces, error = run.predict(run.params, batch)
    assert int(error) == 0
    h = 1e-2
    for atom in (0, int(batch.n_node[0])):
        for axis in range(3):
            energy = []
            for sign in (1, -1):
                moved = batch.positions.copy()
                moved[atom, axis] += sign * h
                e, _, _ = run.predict(run.params,
                                      batch._replace(positions=moved))
                energy.append(float(np.sum(np.asarray(e)[batch.graph_mask])))
            fd = -(energy[0] - energy[1]) / (2 * h)
            assert abs(fd - float(forces[atom, axis])) < 2e-2, (
                atom, axis, fd, float(forces[atom, axis]))
