"""Scenes: particles, a box, effects and an integrator, compiled to a step.

A `Scene` (frozen dataclass, loadable from TOML with `Scene.from_toml` /
`load`) says *what* to simulate; `compile_scene` turns it into jitted
chunks of steps that compute *only* what the scene asks for:

* no neighbour list at all when no effect is pairwise (``gravity`` and
  ``walls`` are one-body);
* one shared list for all pair effects, built at the largest of their
  cutoffs (``lj``: ``r_cutoff``; ``sph_*``: the kernel support ``2h`` or
  ``3h``). Each effect truncates itself at its own cutoff, so a longer list
  only costs extra pairs, never wrong forces; one list means one search and
  one overflow check per step instead of one per effect;
* periodic image work (minimum image in the displacement, wrapping in the
  shift, ``periodic=`` of `jaxrt.neighbor_list`) on periodic axes only;
  wall and free axes use a plain difference;
* no SPH density pass without an ``sph_*`` effect;
* per-particle radii only when they differ (equal radii become one scalar
  ``sigma``); per-particle masses only when they differ.

Overflow is never silent: a chunk whose list overflowed is redone by
`Runner` after reallocating (`run_chunk`), and raises if it overflows again.

TOML layout (every key is checked; unknown keys are errors)::

    name = "my-scene"            # optional
    description = "..."          # optional
    dtype = "float32"            # or "float64" (needs jax x64)

    [box]
    size = [10.0, 10.0, 10.0]    # one side per axis
    boundary = ["periodic", "wall", "free"]   # or one string for all axes

    [particles]
    positions = [[x, y, z], ...]           # or file = "state.npz" (keys as
    velocities = [[vx, vy, vz], ...]       #  these names; path relative to
    masses = 1.0                           #  the TOML file)
    species = [0, 1, ...]                  # optional
    radius = 0.5                           # optional, scalar or per particle
    temperature = 1.0                      # instead of velocities: Maxwell-
    seed = 0                               #  Boltzmann, zero net momentum

    [[effects]]
    kind = "lj"          # sigma, epsilon (default 1), r_cutoff, r_onset
                         # (default 0.8 r_cutoff), truncation ("smooth")
    [[effects]]
    kind = "sph_density"     # h, kernel ("cubic_spline")
    [[effects]]
    kind = "sph_pressure"    # rho0, c0, gamma (7), clip_negative (true)
    [[effects]]
    kind = "sph_viscosity"   # alpha, beta (0), needs sph_pressure's c0
    [[effects]]
    kind = "gravity"         # g = [0, -9.81]
    [[effects]]
    kind = "walls"           # stiffness: harmonic push back into the box
                             # on every "wall" axis

    [integrator]
    kind = "verlet"          # velocity Verlet (NVE), or "langevin" (NVT:
    dt = 0.005               #  Verlet + an Ornstein-Uhlenbeck velocity step,
                             #  kT, gamma, seed): the thermostat

    [neighbors]
    backend = "auto"         # any of jaxrt.available_backends()
    skin = 0.3
    format = "OrderedSparse"
    capacity_multiplier = 1.25
"""
from __future__ import annotations

import dataclasses
import functools
import math
import pathlib
import re
import time
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax_md import partition

from jaxrt import neighbors as _neighbors
from jaxrt.energy import lj as _lj
from jaxrt.energy import sph as _sph

try:
    import tomllib
except ImportError:  # Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

BOUNDARIES = ("periodic", "wall", "free")
FORMATS = {"Dense": partition.Dense, "Sparse": partition.Sparse,
           "OrderedSparse": partition.OrderedSparse}


class SceneError(ValueError):
    """A scene that cannot run; the message names the field (and line)."""


# ---------------------------------------------------------------------------
# Dataclasses


def _fields(cls) -> tuple[str, ...]:
    return tuple(f.name for f in dataclasses.fields(cls))


@dataclasses.dataclass(frozen=True)
class LJ:
    """Lennard-Jones (jaxrt.energy.lj), absolute ``r_cutoff`` / ``r_onset``.

    ``sigma`` / ``epsilon``: float, or ``(S, S)`` nested lists with species.
    """
    r_cutoff: float
    sigma: Any = 1.0
    epsilon: Any = 1.0
    r_onset: float | None = None
    truncation: str = "smooth"
    kind = "lj"
    pairwise = True

    @property
    def cutoff(self) -> float:
        return float(self.r_cutoff)


@dataclasses.dataclass(frozen=True)
class SPHDensity:
    """Summation density with kernel ``kernel`` of smoothing length ``h``."""
    h: float
    kernel: str = "cubic_spline"
    kind = "sph_density"
    pairwise = True

    @property
    def cutoff(self) -> float:
        return float(_sph.KERNELS[self.kernel].support * self.h)


@dataclasses.dataclass(frozen=True)
class SPHPressure:
    """Symmetric pressure force, Tait's equation of state."""
    rho0: float
    c0: float
    gamma: float = 7.0
    clip_negative: bool = True
    kind = "sph_pressure"
    pairwise = True
    cutoff = 0.0  # uses sph_density's list


@dataclasses.dataclass(frozen=True)
class SPHViscosity:
    """Monaghan's artificial viscosity."""
    alpha: float
    beta: float = 0.0
    kind = "sph_viscosity"
    pairwise = True
    cutoff = 0.0


@dataclasses.dataclass(frozen=True)
class Gravity:
    """Uniform acceleration ``g`` (one entry per axis)."""
    g: tuple[float, ...]
    kind = "gravity"
    pairwise = False


@dataclasses.dataclass(frozen=True)
class Walls:
    """``U = k/2 sum (distance outside [0, L])**2`` on every wall axis."""
    stiffness: float
    kind = "walls"
    pairwise = False


EFFECTS = {c.kind: c for c in (LJ, SPHDensity, SPHPressure, SPHViscosity,
                               Gravity, Walls)}
_REQUIRED = {c.kind: tuple(f.name for f in dataclasses.fields(c)
                           if f.default is dataclasses.MISSING)
             for c in EFFECTS.values()}


@dataclasses.dataclass(frozen=True)
class Box:
    """Box sides ``size`` (float, one per axis) and a boundary per axis."""
    size: tuple[float, ...]
    boundary: tuple[str, ...]

    @property
    def periodic(self) -> tuple[bool, ...]:
        return tuple(b == "periodic" for b in self.boundary)


@dataclasses.dataclass(frozen=True, eq=False)
class Particles:
    """Particle data (NumPy).

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
    """``verlet`` (NVE) or ``langevin`` (NVT, friction ``gamma``, ``kT``)."""
    dt: float
    kind: str = "verlet"
    kT: float | None = None
    gamma: float | None = None
    seed: int = 0


@dataclasses.dataclass(frozen=True)
class Neighbors:
    backend: str = "auto"
    skin: float = 0.3
    format: str = "OrderedSparse"
    capacity_multiplier: float = 1.25


@dataclasses.dataclass(frozen=True, eq=False)
class Scene:
    """Everything a run needs. Build directly, or with `Scene.from_toml`.

    Construction validates the scene (raises `SceneError`).
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
        _validate(self)

    # -- TOML -------------------------------------------------------------
    @classmethod
    def from_toml(cls, text: str, *, base: pathlib.Path | None = None
                  ) -> "Scene":
        """Parse TOML text (``base``: folder for ``particles.file``)."""
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as e:
            raise SceneError(f"not valid TOML: {e}") from None
        try:
            return _from_dict(data, base or pathlib.Path("."))
        except SceneError as e:
            raise SceneError(_with_line(str(e), text)) from None

    def to_toml(self) -> str:
        """TOML text that `from_toml` reads back to an equal scene
        (particles inline: meant for small scenes)."""
        return _to_toml(self)

    @property
    def pair_effects(self) -> tuple:
        return tuple(e for e in self.effects if e.pairwise)

    @property
    def cutoff(self) -> float:
        """The shared list's cutoff (without skin): max over pair effects."""
        return max((e.cutoff for e in self.pair_effects), default=0.0)

    def effect(self, kind: str):
        return next((e for e in self.effects if e.kind == kind), None)


def load(path: str | pathlib.Path) -> Scene:
    """Read a scene from a TOML file."""
    path = pathlib.Path(path)
    return Scene.from_toml(path.read_text(), base=path.parent)


# ---------------------------------------------------------------------------
# Parsing and validation


def _err(field: str, msg: str) -> SceneError:
    return SceneError(f"{field}: {msg}")


def _check_keys(table: dict, allowed, where: str) -> None:
    if not isinstance(table, dict):
        raise _err(where, "must be a table.")
    unknown = sorted(set(table) - set(allowed))
    if unknown:
        raise _err(f"{where}.{unknown[0]}" if where else unknown[0],
                   f"unknown key {unknown[0]!r}; allowed: "
                   f"{', '.join(sorted(allowed))}.")


def _from_dict(d: dict, base: pathlib.Path) -> Scene:
    _check_keys(d, ("name", "description", "dtype", "box", "particles",
                    "effects", "integrator", "neighbors"), "")
    for key in ("box", "particles", "integrator"):
        if key not in d:
            raise _err(key, f"missing table [{key}].")
    b = d["box"]
    _check_keys(b, ("size", "boundary"), "box")
    if "size" not in b:
        raise _err("box.size", "missing parameter.")
    size = np.atleast_1d(np.asarray(b["size"], float))
    boundary = b.get("boundary", "periodic")
    boundary = ((boundary,) * size.size if isinstance(boundary, str)
                else tuple(boundary))
    box = Box(tuple(float(s) for s in size), boundary)

    p = dict(d["particles"])
    _check_keys(p, ("positions", "velocities", "masses", "species", "radius",
                    "temperature", "seed", "file"), "particles")
    if "file" in p:
        with np.load(base / p.pop("file")) as f:
            for k in f.files:
                if k not in ("positions", "velocities", "masses", "species",
                             "radius"):
                    raise _err(f"particles.file[{k}]", "unknown array.")
                p.setdefault(k, f[k])
    particles = make_particles(
        positions=p.get("positions"), velocities=p.get("velocities"),
        masses=p.get("masses", 1.0), species=p.get("species"),
        radius=p.get("radius"), temperature=p.get("temperature"),
        seed=p.get("seed", 0))

    effects = []
    raw = d.get("effects", [])
    if not isinstance(raw, list):
        raise _err("effects", "must be an array of tables [[effects]].")
    for i, e in enumerate(raw):
        where = f"effects[{i}]"
        if not isinstance(e, dict) or "kind" not in e:
            raise _err(f"{where}.kind", "missing parameter.")
        kind = e["kind"]
        if kind not in EFFECTS:
            raise _err(f"{where}.kind", f"unknown effect {kind!r}; known: "
                       f"{', '.join(EFFECTS)}.")
        cls = EFFECTS[kind]
        _check_keys(e, ("kind",) + _fields(cls), where)
        for r in _REQUIRED[kind]:
            if r not in e:
                raise _err(f"{where}.{r}", f"missing parameter of {kind!r}.")
        kw = {k: v for k, v in e.items() if k != "kind"}
        if kind == "gravity":
            kw["g"] = tuple(float(x) for x in np.atleast_1d(kw["g"]))
        effects.append(cls(**kw))

    it = d["integrator"]
    _check_keys(it, _fields(Integrator), "integrator")
    if "dt" not in it:
        raise _err("integrator.dt", "missing parameter.")
    nb = d.get("neighbors", {})
    _check_keys(nb, _fields(Neighbors), "neighbors")
    return Scene(particles=particles, box=box, effects=tuple(effects),
                 integrator=Integrator(**it), neighbors=Neighbors(**nb),
                 name=d.get("name", "scene"),
                 description=d.get("description", ""),
                 dtype=d.get("dtype", "float32"))


def make_particles(*, positions, velocities=None, masses=1.0, species=None,
                   radius=None, temperature=None, seed=0) -> Particles:
    """Particles from arrays; ``temperature`` (kT) draws Maxwell-Boltzmann
    velocities with zero net momentum instead of ``velocities``."""
    if positions is None:
        raise _err("particles.positions", "missing parameter.")
    pos = np.asarray(positions, float)
    if pos.ndim != 2 or pos.shape[1] not in (1, 2, 3) or not len(pos):
        raise _err("particles.positions", f"must be (N, dim), dim 1-3; got "
                   f"shape {pos.shape}.")
    n, dim = pos.shape
    m = np.broadcast_to(np.asarray(masses, float), (n,)).copy()
    if np.any(m <= 0):
        raise _err("particles.masses", "must be > 0.")
    if velocities is not None and temperature is not None:
        raise _err("particles.temperature", "give velocities or "
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
            raise _err("particles.velocities", f"shape {v.shape} but "
                       f"positions are {pos.shape}.")
    s = None if species is None else np.asarray(species)
    if s is not None and (s.shape != (n,) or not np.issubdtype(s.dtype,
                                                               np.integer)):
        raise _err("particles.species", f"must be {n} integers.")
    r = None
    if radius is not None:
        r = np.broadcast_to(np.asarray(radius, float), (n,)).copy()
        if np.any(r <= 0):
            raise _err("particles.radius", "must be > 0.")
    return Particles(pos, v, m, s, r)


def _validate(s: Scene) -> None:
    p, box = s.particles, s.box
    dim = p.dim
    if len(box.size) != dim or len(box.boundary) != dim:
        raise _err("box.size", f"needs {dim} entries (positions are "
                   f"{dim}D); got size {box.size}, boundary {box.boundary}.")
    for a, b in enumerate(box.boundary):
        if b not in BOUNDARIES:
            raise _err("box.boundary", f"axis {a}: {b!r} is not one of "
                       f"{BOUNDARIES}.")
        if b != "free" and not box.size[a] > 0:
            raise _err("box.size", f"axis {a} must be > 0.")
        if b == "wall":
            x = p.positions[:, a]
            bad = np.flatnonzero((x < 0) | (x > box.size[a]))
            if bad.size:
                raise _err("particles.positions",
                           f"particle {bad[0]} is outside the walled box on "
                           f"axis {a} (x = {x[bad[0]]:.4g}, box [0, "
                           f"{box.size[a]}]).")
    if s.dtype not in ("float32", "float64"):
        raise _err("dtype", "must be 'float32' or 'float64'.")
    it = s.integrator
    if not (isinstance(it.dt, (int, float)) and it.dt > 0
            and math.isfinite(it.dt)):
        raise _err("integrator.dt", f"time step must be > 0; got {it.dt}.")
    if it.kind not in ("verlet", "langevin"):
        raise _err("integrator.kind", f"{it.kind!r} is not 'verlet' or "
                   "'langevin'.")
    if it.kind == "langevin":
        for k in ("kT", "gamma"):
            v = getattr(it, k)
            if v is None or not v >= 0:
                raise _err(f"integrator.{k}", "langevin needs it, >= 0.")
    elif it.kT is not None or it.gamma is not None:
        raise _err("integrator.kT", "only the langevin integrator takes "
                   "kT / gamma.")
    nb = s.neighbors
    if nb.format not in FORMATS:
        raise _err("neighbors.format", f"{nb.format!r} is not one of "
                   f"{list(FORMATS)}.")
    if not nb.skin >= 0:
        raise _err("neighbors.skin", "must be >= 0.")
    kinds = [e.kind for e in s.effects]
    for i, e in enumerate(s.effects):
        where = f"effects[{i}]"
        if not isinstance(e, tuple(EFFECTS.values())):
            raise _err(where, f"not an effect: {e!r}.")
        if kinds.count(e.kind) > 1:
            raise _err(f"{where}.kind", f"{e.kind!r} given twice.")
        if isinstance(e, LJ):
            if e.truncation not in _lj.TRUNCATIONS:
                raise _err(f"{where}.truncation", f"one of {_lj.TRUNCATIONS}.")
            if not e.r_cutoff > 0:
                raise _err(f"{where}.r_cutoff", "must be > 0.")
            if e.r_onset is not None and not 0 <= e.r_onset < e.r_cutoff:
                raise _err(f"{where}.r_onset", "needs 0 <= r_onset < "
                           "r_cutoff.")
            sig = np.asarray(e.sigma, float)
            if sig.ndim == 2 and p.species is None:
                raise _err(f"{where}.sigma", "a matrix needs "
                           "particles.species.")
            if (p.radius is not None and np.ptp(p.radius) > 0
                    and sig.ndim):
                raise _err(f"{where}.sigma", "per-particle radii set sigma "
                           "(r_i + r_j); give no sigma matrix with them.")
        elif isinstance(e, SPHDensity):
            if not e.h > 0:
                raise _err(f"{where}.h", "must be > 0.")
            if e.kernel not in _sph.KERNELS:
                raise _err(f"{where}.kernel", f"one of {list(_sph.KERNELS)}.")
            if dim not in (2, 3):
                raise _err(f"{where}", "SPH needs 2D or 3D positions.")
        elif isinstance(e, SPHPressure):
            for k in ("rho0", "c0", "gamma"):
                if not getattr(e, k) > 0:
                    raise _err(f"{where}.{k}", "must be > 0.")
        elif isinstance(e, SPHViscosity):
            if not (e.alpha >= 0 and e.beta >= 0):
                raise _err(f"{where}.alpha", "alpha and beta must be >= 0.")
        elif isinstance(e, Gravity):
            if len(e.g) != dim:
                raise _err(f"{where}.g", f"needs {dim} entries.")
        elif isinstance(e, Walls):
            if not e.stiffness > 0:
                raise _err(f"{where}.stiffness", "must be > 0.")
            if "wall" not in box.boundary:
                raise _err(f"{where}.kind", "walls need a 'wall' axis in "
                           "box.boundary.")
        if e.kind in ("sph_pressure", "sph_viscosity") and \
                "sph_density" not in kinds:
            raise _err(f"{where}.kind", f"{e.kind} needs an sph_density "
                       "effect (it sets h and the kernel).")
        if e.kind == "sph_viscosity" and "sph_pressure" not in kinds:
            raise _err(f"{where}.kind", "sph_viscosity needs sph_pressure "
                       "(its c0 gives the sound speed).")
    if s.pair_effects:
        if nb.backend != "auto":
            from jaxrt.backends import available
            if nb.backend not in available():
                raise _err("neighbors.backend", f"{nb.backend!r} not in "
                           f"{available()}.")
        reach = s.cutoff + nb.skin
        for a, per in enumerate(box.periodic):
            if per and reach > box.size[a] / 2:
                i = max(range(len(s.effects)),
                        key=lambda k: s.effects[k].cutoff
                        if s.effects[k].pairwise else -1)
                field = ("h" if s.effects[i].kind == "sph_density"
                         else "r_cutoff")
                raise _err(f"effects[{i}].{field}",
                           f"cutoff + skin = {reach:.4g} is longer than half "
                           f"the periodic box side {box.size[a]} (axis {a}); "
                           "the minimum image would miss pairs.")


def _with_line(msg: str, text: str) -> str:
    """Append ``(line L)`` for the field a message names, when found."""
    m = re.match(r"(effects\[(\d+)\]|[a-z_]+)\.?([a-zA-Z_0-9]*)", msg)
    if not m:
        return msg
    lines = text.splitlines()
    table, key = m.group(1), m.group(3)
    if m.group(2) is not None:
        starts = [i for i, l in enumerate(lines)
                  if l.strip().startswith("[[effects]]")]
        k = int(m.group(2))
        if k >= len(starts):
            return msg
        start = starts[k]
    elif key:
        start = next((i for i, l in enumerate(lines)
                      if l.strip() == f"[{table}]"), None)
        if start is None:
            return msg
    else:
        key, start = table, -1
    for i in range(start + 1, len(lines)):
        s = lines[i].strip()
        if s.startswith("[") and i > start + 1 and start >= 0:
            break
        if re.match(rf"{re.escape(key)}\s*=", s):
            return f"{msg} (line {i + 1})"
    return f"{msg} (line {start + 1})" if start >= 0 else msg


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (np.ndarray, list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in list(v)) + "]"
    if isinstance(v, (np.integer, int)):
        return str(int(v))
    return repr(float(v))


def _to_toml(s: Scene) -> str:
    out = [f"name = {_toml_value(s.name)}",
           f"description = {_toml_value(s.description)}",
           f"dtype = {_toml_value(s.dtype)}", "", "[box]",
           f"size = {_toml_value(s.box.size)}",
           f"boundary = {_toml_value(s.box.boundary)}", "", "[particles]"]
    p = s.particles
    for k in ("positions", "velocities", "masses", "species", "radius"):
        v = getattr(p, k)
        if v is not None:
            out.append(f"{k} = {_toml_value(v)}")
    for e in s.effects:
        out += ["", "[[effects]]", f"kind = {_toml_value(e.kind)}"]
        for f in dataclasses.fields(e):
            v = getattr(e, f.name)
            if v is not None:
                out.append(f"{f.name} = {_toml_value(v)}")
    for title, obj in (("integrator", s.integrator),
                       ("neighbors", s.neighbors)):
        out += ["", f"[{title}]"]
        for f in dataclasses.fields(obj):
            v = getattr(obj, f.name)
            if v is not None:
                out.append(f"{f.name} = {_toml_value(v)}")
    return "\n".join(out) + "\n"


# ---------------------------------------------------------------------------
# Compilation


class State(NamedTuple):
    """The carried state of a run.

    position, velocity, accel: float ``(N, dim)``; rho: float ``(N,)`` (SPH
    density; shape ``(0,)`` without SPH); key: PRNG key (Langevin only, else
    an unused scalar); rebuilds: int32 scalar, list rebuilds so far.
    """
    position: jax.Array
    velocity: jax.Array
    accel: jax.Array
    rho: jax.Array
    key: jax.Array
    rebuilds: jax.Array


class Trace(NamedTuple):
    """Per-step records, each float ``(steps,)`` (momentum ``(steps, dim)``).
    """
    kinetic: jax.Array
    potential: jax.Array
    momentum: jax.Array


@dataclasses.dataclass(frozen=True)
class Compiled:
    """A scene compiled to functions.

    init() -> (State, nbrs or None); chunk(state, nbrs, *, steps) ->
    (state, nbrs, Trace), jitted; neighbor_fn (None without pair effects);
    plan: what the step computes and what it skips, in words.
    """
    scene: Scene
    init: Callable
    chunk: Callable
    step: Callable
    neighbor_fn: Any
    displacement: Callable
    plan: tuple[str, ...]


def _displacement_shift(box: Box):
    """Displacement and shift doing image work on periodic axes only."""
    per = np.asarray(box.periodic)
    if not per.any():
        # Plain difference: no rounding, no modulo (tested through the jaxpr).
        return (lambda ra, rb, **kw: ra - rb), (lambda r, dr, **kw: r + dr)
    side = np.where(per, np.asarray(box.size, float), 1.0)
    axes = np.flatnonzero(per)

    def displacement(ra, rb, **kw):
        d = ra - rb
        L = jnp.asarray(side[axes], d.dtype)
        wrapped = d[..., axes] - L * jnp.round(d[..., axes] / L)
        return d.at[..., axes].set(wrapped)

    def shift(r, dr, **kw):
        x = r + dr
        L = jnp.asarray(side[axes], x.dtype)
        return x.at[..., axes].set(jnp.mod(x[..., axes], L))

    return displacement, shift


def _list_sides(box: Box) -> np.ndarray:
    """The ``box=`` of `jaxrt.neighbor_list`: float64 ``(dim,)``, one
    positive side per axis.

    The list reads the side on periodic axes only, but needs a positive
    number on every axis: a single missing side (a free axis may have size
    0) would make it drop the whole box, and then the periodic axes of a
    mixed box have none. Wall axes keep their size; a free axis without a
    positive size gets 1.0 (never read).
    """
    size = np.asarray(box.size, float)
    ok = np.isfinite(size) & (size > 0)
    return np.where(ok, size, 1.0)


def compile_scene(scene: Scene, *, neighbor_list_fn: Callable | None = None
                  ) -> Compiled:
    """Compile ``scene`` to a step containing only its effects.

    ``neighbor_list_fn``: the list factory (default `jaxrt.neighbor_list`;
    tests pass a counting wrapper).
    """
    nl_fn = neighbor_list_fn or _neighbors.neighbor_list
    dtype = jnp.dtype(scene.dtype)
    p, box = scene.particles, scene.box
    n, dim = p.n, p.dim
    displacement, shift = _displacement_shift(box)
    plan = []
    masses = p.masses
    mass = (float(masses[0]) if np.ptp(masses) == 0
            else jnp.asarray(masses, dtype))
    plan.append("masses: " + ("one scalar" if np.ndim(mass) == 0
                              else "per particle"))
    m_col = mass if np.ndim(mass) == 0 else mass[:, None]

    neighbor_fn = None
    if scene.pair_effects:
        fmt = FORMATS[scene.neighbors.format]
        # Sides on every axis, even with free axes: periodic ones need theirs
        # (periodic= says which axes wrap; the others' sides are not read).
        neighbor_fn = nl_fn(
            displacement, _list_sides(box), scene.cutoff, scene.neighbors.skin,
            capacity_multiplier=scene.neighbors.capacity_multiplier,
            format=fmt, backend=scene.neighbors.backend,
            periodic=box.periodic)
        plan.append(f"one neighbour list, cutoff {scene.cutoff:.4g} + skin "
                    f"{scene.neighbors.skin:.4g}, periodic={box.periodic}")
    else:
        plan.append("no neighbour list (no pair effect)")
    if not any(box.periodic):
        plan.append("no periodic image work")

    # Potential-energy terms U(R, nbrs); force = -grad U.
    terms = []
    ljp = scene.effect("lj")
    if ljp is not None:
        sigma, epsilon = ljp.sigma, ljp.epsilon
        if p.radius is not None and np.ptp(p.radius) > 0:
            # sigma_ij = (sigma_i + sigma_j) / 2 = r_i + r_j.
            sigma = jnp.asarray(2 * p.radius, dtype)
            plan.append("per-particle radii: sigma_ij = r_i + r_j")
        elif p.radius is not None:
            sigma = float(2 * p.radius[0])
            plan.append("equal radii: scalar sigma, no radius handling")
        if np.ndim(sigma) == 2:
            sigma = jnp.asarray(sigma, dtype)
        if np.ndim(epsilon) == 2:
            epsilon = jnp.asarray(epsilon, dtype)
        species = (None if p.species is None or
                   (np.ndim(sigma) < 2 and np.ndim(epsilon) < 2)
                   else jnp.asarray(p.species))
        r_onset = (0.8 * ljp.r_cutoff if ljp.r_onset is None
                   else ljp.r_onset)
        lj_energy = _lj.lennard_jones_pair_neighbor_list(
            displacement, species=species, sigma=sigma, epsilon=epsilon,
            r_onset=r_onset, r_cutoff=ljp.r_cutoff,
            truncation=ljp.truncation)

        def lj(R, nbrs):
            return lj_energy(R, nbrs)
        terms.append(jax.jit(lj))
    g = scene.effect("gravity")
    if g is not None:
        gvec = np.asarray(g.g, float)

        def gravity(R, nbrs):
            return -jnp.sum(m_col * R * jnp.asarray(gvec, R.dtype))
        terms.append(jax.jit(gravity))
    w = scene.effect("walls")
    if w is not None:
        axes = np.flatnonzero(np.asarray(box.boundary) == "wall")
        hi = np.asarray(box.size)[axes]

        def walls(R, nbrs):
            x = R[:, axes]
            out = jnp.maximum(-x, 0) + jnp.maximum(x - hi.astype(x.dtype), 0)
            return 0.5 * w.stiffness * jnp.sum(out * out)
        terms.append(jax.jit(walls))
    plan.append("potential terms: " + (", ".join(
        t.__name__ if hasattr(t, "__name__") else str(t) for t in terms)
        or "none"))

    def potential(R, nbrs):
        return sum((t(R, nbrs) for t in terms), jnp.zeros((), R.dtype))

    dens = scene.effect("sph_density")
    pres = scene.effect("sph_pressure")
    visc = scene.effect("sph_viscosity")
    if dens is not None:
        kern = _sph.kernel(dens.kernel, dens.h, dim=dim)
        density_fn = _sph.density(displacement, kern, mass=mass)
        eos = (None if pres is None else
               _sph.Tait(rho0=pres.rho0, c0=pres.c0, gamma=pres.gamma))

        def sph_density(R, nbrs):
            return density_fn(R, nbrs)
        sph_density = jax.jit(sph_density)
        plan.append("SPH: density" + (", pressure" if pres else "")
                    + (", viscosity" if visc else ""))
        if pres is not None:
            accel_fn = _sph.acceleration(
                displacement, kern, eos, mass=mass,
                alpha=0.0 if visc is None else visc.alpha,
                beta=0.0 if visc is None else visc.beta)

            def sph_forces(R, V, nbrs, rho):
                pr = eos.pressure(rho)
                if pres.clip_negative:  # a free surface cannot pull
                    pr = jnp.maximum(pr, 0)
                a = accel_fn(R, V, nbrs, rho=rho, pressure=pr)
                # Unused terms are dropped by XLA: no viscosity pass is
                # kept without sph_viscosity.
                return a.pressure + (a.viscosity if visc is not None else 0)
            sph_forces = jax.jit(sph_forces)
    else:
        plan.append("no SPH density pass")

    def accel(R, V, nbrs):
        """Returns (acceleration (N, dim), potential energy (), rho)."""
        if terms:
            u, grad = jax.value_and_grad(potential)(R, nbrs)
            a = -grad / m_col
        else:
            u, a = jnp.zeros((), R.dtype), jnp.zeros_like(R)
        rho = jnp.zeros((0,), R.dtype)
        if dens is not None:
            rho = sph_density(R, nbrs)
            if pres is not None:
                a = a + sph_forces(R, V, nbrs, rho)
        return a, u, rho

    it = scene.integrator
    dt = it.dt

    def step(state: State, nbrs):
        """One kick-drift-kick velocity Verlet step (the update of
        jax_md.simulate.nve), then the Langevin O step if NVT."""
        v_half = state.velocity + 0.5 * dt * state.accel
        R = shift(state.position, dt * v_half)
        rebuilds = state.rebuilds
        if nbrs is not None:
            new = neighbor_fn.update(R, nbrs)
            rebuilds = rebuilds + jnp.any(
                new.reference_position != nbrs.reference_position)
            nbrs = new
        # Velocity-dependent SPH terms see the half-step velocity.
        a, u, rho = accel(R, v_half, nbrs)
        v = v_half + 0.5 * dt * a
        key = state.key
        if it.kind == "langevin":
            key, sub = jax.random.split(key)
            c1 = math.exp(-it.gamma * dt)
            sd = jnp.sqrt((1 - c1 * c1) * it.kT / m_col)
            v = c1 * v + sd * jax.random.normal(sub, v.shape, v.dtype)
        ke = 0.5 * jnp.sum(m_col * v * v)
        mom = jnp.sum(m_col * v, axis=0)
        return State(R, v, a, rho, key, rebuilds), nbrs, (ke, u, mom)

    @functools.partial(jax.jit, static_argnames=("steps",))
    def chunk(state, nbrs, *, steps):
        def body(carry, _):
            s, nb = carry
            s, nb, rec = step(s, nb)
            return (s, nb), rec
        (state, nbrs), (ke, u, mom) = lax.scan(body, (state, nbrs), None,
                                               length=steps)
        return state, nbrs, Trace(ke, u, mom)

    def init():
        R = jnp.asarray(p.positions, dtype)
        V = jnp.asarray(p.velocities, dtype)
        nbrs = None if neighbor_fn is None else neighbor_fn.allocate(R)
        a, u, rho = jax.jit(accel)(R, V, nbrs)
        key = (jax.random.PRNGKey(it.seed) if it.kind == "langevin"
               else jnp.zeros((), jnp.uint32))
        return State(R, V, a, rho, key, jnp.zeros((), jnp.int32)), nbrs

    return Compiled(scene, init, chunk, step, neighbor_fn, displacement,
                    tuple(plan))


# ---------------------------------------------------------------------------
# Running


@dataclasses.dataclass
class RunStats:
    steps: int = 0
    seconds: float = 0.0
    overflows: int = 0
    rebuilds: int = 0
    kinetic: list = dataclasses.field(default_factory=list)
    potential: list = dataclasses.field(default_factory=list)
    momentum: list = dataclasses.field(default_factory=list)


def run_chunk(compiled: Compiled, state: State, nbrs, *, steps: int,
              stats: RunStats | None = None):
    """Run ``steps`` steps; if the list overflowed, reallocate at the
    chunk's start and redo it (raises if it overflows again)."""
    new_state, new_nbrs, trace = compiled.chunk(state, nbrs, steps=steps)
    if new_nbrs is not None and new_nbrs.did_buffer_overflow:
        if stats is not None:
            stats.overflows += 1
        from jaxrt.errors import check
        code = int(np.asarray(new_nbrs.error.code))
        if code & 16:  # non-finite position: reallocating cannot help
            check(new_nbrs)
        nbrs = compiled.neighbor_fn.allocate(state.position)
        new_state, new_nbrs, trace = compiled.chunk(state, nbrs, steps=steps)
        if new_nbrs.did_buffer_overflow:
            raise RuntimeError(
                "the neighbour list overflowed twice in one chunk: lower the "
                "chunk length or raise neighbors.capacity_multiplier.")
    if stats is not None:
        stats.steps += steps
        stats.kinetic.append(np.asarray(trace.kinetic))
        stats.potential.append(np.asarray(trace.potential))
        stats.momentum.append(np.asarray(trace.momentum))
        stats.rebuilds = int(new_state.rebuilds)
    return new_state, new_nbrs


# ---------------------------------------------------------------------------
# Built-in scenes


def lj_fluid(*, n: int = 2048, density: float = 0.8, kT: float = 1.0,
             dt: float = 0.005, backend: str = "auto", seed: int = 0
             ) -> Scene:
    """LJ fluid: ``n`` particles on a cubic lattice, periodic, rho = 0.8,
    kT = 1 velocities, smooth cut 2.0-2.5 sigma, skin 0.3, NVE."""
    from jaxrt import scenes
    side = (n / density) ** (1 / 3)
    pos = scenes.lattice(n, side)
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
    """2D SPH dam break: a 1 x 2 m water column in a 4 x 3 m walled tank,
    gravity, Tait pressure, artificial viscosity; potential walls."""
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
    """SPH gas released from seed 001's sphere-surface distribution
    (`jaxrt.scenes.sphere_surface`), free space, no gravity: the shell
    relaxes under pressure. Kernel support = the seed's cutoff."""
    from jaxrt import scenes
    pos, cutoff = scenes.sphere_surface(alpha, p, seed)
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
    """A built-in scene by name (see `BUILTIN`)."""
    if name not in BUILTIN:
        raise SceneError(f"no built-in scene {name!r}; known: "
                         f"{', '.join(BUILTIN)}.")
    return BUILTIN[name][0](**kwargs)
