"""`jaxrt.pairs`: pairs with lattice shifts, checked against ASE's
``neighbor_list("ijS", ...)`` and a float64 brute force over every image.

Sets of ``(i, j, S)`` are compared exactly (integers). Distances: float64
within 1e-12 Å of ASE's (both compute ``R[j] - R[i] + S @ cell`` from the
same float64 numbers; only the order of the three products in ``S @ cell``
may differ: a few ulps of the ~10-30 Å involved); float32 within 16 ulps of
the largest magnitude involved (positions plus shift vectors: the inputs
are rounded to float32 once, each difference and product rounds once more,
a handful of ulps in all). A float32 set equals ASE's except for pairs
whose float64 distance lies within float32 rounding of the cutoff; the
random systems here have none (checked).
"""
from __future__ import annotations

import importlib
import importlib.util
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

ase = pytest.importorskip("ase")
from ase import Atoms  # noqa: E402
from ase.build import bulk, fcc111, molecule  # noqa: E402
from ase.neighborlist import neighbor_list as ase_neighbor_list  # noqa: E402

import jaxrt  # noqa: E402
from oracle import brute_pairs_shifts  # noqa: E402

pairs_module = importlib.import_module("jaxrt.pairs.search")
checks_module = importlib.import_module("jaxrt.pairs.checks")



def keys(result) -> list:
    """The stored (i, j, S) in order (the first min(count, capacity))."""
    count = min(int(result.count), result.capacity)
    return [(int(a), int(b), *map(int, c)) for a, b, c in zip(
        np.asarray(result.i)[:count], np.asarray(result.j)[:count],
        np.asarray(result.shift)[:count])]


def as_set(result) -> set:
    """The stored pairs, and ("pad", smallest padded i) if any slot is
    padding (so a padding entry other than N shows up)."""
    count = min(int(result.count), result.capacity)
    i = np.asarray(result.i)
    j = np.asarray(result.j)
    s = np.asarray(result.shift)
    n_pad = i[count:]
    return {(int(a), int(b), *map(int, c)) for a, b, c in
            zip(i[:count], j[:count], s[:count])} | (
        set() if len(n_pad) == 0 else {("pad", int(n_pad.min()))})


def ase_set(atoms, cutoff) -> set:
    i, j, s = ase_neighbor_list("ijS", atoms, cutoff)
    return {(int(a), int(b), *map(int, c)) for a, b, c in zip(i, j, s)}


def run(atoms, cutoff, dtype=np.float64, **kw):
    cell = np.asarray(atoms.get_cell(complete=True)) if atoms.pbc.any() \
        else None
    return jaxrt.pairs(np.asarray(atoms.positions, dtype), cutoff, cell=cell,
                       pbc=tuple(bool(p) for p in atoms.pbc), **kw)


# --- systems -----------------------------------------------------------------

def si2():
    return bulk("Si", "diamond", a=5.43)  # heights 3.13 Å: shifts up to 2


def cu_primitive():
    return bulk("Cu", "fcc", a=3.61)  # one atom, heights 2.08 Å


def fe_bcc_rattled():
    atoms = bulk("Fe", "bcc", a=2.87, cubic=True).repeat((2, 2, 2))
    atoms.rattle(0.1, seed=1)
    return atoms


def triclinic(seed=0, n=7):
    """A strongly skewed random cell (angles far from 90°, heights 2-3 Å),
    atoms partly outside it."""
    rng = np.random.default_rng(seed)
    cell = np.array([[4.0, 0, 0], [3.1, 3.5, 0], [-2.7, 1.9, 3.2]])
    cell = cell + rng.uniform(-0.3, 0.3, (3, 3))
    frac = rng.uniform(-0.5, 1.7, (n, 3))
    return Atoms("H" * n, positions=frac @ cell, cell=cell, pbc=True)


def slab():
    atoms = fcc111("Al", size=(2, 2, 3), vacuum=4.0)  # pbc (T, T, F)
    atoms.rattle(0.05, seed=2)
    return atoms


def benzene():
    return molecule("C6H6")  # free space, zero cell


def si_supercell():
    atoms = bulk("Si", "diamond", a=5.43, cubic=True).repeat((3, 3, 3))
    atoms.rattle(0.1, seed=3)
    return atoms  # 216 atoms: the cell grid under "auto"


def mixed_slab_zero_row():
    """A slab whose free axis has no lattice vector (completed as ASE does)."""
    rng = np.random.default_rng(4)
    pos = rng.uniform(0, 1, (6, 3)) * [5.0, 4.0, 6.0]
    return Atoms("H6", positions=pos,
                 cell=[[5.0, 0, 0], [1.0, 4.0, 0], [0, 0, 0]],
                 pbc=(True, True, False))


SLOW = pytest.mark.slow

SYSTEMS = {
    "si2_rc5": (si2, 5.0),
    "si2_rc9": (si2, 9.0),
    "cu_primitive_rc6": (cu_primitive, 6.0),
    "fe_bcc_rc4": (fe_bcc_rattled, 4.0),
    "triclinic_rc4": (triclinic, 4.0),
    "triclinic_rc7": (lambda: triclinic(1, 5), 7.0),
    "triclinic_rc11": (lambda: triclinic(8, 4), 11.0),
    "slab_rc5": (slab, 5.0),
    "benzene_rc3": (benzene, 3.0),
    "slab_zero_row_rc4.5": (mixed_slab_zero_row, 4.5),
    "si_216_rc5": (si_supercell, 5.0),
}


# Every case in CI; its variants (a larger cutoff, another seed) with the
# slow tests.
_SLOW_SYSTEMS = {"si2_rc9", "triclinic_rc7", "triclinic_rc11", "fe_bcc_rc4"}


@pytest.mark.parametrize("backend", ["brute", "cell"])
@pytest.mark.parametrize("name", [
    pytest.param(name, marks=SLOW) if name in _SLOW_SYSTEMS else name
    for name in SYSTEMS])
def test_same_pairs_as_ase_and_brute_force(name, backend, x64):
    build, cutoff = SYSTEMS[name]
    atoms = build()
    want = ase_set(atoms, cutoff)
    assert want, "every system has pairs"
    result = run(atoms, cutoff, backend=backend)
    got = as_set(result)
    assert got == want
    assert int(result.count) == len(want) == result.capacity
    assert not bool(result.overflow)
    # Full lists: (i, j, S) and (j, i, -S).
    assert {(j, i, -a, -b, -c) for i, j, a, b, c in got} == got
    if len(atoms) <= 20:  # the float64 brute force, every image
        h = np.asarray(atoms.get_cell(complete=True))
        assert brute_pairs_shifts(atoms.positions, h, atoms.pbc, cutoff) \
            == want
    # Distances as ASE's (float64: see the module docstring).
    d = np.asarray(result.distances(atoms.positions,
                                    atoms.get_cell(complete=True)))
    i, j, s = (np.asarray(x) for x in (result.i, result.j, result.shift))
    vec = atoms.positions[j] - atoms.positions[i] + s @ atoms.get_cell(
        complete=True)
    np.testing.assert_allclose(d, np.linalg.norm(vec, axis=1), rtol=0,
                               atol=1e-12)
    assert np.all(d < cutoff)


@pytest.mark.parametrize("name", ["si2_rc5", "triclinic_rc4",
                                  pytest.param("slab_rc5", marks=SLOW),
                                  pytest.param("si_216_rc5", marks=SLOW)])
def test_float32_pairs_and_distances(name):
    build, cutoff = SYSTEMS[name]
    atoms = build()
    i, j, s, d64 = ase_neighbor_list("ijSd", atoms, cutoff)
    # No float64 distance within float32 rounding of the cutoff here.
    i_all, d_all = ase_neighbor_list("id", atoms, cutoff * 1.001)
    assert not np.any(np.abs(d_all - cutoff) < 1e-4 * cutoff)
    result = run(atoms, cutoff, dtype=np.float32)
    assert as_set(result) == ase_set(atoms, cutoff)
    cell = np.asarray(atoms.get_cell(complete=True).array, np.float32)
    pos = np.asarray(atoms.positions, np.float32)
    d = np.asarray(result.distances(pos, cell))
    assert d.dtype == np.float32
    got = dict(zip(keys(result), d))
    want = dict(((int(a), int(b), *map(int, c)), x)
                for a, b, c, x in zip(i, j, s, d64))
    scale = np.max(np.abs(pos)) + np.max(np.abs(s @ cell), initial=0)
    tol = 16 * np.finfo(np.float32).eps * scale
    assert max(abs(got[k] - want[k]) for k in want) <= tol


def random_cells(count, n, seed):
    """Random cells: general triclinic (some nearly flat), atoms anywhere
    in [-1, 2) fractional, mixed pbc."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(count):
        cell = rng.normal(size=(3, 3)) * rng.uniform(2.0, 6.0)
        while abs(np.linalg.det(cell)) < 2.0:
            cell = rng.normal(size=(3, 3)) * 4.0
        pbc = (True, True, True) if k % 3 else tuple(rng.random(3) < 0.6)
        frac = rng.uniform(-1, 2, (n, 3))
        out.append(Atoms("H" * n, positions=frac @ cell, cell=cell, pbc=pbc))
    return out


@pytest.mark.parametrize("backend", [pytest.param("brute", marks=SLOW),
                                     "cell"])
def test_random_cells_under_jit_match_ase(backend, x64):
    # One program per backend and pbc (static capacity and max_shift): the
    # cell and the cutoff are traced.
    systems = random_cells(12, 6, seed=11)
    programs = {}
    for k, atoms in enumerate(systems):
        cutoff = [2.5, 4.0, 6.0][k % 3]
        cell = atoms.cell.array
        pbc = tuple(bool(p) for p in atoms.pbc)
        need = checks_module.shift_for_cell(cell, cutoff, pbc)
        if max(need) > 4:
            continue  # too flat for the program's reach
        if pbc not in programs:
            programs[pbc] = jax.jit(lambda r, c, rc, pbc=pbc: jaxrt.pairs(
                r, rc, cell=c, pbc=pbc, capacity=1201, max_shift=4,
                backend=backend))
        got = programs[pbc](atoms.positions, cell, cutoff)
        assert not bool(got.overflow)
        assert as_set(got) == ase_set(atoms, cutoff) | {("pad", 6)}, k
        assert brute_pairs_shifts(atoms.positions, cell, pbc, cutoff) == \
            ase_set(atoms, cutoff)


def test_exactly_at_the_cutoff_is_out_as_in_ase(x64):
    # Exact arithmetic: 2.5 = 0.5 * 5 and 7.5 - 10 + ... are representable,
    # so |d| == cutoff exactly; ASE keeps |d| < cutoff (strict), and so do we.
    atoms = Atoms("H4", positions=[[0, 0, 0], [2.5, 0, 0], [7.5, 0, 0],
                                   [0, 2.4999999, 0]],
                  cell=[10.0, 10.0, 10.0], pbc=True)
    want = ase_set(atoms, 2.5)
    got = as_set(run(atoms, 2.5))
    assert got == want
    assert (0, 1, 0, 0, 0) not in got and (0, 2, -1, 0, 0) not in got
    assert (0, 3, 0, 0, 0) in got
    assert as_set(run(atoms, 2.5, backend="cell")) == want


@SLOW  # the triclinic systems have atoms up to a cell outside already
def test_positions_far_outside_the_cell_shift_as_ase(x64):
    atoms = triclinic(5, 6)
    atoms.positions[0] += 3 * atoms.cell[0] - 2 * atoms.cell[2]
    atoms.positions[3] -= 5 * atoms.cell[1]
    assert as_set(run(atoms, 4.0)) == ase_set(atoms, 4.0)
    assert as_set(run(atoms, 4.0, backend="cell")) == ase_set(atoms, 4.0)


def test_ase_drop_in_returns_what_ase_returns(x64):
    for atoms, cutoff in ((si2(), 5.0), (slab(), 5.0), (benzene(), 3.0)):
        got = jaxrt.ase_neighbor_list("ijdDS", atoms, cutoff)
        want = ase_neighbor_list("ijdDS", atoms, cutoff)
        order = np.lexsort((want[4][:, 2], want[4][:, 1], want[4][:, 0],
                            want[1], want[0]))
        want = [w[order] for w in want]
        for g, w, q in zip(got, want, "ijdDS"):
            assert g.dtype == w.dtype or q in "dD", q
            np.testing.assert_allclose(g, w, rtol=0, atol=1e-12, err_msg=q)
        assert np.all(np.diff(got[0]) >= 0)  # sorted by i, as ASE
    result = jaxrt.pairs_from_ase(si2(), 5.0)
    i, j, s = jaxrt.pairs_to_ase(result)
    assert {(a, b, *c) for a, b, c in zip(i.tolist(), j.tolist(),
                                          s.tolist())} == ase_set(si2(), 5.0)
    with pytest.raises(NotImplementedError, match="per-atom radii"):
        jaxrt.ase_neighbor_list("ij", si2(), [3.0, 3.0])


# --- jit, vmap, overflow -------------------------------------------------------

def test_jit_with_traced_cell_matches_eager(x64):
    atoms = triclinic(2, 8)
    eager = run(atoms, 4.0)
    sizes = jaxrt.pairs_sizes(atoms.positions, 4.0, cell=np.asarray(atoms.cell))
    assert sizes.capacity == int(eager.count)

    @jax.jit
    def f(r, cell):
        return jaxrt.pairs(r, 4.0, cell=cell, **sizes.kwargs)

    got = f(jnp.asarray(atoms.positions), jnp.asarray(np.asarray(atoms.cell)))
    assert as_set(got) == as_set(eager) == ase_set(atoms, 4.0)


def test_vmap_over_padded_batch_of_different_systems(x64):
    systems = [si2(), triclinic(3, 6), fe_bcc_rattled(), cu_primitive()]
    cutoff = 4.5
    n_max = max(len(a) for a in systems)
    pos = np.zeros((len(systems), n_max, 3))
    mask = np.zeros((len(systems), n_max), bool)
    cells = np.stack([np.asarray(a.cell) for a in systems])
    for b, a in enumerate(systems):
        pos[b, :len(a)] = a.positions
        pos[b, len(a):] = a.positions[0]  # padding on top of a real atom
        mask[b, :len(a)] = True
    sizes = jaxrt.pairs_sizes(pos, cutoff, cell=cells, mask=mask)
    for backend in ("brute", "cell"):
        batch = jax.jit(jax.vmap(lambda r, c, m: jaxrt.pairs(
            r, cutoff, cell=c, mask=m, backend=backend, **sizes.kwargs)))(
                pos, cells, mask)
        assert batch.i.shape == (len(systems), sizes.capacity)
        for b, a in enumerate(systems):
            one = jax.tree_util.tree_map(lambda x: x[b], batch)
            got = {p for p in as_set(one) if p[0] != "pad"}
            assert got == ase_set(a, cutoff), (backend, b)
            assert not bool(one.overflow)
            assert np.all(np.asarray(one.i)[int(one.count):] == n_max)
        assert int(np.max(batch.count)) == sizes.capacity


def test_overflow_is_never_silent(x64):
    atoms = si2()
    cell = np.asarray(atoms.cell)
    full = run(atoms, 5.0)
    with pytest.raises(jaxrt.PairsError, match="capacity"):
        jaxrt.pairs(atoms.positions, 5.0, cell=cell, capacity=10)

    @jax.jit
    def small(r, c):
        return jaxrt.pairs(r, 5.0, cell=c, capacity=10, max_shift=2)

    out = small(atoms.positions, cell)
    assert bool(out.overflow) and int(out.count) == int(full.count)
    assert int(out.error) == pairs_module.ErrorBit.CAPACITY
    with pytest.raises(jaxrt.PairsError, match="count 56, capacity 10"):
        out.check()
    # Stored pairs are real pairs even when some were dropped.
    assert {p for p in as_set(out) if p[0] != "pad"} <= as_set(full)

    # A cell that shrank past what max_shift reaches.
    @jax.jit
    def reach1(r, c):
        return jaxrt.pairs(r, 5.0, cell=c, capacity=100, max_shift=1)

    out = reach1(atoms.positions, cell)
    assert bool(out.overflow)
    assert int(out.error) & pairs_module.ErrorBit.MAX_SHIFT
    with pytest.raises(jaxrt.PairsError, match="max_shift"):
        out.check()
    # A NaN position of a real atom.
    bad = np.array(atoms.positions)
    bad[1, 0] = np.nan
    out = small(bad, cell)
    assert int(out.error) & pairs_module.ErrorBit.NONFINITE_POSITION
    with pytest.raises(jaxrt.PairsError, match="NaN"):
        jaxrt.pairs(bad, 5.0, cell=cell)


def test_clear_errors_for_bad_arguments():
    r = np.zeros((2, 3))
    cell = np.eye(3) * 5
    cases = [
        (dict(cutoff=0.0), ValueError, "cutoff must be finite and > 0"),
        (dict(cutoff=-1.0), ValueError, "cutoff"),
        (dict(pbc=(True, False)), ValueError, "pbc must be a bool or three"),
        (dict(cell=np.ones((3, 3))), ValueError, "cell is singular"),
        (dict(cell=np.ones((2, 2))), ValueError, "cell must be a"),
        (dict(backend="fast"), ValueError, "backend='fast'"),
        (dict(mask=np.ones(3, bool)), ValueError, "mask must be bool"),
        (dict(capacity=-1), ValueError, "capacity must be >= 0"),
        (dict(capacity=2.5), TypeError, "capacity must be an int"),
        (dict(max_shift=(1, 1)), ValueError, "max_shift"),
        (dict(cell=None, pbc=True), ValueError, "cell=None"),
        (dict(cell=np.diag([5.0, 5.0, 0.0]), pbc=True), ValueError,
         "zero on a periodic axis"),
    ]
    for kw, err, msg in cases:
        args = dict(cutoff=2.0, cell=cell)
        args.update(kw)
        with pytest.raises(err, match=msg):
            jaxrt.pairs(r, args.pop("cutoff"), **args)
    with pytest.raises(TypeError, match="floating point"):
        jaxrt.pairs(np.zeros((2, 3), int), 2.0)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        jaxrt.pairs(np.zeros((2, 2)), 2.0)
    with pytest.raises(ValueError, match="pass capacity"):
        jax.jit(lambda x: jaxrt.pairs(x, 2.0, cell=cell))(r)
    with pytest.raises(ValueError, match="pass max_shift"):
        jax.jit(lambda x, c: jaxrt.pairs(x, 2.0, cell=c, capacity=4))(r, cell)
    with pytest.raises(TypeError, match="cutoff must be a Python float"):
        jax.jit(lambda x, rc: jaxrt.pairs(x, rc, capacity=4))(r, 2.0)


def test_free_space_and_empty_systems(x64):
    atoms = benzene()
    got = jaxrt.pairs(atoms.positions, 3.0)  # cell=None: free space
    assert as_set(got) == ase_set(atoms, 3.0)
    assert np.all(np.asarray(got.shift) == 0)
    empty = jaxrt.pairs(np.zeros((0, 3)), 3.0)
    assert int(empty.count) == 0 and empty.capacity == 0
    lonely = jaxrt.pairs(np.zeros((1, 3)), 3.0, cell=np.eye(3) * 10)
    assert int(lonely.count) == 0


def test_cell_as_sides_and_sizes_of_a_batch_of_sides(x64):
    atoms = fe_bcc_rattled()
    sides = np.diag(atoms.cell.array)
    by_sides = jaxrt.pairs(atoms.positions, 4.0, cell=sides)
    assert as_set(by_sides) == ase_set(atoms, 4.0)
    batch = np.stack([atoms.positions, atoms.positions * 1.01])
    sizes = jaxrt.pairs_sizes(batch, 4.0, cell=np.stack([sides, sides * 1.01]))
    assert sizes.capacity == int(by_sides.count)
    assert sizes.max_shift == (1, 1, 1)


# --- gradients -----------------------------------------------------------------

CUT = 4.5


def energy_of_vectors(vec, valid):
    """A smooth pair potential that vanishes with its derivatives at CUT."""
    d = pairs_module._safe_norm(vec)
    x = jnp.where(valid, d / CUT, 1.0)
    return 0.5 * jnp.sum((1 - x) ** 3 * (1 + 2 * x) * jnp.exp(-d))


def pair_energy(result, positions, cell):
    return energy_of_vectors(result.vectors(positions, cell), result.valid)


def energy_of(positions, cell, sizes):
    result = jaxrt.pairs(jax.lax.stop_gradient(positions), CUT, cell=cell,
                         **sizes.kwargs)
    return pair_energy(result, positions, cell)


def test_forces_and_cell_gradient_match_finite_differences(x64):
    atoms = triclinic(6, 5)
    r = jnp.asarray(atoms.positions)
    h = jnp.asarray(np.asarray(atoms.cell))
    sizes = jaxrt.pairs_sizes(r, CUT, cell=h)
    sizes = jaxrt.PairSizes(sizes.capacity + 32, sizes.max_shift)
    both = jax.jit(jax.value_and_grad(lambda r, h: energy_of(r, h, sizes),
                                      argnums=(0, 1)))

    def e(r, h):
        return both(r, h)[0]

    g_r, g_h = both(r, h)[1]
    eps = 1e-6
    for (a, b) in [(0, 0), (2, 1), (4, 2)]:
        dr = np.zeros(r.shape)
        dr[a, b] = eps
        fd = (e(r + dr, h) - e(r - dr, h)) / (2 * eps)
        assert abs(fd - g_r[a, b]) < 1e-7 * max(1, abs(fd))
    for (a, b) in [(0, 0), (1, 0), (2, 2), (2, 1)]:
        dh = np.zeros((3, 3))
        dh[a, b] = eps
        fd = (e(r, h + dh) - e(r, h - dh)) / (2 * eps)
        assert abs(fd - g_h[a, b]) < 1e-7 * max(1, abs(fd))


def test_forces_scatter_materialized_pair_ends():
    # Reverse mode of the vectors' gathers is a scatter-add; the gathered
    # ends are written out first, so XLA:GPU cannot fuse the gathers into
    # it (jaxrt.layouts.edges).
    atoms = triclinic(6, 5)
    r = jnp.asarray(atoms.positions, jnp.float32)
    h = jnp.asarray(np.asarray(atoms.cell), jnp.float32)
    sizes = jaxrt.pairs_sizes(r, CUT, cell=h)
    text = jax.jit(jax.grad(lambda r: energy_of(r, h, sizes))).lower(
        r).as_text()
    assert "scatter" in text and "optimization_barrier" in text


def test_stress_from_the_strain_derivative_is_the_virial(x64):
    atoms = si2()
    atoms.rattle(0.05, seed=7)
    r = jnp.asarray(atoms.positions)
    h = jnp.asarray(np.asarray(atoms.cell))
    sizes = jaxrt.pairs_sizes(r, CUT, cell=h)
    volume = abs(float(np.linalg.det(np.asarray(h))))

    def strained(eps):
        f = jnp.eye(3) + eps
        return energy_of(r @ f, h @ f, sizes)

    both = jax.jit(jax.value_and_grad(strained))
    stress = both(jnp.zeros((3, 3)))[1] / volume
    # The virial: sum over the list of d ⊗ dE/dd.
    result = jaxrt.pairs(r, CUT, cell=h, **sizes.kwargs)
    vec = result.vectors(r, h)
    de_dd = jax.jit(jax.grad(energy_of_vectors))(vec, result.valid)
    virial = jnp.einsum("pa,pb->ab", vec, de_dd) / volume
    np.testing.assert_allclose(stress, virial, rtol=1e-10, atol=1e-14)
    # And by finite differences of the strain.
    eps = 1e-6
    de = np.zeros((3, 3))
    de[0, 1] = eps
    fd = (both(de)[0] - both(-de)[0]) / (2 * eps) / volume
    assert abs(fd - stress[0, 1]) < 1e-7 * max(1.0, abs(float(fd)))


def test_gradients_finite_at_coincident_atoms_and_padding(x64):
    r = jnp.array([[0.0, 0, 0], [0.0, 0, 0], [1.0, 0, 0], [9.0, 9, 9]])
    mask = jnp.array([True, True, True, False])
    result = jaxrt.pairs(r, 2.0, mask=mask, capacity=12)
    assert int(result.count) == 6

    def energy(r):
        return jnp.sum(result.distances(r) ** 2 + result.distances(r))

    g = jax.grad(energy)(r)
    assert np.all(np.isfinite(np.asarray(g)))
    assert np.all(np.asarray(g)[3] == 0)  # the padded atom
    # At the cutoff itself: the pair is out (strict), its gradient zero.
    at = jnp.array([[0.0, 0, 0], [2.0, 0, 0]])
    assert int(jaxrt.pairs(at, 2.0).count) == 0


def test_auto_switches_from_brute_force_to_the_cell_grid():
    plan = checks_module.plan
    # 2 atoms, 5^3 images: brute; 216 atoms in a cell taller than the
    # cutoff (27 images): N^2 * 27 = 1.3e6 > BRUTE_CANDIDATES, the grid.
    assert plan(2, (True,) * 3, (2, 2, 2), "auto")[0]
    assert not plan(216, (True,) * 3, (1, 1, 1), "auto")[0]
    assert plan(216, (True,) * 3, (1, 1, 1), "brute")[0]
    assert not plan(2, (True,) * 3, (2, 2, 2), "cell")[0]


def test_graph_energy_example_trains(x64):
    spec = importlib.util.spec_from_file_location(
        "graph_energy", pathlib.Path(__file__).resolve().parents[2]
        / "examples" / "graph_energy.py")
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    history, _, sizes = example.train(steps=12, n_train=3, log_every=12,
                                      learning_rate=0.05)
    assert sizes.max_shift == (2, 2, 2)  # the 2-atom cells' images
    (_, loss0, _, _), (_, loss, _, _) = history[0], history[-1]
    assert np.isfinite(loss) and loss < 0.5 * loss0, history


# --- regressions ---------------------------------------------------------------

def test_traced_cell_with_zero_rows_is_completed_under_jit(x64):
    # ASE's molecules have an all-zero cell and vacuum=None slabs a zero
    # third row; outside jit they are completed as ASE completes them, and
    # under jit (a traced cell) the same pairs must come out, unflagged.
    cases = [(molecule("CH3CH2OH"), 3.0),
             (fcc111("Al", size=(2, 2, 3), vacuum=None), 6.0)]
    for atoms, cutoff in cases:
        cell = np.asarray(atoms.cell.array)
        assert not cell.any(axis=1).all()  # a zero row
        pbc = tuple(bool(p) for p in atoms.pbc)
        want = ase_set(atoms, cutoff)
        eager = jaxrt.pairs(atoms.positions, cutoff, cell=cell, pbc=pbc)
        assert as_set(eager) == want
        capacity = len(want) + 8
        got = jax.jit(lambda r, c, pbc=pbc, cutoff=cutoff: jaxrt.pairs(
            r, cutoff, cell=c, pbc=pbc, capacity=capacity, max_shift=3))(
                atoms.positions, cell)
        assert int(got.error) == 0, int(got.error)
        assert as_set(got) == want | {("pad", len(atoms))}


def test_vectors_and_distances_take_float32_positions_and_an_ase_cell():
    atoms = si2()
    pos = np.asarray(atoms.positions, np.float32)
    result = jaxrt.pairs(pos, 5.0, cell=np.asarray(atoms.cell.array,
                                                   np.float32))
    i, j, s, d64 = ase_neighbor_list("ijSd", atoms, 5.0)
    for cell in (atoms.cell, atoms.cell.array):  # an ase.Cell, float64 numpy
        d = np.asarray(result.distances(pos, cell))
        vec = np.asarray(result.vectors(pos, cell))
        assert d.dtype == vec.dtype == np.float32
        got = dict(zip(keys(result), d))
        # float32: a few ulps of the ~10 Å involved (module docstring).
        assert max(abs(got[(a, b, *c)] - x) for a, b, c, x in
                   zip(i, j, s.tolist(), d64)) < 16 * 2.0 ** -23 * 16
    shifts = np.asarray(result.shift_vectors(atoms.cell))
    np.testing.assert_allclose(shifts, np.asarray(result.shift)
                               @ atoms.cell.array, rtol=0, atol=1e-5)


def test_float64_numpy_searched_in_float32_warns_naming_the_fix():
    atoms = si2()
    assert not jax.config.jax_enable_x64
    with pytest.warns(jaxrt.Float32Warning, match="jax_enable_x64"):
        jaxrt.pairs(atoms.positions, 5.0, cell=atoms.cell.array)
    with pytest.warns(jaxrt.Float32Warning, match="float32"):
        jaxrt.pairs_sizes(atoms.positions[None], 5.0, cell=atoms.cell.array)
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        jaxrt.pairs(atoms.positions.astype(np.float32), 5.0,
                    cell=atoms.cell.array)  # float32 on purpose: no warning
        with jax.enable_x64(True):
            jaxrt.pairs(atoms.positions, 5.0, cell=atoms.cell.array)
