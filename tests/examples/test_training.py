"""The training loop of examples/fit_lj.py: a jit-compiled optax loop whose
loss scans over snapshots with ``nbrs.update`` inside, overflow handled
between epochs. It must lower its loss and move sigma and epsilon toward the
reference values in a few epochs."""
from __future__ import annotations

import importlib.util
import pathlib

import numpy as np
from jax_md import partition

_PATH = pathlib.Path(__file__).resolve().parents[2] / "examples" / "fit_lj.py"
_spec = importlib.util.spec_from_file_location("fit_lj", _PATH)
fit_lj = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(fit_lj)


def test_fit_recovers_sigma_and_epsilon_and_survives_overflow():
    # Dense with no spare capacity, sized on a perfect lattice (every row
    # holds exactly 20 neighbours): the fluid's rows are longer, so the first
    # epoch overflows and the loop must reallocate and redo it.
    problem = fit_lj.make_reference(n_side=8, dim=2, density=0.7,
                                    snapshots=4, every=30, burn_in=150,
                                    capacity_multiplier=1.0,
                                    format=partition.Dense)
    lattice, _ = fit_lj.lattice(8, 2, 0.7)
    history, reallocations = fit_lj.fit(problem, epochs=3, steps=15,
                                        learning_rate=0.05,
                                        allocate_on=lattice)
    assert reallocations >= 1
    (loss0, s0, e0), (loss, s, e) = history[0], history[-1]
    assert np.isfinite(loss) and loss < 0.2 * loss0, history
    assert abs(s - fit_lj.SIGMA_REF) < 0.5 * abs(s0 - fit_lj.SIGMA_REF), (
        history)
    assert abs(e - fit_lj.EPSILON_REF) < 0.8 * abs(e0 - fit_lj.EPSILON_REF), (
        history)
