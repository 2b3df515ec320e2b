"""`jaxrt.pairs`' options against ASE's ``neighbor_list``: half lists,
pairs sorted by ``i``, self pairs, cutoffs by species (ASE's dict, or a
matrix), Cartesian shifts; and the ASE bridge's dict cutoffs and
``self_interaction``.

Sets of ``(i, j, S)`` are compared exactly (float64). A half list is ASE's
full list with one representative of each unordered pair kept: ``(i, j,
S)`` with ``i < j``, or ``i == j`` and ``S`` lexicographically positive.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

ase = pytest.importorskip("ase")
from ase import Atoms  # noqa: E402
from ase.build import bulk, molecule  # noqa: E402
from ase.neighborlist import neighbor_list as ase_neighbor_list  # noqa: E402

import jaxrt  # noqa: E402



def stored(result) -> list:
    """The (i, j, S) stored, in order."""
    count = min(int(result.count), result.capacity)
    return [(int(a), int(b), *map(int, c)) for a, b, c in zip(
        np.asarray(result.i)[:count], np.asarray(result.j)[:count],
        np.asarray(result.shift)[:count])]


def ase_set(atoms, cutoff, self_interaction=False) -> set:
    i, j, s = ase_neighbor_list("ijS", atoms, cutoff,
                                self_interaction=self_interaction)
    return {(int(a), int(b), *map(int, c)) for a, b, c in zip(i, j, s)}


def representative(p) -> bool:
    i, j, *s = p
    return i < j or (i == j and tuple(s) > (0, 0, 0))


def halved(full: set) -> set:
    return {p for p in full if representative(p)}


def si2():
    return bulk("Si", "diamond", a=5.43)  # 2 atoms, shifts up to 2 at 5 Å


def rock_salt():
    atoms = bulk("NaCl", "rocksalt", a=5.64).repeat((2, 1, 1))
    atoms.rattle(0.05, seed=3)
    return atoms


def cell_of(atoms):
    return np.asarray(atoms.get_cell(complete=True).array)


def run(atoms, cutoff, **kw):
    return jaxrt.pairs(atoms.positions, cutoff, cell=cell_of(atoms),
                       pbc=tuple(bool(p) for p in atoms.pbc), **kw)


def test_half_list_is_one_representative_of_each_pair_sorted_by_i(x64):
    atoms = si2()  # (i, i, S) pairs: the i == j rule is exercised
    full = ase_set(atoms, 5.0)
    got = run(atoms, 5.0, half=True, sort="i")
    pairs = stored(got)
    assert len(pairs) == len(set(pairs)) == int(got.count)
    assert set(pairs) == halved(full)
    assert {(j, i, -a, -b, -c) for i, j, a, b, c in pairs} | set(pairs) \
        == full
    assert any(p[0] == p[1] for p in pairs)
    assert np.all(np.diff(np.asarray(got.i)) >= 0)


def test_sorted_by_i_under_jit_padding_included(x64):
    atoms = rock_salt()
    want = ase_set(atoms, 4.0)
    f = jax.jit(lambda r, c: jaxrt.pairs(r, 4.0, cell=c, capacity=len(want)
                                         + 7, max_shift=1, sort="i"))
    got = f(atoms.positions, cell_of(atoms))
    i = np.asarray(got.i)
    assert set(stored(got)) == want
    # Padding (i = N) at the end: segment_sum(indices_are_sorted=True) holds.
    assert np.all(np.diff(i) >= 0) and np.all(i[len(want):] == len(atoms))
    degree = jax.ops.segment_sum(jnp.ones_like(got.i), got.i, len(atoms),
                                 indices_are_sorted=True)
    np.testing.assert_array_equal(degree, np.bincount(
        [p[0] for p in want], minlength=len(atoms)))


def test_self_interaction_as_ase(x64):
    atoms = si2()
    got = run(atoms, 5.0, self_interaction=True)
    assert set(stored(got)) == ase_set(atoms, 5.0, self_interaction=True)
    half = run(atoms, 5.0, self_interaction=True, half=True, sort="i")
    assert set(stored(half)) == halved(ase_set(atoms, 5.0)) | {
        (0, 0, 0, 0, 0), (1, 1, 0, 0, 0)}


SPECIES_CUTOFFS = {(11, 17): 3.2, (17, 17): 4.2}  # Na-Na: no pairs


def test_cutoffs_by_species_dict_and_matrix_as_ase(x64):
    atoms = rock_salt()
    want = ase_set(atoms, SPECIES_CUTOFFS)
    assert want and all(
        {atoms.numbers[i], atoms.numbers[j]} != {11} for i, j, *_ in want)
    by_dict = run(atoms, SPECIES_CUTOFFS, species=atoms.numbers)
    assert set(stored(by_dict)) == want
    matrix = np.zeros((18, 18))
    matrix[11, 17] = matrix[17, 11] = 3.2
    matrix[17, 17] = 4.2
    f = jax.jit(lambda r, c, m, s: jaxrt.pairs(
        r, m, cell=c, species=s, capacity=len(want) + 3, max_shift=2,
        self_interaction=True))
    got = f(atoms.positions, cell_of(atoms), matrix, atoms.numbers)
    # Self pairs only for the species whose own cutoff is > 0 (Cl), as ASE.
    assert set(stored(got)) == ase_set(atoms, SPECIES_CUTOFFS, True)
    assert int(got.error) == 0


def test_cutoffs_by_species_in_a_molecule_and_bad_species(x64):
    atoms = molecule("CH3CH2OH")
    cutoffs = {(1, 6): 1.2, (6, 6): 1.6, (6, 8): 1.5, (1, 8): 1.0}
    got = jaxrt.pairs(atoms.positions, cutoffs, species=atoms.numbers)
    assert set(stored(got)) == ase_set(atoms, cutoffs)
    with pytest.raises(ValueError, match="species must index"):
        jaxrt.pairs(atoms.positions, {(1, 6): 1.2}, species=atoms.numbers)
    with pytest.raises(ValueError, match="need species="):
        jaxrt.pairs(atoms.positions, cutoffs)
    with pytest.raises(ValueError, match="symmetric"):
        jaxrt.pairs(atoms.positions, np.triu(np.ones((9, 9))),
                    species=atoms.numbers)


def test_cartesian_shifts_beside_integer_shifts(x64):
    atoms = si2()
    got = run(atoms, 5.0)
    h = jnp.asarray(cell_of(atoms))
    np.testing.assert_array_equal(got.shift_vectors(h),
                                  np.asarray(got.shift) @ cell_of(atoms))
    # Differentiable in the cell: d/dh sum(S @ h) = sum of S per row.
    grad = jax.grad(lambda h: jnp.sum(got.shift_vectors(h)))(h)
    np.testing.assert_array_equal(
        grad, np.repeat(np.asarray(got.shift).sum(0)[:, None], 3, axis=1))


def test_ase_bridge_takes_dict_cutoffs_and_self_interaction(x64):
    atoms = rock_salt()
    cutoffs = {("Na", "Cl"): 3.2, ("Cl", "Cl"): 4.2}
    got = jaxrt.ase_neighbor_list("ijS", atoms, cutoffs,
                                  self_interaction=True)
    want = ase_neighbor_list("ijS", atoms, cutoffs, self_interaction=True)
    assert {(a, b, *c) for a, b, c in zip(*[x.tolist() for x in got])} == \
        {(a, b, *c) for a, b, c in zip(*[x.tolist() for x in want])}
    assert np.all(np.diff(got[0]) >= 0)  # sorted by i, as ASE's
    with pytest.raises(NotImplementedError, match="per-atom"):
        jaxrt.ase_neighbor_list("ij", atoms, [1.0] * len(atoms))


def test_free_space_half_list_of_a_random_cloud(x64):
    rng = np.random.default_rng(5)
    atoms = Atoms("H40", positions=rng.uniform(0, 6, (40, 3)))
    got = jaxrt.pairs(atoms.positions, 2.0, half=True)
    assert set(stored(got)) == halved(ase_set(atoms, 2.0))
    assert all(i < j for i, j, *_ in stored(got))


@pytest.mark.parametrize("options", [
    {"self_interaction": True},
    {"half": True, "species": [11, 17, 11, 17],
     "cutoff": {(11, 11): 4.0, (11, 17): 2.82, (17, 17): 5.0}}])
def test_host_search_of_small_systems_equals_the_jitted_program(options,
                                                                x64):
    """Eager calls of small systems search on the host (numpy), jitted ones
    in the program: the same pairs, both sorted by i (the order within an
    atom's pairs is the search's), a pair at the cutoff (to rounding)
    decided alike."""
    atoms = rock_salt()
    atoms.positions[1] = atoms.positions[0] + [2.82, 0, 0]  # |d| = 2.82
    options = dict(options)
    cutoff = options.pop("cutoff", 2.82)
    species = options.pop("species", None)
    r, h = atoms.positions, cell_of(atoms)
    host = jaxrt.pairs(r, cutoff, cell=h, species=species, sort="i",
                       **options)
    sizes = jaxrt.pairs_sizes(r, cutoff, cell=h, species=species, **options)
    program = jax.jit(lambda r, h: jaxrt.pairs(
        r, cutoff, cell=h, species=species, sort="i", capacity=sizes.capacity
        + 3, max_shift=sizes.max_shift, **options))(jnp.asarray(r),
                                                    jnp.asarray(h))
    assert int(program.count) == int(host.count) > 0
    for result in (host, program):
        i = [p[0] for p in stored(result)]
        assert i == sorted(i)
    assert sorted(stored(program)) == sorted(stored(host))


@pytest.mark.parametrize("half", [False, True])
def test_host_search_with_atoms_outside_the_cell_and_a_repeated_cell(half,
                                                                     x64):
    """The host search keeps each cell's stencil vectors between calls; with
    atoms wrapped back into the cell it uses them, with atoms outside (whose
    shifts differ) it does not: ASE's set either way, call after call, and
    a changed cell is not served the old cell's vectors."""
    atoms = si2()
    for pbc in [(True, True, True), (True, False, True)]:
        atoms.pbc = pbc
        for k, move in enumerate([(0, 0, 0), (1, -2, 0), (0, 0, 0)]):
            moved = atoms.copy()
            moved.positions[k % 2] += np.array(move) @ moved.cell.array
            want = ase_set(moved, 5.0)
            got = set(stored(run(moved, 5.0, half=half)))
            assert got == (halved(want) if half else want)
    strained = atoms.copy()
    strained.set_cell(atoms.cell.array * 1.02, scale_atoms=True)
    strained.pbc = True
    for a in (atoms, strained, atoms):
        a.pbc = True
        assert set(stored(run(a, 5.0))) == ase_set(a, 5.0)
