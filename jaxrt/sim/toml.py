"""Scenes as TOML: `from_toml`, `load` (read) and `to_toml` (write).

Every key is checked: an unknown key or a bad value is a `SceneError` that
names the field and its line. Effects are looked up by ``kind`` in a
`jaxrt.sim.effects.Registry` (by default ``EFFECTS``, the package's own);
each effect's keys are its dataclass fields.

Layout::

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
                             #  kT, gamma, seed): the thermostat; or "perse"
                             #  (ORCS-persé: one kernel per step, no list;
                             #  one smooth "lj", equal radii and masses)

    [neighbors]
    backend = "auto"         # any of jaxrt.available_backends()
    skin = 0.3
    format = "OrderedSparse"
    capacity_multiplier = 1.25
"""
from __future__ import annotations

import dataclasses
import pathlib
import re
import tomllib
from typing import TYPE_CHECKING

import numpy as np

from jaxrt.sim.spec import (Box, Integrator, Neighbors, Particles, Scene,
                            SceneError, make_particles)
from jaxrt.sim.validate import check_backend

_PARTICLE_ARRAYS = ("positions", "velocities", "masses", "species", "radius")

if TYPE_CHECKING:  # the effects import JAX; `check_text` runs without it
    from jaxrt.sim.effects import Registry


def from_toml(text: str, *, base: pathlib.Path | None = None,
              effects: Registry | None = None) -> Scene:
    """Parse TOML text into a `Scene`.

    base: folder for ``particles.file`` (default: the working directory).
    effects: the registry to look ``kind`` up in (default ``EFFECTS``).
    """
    data = _parse(text)
    if effects is None:
        from jaxrt.sim.effects import EFFECTS
        effects = EFFECTS
    try:
        scene = _scene(data, base or pathlib.Path("."), effects)
        check_backend(scene)
        return scene
    except SceneError as e:
        raise SceneError(_with_line(str(e), text)) from None


def check_text(text: str, *, base: pathlib.Path | None = None) -> None:
    """Check scene TOML as far as the spec alone can, without importing
    JAX: the TOML itself, the keys and values of every table, and each
    effect's kind and keys (`from_toml` also runs the effects' checks
    against the whole scene, which need JAX). Raises `SceneError` naming
    the field and its line. ``base`` as in `from_toml`."""
    from jaxrt.sim.effects import EFFECTS
    data = _parse(text)
    try:
        _parts(data, base or pathlib.Path("."))
        _effects(data.get("effects", []), EFFECTS)
    except SceneError as e:
        raise SceneError(_with_line(str(e), text)) from None


def _parse(text: str) -> dict:
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise SceneError(f"not valid TOML: {e}") from None


def load(path: str | pathlib.Path, *, effects: Registry | None = None
         ) -> Scene:
    """Read a scene from a TOML file (``effects`` as in `from_toml`)."""
    path = pathlib.Path(path)
    return from_toml(path.read_text(), base=path.parent, effects=effects)


def to_toml(scene: Scene) -> str:
    """TOML text that `from_toml` reads back to an equal scene (particles
    inline: meant for small scenes)."""
    s = scene
    out = [f"name = {_value(s.name)}",
           f"description = {_value(s.description)}",
           f"dtype = {_value(s.dtype)}", "", "[box]",
           f"size = {_value(s.box.size)}",
           f"boundary = {_value(s.box.boundary)}", "", "[particles]"]
    p = s.particles
    for k in _PARTICLE_ARRAYS:
        v = getattr(p, k)
        if v is not None:
            out.append(f"{k} = {_value(v)}")
    for e in s.effects:
        out += ["", "[[effects]]", f"kind = {_value(e.kind)}"]
        out += _fields_toml(e)
    for title, obj in (("integrator", s.integrator),
                       ("neighbors", s.neighbors)):
        out += ["", f"[{title}]"] + _fields_toml(obj)
    return "\n".join(out) + "\n"


# ---------------------------------------------------------------------------
# Reading


def _fields(cls) -> tuple[str, ...]:
    return tuple(f.name for f in dataclasses.fields(cls))


def _check_keys(table: dict, allowed, where: str) -> None:
    if not isinstance(table, dict):
        raise SceneError.at(where, "must be a table.")
    unknown = sorted(set(table) - set(allowed))
    if unknown:
        raise SceneError.at(f"{where}.{unknown[0]}" if where else unknown[0],
                            f"unknown key {unknown[0]!r}; allowed: "
                            f"{', '.join(sorted(allowed))}.")


def _scene(d: dict, base: pathlib.Path, effects: Registry) -> Scene:
    box, particles, integrator, neighbors = _parts(d, base)
    effect_list = _effects(d.get("effects", []), effects)
    return Scene(particles=particles, box=box, effects=effect_list,
                 integrator=integrator, neighbors=neighbors,
                 name=d.get("name", "scene"),
                 description=d.get("description", ""),
                 dtype=d.get("dtype", "float32"))


def _parts(d: dict, base: pathlib.Path
           ) -> tuple[Box, Particles, Integrator, Neighbors]:
    """The scene's parts other than its effects, checked and built by the
    spec alone (no JAX); of the effects, that each is a table with a
    kind."""
    _check_keys(d, ("name", "description", "dtype", "box", "particles",
                    "effects", "integrator", "neighbors"), "")
    for key in ("box", "particles", "integrator"):
        if key not in d:
            raise SceneError.at(key, f"missing table [{key}].")
    box = _box(d["box"])
    particles = _particles(d["particles"], base)
    _effect_tables(d.get("effects", []))
    it = d["integrator"]
    _check_keys(it, _fields(Integrator), "integrator")
    if "dt" not in it:
        raise SceneError.at("integrator.dt", "missing parameter.")
    nb = d.get("neighbors", {})
    _check_keys(nb, _fields(Neighbors), "neighbors")
    return box, particles, Integrator(**it), Neighbors(**nb)


def _box(b) -> Box:
    _check_keys(b, ("size", "boundary"), "box")
    if "size" not in b:
        raise SceneError.at("box.size", "missing parameter.")
    size = np.atleast_1d(np.asarray(b["size"], float))
    boundary = b.get("boundary", "periodic")
    boundary = ((boundary,) * size.size if isinstance(boundary, str)
                else tuple(boundary))
    return Box(tuple(float(s) for s in size), boundary)


def _particles(table, base: pathlib.Path) -> Particles:
    _check_keys(table, _PARTICLE_ARRAYS + ("temperature", "seed", "file"),
                "particles")
    p = dict(table)
    if "file" in p:
        with np.load(base / p.pop("file")) as f:
            for k in f.files:
                if k not in _PARTICLE_ARRAYS:
                    raise SceneError.at(f"particles.file[{k}]",
                                        "unknown array.")
                p.setdefault(k, f[k])
    return make_particles(
        positions=p.get("positions"), velocities=p.get("velocities"),
        masses=p.get("masses", 1.0), species=p.get("species"),
        radius=p.get("radius"), temperature=p.get("temperature"),
        seed=p.get("seed", 0))


def _effect_tables(raw) -> None:
    if not isinstance(raw, list):
        raise SceneError.at("effects", "must be an array of tables "
                            "[[effects]].")
    for i, e in enumerate(raw):
        if not isinstance(e, dict) or "kind" not in e:
            raise SceneError.at(f"effects[{i}].kind", "missing parameter.")


def _effects(raw, registry: Registry) -> tuple:
    _effect_tables(raw)
    out = []
    for i, e in enumerate(raw):
        where = f"effects[{i}]"
        kind = e["kind"]
        if kind not in registry:
            raise SceneError.at(f"{where}.kind", f"unknown effect {kind!r}; "
                                f"known: {', '.join(registry)}.")
        cls = registry[kind]
        _check_keys(e, ("kind",) + _fields(cls), where)
        for f in dataclasses.fields(cls):
            if (f.default is dataclasses.MISSING and f.default_factory is
                    dataclasses.MISSING and f.name not in e):
                raise SceneError.at(f"{where}.{f.name}", f"missing parameter "
                                    f"of {kind!r}.")
        out.append(cls(**{k: v for k, v in e.items() if k != "kind"}))
    return tuple(out)


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
        if re.match(rf"{re.escape(key)}\s*=", s) or (
                start < 0 and s in (f"[{key}]", f"[[{key}]]")):
            return f"{msg} (line {i + 1})"
    return f"{msg} (line {start + 1})" if start >= 0 else msg


# ---------------------------------------------------------------------------
# Writing


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (np.ndarray, list, tuple)):
        return "[" + ", ".join(_value(x) for x in list(v)) + "]"
    if isinstance(v, (np.integer, int)):
        return str(int(v))
    return repr(float(v))


def _fields_toml(obj) -> list[str]:
    """``key = value`` lines of a dataclass's fields that are not None."""
    return [f"{f.name} = {_value(getattr(obj, f.name))}"
            for f in dataclasses.fields(obj) if getattr(obj, f.name)
            is not None]
