"""The built-in scenes, by name in `BUILTIN` (``jaxrt scenes`` lists them).

Each factory returns a `Scene`; the first line of its docstring is the
summary ``jaxrt scenes`` prints.
"""
from __future__ import annotations

import math
from typing import Callable

import jax.numpy as jnp
import numpy as np

from jaxrt import seed_distributions
from jaxrt.energy import sph as _sph
from jaxrt.sim.effects import (LJ, Gravity, SPHDensity, SPHPressure,
                               SPHViscosity, Walls)
from jaxrt.sim.spec import (Box, Integrator, Neighbors, Scene, SceneError,
                            make_particles)


def lj_fluid(*, n: int = 2048, density: float = 0.8, kT: float = 1.0,
             dt: float = 0.005, backend: str = "auto", seed: int = 0
             ) -> Scene:
    """Lennard-Jones fluid, periodic, NVE: watch the energy drift.

    ``n`` particles on a cubic lattice at number density ``density``,
    Maxwell-Boltzmann velocities at ``kT``, smooth cut from 2.0 to 2.5
    sigma, skin 0.3, time step ``dt``.
    """
    side = (n / density) ** (1 / 3)
    pos = seed_distributions.lattice(n, side)
    return Scene(
        particles=make_particles(positions=pos, temperature=kT, seed=seed),
        box=Box((side,) * 3, ("periodic",) * 3),
        effects=(LJ(r_cutoff=2.5, r_onset=2.0),),
        integrator=Integrator(dt=dt),
        neighbors=Neighbors(backend=backend, skin=0.3),
        name="lj-fluid",
        description=f"Lennard-Jones fluid, N={n}, rho={density}, periodic, "
                    "NVE (energy drift)")


def dam_break(*, dx: float = 0.05, backend: str = "auto") -> Scene:
    """2D SPH dam break: a water column collapses in a walled tank.

    A 1 x 2 m column at particle spacing ``dx`` in a 4 x 3 m tank, gravity,
    Tait pressure, artificial viscosity, potential walls.
    """
    g, height = 9.81, 2.0
    xs = np.arange(dx / 2, 1.0, dx)
    ys = np.arange(dx / 2, height, dx)
    pos = np.stack(np.meshgrid(xs, ys, indexing="ij"), -1).reshape(-1, 2)
    h = 1.3 * dx
    c0 = 10 * math.sqrt(g * height)
    mass = 1000.0 * dx * dx
    return Scene(
        particles=make_particles(positions=pos, masses=mass),
        box=Box((4.0, 3.0), ("wall", "wall")),
        effects=(SPHDensity(h=h), SPHPressure(rho0=1000.0, c0=c0),
                 SPHViscosity(alpha=0.05), Gravity(g=(0.0, -g)),
                 # Stiff enough that the hydrostatic load (rho g H dx per
                 # particle) pushes a particle ~dx/10 into the wall.
                 Walls(stiffness=1000.0 * g * height / 0.1)),
        integrator=Integrator(dt=0.2 * h / c0),
        neighbors=Neighbors(backend=backend, skin=0.5 * h),
        name="dam-break",
        description="2D SPH dam break in a walled tank with gravity "
                    "(mass exact, fluid stays in the tank)")


def sphere_surface(*, alpha: int = 8, p: int = 2, backend: str = "auto",
                   seed: int = 0) -> Scene:
    """SPH gas shell from seed 001's sphere surface, relaxing in free space.

    Particles of `jaxrt.seed_distributions.sphere_surface` (``alpha``,
    ``p``), no gravity: the shell relaxes under pressure. Kernel support =
    the seed's cutoff.
    """
    pos, cutoff = seed_distributions.sphere_surface(alpha, p, seed)
    h = cutoff / 2  # cubic spline support is 2h
    c0 = 1.0
    # rho0 = the shell's mean summation density (all pairs, once), so that
    # only compressed regions push: the flow stays subsonic for this dt.
    r = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
    w = np.asarray(_sph.kernel("cubic_spline", h, dim=3).w(jnp.asarray(r)))
    rho0 = float(np.mean(w.sum(1))) / len(pos)
    return Scene(
        particles=make_particles(positions=pos, masses=1.0 / len(pos)),
        box=Box((2.0, 2.0, 2.0), ("free",) * 3),
        effects=(SPHDensity(h=h), SPHPressure(rho0=rho0, c0=c0),
                 SPHViscosity(alpha=0.1)),
        integrator=Integrator(dt=0.2 * h / c0),
        neighbors=Neighbors(backend=backend, skin=0.5 * h),
        name="sphere-surface",
        description="SPH gas shell from seed 001's sphere surface, free "
                    "space (mass and momentum exact)")


BUILTIN: dict[str, tuple[Callable[..., Scene], int]] = {
    "lj-fluid": (lj_fluid, 1000),
    "dam-break": (dam_break, 1000),
    "sphere-surface": (sphere_surface, 500),
}
"""Built-in scenes: name -> (factory, default steps)."""


def builtin(name: str, **kwargs) -> Scene:
    """A built-in scene by name (see `BUILTIN`); ``kwargs`` go to its
    factory."""
    if name not in BUILTIN:
        raise SceneError(f"no built-in scene {name!r}; known: "
                         f"{', '.join(BUILTIN)}.")
    return BUILTIN[name][0](**kwargs)
