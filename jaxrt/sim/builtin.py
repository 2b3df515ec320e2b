"""The built-in scenes, by name in `BUILTIN` (``jaxrt scenes`` lists them).

Each factory returns a `Scene`; the first line of its docstring is the
summary ``jaxrt scenes`` prints. The effects (and JAX with them) are
imported by the factories, so that `BUILTIN` lists the scenes without JAX.
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np

from jaxrt.sim import distributions as seed_distributions
from jaxrt.sim.spec import (Box, Integrator, Neighbors, Scene, SceneError,
                            make_particles)


def lj_fluid(*, n: int = 2048, density: float = 0.8, kT: float = 1.0,
             dt: float = 0.005, backend: str = "auto", seed: int = 0,
             dim: int = 3) -> Scene:
    """Lennard-Jones fluid, periodic, NVE: watch the energy drift.

    ``n`` particles on a cubic (``dim`` 2: square) lattice at number
    density ``density``, Maxwell-Boltzmann velocities at ``kT``, smooth
    cut from 2.0 to 2.5 sigma, skin 0.3, time step ``dt``. Named
    ``lj-fluid`` (``lj-fluid-2d`` in 2D).
    """
    from jaxrt.sim.effects import LJ
    side = math.sqrt(n / density) if dim == 2 else (n / density) ** (1 / 3)
    pos = seed_distributions.lattice(n, side, dim=dim)
    flat = dim == 3  # the 3D scene keeps its name and description
    return Scene(
        particles=make_particles(positions=pos, temperature=kT, seed=seed),
        box=Box((side,) * dim, ("periodic",) * dim),
        effects=(LJ(r_cutoff=2.5, r_onset=2.0),),
        integrator=Integrator(dt=dt),
        neighbors=Neighbors(backend=backend, skin=0.3),
        name="lj-fluid" if flat else "lj-fluid-2d",
        description=("" if flat else "2D ") + f"Lennard-Jones fluid, N={n}, "
                    f"rho={density}, periodic, NVE"
                    + (" (energy drift)" if flat else ""))


def lj_polydisperse(*, n: int = 1000, density: float = 0.45,
                    kT: float = 1.0, dt: float = 0.005,
                    radii: tuple[float, ...] = (2.5, 6.0),
                    fractions: tuple[float, ...] = (0.99, 0.01),
                    backend: str = "auto", seed: int = 0, dim: int = 3
                    ) -> Scene:
    """Lennard-Jones mixture with per-particle cutoff radii, periodic, NVE.

    Species ``k`` has the cutoff radius ``radii[k]`` (absolute) and makes
    ``fractions[k]`` of the ``n`` particles (the first species takes what
    rounding leaves). Pair ``ij`` is cut at ``max(r_i, r_j)``, its LJ
    stretched by ``max(r_i, r_j) / 2.5`` (`jaxrt.sim.LJ` ``radii=``, smooth
    from 2.0 to 2.5 before stretching): a particle of radius 2.5 is the
    plain fluid's, one of 6.0 has sigma 2.4 with everyone. The default, a
    few large particles in a fluid of small ones, spans two radius classes
    (`jaxrt.backends.cell.radius_classes`: reaches 2.8 and 6.3 with the skin 0.3).

    Placement, so that no pair starts inside its core: the species other
    than the smallest at random positions (``seed``), each pair at least
    ``2**(1/6) sigma_ij`` apart (minimum image); the smallest on the
    sites of a cubic (``dim`` 2: square) lattice, those closer than that
    to a larger particle left out, ``n_small`` of the rest picked at
    random. Maxwell-Boltzmann velocities at ``kT``, number density
    ``density``, skin 0.3, time step ``dt``. Positions float64 ``(n,
    dim)``; the LJ's radii float ``(n,)``, in the particles' order.
    """
    from jaxrt.sim.effects import LJ
    r = np.asarray(radii, float)
    f = np.asarray(fractions, float)
    if r.ndim != 1 or not r.size or not np.all(np.isfinite(r) & (r > 0)):
        raise SceneError.at("lj_polydisperse.radii", f"must be a sequence of "
                            f"finite radii > 0, one per species; got {radii}.")
    if f.shape != r.shape or not np.all(f >= 0) or \
            not math.isclose(f.sum(), 1.0, abs_tol=1e-9):
        raise SceneError.at("lj_polydisperse.fractions", f"must be one "
                            f"fraction >= 0 per radius, summing to 1; got "
                            f"{fractions} for radii {radii}.")
    if dim not in (2, 3):
        raise SceneError.at("lj_polydisperse.dim", f"2 or 3; got {dim!r}.")
    r_cut = 2.5
    side = math.sqrt(n / density) if dim == 2 else (n / density) ** (1 / 3)
    counts = np.round(f * n).astype(int)
    smallest = int(np.argmin(r))
    counts[smallest] += n - counts.sum()
    rng = np.random.default_rng(seed)
    core = 2.0 ** (1 / 6) / r_cut  # 2^(1/6) sigma_ij per unit of max(r)

    def gaps(x, pts):
        d = x[None, :] - pts
        d -= side * np.round(d / side)
        return np.sqrt(np.sum(d * d, -1))

    # Larger species first, largest first (rejection sampling).
    pos, rad = [], []
    for k in sorted(np.flatnonzero(np.arange(r.size) != smallest),
                    key=lambda k: -r[k]):
        for _ in range(counts[k]):
            for _try in range(10_000):
                x = rng.uniform(0, side, dim)
                if not pos or np.all(gaps(x, np.array(pos))
                                     >= core * np.maximum(r[k], rad)):
                    break
            else:
                raise SceneError.at("lj_polydisperse.density", "no room for "
                                    f"the particles of radius {r[k]:g}; "
                                    "lower the density or their fraction.")
            pos.append(x)
            rad.append(r[k])
    # The smallest on the free sites of the finest lattice that has enough.
    need = int(counts[smallest])
    per_side = max(1, math.ceil(need ** (1 / dim)))
    while True:
        sites = seed_distributions.lattice(per_side ** dim, side, dim=dim)
        free = np.ones(len(sites), bool)
        for x, rx in zip(pos, rad):
            free &= gaps(x, sites) >= core * rx
        if free.sum() >= need:
            break
        per_side += 1
    pick = np.sort(rng.choice(np.flatnonzero(free), need, replace=False))
    pos = np.concatenate([np.reshape(pos, (-1, dim)), sites[pick]])
    rad = np.concatenate([rad, np.full(need, r[smallest])])
    return Scene(
        particles=make_particles(positions=np.mod(pos, side), temperature=kT,
                                 seed=seed),
        box=Box((side,) * dim, ("periodic",) * dim),
        effects=(LJ(r_cutoff=r_cut, r_onset=2.0, radii=tuple(rad)),),
        integrator=Integrator(dt=dt),
        neighbors=Neighbors(backend=backend, skin=0.3),
        name="lj-polydisperse",
        description=f"{dim}D Lennard-Jones mixture with cutoff radii "
                    + ", ".join(f"{x:g} ({c})" for x, c in zip(r, counts))
                    + f", N={n}, rho={density}, periodic, NVE")


def dam_break(*, dx: float = 0.05, backend: str = "auto") -> Scene:
    """2D SPH dam break: a water column collapses in a walled tank.

    A 1 x 2 m column at particle spacing ``dx`` in a 4 x 3 m tank, gravity,
    Tait pressure, artificial viscosity, potential walls.
    """
    from jaxrt.sim.effects import (Gravity, SPHDensity, SPHPressure,
                                   SPHViscosity, Walls)
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

    Particles of `jaxrt.sim.distributions.sphere_surface` (``alpha``,
    ``p``), no gravity: the shell relaxes under pressure. Kernel support =
    the seed's cutoff.
    """
    import jax.numpy as jnp

    from jaxrt.energy import sph as _sph
    from jaxrt.sim.effects import SPHDensity, SPHPressure, SPHViscosity
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


def boids(*, n: int = 2000, neighbours: float = 12.0, dt: float = 0.05,
          backend: str = "delaunay", seed: int = 0) -> Scene:
    """2D Boids (seed 004) in a periodic square, float64, Delaunay lists.

    ``n`` boids on a jittered square lattice (jitter 0.3 spacings), random
    headings at speed 0.75, in a periodic square sized for ``neighbours``
    boids within the radius R = 1 on average (side sqrt(pi R^2 n /
    neighbours)). Rules and their parameters: `jaxrt.sim.effects.Boids`'s
    defaults (cohesion 0.5, alignment 1.0, separation 0.02 within 0.25,
    speed in [0.5, 1.0], relaxation 0.05); time step ``dt``; list skin
    0.1, Dense, capacity multiplier 2. ``jaxrt run boids`` checks the list
    against brute force after every chunk and draws the triangulation.
    """
    from jaxrt.sim.effects import Boids
    rng = np.random.default_rng(seed)
    rule = Boids()
    side = math.sqrt(math.pi * rule.radius ** 2 * n / neighbours)
    per_row = math.ceil(math.sqrt(n))
    a = side / per_row
    grid = (np.stack(np.meshgrid(np.arange(per_row), np.arange(per_row),
                                 indexing="ij"), -1).reshape(-1, 2)[:n] + 0.5)
    pos = np.mod((grid + rng.uniform(-0.3, 0.3, grid.shape)) * a, side)
    heading = rng.uniform(0, 2 * math.pi, n)
    vel = 0.75 * np.stack([np.cos(heading), np.sin(heading)], -1)
    return Scene(
        particles=make_particles(positions=pos, velocities=vel),
        box=Box((side, side), ("periodic", "periodic")),
        effects=(rule,),
        integrator=Integrator(dt=dt),
        # Flocks gather: head-room for the denser regions they form.
        neighbors=Neighbors(backend=backend, skin=0.1, format="Dense",
                            capacity_multiplier=2.0),
        name="boids", dtype="float64",
        description=f"2D Boids, N={n}, ~{neighbours:g} neighbours within "
                    "R, periodic square, float64 (seed 004)")


BUILTIN: dict[str, tuple[Callable[..., Scene], int]] = {
    "lj-fluid": (lj_fluid, 1000),
    "dam-break": (dam_break, 1000),
    "sphere-surface": (sphere_surface, 500),
    "boids": (boids, 200),
    "lj-polydisperse": (lj_polydisperse, 500),
}
"""Built-in scenes: name -> (factory, default steps)."""


def builtin(name: str, **kwargs) -> Scene:
    """A built-in scene by name (see `BUILTIN`); ``kwargs`` go to its
    factory."""
    if name not in BUILTIN:
        raise SceneError(f"no built-in scene {name!r}; known: "
                         f"{', '.join(BUILTIN)}.")
    return BUILTIN[name][0](**kwargs)
