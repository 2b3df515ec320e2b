"""The cells' coarsening (`jaxrt.pairs.cells.coarsening`): factors
``1.25^m`` taken from a table, the first that fits, give the cells the
loop multiplying by 1.25 until the cells fit gave, bit for bit, in both
dtypes, on the CPU's table (a loop past it) and a GPU's (every factor up
to inf, no loop), with free extents far past the cutoff."""
from __future__ import annotations

import importlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

cells = importlib.import_module("jaxrt.pairs.cells")
platforms = importlib.import_module("jaxrt.platforms")


def looped(over, g, dtype, steps):
    """The coarsening as a loop: every system's factor times 1.25 while
    its cells pass the budget."""
    return jax.lax.while_loop(
        lambda c: jnp.any(over(c)),
        lambda c: jnp.where(over(c), c * 1.25, c), jnp.ones((g,), dtype))


def test_powers_round_as_the_loop(x64):
    for dtype in (np.float32, np.float64):
        table = cells.powers(np.dtype(dtype))
        assert np.isinf(table[-1]) and np.all(np.isfinite(table[:-1]))
        got = jax.lax.fori_loop(
            0, len(table) - 1, lambda m, c: c.at[m + 1].set(c[m] * 1.25),
            jnp.ones((len(table),), dtype))
        np.testing.assert_array_equal(np.asarray(got), table)
        assert not np.all(table[:-1] == 1.25 ** np.arange(len(table) - 1))


def grids(dtype, seed):
    """Systems whose free extents are up to 1e12 times the cells the
    cutoff allows (many factors past the table), next to periodic and
    empty ones: grid's arguments."""
    rng = np.random.default_rng(seed)
    g, per = 7, 3
    span = np.array([1e-3, 1.0, 40.0, 3e3, 1e6, 1e9, 1e12])
    fw = rng.uniform(0, 1, (g * per, 3)) * np.repeat(span, per)[:, None]
    graph = np.repeat(np.arange(g), per).astype(np.int32)
    real = np.ones(g * per, bool)
    real[-per:] = False  # an empty system
    pbc = rng.uniform(size=(g, 3)) < 0.3
    pbc[0] = True
    h_height = rng.uniform(0.5, 2.0, (g, 3))
    count = np.bincount(graph[real], minlength=g).astype(np.int32)
    return (jnp.asarray(fw, dtype), jnp.asarray(graph), jnp.asarray(real),
            jnp.asarray(pbc), jnp.asarray(h_height, dtype)), count, g


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("branch", ["default", "cuda", "cuda-whole"])
def test_cells_as_the_loop_gave_with_huge_free_extents(x64, monkeypatch,
                                                       dtype, branch):
    """Every output of grid (cells, origin, width, first cells) bit for
    bit as with the loop, jitted; some systems need factors past the
    table (the CPU's loop after it), a zero cutoff every factor to inf."""
    if branch != "default":
        monkeypatch.setattr(platforms, "cuda_or_default",
                            lambda cuda, default: cuda())
    if branch == "cuda-whole":  # every factor in one table for 7 systems
        monkeypatch.setattr(cells, "COARSEN_TABLE_MOST", 2 ** 30)
    tabled = cells.coarsening
    factors = []

    def recorded(*a):
        factors.append(np.asarray(looped(*a)))
        return factors[-1]

    for seed in range(3):
        args, count, g = grids(dtype, seed)
        for cutoff in (1e-4, 0.3, 2.5, 0.0):
            def grid(coarsening, jit=True):
                monkeypatch.setattr(cells, "coarsening", coarsening)
                f = lambda *a: cells.grid(  # noqa: E731
                    *a, jnp.asarray(cutoff, dtype), (1, 2, 1), g, False,
                    jnp.asarray(count))
                return (jax.jit(f) if jit else f)(*args)
            want = grid(looped)
            got = grid(tabled)
            loops = "while" in str(jax.make_jaxpr(lambda *a: cells.grid(
                *a, jnp.asarray(cutoff, dtype), (1, 2, 1), g, False,
                jnp.asarray(count)))(*args))
            # No loop on a GPU where the whole table fits.
            assert loops == (branch == "default" or (
                branch == "cuda" and dtype == np.float64))
            for a, b in zip(got, want):
                a, b = np.asarray(a), np.asarray(b)
                assert a.dtype == b.dtype and a.shape == b.shape
                np.testing.assert_array_equal(a.view(np.uint8),
                                              b.view(np.uint8))
            grid(recorded, jit=False)
    every = np.concatenate(factors)
    assert np.any(np.isfinite(every) & (
        every > 1.25 ** cells.COARSEN_STEPS))  # past the CPU's table
    assert np.any(np.isinf(every))  # the zero cutoff: the table's end
    assert np.any(every == 1) and len(np.unique(every)) > 10
