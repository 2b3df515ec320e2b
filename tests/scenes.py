"""Scenes shared by test files in different folders (importable as
``scenes``: pyproject's ``pythonpath`` holds ``tests``)."""
import jax
import jax.numpy as jnp
import numpy as np
from jax_md import space


def lattice(n_per_side, spacing, dim=3):
    """float32 ``(n_per_side**dim, dim)``: a cubic lattice from the origin."""
    g = np.arange(n_per_side, dtype=np.float32) * spacing
    return np.stack(np.meshgrid(*[g] * dim, indexing="ij"), -1).reshape(-1, dim)


def fluid(n_side=6, dim=3, density=0.8, seed=0, jitter=0.15):
    """A jittered lattice in ``[0, side)``: (R float64 (N, dim), side)."""
    side = (n_side ** dim / density) ** (1 / dim)
    a = side / n_side
    g = np.stack(np.meshgrid(*[np.arange(n_side)] * dim, indexing="ij"),
                 -1).reshape(-1, dim) * a
    rng = np.random.default_rng(seed)
    return (g + rng.uniform(-jitter, jitter, g.shape) * a) % side, side


def slab_displacement(side, periodic_axes=2):
    """Periodic on the first ``periodic_axes`` axes (x and y by default),
    free on the others."""
    k = periodic_axes

    def displacement(a, b, **unused):
        d = a - b
        return d.at[:k].set(jnp.mod(d[:k] + side / 2, side) - side / 2)
    return displacement


def kicked_updates(nbrs, shift, R, steps, seed=13, scale=0.03):
    """``steps`` random kicks (``scale`` times normal deviates from
    ``PRNGKey(seed)``) under ``lax.scan``, the list updated after each:
    (the last list, then per step the positions ``(steps, N, dim)``, the
    list's ``idx`` and its reference positions)."""
    kicks = scale * jax.random.normal(jax.random.PRNGKey(seed),
                                      (steps,) + R.shape)

    def step(carry, kick):
        R, nbrs = carry
        R = shift(R, kick)
        nbrs = nbrs.update(R)
        return (R, nbrs), (R, nbrs.idx, nbrs.reference_position)

    (_, last), per_step = jax.lax.scan(step, (R, nbrs), kicks)
    return (last, *per_step)


# The list-free LJ tests' boxes: name -> side -> (displacement, box,
# periodic axes or None).
GEOMETRIES = {
    "periodic": lambda side: (space.periodic(side)[0], side, None),
    "free": lambda side: (space.free()[0], None, None),
    "slab": lambda side: (slab_displacement(side), side, (True, True, False)),
}


# A small 2D LJ scene in TOML.
GOOD = """
[box]
size = [6.0, 6.0]
boundary = "periodic"

[particles]
positions = [[1.0, 1.0], [2.0, 1.5], [3.0, 4.0]]

[[effects]]
kind = "lj"
r_cutoff = 2.5

[integrator]
dt = 0.001
"""
