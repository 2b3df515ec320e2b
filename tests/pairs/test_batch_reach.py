"""Flat batches searched with each system's own reach
(`jaxrt.pairs.reach`): a tiny triclinic cell needing shifts of 3 and more,
anisotropic cells, a large bulk cell and a molecule in one batch, checked
against ASE's ``neighbor_list("ijS")`` system by system (exact sets,
float64), and against the same program with the batch's static reach.
The ``ragged`` fixture makes the own reach's search run wherever it can
(the program otherwise picks it only where it estimates it cheaper).
"""
from __future__ import annotations

import importlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

ase = pytest.importorskip("ase")
from ase import Atoms  # noqa: E402
from ase.build import bulk, molecule  # noqa: E402

import jaxrt  # noqa: E402
from batch_cases import CUTOFF, ase_set, half_of, per_system  # noqa: E402

program = importlib.import_module("jaxrt.pairs.program")
reach = importlib.import_module("jaxrt.pairs.reach")
checks = importlib.import_module("jaxrt.pairs.checks")
ErrorBit = importlib.import_module("jaxrt.pairs.bits").ErrorBit


@pytest.fixture
def ragged(monkeypatch):
    """The own reach's search wherever no cell holds more than a word
    (its estimate against the static stencil's set aside), the search's
    traced programs dropped before and after."""
    monkeypatch.setattr(reach, "RAGGED_SLOT_COST", 0.0)
    program.search.clear_cache()
    yield
    program.search.clear_cache()


def tiny_triclinic():
    """Three atoms in a skewed cell whose heights are well under half the
    cutoff: shifts of 3 and 4 along its axes."""
    rng = np.random.default_rng(7)
    cell = np.array([[1.9, 0.0, 0.0], [1.2, 1.6, 0.0], [-0.7, 0.5, 1.3]])
    return Atoms("H3", positions=rng.uniform(-0.3, 1.3, (3, 3)) @ cell,
                 cell=cell, pbc=True)


def needle():
    """A cell long on two axes and short on one (needs shift 2 there)."""
    rng = np.random.default_rng(8)
    cell = np.diag([9.0, 2.3, 8.5])
    return Atoms("H6", positions=rng.uniform(0, 1, (6, 3)) @ cell,
                 cell=cell, pbc=True)


def reach_batch():
    big = bulk("Cu", "fcc", a=3.61, cubic=True).repeat((3, 3, 3))
    big.rattle(0.05, seed=3)
    near = bulk("Cu", "fcc", a=3.61, cubic=True).repeat((2, 1, 2))
    near.rattle(0.1, seed=4)   # heights just under and over the cutoff
    return [molecule("CH3CH2OH"), tiny_triclinic(), big, needle(), near]


def own_reaches(systems):
    """Each system's own reach as `jaxrt.pairs.reach` computes it, and the
    batch's static reach."""
    h = np.stack([checks.concrete_cell(a.cell.array, tuple(a.pbc))
                  for a in systems])
    pbc = np.array([a.pbc for a in systems])
    height = 1 / np.linalg.norm(np.linalg.inv(h), axis=1)
    static = tuple(int(v) for v in np.max(np.where(pbc, np.ceil(
        CUTOFF / height), 1), axis=0))
    got = reach.system_reach(jnp.asarray(height), jnp.asarray(pbc),
                             jnp.asarray(CUTOFF), static)
    return np.asarray(got), static


def test_system_reach_follows_each_cell():
    systems = reach_batch()
    got, static = own_reaches(systems)
    assert static[0] >= 3 and static[1] >= 3
    assert got[0].tolist() == [1, 1, 1]            # a molecule: free
    assert got[1].tolist() == list(static)          # the tiny cell
    assert got[2].tolist() == [1, 1, 1]            # large bulk
    assert got[3].tolist() == [1, 2, 1]            # the needle
    for (h, p), r in zip(((checks.concrete_cell(a.cell.array, tuple(a.pbc)),
                           tuple(a.pbc)) for a in systems), got):
        need = checks.shift_for_cell(h, CUTOFF, p)
        # Never less than the shifts the cell needs.
        assert all(a >= b for a, b in zip(r, need))


@pytest.mark.parametrize("own", [True, False])
def test_own_reach_batch_matches_ase_per_system_under_jit(x64, own, ragged,
                                                          monkeypatch):
    """The tiny triclinic cell, read with a reach any smaller than its own,
    loses pairs at shifts 3 and 4; the large cell's and the needle's own
    reaches (1, and 2 on one axis) are far below the batch's."""
    monkeypatch.setattr(program, "OWN_REACH", own)
    systems = reach_batch()
    want = [ase_set(a) for a in systems]
    assert any(max(abs(p[2]), abs(p[3]), abs(p[4])) >= 3 for p in want[1])
    batch = jaxrt.batch_from_ase(systems)
    sizes = jaxrt.pairs_batch_sizes(batch.positions, batch.n_node, CUTOFF,
                                    **batch.kwargs)

    @jax.jit
    def edges(r, n_node, cell, pbc, mask):
        return jaxrt.pairs_batch(r, n_node, CUTOFF, cell=cell, pbc=pbc,
                                 graph_mask=mask, **sizes.kwargs)

    got = edges(*batch[:1], *batch[2:])
    assert int(got.error) == 0
    assert per_system(got, batch.n_node, len(systems)) == want
    count = int(got.count)
    assert np.all(np.diff(np.asarray(got.i)[:count]) >= 0)  # sorted by i
    assert np.asarray(got.n_edge)[:len(systems)].tolist() == [
        len(w) for w in want]


def test_own_reach_half_self_and_species(x64, ragged):
    systems = reach_batch()
    batch = jaxrt.batch_from_ase(systems, pad=False)
    half = jaxrt.pairs_batch(batch.positions, batch.n_node, CUTOFF,
                             half=True, **batch.kwargs)
    assert per_system(half, batch.n_node, len(systems)) == [
        half_of(ase_set(a)) for a in systems]
    with_self = jaxrt.pairs_batch(batch.positions, batch.n_node, CUTOFF,
                                  self_interaction=True, **batch.kwargs)
    assert per_system(with_self, batch.n_node, len(systems)) == [
        ase_set(a, self_interaction=True) for a in systems]
    # Cutoffs by species: H-H 2.2, Cu-Cu 3.0, the rest 2.6 (ASE's dict).
    numbers = np.concatenate([a.numbers for a in systems])
    kinds = np.unique(numbers)
    species = np.searchsorted(kinds, numbers).astype(np.int32)
    pick = {(1, 1): 2.2, (29, 29): 3.0}
    matrix = np.array([[pick.get((int(a), int(b)), 2.6) for b in kinds]
                       for a in kinds])
    by_species = jaxrt.pairs_batch(batch.positions, batch.n_node, matrix,
                                   species=species, **batch.kwargs)
    want = []
    for a in systems:
        z = sorted(set(int(v) for v in a.numbers))
        cutoffs = {(p, q): pick.get((p, q), 2.6) for p in z for q in z}
        want.append(ase_set(a, cutoffs))
    assert per_system(by_species, batch.n_node, len(systems)) == want


def test_a_cell_past_a_word_falls_back_to_the_static_stencil(x64, ragged):
    """A molecule of 40 atoms within one cell's width (more than a word in
    a cell) beside the tiny triclinic cell: the static stencil's search,
    the same sets."""
    rng = np.random.default_rng(9)
    blob = Atoms("H40", positions=rng.uniform(0, 3.0, (40, 3)))
    systems = [blob, tiny_triclinic(), needle()]
    batch = jaxrt.batch_from_ase(systems, pad=False)
    got = jaxrt.pairs_batch(batch.positions, batch.n_node, CUTOFF,
                            **batch.kwargs)
    assert per_system(got, batch.n_node, len(systems)) == [
        ase_set(a) for a in systems]


def test_too_small_max_shift_is_flagged(x64, ragged):
    systems = reach_batch()
    batch = jaxrt.batch_from_ase(systems)
    _, static = own_reaches(systems)
    short = tuple(max(r - 1, 1) for r in static)

    @jax.jit
    def edges(r, n_node, cell, pbc, mask):
        return jaxrt.pairs_batch(r, n_node, CUTOFF, cell=cell, pbc=pbc,
                                 graph_mask=mask, capacity=4096,
                                 max_shift=short)

    got = edges(*batch[:1], *batch[2:])
    assert int(got.error) & int(ErrorBit.MAX_SHIFT)


def test_auto_choice_matches_ase(x64):
    """Without the fixture: whichever search the estimate picks."""
    program.search.clear_cache()
    systems = reach_batch()
    batch = jaxrt.batch_from_ase(systems, pad=False)
    got = jaxrt.pairs_batch(batch.positions, batch.n_node, CUTOFF,
                            **batch.kwargs)
    assert per_system(got, batch.n_node, len(systems)) == [
        ase_set(a) for a in systems]
