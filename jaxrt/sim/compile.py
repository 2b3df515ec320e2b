"""The compiler: a `Scene` to jitted steps that compute only what it asks.

`compile_scene` asks each effect for its `Term` (`Effect.term`) and builds
a velocity Verlet step (plus a Langevin velocity step for NVT) around them:

* no neighbour list at all when no effect is pairwise (``gravity`` and
  ``walls`` are one-body);
* one shared list for all pair effects, built at the largest of their
  cutoffs (``lj``: ``r_cutoff``; ``sph_*``: the kernel support ``2h`` or
  ``3h``). Each effect truncates itself at its own cutoff, so a longer list
  only costs extra pairs, never wrong forces; one list means one search and
  one overflow check per step instead of one per effect; with per-particle
  cutoff radii (``lj.radii``) the list takes radii too (`list_radii`:
  pair ``ij`` within ``max(r_i, r_j)``), so the search skips the pairs no
  effect needs;
* periodic image work (minimum image in the displacement, wrapping in the
  shift, ``periodic=`` of `jaxrt.neighbor_list`) on periodic axes only;
  wall and free axes use a plain difference;
* no density pass without an effect that gives one (``sph_density``);
* per-particle masses only when they differ; the effects make the same
  choice for what they read (`LJ` takes one scalar sigma for equal radii).

Integrator ``perse`` (ORCS-persé, `jaxrt.energy.lennard_jones_perse_step`)
replaces all of it by one kernel per step and no list: the state's
velocity is then the half-step one, v(t + dt/2), and each step's trace
holds the energies at its start, x(t), where the kernel evaluates them.

The terms are summed in the order the scene lists its effects. Overflow is
never silent: `jaxrt.sim.run.run_chunk` redoes a chunk whose list
overflowed.
"""
from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax_md import partition

from jaxrt import backends
from jaxrt.lists import neighbors as _neighbors
from jaxrt.sim.spec import Box, Context, Scene, SceneError
from jaxrt.sim.validate import check_backend

FORMATS = {"Dense": partition.Dense, "Sparse": partition.Sparse,
           "OrderedSparse": partition.OrderedSparse}
"""`jaxrt.sim.spec.FORMAT_NAMES` -> jax-md's list formats."""


class State(NamedTuple):
    """The carried state of a run.

    position, velocity, accel: float ``(N, dim)``; rho: float ``(N,)`` (the
    density term's; shape ``(0,)`` without one); key: PRNG key (Langevin
    only, else an unused scalar); rebuilds: int32 scalar, list rebuilds so
    far.
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
    (state, nbrs, Trace), jitted; step(state, nbrs) -> (state, nbrs,
    (kinetic, potential, momentum)), one step, unjitted; neighbor_fn (None
    without pair effects); displacement: the scene's ``d(Ra, Rb)``; plan:
    what the step computes and what it skips, in words; conservative: True
    when every force comes from the potential and the integrator is NVE,
    so the total energy is conserved up to the integrator's error;
    energy(state, nbrs): the total energy (kinetic + potential, float
    ``()``) of a state, jitted (`jaxrt.sim.run.run_chunk` reads it at the
    start of each chunk of a conservative scene to detect a blow-up).
    """
    scene: Scene
    init: Callable
    chunk: Callable
    step: Callable
    neighbor_fn: Any
    displacement: Callable
    plan: tuple[str, ...]
    conservative: bool
    energy: Callable | None = None


def compile_scene(scene: Scene, *, neighbor_list_fn: Callable | None = None
                  ) -> Compiled:
    """Compile ``scene`` to a step containing only its effects.

    ``neighbor_list_fn``: the list factory (default `jaxrt.neighbor_list`;
    tests pass a counting wrapper). Raises `SceneError` if the scene's
    neighbour backend is not available here.
    """
    check_backend(scene)
    dtype = jnp.dtype(scene.dtype)
    displacement, shift = _displacement_shift(scene.box)
    if scene.integrator.kind == "perse":
        return _compile_perse(scene, displacement, dtype)
    mass = _mass(scene.particles.masses, dtype)
    plan = ["masses: " + ("one scalar" if np.ndim(mass) == 0
                          else "per particle")]
    neighbor_fn = _neighbor_fn(scene, displacement,
                               neighbor_list_fn or _neighbors.neighbor_list,
                               plan)
    ctx = Context(scene, displacement, dtype, mass)
    forces = _Forces.collect(scene, ctx, plan)
    step = _step_fn(scene, shift, neighbor_fn, forces.accel, ctx.mass_column)
    init = _init_fn(scene, neighbor_fn, forces.accel, dtype)
    conservative = (scene.integrator.kind == "verlet"
                    and not forces.accel_terms)
    m_col = ctx.mass_column

    @jax.jit
    def energy(state: State, nbrs):
        ke = 0.5 * jnp.sum(m_col * state.velocity * state.velocity)
        return ke + forces.potential(state.position, nbrs)

    return Compiled(scene, init, _chunk_fn(step), step, neighbor_fn,
                    displacement, tuple(plan), conservative, energy)


def _compile_perse(scene: Scene, displacement, dtype) -> Compiled:
    """A scene whose step is one ORCS-persé kernel (`jaxrt.sim.spec`
    checked that it applies)."""
    from jaxrt.energy import lennard_jones_fused, lennard_jones_perse_step
    lj, p, box = scene.effects[0], scene.particles, scene.box
    sigma = float(lj._sigma(p.radius, dtype)[0])
    r_onset = 0.8 * lj.r_cutoff if lj.r_onset is None else lj.r_onset
    backend = "bvh" if scene.neighbors.backend == "auto" else scene.neighbors.backend
    dt, mass = scene.integrator.dt, float(p.masses[0])
    potential = dict(sigma=sigma, epsilon=float(lj.epsilon),
                     r_onset=r_onset / sigma, r_cutoff=lj.r_cutoff / sigma,
                     backend=backend, periodic=box.periodic)
    sides = _list_sides(box)
    perse = lennard_jones_perse_step(displacement, sides, dt=dt, mass=mass,
                                     **potential)
    energy = lennard_jones_fused(displacement, sides, **potential)

    def init():
        R = jnp.asarray(p.positions, dtype)
        V = jnp.asarray(p.velocities, dtype)
        a = -jax.grad(energy)(R) / mass
        # Leapfrog carries v(t - dt/2).
        return State(R, V - 0.5 * dt * a, a, jnp.zeros((0,), dtype),
                     jnp.zeros((), jnp.uint32), jnp.zeros((), jnp.int32)), None

    def step(state: State, nbrs):
        R, V, u = perse.energy(state.position, state.velocity)
        v_mid = 0.5 * (state.velocity + V)  # v(t), for the trace
        ke = 0.5 * mass * jnp.sum(v_mid * v_mid)
        mom = mass * jnp.sum(v_mid, axis=0)
        a = (V - state.velocity) / dt
        return (State(R, V, a, state.rho, state.key, state.rebuilds), nbrs,
                (ke, u, mom))

    plan = ("integrator 'perse': one ORCS-persé kernel per step (seed 003 "
            f"§3.2.1), backend {backend!r}, no neighbour list",
            f"lj: sigma {sigma:.4g}, epsilon {float(lj.epsilon):.4g}, smooth "
            f"from {r_onset:.4g} to {lj.r_cutoff:.4g}",
            "state velocity at the half step; trace energies at each "
            "step's start")
    return Compiled(scene, init, _chunk_fn(step), step, None, displacement,
                    plan, True)


def _mass(masses: np.ndarray, dtype):
    """A Python float when all masses are equal, else ``dtype`` ``(N,)``."""
    return (float(masses[0]) if np.ptp(masses) == 0
            else jnp.asarray(masses, dtype))


def _displacement_shift(box: Box):
    """Displacement and shift doing image work on periodic axes only."""
    per = np.asarray(box.periodic)
    if not per.any():
        # Plain difference: no rounding, no modulo (tested through the jaxpr).
        return (lambda ra, rb, **kw: ra - rb), (lambda r, dr, **kw: r + dr)
    axes = np.flatnonzero(per)
    side = np.asarray(box.size, float)[axes]  # the periodic sides

    def displacement(ra, rb, **kw):
        d = ra - rb
        L = jnp.asarray(side, d.dtype)
        wrapped = d[..., axes] - L * jnp.round(d[..., axes] / L)
        return d.at[..., axes].set(wrapped)

    def shift(r, dr, **kw):
        x = r + dr
        L = jnp.asarray(side, x.dtype)
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


def list_radii(scene: Scene) -> np.ndarray | None:
    """The shared list's per-particle radii: float64 ``(N,)``, or None when
    no pair effect has ``radii`` (the list then has one cutoff).

    Effect ``e`` needs pair ``ij`` within ``max(a_i, a_j)``, ``a`` its radii
    (or its ``cutoff`` for every particle), so the list needs it within
    ``max_e max(a_i, a_j) = max(r_i, r_j)`` with ``r = max_e a``, the
    elementwise largest: exactly the union of what the effects need.
    """
    effects = scene.pair_effects
    if all(getattr(e, "radii", None) is None for e in effects):
        return None
    n = scene.particles.n
    return np.max([np.broadcast_to(
        np.asarray(e.cutoff if getattr(e, "radii", None) is None
                   else e.radii, np.float64), (n,)) for e in effects], axis=0)


def _check_radii_backend(scene: Scene) -> None:
    """`SceneError` at ``neighbors.backend`` if the scene's list needs
    radii and its backend has none."""
    backend = scene.neighbors.backend
    if isinstance(backend, str):
        if backend == "auto":
            return  # auto picks one with radii (jaxrt.lists.neighbors)
        backend = backends.resolve(backend)
    if not backends.capabilities(backend).supports_radii:
        raise SceneError.at("neighbors.backend", f"{backend.name!r} has no "
                            "per-particle radii, which the scene's lj.radii "
                            "need; use 'cell', 'bvh', 'brute' or 'auto'.")


def _neighbor_fn(scene: Scene, displacement, nl_fn, plan: list):
    """The shared list's functions, or None without pair effects; appends
    to ``plan`` what it chose."""
    box = scene.box
    neighbor_fn = None
    if scene.pair_effects:
        nb = scene.neighbors
        radii = list_radii(scene)
        # Only a list with radii gets the keyword: a caller's factory
        # (jax_md.partition.neighbor_list) may not take it.
        extra = {}
        if radii is not None:
            _check_radii_backend(scene)
            extra["radii"] = radii
        neighbor_fn = nl_fn(
            displacement, _list_sides(box), scene.cutoff, nb.skin,
            capacity_multiplier=nb.capacity_multiplier,
            format=FORMATS[nb.format], backend=nb.backend,
            periodic=box.periodic, **extra)
        plan.append(f"one neighbour list, cutoff {scene.cutoff:.4g} + skin "
                    f"{nb.skin:.4g}, periodic={box.periodic}"
                    + ("" if radii is None else
                       f", per-particle radii {radii.min():.4g} to "
                       f"{radii.max():.4g} (pair ij within max(r_i, r_j))"))
    else:
        plan.append("no neighbour list (no pair effect)")
    if not any(box.periodic):
        plan.append("no periodic image work")
    return neighbor_fn


@dataclasses.dataclass(frozen=True)
class _Forces:
    """The effects' terms, each jitted under its own name, grouped by what
    they give (see `jaxrt.sim.spec.Term`)."""
    energy_terms: tuple
    density_term: Callable | None
    accel_terms: tuple
    mass_column: Any

    @classmethod
    def collect(cls, scene: Scene, ctx: Context, plan: list) -> "_Forces":
        terms = [e.term(ctx) for e in scene.effects]
        for t in terms:
            plan.extend(t.notes)
        energy = tuple(jax.jit(t.energy) for t in terms if t.energy)
        density = [jax.jit(t.density) for t in terms if t.density]
        accel = tuple(jax.jit(t.accel) for t in terms if t.accel)
        if len(density) > 1:
            raise SceneError.at("effects", "two effects give a density; a "
                                "scene holds one.")

        def names(fns):
            return ", ".join(f.__name__ for f in fns) or "none"
        plan.append(f"potential terms: {names(energy)}")
        plan.append(f"density pass: {names(density)}" if density
                    else "no density pass")
        if accel:
            plan.append(f"forces not from the potential: {names(accel)}")
        return cls(energy, density[0] if density else None, accel,
                   ctx.mass_column)

    def potential(self, R, nbrs):
        """The total potential energy, float ``()``."""
        return sum((t(R, nbrs) for t in self.energy_terms),
                   jnp.zeros((), R.dtype))

    def accel(self, R, V, nbrs):
        """Returns (acceleration (N, dim), potential energy (), rho)."""
        if self.energy_terms:
            u, grad = jax.value_and_grad(self.potential)(R, nbrs)
            a = -grad / self.mass_column
        else:
            u, a = jnp.zeros((), R.dtype), jnp.zeros_like(R)
        rho = jnp.zeros((0,), R.dtype)
        if self.density_term is not None:
            rho = self.density_term(R, nbrs)
        if self.accel_terms:
            other = self.accel_terms[0](R, V, nbrs, rho)
            for t in self.accel_terms[1:]:
                other = other + t(R, V, nbrs, rho)
            a = a + other
        return a, u, rho


def _thermostat(scene: Scene, m_col):
    """The Langevin (Ornstein-Uhlenbeck) velocity step ``(v, key) -> (v,
    key)`` of an NVT scene, or None for NVE."""
    it = scene.integrator
    if it.kind != "langevin":
        return None
    c1 = math.exp(-it.gamma * it.dt)

    def o_step(v, key):
        key, sub = jax.random.split(key)
        sd = jnp.sqrt((1 - c1 * c1) * it.kT / m_col)
        return c1 * v + sd * jax.random.normal(sub, v.shape, v.dtype), key
    return o_step


def _step_fn(scene: Scene, shift, neighbor_fn, accel, m_col):
    dt = scene.integrator.dt
    o_step = _thermostat(scene, m_col)

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
        # Velocity-dependent terms (SPH viscosity) see the half-step
        # velocity.
        a, u, rho = accel(R, v_half, nbrs)
        v = v_half + 0.5 * dt * a
        key = state.key
        if o_step is not None:
            v, key = o_step(v, key)
        ke = 0.5 * jnp.sum(m_col * v * v)
        mom = jnp.sum(m_col * v, axis=0)
        return State(R, v, a, rho, key, rebuilds), nbrs, (ke, u, mom)
    return step


def _chunk_fn(step):
    @functools.partial(jax.jit, static_argnames=("steps",))
    def chunk(state, nbrs, *, steps):
        def body(carry, _):
            s, nb = carry
            s, nb, rec = step(s, nb)
            return (s, nb), rec
        (state, nbrs), (ke, u, mom) = lax.scan(body, (state, nbrs), None,
                                               length=steps)
        return state, nbrs, Trace(ke, u, mom)
    return chunk


def _init_fn(scene: Scene, neighbor_fn, accel, dtype):
    p, it = scene.particles, scene.integrator

    def init():
        R = jnp.asarray(p.positions, dtype)
        V = jnp.asarray(p.velocities, dtype)
        nbrs = None if neighbor_fn is None else neighbor_fn.allocate(R)
        a, u, rho = jax.jit(accel)(R, V, nbrs)
        key = (jax.random.PRNGKey(it.seed) if it.kind == "langevin"
               else jnp.zeros((), jnp.uint32))
        return State(R, V, a, rho, key, jnp.zeros((), jnp.int32)), nbrs
    return init
