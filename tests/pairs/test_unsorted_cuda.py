"""Unsorted lists (`jaxrt.pairs`' default) as a GPU searches them: from
the full stencil, rows ``i``-major (`jaxrt.pairs.program`'s
``FULL_STENCIL_UNSORTED_ON_CUDA``), taken here on the CPU by forcing the
CUDA branch of `jaxrt.platforms.cuda_or_default`.

Against the CPU's branch (the half stencil) and ASE, float64: the set of
``(i, j, S)`` stored, the count, the counts per system and the error bits
are identical, padding rows included; past the capacity the counts stay
exact and every stored row is a real pair, stored once.
"""
from __future__ import annotations

import importlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

ase = pytest.importorskip("ase")
from ase import Atoms  # noqa: E402
from ase.build import bulk, fcc111, molecule  # noqa: E402

import jaxrt  # noqa: E402
from batch_cases import CUTOFF, ase_set, half_of, skewed  # noqa: E402
from jaxrt import platforms  # noqa: E402

program = importlib.import_module("jaxrt.pairs.program")
checks = importlib.import_module("jaxrt.pairs.checks")
ErrorBit = importlib.import_module("jaxrt.pairs.bits").ErrorBit


@pytest.fixture
def branch(monkeypatch):
    """``branch(name)``: every `cuda_or_default` of the program takes
    ``"cuda"`` or ``"default"``; ``"both"``: both are traced (as where a
    CUDA backend exists) and the CPU lowers its own. The compiled programs
    are dropped, or one traced for the other branch would be reused."""
    def take(name):
        if name == "both":
            monkeypatch.setattr(platforms, "cuda_present", lambda: True)
        elif name == "cuda":
            monkeypatch.setattr(platforms, "cuda_or_default",
                                lambda cuda, default: cuda())
        else:
            monkeypatch.setattr(platforms, "cuda_or_default",
                                lambda cuda, default: default())
        jax.clear_caches()
    yield take
    jax.clear_caches()


def mixed():
    cu = bulk("Cu", "fcc", a=3.61, cubic=True)
    cu.rattle(0.05, seed=1)
    slab = fcc111("Al", size=(2, 2, 2), vacuum=None)
    return [molecule("CH3CH2OH"), slab, cu, bulk("Cu", "fcc", a=3.61),
            skewed()]


def batch_search(systems, cutoff, *, capacity, half=False,
                 self_interaction=False, species=False):
    """`program.search` unsorted on a padded flat batch (a padding system
    of padding atoms, as jraph pads). ``cutoff``: a float, or ASE's dict by
    atomic numbers with ``species``. Returns the rows, count, counts per
    system, error bits (numpy) and the real atoms' count."""
    batch = jaxrt.batch_from_ase(systems)
    n, g = len(batch.positions), len(batch.n_node)
    graph = np.repeat(np.arange(g, dtype=np.int32), batch.n_node)
    mask = batch.graph_mask[graph]
    spec = None
    if species:
        numbers = sorted({z for pair in cutoff for z in pair})
        matrix = np.zeros((len(numbers), len(numbers)))
        for (a, b), rc in cutoff.items():
            matrix[numbers.index(a), numbers.index(b)] = rc
            matrix[numbers.index(b), numbers.index(a)] = rc
        spec = np.array([numbers.index(z) if z in numbers else 0
                         for z in batch.numbers], np.int32)
        cut, radius = matrix, float(matrix.max())
    else:
        cut = radius = cutoff
    shift = np.max([checks.shift_for_cell(checks.concrete_cell(
        a.cell.array, tuple(a.pbc)), radius, tuple(a.pbc))
        if a.pbc.any() else (0, 0, 0) for a in systems], axis=0)
    brute, reach, chunk = checks.plan(n, (True,) * 3, tuple(shift), "cell")
    real = int(np.sum(mask))
    out = program.search(
        jnp.asarray(batch.positions), jnp.asarray(graph), jnp.asarray(mask),
        jnp.asarray(batch.cell), jnp.asarray(batch.pbc), jnp.asarray(cut),
        None if spec is None else jnp.asarray(spec), jnp.int32(real),
        periodic=(True,) * 3, reach=reach, capacity=capacity, brute=brute,
        chunk=chunk, half=half, sort=False,
        self_interaction=self_interaction, n_graph=g)
    return (*(np.asarray(x) for x in out), real)


def row_set(rows, count):
    stored = [tuple(int(v) for v in r) for r in rows[:count]]
    assert len(set(stored)) == len(stored), "a row stored twice"
    return set(stored)


def local_sets(rows, count, systems):
    """The stored rows split by system (indices local)."""
    starts = np.cumsum([0] + [len(a) for a in systems])
    out = [set() for _ in systems]
    for i, j, *s in row_set(rows, count):
        g = int(np.searchsorted(starts, i, side="right")) - 1
        assert starts[g] <= j < starts[g + 1], (i, j)
        out[g].add((i - starts[g], j - starts[g], *s))
    return out


def on_both_branches(branch, systems, cutoff, **kwargs):
    """`batch_search` on the CUDA branch, then on the default one."""
    got = {}
    for name in ("cuda", "default"):
        branch(name)
        got[name] = batch_search(systems, cutoff, **kwargs)
    return got["cuda"], got["default"]


def assert_same(cuda, cpu):
    """Identical results as sets: count, per system, error, padding."""
    rows, count, per_system, error, _ = cuda
    assert int(count) == int(cpu[1]) and int(error) == int(cpu[3])
    np.testing.assert_array_equal(per_system, cpu[2])
    stored = min(int(count), len(rows))
    assert row_set(rows, stored) == row_set(cpu[0], stored)
    np.testing.assert_array_equal(rows[stored:], cpu[0][stored:])


@pytest.mark.parametrize("half", [False, True])
def test_mixed_batch_unsorted_on_cuda_equals_the_cpu_and_ase(x64, branch,
                                                             half):
    systems = mixed()
    want = [ase_set(a) for a in systems]
    if half:
        want = [half_of(w) for w in want]
    capacity = sum(len(w) for w in want) + 7
    cuda, cpu = on_both_branches(branch, systems, CUTOFF, capacity=capacity,
                                 half=half)
    rows, count, per_system, error, real = cuda
    assert int(error) == 0
    assert local_sets(rows, count, systems) == want
    np.testing.assert_array_equal(per_system[:len(systems)],
                                  [len(w) for w in want])
    assert np.all(per_system[len(systems):] == 0)
    # Padding rows (pad, pad, 0) after the pairs.
    np.testing.assert_array_equal(rows[count:], [[real, real, 0, 0, 0]] * (
        capacity - count))
    assert_same(cuda, cpu)
    # i-major: the full stencil's order.
    assert np.all(np.diff(rows[:count, 0]) >= 0)


def test_self_pairs_species_and_half_in_a_batch_on_cuda(x64, branch):
    systems = [bulk("NaCl", "rocksalt", a=5.64), molecule("CH3CH2OH")]
    cutoffs = {(11, 17): 3.2, (17, 17): 4.2, (1, 6): 1.2, (6, 6): 1.6,
               (6, 8): 1.5, (1, 8): 1.0}
    for half in (False, True):
        want = [ase_set(a, cutoffs, self_interaction=True) for a in systems]
        if half:
            want = [half_of(w) for w in want]
        capacity = sum(len(w) for w in want) + 3
        cuda, cpu = on_both_branches(
            branch, systems, cutoffs, capacity=capacity, half=half,
            self_interaction=True, species=True)
        rows, count, _, error, _ = cuda
        assert int(error) == 0
        assert local_sets(rows, count, systems) == want
        assert_same(cuda, cpu)
        # Each atom's self pair, where it has one, before its other pairs.
        first = {}
        for i, j, *s in rows[:count].tolist():
            first.setdefault(i, (j, *s))
        owners = {i for i, j, *s in rows[:count].tolist()
                  if i == j and not any(s)}
        assert owners and all(first[i] == (i, 0, 0, 0) for i in owners)


def test_overflow_on_cuda_keeps_exact_counts(x64, branch):
    systems = mixed()[2:4]
    want = [ase_set(a) for a in systems]
    cuda, cpu = on_both_branches(branch, systems, CUTOFF, capacity=10,
                                 self_interaction=True)
    rows, count, per_system, error, _ = cuda
    assert int(error) == int(ErrorBit.CAPACITY)
    assert int(count) == sum(len(w) + len(a) for w, a in zip(want, systems))
    np.testing.assert_array_equal(per_system[:2], [
        len(w) + len(a) for w, a in zip(want, systems)])
    np.testing.assert_array_equal(per_system, cpu[2])
    assert int(count) == int(cpu[1])
    assert int(error) == int(cpu[3])
    # Every row stored is a real pair (self pairs included), none twice.
    selfs = [{(i, i, 0, 0, 0) for i in range(len(a))} for a in systems]
    stored = local_sets(rows, 10, systems)
    assert sum(map(len, stored)) == 10
    assert all(s <= w | p for s, w, p in zip(stored, want, selfs))


def _scene(clustered):
    """Random atoms in a triclinic box, some outside it; ``clustered``:
    some packed in a ball, whose cells hold more than a word of atoms
    (the full stencil's stream, not its words)."""
    rng = np.random.default_rng(5)
    cell = np.array([[11.0, 0, 0], [1.5, 10.0, 0], [0.5, -1.0, 12.0]])
    r = rng.uniform(-0.1, 1.1, (220, 3)) @ cell
    if clustered:
        r = np.concatenate([r, rng.normal(0, 0.6, (90, 3)) + 5.0])
    return r, cell


@pytest.mark.parametrize("options", [
    dict(), dict(half=True), dict(self_interaction=True),
    dict(half=True, self_interaction=True, species=True),
    dict(clustered=True), dict(clustered=True, half=True),
    dict(backend="brute"), dict(backend="brute", half=True)])
def test_single_system_unsorted_on_cuda_equals_ase(x64, branch, options):
    options = dict(options)
    r, cell = _scene(options.pop("clustered", False))
    if options.get("backend") == "brute":
        r = r[:120]  # past the brute force's one step: its stream
    atoms = Atoms(positions=r, cell=cell, pbc=True)
    cutoff = 3.0
    kw = {}
    if options.pop("species", False):
        kinds = np.arange(len(r)) % 2
        matrix = np.array([[2.5, 3.0], [3.0, 0.0]])  # no 2-2 pairs
        kw = dict(species=kinds)
        cutoff = matrix
        atoms.numbers = kinds + 1
        oracle = {(1, 1): 2.5, (1, 2): 3.0}
    else:
        oracle = cutoff
    want = ase_set(atoms, oracle, self_interaction=options.get(
        "self_interaction", False))
    if options.get("half"):
        want = half_of(want)
    capacity = len(want) + 11
    got = {}
    for name in ("cuda", "default"):
        branch(name)
        f = jax.jit(lambda x: jaxrt.pairs(
            x, cutoff, cell=cell, capacity=capacity, max_shift=1,
            **kw, **options))
        p = f(jnp.asarray(r))
        got[name] = (np.asarray(jnp.concatenate(
            [p.i[:, None], p.j[:, None], p.shift], axis=1)),
            np.asarray(p.count), np.asarray(p.count)[None],
            np.asarray(p.error), len(r))
    rows, count, _, error, n = got["cuda"]
    assert int(error) == 0 and int(count) == len(want)
    assert row_set(rows, count) == want
    np.testing.assert_array_equal(rows[count:], [[n, n, 0, 0, 0]] * (
        capacity - count))
    assert_same(got["cuda"], got["default"])


def test_both_branches_trace_alike_under_vmap(x64, branch):
    """Where a CUDA backend exists both branches are traced (their outputs
    must agree in shape and dtype), under ``vmap`` too (`pairs_sizes`):
    here the CPU lowers its own branch, so the results are the CPU's."""
    r, cell = _scene(False)
    want = jaxrt.pairs_sizes(r, 3.0, cell=cell, half=True)
    branch("both")
    assert jaxrt.pairs_sizes(r, 3.0, cell=cell, half=True) == want
    p = jax.jit(lambda x: jaxrt.pairs(x, 3.0, cell=cell, capacity=8000,
                                      max_shift=1, self_interaction=True))(
        jnp.asarray(r))
    assert int(p.error) == 0
    assert row_set(np.asarray(jnp.concatenate(
        [p.i[:, None], p.j[:, None], p.shift], axis=1)), int(p.count)) == \
        ase_set(Atoms(positions=r, cell=cell, pbc=True), 3.0,
                self_interaction=True)
