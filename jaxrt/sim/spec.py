"""The scene spec: what to simulate, as frozen dataclasses, and its checks.

A `Scene` holds `Particles`, a `Box`, effects, an `Integrator` and
`Neighbors` settings. Building one checks it: a `SceneError` names the
field (``"integrator.dt: ..."``), so the TOML reader can add its line.

Effects are any objects that follow the `Effect` protocol defined here; the
package's own are in `jaxrt.sim.effects`. An effect hands the compiler its
contribution as a `Term`, built from the `Context` the compiler gives it.

This module imports nothing else from jaxrt but `jaxrt.errors` (the base
of `SceneError`): the TOML reader
(`jaxrt.sim.toml`), the effects and the compiler (`jaxrt.sim.compile`)
build on the spec, never the reverse.
"""
from __future__ import annotations

import dataclasses
import inspect
import math
from typing import Any, Callable, ClassVar, Protocol

import numpy as np

from jaxrt.errors import Error

BOUNDARIES = ("periodic", "wall", "free")
FORMAT_NAMES = ("Dense", "Sparse", "OrderedSparse")
"""jax-md's list layouts, by name (`jaxrt.sim.compile.FORMATS` maps them)."""
INTEGRATORS = ("verlet", "langevin", "perse")
DTYPES = ("float32", "float64")


class SceneError(Error, ValueError):
    """A scene that cannot run; the message names the field (and line)."""

    @classmethod
    def at(cls, field: str, msg: str) -> "SceneError":
        """The error for ``field`` (``"effects[1].h"``): ``"field: msg"``,
        the form the TOML reader finds the line of."""
        return cls(f"{field}: {msg}")


# ---------------------------------------------------------------------------
# The effect protocol


@dataclasses.dataclass(frozen=True)
class Term:
    """What one effect adds to the step. Any of the functions may be None.

    The compiler jits each function under its own ``__name__``, which the
    plan and the jaxpr show, so name them after the effect.

    energy: ``U(R, nbrs) -> float ()``, a potential energy; the force is
      ``-grad U`` and U is part of the reported potential energy.
    density: ``rho(R, nbrs) -> float (N,)``, a per-particle density that
      every ``accel`` then reads (one effect per scene at most).
    accel: ``a(R, V, nbrs, rho) -> float (N, dim)``, an acceleration that
      does not come from a potential (SPH pressure, viscosity).
    notes: lines for the plan, what the term chose or skipped.

    ``R``, ``V``: float ``(N, dim)`` positions and velocities; ``nbrs``: the
    shared neighbour list, or None when the scene has no pair effect;
    ``rho``: float ``(N,)``, or shape ``(0,)`` without a density term.
    """
    energy: Callable | None = None
    density: Callable | None = None
    accel: Callable | None = None
    notes: tuple[str, ...] = ()


@dataclasses.dataclass(frozen=True)
class Context:
    """What the compiler hands `Effect.term`.

    scene: the `Scene`. displacement: ``d(Ra, Rb) -> (dim,)`` with the box's
    image rule (minimum image on periodic axes only). dtype: the run's
    float dtype (a numpy dtype). mass: a Python float when all masses are
    equal, else a ``dtype`` array ``(N,)``.
    """
    scene: "Scene"
    displacement: Callable
    dtype: Any
    mass: Any

    @property
    def mass_column(self):
        """``mass`` shaped to broadcast against ``(N, dim)``."""
        return self.mass if np.ndim(self.mass) == 0 else self.mass[:, None]


class Effect(Protocol):
    """An effect: one frozen dataclass whose fields are its parameters (the
    keys of its ``[[effects]]`` table, defaults for the optional ones).

    kind: its name in TOML (``"lj"``), a class attribute.
    pairwise: a class attribute (or a property of its fields: the SPH
      effects' ``list_free``), True if it reads the shared neighbour list.
    cutoff: float, the pair distance it needs the list to reach (0.0 for an
      effect that only reads pairs another effect asked for, or none).
    radii (optional): None, or per-particle cutoff radii, float, one per
      particle: the effect needs pair ``ij`` only within ``max(r_i, r_j)``
      (its ``cutoff`` is then their largest), and the shared list is built
      with radii (`jaxrt.sim.compile.list_radii`).
    validate(scene, where): raise `SceneError` (``SceneError.at``) naming
      ``f"{where}.<field>"`` if it cannot run in ``scene``, also when it
      needs another effect; ``where`` is ``"effects[i]"``.
    term(ctx): its contribution, a `Term` built from a `Context`.
    """
    kind: ClassVar[str]
    pairwise: ClassVar[bool]

    @property
    def cutoff(self) -> float: ...

    def validate(self, scene: "Scene", where: str) -> None: ...

    def term(self, ctx: Context) -> Term: ...


def check_reach(scene: "Scene", cutoff: float, field: str) -> None:
    """Raise at ``field`` if ``cutoff`` plus the skin is longer than half a
    periodic side: the minimum image would then miss pairs. For effects
    with a cutoff of their own, from their ``validate``."""
    reach = cutoff + scene.neighbors.skin
    for a, per in enumerate(scene.box.periodic):
        if per and reach > scene.box.size[a] / 2:
            raise SceneError.at(
                field, f"cutoff + skin = {reach:.4g} is longer than half the "
                f"periodic box side {scene.box.size[a]} (axis {a}); the "
                "minimum image would miss pairs.")


# ---------------------------------------------------------------------------
# The spec


@dataclasses.dataclass(frozen=True)
class Box:
    """Box sides ``size`` (float, one per axis) and a boundary per axis
    (one of `BOUNDARIES`)."""
    size: tuple[float, ...]
    boundary: tuple[str, ...]

    @property
    def periodic(self) -> tuple[bool, ...]:
        return tuple(b == "periodic" for b in self.boundary)


@dataclasses.dataclass(frozen=True, eq=False)
class Particles:
    """Particle data (NumPy), best made with `make_particles`.

    positions, velocities: float ``(N, dim)``; masses: float ``(N,)``;
    species: int ``(N,)`` or None; radius: float ``(N,)`` or None.
    """
    positions: np.ndarray
    velocities: np.ndarray
    masses: np.ndarray
    species: np.ndarray | None = None
    radius: np.ndarray | None = None

    @property
    def n(self) -> int:
        return self.positions.shape[0]

    @property
    def dim(self) -> int:
        return self.positions.shape[1]


@dataclasses.dataclass(frozen=True)
class Integrator:
    """``verlet`` (NVE, time step ``dt``), ``langevin`` (NVT: Verlet, then
    an Ornstein-Uhlenbeck velocity step of friction ``gamma`` towards
    ``kT``, random numbers from ``seed``) or ``perse`` (NVE by ORCS-persé,
    seed 003 §3.2.1: a whole leapfrog step in one kernel, no neighbour
    list; only for a scene whose one effect is ``lj`` with scalar sigma and
    epsilon, the smooth truncation, equal radii and equal masses)."""
    dt: float
    kind: str = "verlet"
    kT: float | None = None
    gamma: float | None = None
    seed: int = 0


@dataclasses.dataclass(frozen=True)
class Neighbors:
    """The shared neighbour list: ``backend`` (``"auto"`` or one of
    `jaxrt.available_backends`), ``skin`` (jax-md's ``dr_threshold``),
    ``format`` (one of `FORMAT_NAMES`), ``capacity_multiplier``."""
    backend: str = "auto"
    skin: float = 0.3
    format: str = "OrderedSparse"
    capacity_multiplier: float = 1.25


@dataclasses.dataclass(frozen=True, eq=False)
class Scene:
    """Everything a run needs. Build directly, or read one with
    `jaxrt.sim.from_toml` / `jaxrt.sim.load`.

    effects: a tuple of `Effect` objects, at most one of each kind.
    dtype: ``"float32"`` or ``"float64"`` (needs jax x64).
    Construction checks the scene (raises `SceneError`); the neighbour
    backend is checked against the installation when the scene is read or
    compiled (`jaxrt.sim.validate`).
    """
    particles: Particles
    box: Box
    effects: tuple
    integrator: Integrator
    neighbors: Neighbors = Neighbors()
    name: str = "scene"
    description: str = ""
    dtype: str = "float32"

    def __post_init__(self):
        _check_box(self.box, self.particles)
        _check_dtype(self.dtype)
        _check_integrator(self.integrator)
        _check_neighbors(self.neighbors)
        _check_effects(self)
        _check_perse(self)

    @property
    def pair_effects(self) -> tuple:
        return tuple(e for e in self.effects if e.pairwise)

    @property
    def cutoff(self) -> float:
        """The shared list's cutoff (without skin): max over pair effects."""
        return max((e.cutoff for e in self.pair_effects), default=0.0)

    def effect(self, kind: str):
        """The effect of ``kind``, or None."""
        return next((e for e in self.effects if e.kind == kind), None)


def make_particles(*, positions, velocities=None, masses=1.0, species=None,
                   radius=None, temperature=None, seed=0) -> Particles:
    """Particles from arrays; ``temperature`` (kT) draws Maxwell-Boltzmann
    velocities with zero net momentum instead of ``velocities``.

    positions: ``(N, dim)``, dim 1 to 3; velocities: ``(N, dim)`` or None
    (at rest); masses, radius: scalar or ``(N,)``, > 0; species: ints
    ``(N,)``; seed: int, for ``temperature``.
    """
    if positions is None:
        raise SceneError.at("particles.positions", "missing parameter.")
    pos = np.asarray(positions, float)
    if pos.ndim != 2 or pos.shape[1] not in (1, 2, 3) or not len(pos):
        raise SceneError.at("particles.positions", f"must be (N, dim), dim "
                            f"1-3; got shape {pos.shape}.")
    n, dim = pos.shape
    m = np.broadcast_to(np.asarray(masses, float), (n,)).copy()
    if np.any(m <= 0):
        raise SceneError.at("particles.masses", "must be > 0.")
    if velocities is not None and temperature is not None:
        raise SceneError.at("particles.temperature", "give velocities or "
                            "temperature, not both.")
    if temperature is not None:
        rng = np.random.default_rng(seed)
        v = rng.standard_normal((n, dim)) * np.sqrt(temperature / m)[:, None]
        v -= (m[:, None] * v).sum(0) / m.sum()  # no drift of the centre
    elif velocities is None:
        v = np.zeros_like(pos)
    else:
        v = np.asarray(velocities, float)
        if v.shape != pos.shape:
            raise SceneError.at("particles.velocities", f"shape {v.shape} "
                                f"but positions are {pos.shape}.")
    s = None if species is None else np.asarray(species)
    if s is not None and (s.shape != (n,) or not np.issubdtype(s.dtype,
                                                               np.integer)):
        raise SceneError.at("particles.species", f"must be {n} integers.")
    r = None
    if radius is not None:
        r = np.broadcast_to(np.asarray(radius, float), (n,)).copy()
        if np.any(r <= 0):
            raise SceneError.at("particles.radius", "must be > 0.")
    return Particles(pos, v, m, s, r)


# ---------------------------------------------------------------------------
# Checks, run by Scene.__post_init__ in this order


def _check_box(box: Box, p: Particles) -> None:
    dim = p.dim
    if len(box.size) != dim or len(box.boundary) != dim:
        raise SceneError.at("box.size", f"needs {dim} entries (positions are "
                            f"{dim}D); got size {box.size}, boundary "
                            f"{box.boundary}.")
    for a, b in enumerate(box.boundary):
        if b not in BOUNDARIES:
            raise SceneError.at("box.boundary", f"axis {a}: {b!r} is not one "
                                f"of {BOUNDARIES}.")
        if b != "free" and not box.size[a] > 0:
            raise SceneError.at("box.size", f"axis {a} must be > 0.")
        if b == "wall":
            x = p.positions[:, a]
            bad = np.flatnonzero((x < 0) | (x > box.size[a]))
            if bad.size:
                raise SceneError.at(
                    "particles.positions", f"particle {bad[0]} is outside the "
                    f"walled box on axis {a} (x = {x[bad[0]]:.4g}, box [0, "
                    f"{box.size[a]}]).")


def _check_dtype(dtype: str) -> None:
    if dtype not in DTYPES:
        raise SceneError.at("dtype", "must be 'float32' or 'float64'.")


def _check_integrator(it: Integrator) -> None:
    if not (isinstance(it.dt, (int, float)) and it.dt > 0
            and math.isfinite(it.dt)):
        raise SceneError.at("integrator.dt", f"time step must be > 0; got "
                            f"{it.dt}.")
    if it.kind not in INTEGRATORS:
        raise SceneError.at("integrator.kind", f"{it.kind!r} is not "
                            "'verlet', 'langevin' or 'perse'.")
    if it.kind == "langevin":
        for k in ("kT", "gamma"):
            v = getattr(it, k)
            if v is None or not v >= 0:
                raise SceneError.at(f"integrator.{k}", "langevin needs it, "
                                    ">= 0.")
    elif it.kT is not None or it.gamma is not None:
        raise SceneError.at("integrator.kT", "only the langevin integrator "
                            "takes kT / gamma.")


def _check_perse(scene: "Scene") -> None:
    """ORCS-persé applies to one smooth LJ effect with scalar parameters,
    equal radii and equal masses (seed 003 §3.2.3)."""
    if scene.integrator.kind != "perse":
        return
    field = "integrator.kind"
    kinds = [getattr(e, "kind", None) for e in scene.effects]
    if kinds != ["lj"]:
        raise SceneError.at(field, f"'perse' computes LJ only; the scene has "
                            f"effects {kinds}. Use 'verlet'.")
    lj = scene.effects[0]
    if (np.ndim(lj.sigma) or np.ndim(lj.epsilon)
            or getattr(lj, "truncation", "smooth") != "smooth"):
        raise SceneError.at(field, "'perse' needs scalar sigma and epsilon "
                            "and truncation 'smooth'. Use 'verlet'.")
    if getattr(lj, "radii", None) is not None:
        raise SceneError.at(field, "'perse' needs one cutoff for every pair "
                            "(with cutoff radii each pair is found from one "
                            "side only); drop lj.radii or use 'verlet'.")
    p = scene.particles
    if p.radius is not None and np.ptp(p.radius) > 0:
        raise SceneError.at(field, "'perse' needs equal radii (with "
                            "different radii each pair is found from one "
                            "side only). Use 'verlet'.")
    if np.ptp(p.masses) > 0:
        raise SceneError.at(field, "'perse' needs equal masses. Use "
                            "'verlet'.")
    if scene.neighbors.backend not in ("auto", "bvh", "brute"):
        raise SceneError.at("neighbors.backend", "'perse' runs on 'bvh' (or "
                            "'brute', its pure-JAX reference); got "
                            f"{scene.neighbors.backend!r}.")


def _check_neighbors(nb: Neighbors) -> None:
    if nb.format not in FORMAT_NAMES:
        raise SceneError.at("neighbors.format", f"{nb.format!r} is not one "
                            f"of {list(FORMAT_NAMES)}.")
    if not nb.skin >= 0:
        raise SceneError.at("neighbors.skin", "must be >= 0.")


def _is_effect(e) -> bool:
    # Looked up statically: a property such as ``cutoff`` may not be able to
    # run before the effect's own validate has checked its parameters.
    missing = object()
    return all(inspect.getattr_static(e, a, missing) is not missing
               for a in ("kind", "pairwise", "cutoff", "validate", "term"))


def _check_effects(scene: Scene) -> None:
    kinds = [getattr(e, "kind", None) for e in scene.effects]
    for i, e in enumerate(scene.effects):
        where = f"effects[{i}]"
        if not _is_effect(e):
            raise SceneError.at(where, f"not an effect: {e!r}.")
        if kinds.count(e.kind) > 1:
            raise SceneError.at(f"{where}.kind", f"{e.kind!r} given twice.")
        e.validate(scene, where)
