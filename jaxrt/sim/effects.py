"""The effects a scene can name, one class each, and their registry.

Each class here is a complete effect (the `jaxrt.sim.spec.Effect`
protocol): a frozen dataclass whose fields are its TOML parameters, its
``kind``, whether it reads the shared neighbour list (``pairwise``), its
``cutoff``, its checks (``validate``) and its contribution to the step
(``term``, from `jaxrt.energy`). ``@register`` makes it readable from TOML
by its ``kind``.

Adding an effect is one class (here, or in your own module) and one
``@register`` line; a Python-built `Scene` takes an unregistered effect as
well. To register one for a while only, use ``registered(cls)`` (a context
manager), or pass ``effects=EFFECTS.extended(cls)`` to the TOML reader.
"""
from __future__ import annotations

import contextlib
import dataclasses
from typing import Any, ClassVar, Iterator

import numpy as np

from jaxrt.lazy import lazy_module
from jaxrt.sim.spec import Context, SceneError, Term, check_reach

# Imported on first use: the TOML reader checks an effect's keys, and the
# jaxrt command a scene file, before JAX and jax-md are loaded.
jax = lazy_module("jax")
jnp = lazy_module("jax.numpy")
_lj = lazy_module("jaxrt.energy.lj")
_sph = lazy_module("jaxrt.energy.sph")


class Registry:
    """Effect classes by ``kind``, in registration order.

    ``register`` refuses a kind that is already there and ``unregister``
    removes one: registering never replaces an effect silently.
    """

    def __init__(self, classes=()):
        self._classes: dict[str, type] = {}
        for cls in classes:
            self.register(cls)

    def register(self, cls: type) -> type:
        """Add ``cls`` under ``cls.kind``; returns ``cls`` (a decorator)."""
        if not dataclasses.is_dataclass(cls):
            raise TypeError(f"{cls.__qualname__} is not a dataclass; an "
                            "effect's dataclass fields are its parameters.")
        kind = getattr(cls, "kind", None)
        if not isinstance(kind, str):
            raise TypeError(f"{cls.__qualname__} has no kind (str).")
        if kind in self._classes:
            raise ValueError(f"an effect of kind {kind!r} is already "
                             f"registered ({self._classes[kind].__qualname__})"
                             "; unregister it first.")
        self._classes[kind] = cls
        return cls

    def unregister(self, kind: str) -> type:
        """Remove the effect of ``kind``; returns its class."""
        if kind not in self._classes:
            raise KeyError(f"no effect of kind {kind!r} is registered.")
        return self._classes.pop(kind)

    @contextlib.contextmanager
    def registered(self, *classes: type) -> Iterator["Registry"]:
        """Register ``classes`` for the ``with`` block only."""
        done = []
        try:
            for cls in classes:
                done.append(self.register(cls))
            yield self
        finally:
            for cls in done:
                self.unregister(cls.kind)

    def extended(self, *classes: type) -> "Registry":
        """A new registry: these effects and ``classes``."""
        return Registry((*self._classes.values(), *classes))

    def __getitem__(self, kind: str) -> type:
        return self._classes[kind]

    def __contains__(self, kind) -> bool:
        return kind in self._classes

    def __iter__(self) -> Iterator[str]:
        return iter(self._classes)


EFFECTS = Registry()
"""The effects the TOML reader knows by default."""
register = EFFECTS.register
unregister = EFFECTS.unregister
registered = EFFECTS.registered


def _positive(effect, where: str, *names: str) -> None:
    for k in names:
        if not getattr(effect, k) > 0:
            raise SceneError.at(f"{where}.{k}", "must be > 0.")


def _needs(scene, where: str, kind: str, why: str) -> None:
    if scene.effect(kind) is None:
        raise SceneError.at(f"{where}.kind", why)


# ---------------------------------------------------------------------------
# Per-particle cutoff radii (the LJ effect's ``radii``; the accuracy sweep's
# list-free LJ effects share these)


def _radii_as_tuple(effect) -> None:
    """``effect.radii`` as a tuple of floats (TOML and NumPy give lists and
    arrays: a tuple keeps the frozen effect hashable and comparable)."""
    r = effect.radii
    if r is None or isinstance(r, tuple):
        return
    a = np.asarray(r)
    if a.ndim != 1:
        raise SceneError.at(f"{effect.kind}.radii", f"must be a flat sequence of floats, one "
                            f"per particle; got shape {a.shape}.")
    try:
        object.__setattr__(effect, "radii", tuple(float(x) for x in a))
    except (TypeError, ValueError):
        raise SceneError.at(f"{effect.kind}.radii", f"must be floats; got "
                            f"dtype {a.dtype}.") from None


def check_cutoff_radii(effect, scene, where: str) -> None:
    """Raise `SceneError` at ``{where}.radii`` unless ``effect.radii`` is one
    finite radius >= 0 per particle, some > 0, with scalar sigma and
    epsilon and no differing ``particles.radius``."""
    r = np.asarray(effect.radii, float)
    n = scene.particles.n
    if r.shape != (n,):
        raise SceneError.at(f"{where}.radii", f"needs one radius per particle "
                            f"({n}); got {r.size}.")
    if not np.all(np.isfinite(r) & (r >= 0)):
        k = int(np.flatnonzero(~(np.isfinite(r) & (r >= 0)))[0])
        raise SceneError.at(f"{where}.radii", f"radii[{k}] = {r[k]}; radii "
                            "must be finite and >= 0.")
    if not r.max() > 0:
        raise SceneError.at(f"{where}.radii", "all radii are 0: nothing "
                            "interacts; give positive radii or none.")
    if np.ndim(effect.sigma) or np.ndim(effect.epsilon):
        raise SceneError.at(f"{where}.radii", "radii stretch one scalar "
                            "sigma and epsilon; give scalars with them.")
    p = scene.particles
    if p.radius is not None and np.ptp(p.radius) > 0:
        raise SceneError.at(f"{where}.radii", "particles.radius that differ "
                            "set sigma_ij = r_i + r_j; cutoff radii set it "
                            "from max(r_i, r_j): give one of the two.")


# ---------------------------------------------------------------------------
# Pair effects


@dataclasses.dataclass(frozen=True)
class LJFields:
    """The fields of the Lennard-Jones effect (`LJ`) and of the effects that
    stand in for it with another search (`jaxrt.tools.accuracy`'s `LJFused`,
    `LJPairs`): the potential, its cutoff and the cutoff radii."""

    r_cutoff: float
    sigma: Any = 1.0
    epsilon: Any = 1.0
    r_onset: float | None = None
    truncation: str = "smooth"
    radii: tuple[float, ...] | None = None

    def __post_init__(self):
        _radii_as_tuple(self)

    @property
    def cutoff(self) -> float:
        if self.radii is not None:
            return max(self.radii, default=0.0)
        return float(self.r_cutoff)


@register
@dataclasses.dataclass(frozen=True)
class LJ(LJFields):
    """Lennard-Jones (`jaxrt.energy.lj`), absolute ``r_cutoff`` /
    ``r_onset`` (default ``0.8 r_cutoff``), ``truncation`` one of
    `jaxrt.energy.lj.TRUNCATIONS`.

    ``sigma`` / ``epsilon``: float, or ``(S, S)`` nested lists with
    ``particles.species``. Per-particle radii that differ replace sigma by
    ``sigma_ij = r_i + r_j``; equal radii give the scalar ``2 r``.

    ``radii``: None, or per-particle *cutoff* radii (seed 003 §3; float,
    one per particle, >= 0, absolute; a tuple, converted from any
    sequence): pair ``ij`` is cut at ``max(r_i, r_j)`` and its potential
    is the one above stretched by ``s_ij = max(r_i, r_j) / r_cutoff``
    (``sigma s_ij``, ``r_onset s_ij``; `jaxrt.energy.lennard_jones_radii`),
    as `jaxrt.energy.lennard_jones_fused` (``radii=``) defines it. The
    effect's ``cutoff`` is then ``max(radii)`` and the shared list is built
    with these radii (`jaxrt.sim.compile.list_radii`). Scalar sigma and
    epsilon only, and not with ``particles.radius`` that differ (those set
    sigma_ij instead).
    """
    kind: ClassVar[str] = "lj"
    pairwise: ClassVar[bool] = True

    def validate(self, scene, where: str) -> None:
        p = scene.particles
        if self.truncation not in _lj.TRUNCATIONS:
            raise SceneError.at(f"{where}.truncation",
                                f"one of {_lj.TRUNCATIONS}.")
        _positive(self, where, "r_cutoff")
        if self.r_onset is not None and not 0 <= self.r_onset < self.r_cutoff:
            raise SceneError.at(f"{where}.r_onset", "needs 0 <= r_onset < "
                                "r_cutoff.")
        sig = np.asarray(self.sigma, float)
        if sig.ndim == 2 and p.species is None:
            raise SceneError.at(f"{where}.sigma", "a matrix needs "
                                "particles.species.")
        if p.radius is not None and np.ptp(p.radius) > 0 and sig.ndim:
            raise SceneError.at(f"{where}.sigma", "per-particle radii set "
                                "sigma (r_i + r_j); give no sigma matrix "
                                "with them.")
        if self.radii is not None:
            check_cutoff_radii(self, scene, where)
            check_reach(scene, self.cutoff, f"{where}.radii")
        else:
            check_reach(scene, self.cutoff, f"{where}.r_cutoff")

    def _sigma(self, radius, dtype):
        """sigma for the energy, and the plan's note on radii."""
        if radius is not None and np.ptp(radius) > 0:
            # sigma_ij = (sigma_i + sigma_j) / 2 = r_i + r_j.
            return (jnp.asarray(2 * radius, dtype),
                    ("per-particle radii: sigma_ij = r_i + r_j",))
        if radius is not None:
            return (float(2 * radius[0]),
                    ("equal radii: scalar sigma, no radius handling",))
        if np.ndim(self.sigma) == 2:
            return jnp.asarray(self.sigma, dtype), ()
        return self.sigma, ()

    def term(self, ctx: Context) -> Term:
        p = ctx.scene.particles
        sigma, notes = self._sigma(p.radius, ctx.dtype)
        epsilon = self.epsilon
        if np.ndim(epsilon) == 2:
            epsilon = jnp.asarray(epsilon, ctx.dtype)
        # Species only index a matrix: without one they are not gathered.
        species = (None if p.species is None or
                   (np.ndim(sigma) < 2 and np.ndim(epsilon) < 2)
                   else jnp.asarray(p.species))
        r_onset = 0.8 * self.r_cutoff if self.r_onset is None else self.r_onset
        radii = None
        if self.radii is not None:
            # In the run's dtype, as the list's reach is (radii + skin).
            radii = jnp.asarray(self.radii, ctx.dtype)
            notes = notes + (f"cutoff radii: pair ij cut at max(r_i, r_j), "
                             f"{min(self.radii):.4g} to "
                             f"{max(self.radii):.4g}, the potential "
                             f"stretched from r_cutoff {self.r_cutoff:.4g}",)
        energy = _lj.lennard_jones_pair_neighbor_list(
            ctx.displacement, species=species, sigma=sigma, epsilon=epsilon,
            r_onset=r_onset, r_cutoff=self.r_cutoff,
            truncation=self.truncation, radii=radii)

        def lj(R, nbrs):
            return energy(R, nbrs)
        return Term(energy=lj, notes=notes)


@register
@dataclasses.dataclass(frozen=True)
class SPHDensity:
    """Summation density with kernel ``kernel`` (one of
    `jaxrt.energy.sph.KERNELS`) of smoothing length ``h``; the list's
    cutoff is the kernel's support (``2h`` or ``3h``).

    ``list_free``: no neighbour list, a walk over the cell grid at every
    step (`jaxrt.energy.density_fused`); sph_pressure and
    sph_viscosity must say the same. ``walk`` (with ``list_free`` only),
    the walk's program for all three (`jaxrt.energy.listfree.sph.WALKS`):
    ``"auto"``, the Pallas kernel on CUDA and array programs elsewhere;
    ``"xla"``, the arrays; ``"pallas"``, the kernel (CUDA only; the scene
    fails to compile elsewhere); ``"interpret"``, the kernel in Pallas'
    interpreter (tests)."""
    h: float
    kernel: str = "cubic_spline"
    list_free: bool = False
    walk: str = "auto"
    kind: ClassVar[str] = "sph_density"

    @property
    def pairwise(self) -> bool:
        return not self.list_free

    @property
    def cutoff(self) -> float:
        return float(_sph.KERNELS[self.kernel].support * self.h)

    def smoothing_kernel(self, dim: int):
        """The `jaxrt.energy.sph` kernel in ``dim`` dimensions."""
        return _sph.kernel(self.kernel, self.h, dim=dim)

    def validate(self, scene, where: str) -> None:
        _positive(self, where, "h")
        if self.kernel not in _sph.KERNELS:
            raise SceneError.at(f"{where}.kernel",
                                f"one of {list(_sph.KERNELS)}.")
        if scene.particles.dim not in (2, 3):
            raise SceneError.at(f"{where}", "SPH needs 2D or 3D positions.")
        from jaxrt.energy.listfree.sph import WALKS
        if self.walk not in WALKS:
            raise SceneError.at(f"{where}.walk", f"one of {list(WALKS)}.")
        if self.walk != "auto" and not self.list_free:
            raise SceneError.at(f"{where}.walk", "needs list_free = true "
                                "(the list path has no cell walk).")
        check_reach(scene, self.cutoff, f"{where}.h")

    def walk_backend(self):
        """``backend=`` of the list-free SPH factories."""
        from jaxrt.backends import Cell
        return Cell(kernel=self.walk)

    def term(self, ctx: Context) -> Term:
        kern = self.smoothing_kernel(ctx.scene.particles.dim)
        if self.list_free:
            from jaxrt.energy import density_fused
            sides, periodic = _fused_box(ctx)
            density = density_fused(ctx.displacement, sides, kern,
                                    mass=ctx.mass,
                                    backend=self.walk_backend(), **periodic)

            def sph_density(R, nbrs):
                return density(R)
            return Term(density=sph_density, notes=(
                "sph: list-free (a walk over the cell grid per term and "
                f"step; walk {self.walk!r})",))
        density = _sph.density(ctx.displacement, kern, mass=ctx.mass)

        def sph_density(R, nbrs):
            return density(R, nbrs)
        return Term(density=sph_density)


def _fused_box(ctx: Context):
    """(box sides, periodic axes) for the list-free SPH factories: the
    sides are read on periodic axes only (free and wall axes get a positive
    placeholder, as the list's box does)."""
    box = ctx.scene.box
    size = np.asarray(box.size, float)
    sides = np.where(np.isfinite(size) & (size > 0), size, 1.0)
    return tuple(float(x) for x in sides), dict(periodic=box.periodic)


def _sph_acceleration(ctx: Context, **viscosity):
    """``accel(R, V, nbrs, **kw) -> Acceleration``: `jaxrt.energy.sph`'s
    acceleration with the scene's kernel and equation of state (from its
    sph_density and sph_pressure effects), on the list or list-free as the
    sph_density effect says."""
    density = ctx.scene.effect("sph_density")
    kern = density.smoothing_kernel(ctx.scene.particles.dim)
    eos = ctx.scene.effect("sph_pressure").equation_of_state()
    if density.list_free:
        from jaxrt.energy import acceleration_fused
        sides, periodic = _fused_box(ctx)
        fused = acceleration_fused(ctx.displacement, sides, kern, eos,
                                   mass=ctx.mass,
                                   backend=density.walk_backend(),
                                   **periodic, **viscosity)
        return lambda R, V, nbrs, **kw: fused(R, V, **kw)
    return _sph.acceleration(ctx.displacement, kern, eos, mass=ctx.mass,
                             **viscosity)


def _same_list_free(effect, scene, where: str) -> None:
    density = scene.effect("sph_density")
    if density is not None and effect.list_free != density.list_free:
        raise SceneError.at(f"{where}.list_free", "must equal sph_density's "
                            f"list_free ({density.list_free}): the SPH "
                            "effects share one way to find pairs.")


@register
@dataclasses.dataclass(frozen=True)
class SPHPressure:
    """Symmetric pressure force, Tait's equation of state (``rho0``, ``c0``,
    ``gamma``); ``clip_negative``: no tension (a free surface cannot pull).
    Needs sph_density (kernel and densities); ``list_free`` as its."""
    rho0: float
    c0: float
    gamma: float = 7.0
    clip_negative: bool = True
    list_free: bool = False
    kind: ClassVar[str] = "sph_pressure"
    cutoff: ClassVar[float] = 0.0  # reads sph_density's pairs

    @property
    def pairwise(self) -> bool:
        return not self.list_free

    def equation_of_state(self):
        return _sph.Tait(rho0=self.rho0, c0=self.c0, gamma=self.gamma)

    def validate(self, scene, where: str) -> None:
        _positive(self, where, "rho0", "c0", "gamma")
        _needs(scene, where, "sph_density", "sph_pressure needs an "
               "sph_density effect (it sets h and the kernel).")
        _same_list_free(self, scene, where)

    def term(self, ctx: Context) -> Term:
        eos = self.equation_of_state()
        # No viscosity here (alpha = 0): sph_viscosity adds its own term.
        accel = _sph_acceleration(ctx, alpha=0.0, beta=0.0)

        def sph_pressure(R, V, nbrs, rho):
            pr = eos.pressure(rho)
            if self.clip_negative:
                pr = jnp.maximum(pr, 0)
            return accel(R, V, nbrs, rho=rho, pressure=pr).pressure
        return Term(accel=sph_pressure)


@register
@dataclasses.dataclass(frozen=True)
class SPHViscosity:
    """Monaghan's artificial viscosity (``alpha``, ``beta``); needs
    sph_density and sph_pressure (its c0 gives the sound speed);
    ``list_free`` as sph_density's."""
    alpha: float
    beta: float = 0.0
    list_free: bool = False
    kind: ClassVar[str] = "sph_viscosity"
    cutoff: ClassVar[float] = 0.0  # reads sph_density's pairs

    @property
    def pairwise(self) -> bool:
        return not self.list_free

    def validate(self, scene, where: str) -> None:
        if not (self.alpha >= 0 and self.beta >= 0):
            raise SceneError.at(f"{where}.alpha", "alpha and beta must be "
                                ">= 0.")
        _needs(scene, where, "sph_density", "sph_viscosity needs an "
               "sph_density effect (it sets h and the kernel).")
        _needs(scene, where, "sph_pressure", "sph_viscosity needs "
               "sph_pressure (its c0 gives the sound speed).")
        _same_list_free(self, scene, where)

    def term(self, ctx: Context) -> Term:
        accel = _sph_acceleration(ctx, alpha=self.alpha, beta=self.beta)

        def sph_viscosity(R, V, nbrs, rho):
            return accel(R, V, nbrs, rho=rho).viscosity
        return Term(accel=sph_viscosity)


# ---------------------------------------------------------------------------
# One-body effects (external forces: they change the total momentum)


@register
@dataclasses.dataclass(frozen=True)
class Gravity:
    """Uniform acceleration ``g``, float, one entry per axis (a tuple; a
    list or a scalar is converted)."""
    g: tuple[float, ...]
    kind: ClassVar[str] = "gravity"
    pairwise: ClassVar[bool] = False
    cutoff: ClassVar[float] = 0.0

    def __post_init__(self):
        # TOML gives a list: a tuple keeps the effect hashable and equal to
        # the one written.
        object.__setattr__(self, "g", tuple(float(x) for x in
                                            np.atleast_1d(self.g)))

    def validate(self, scene, where: str) -> None:
        if len(self.g) != scene.particles.dim:
            raise SceneError.at(f"{where}.g", f"needs "
                                f"{scene.particles.dim} entries.")

    def term(self, ctx: Context) -> Term:
        gvec = np.asarray(self.g, float)
        m = ctx.mass_column

        def gravity(R, nbrs):
            return -jnp.sum(m * R * jnp.asarray(gvec, R.dtype))
        return Term(energy=gravity)


@register
@dataclasses.dataclass(frozen=True)
class Walls:
    """``U = k/2 sum (distance outside [0, L])**2`` on every "wall" axis of
    the box, ``k`` = ``stiffness``."""
    stiffness: float
    kind: ClassVar[str] = "walls"
    pairwise: ClassVar[bool] = False
    cutoff: ClassVar[float] = 0.0

    def validate(self, scene, where: str) -> None:
        _positive(self, where, "stiffness")
        if "wall" not in scene.box.boundary:
            raise SceneError.at(f"{where}.kind", "walls need a 'wall' axis "
                                "in box.boundary.")

    def term(self, ctx: Context) -> Term:
        box = ctx.scene.box
        axes = np.flatnonzero(np.asarray(box.boundary) == "wall")
        hi = np.asarray(box.size)[axes]
        k = self.stiffness

        def walls(R, nbrs):
            x = R[:, axes]
            out = jnp.maximum(-x, 0) + jnp.maximum(x - hi.astype(x.dtype), 0)
            return 0.5 * k * jnp.sum(out * out)
        return Term(energy=walls)


# ---------------------------------------------------------------------------
# Boids (seed 004's scene)


@register
@dataclasses.dataclass(frozen=True)
class Boids:
    """Reynolds' boids (1987), in the form of seed 004's spec (SPECS.md
    §6; the poster gives no rules or parameters, so every one is here).

    For boid i with neighbours j within ``radius`` (R):

    * cohesion ``w_c (mean_j x_j - x_i)`` (minimum-image offsets),
    * alignment ``w_a (mean_j v_j - v_i)``,
    * separation ``w_s sum_{d_ij < R_s} (x_i - x_j) / d_ij^2`` with
      ``R_s`` = ``separation_radius``,
    * speed limits: an acceleration ``(v* - v) / tau`` towards ``v*``, the
      velocity with its speed clamped to ``[min_speed, max_speed]``
      (``tau`` = ``speed_relaxation``). A force cannot clamp exactly: the
      other rules push speeds past the limits by about their acceleration
      times ``tau`` (with the defaults and dt = 0.05, speeds stay within
      about 12% of the limits: 0.44 to 1.0 seen in the built-in scene).

    Weights: ``cohesion`` (w_c, 1/time^2), ``alignment`` (w_a, 1/time),
    ``separation`` (w_s, length^2/time^2). A boid without neighbours feels
    only the speed limits.
    """
    radius: float = 1.0
    separation_radius: float = 0.25
    cohesion: float = 0.5
    alignment: float = 1.0
    separation: float = 0.02
    min_speed: float = 0.5
    max_speed: float = 1.0
    speed_relaxation: float = 0.05
    kind: ClassVar[str] = "boids"
    pairwise: ClassVar[bool] = True

    @property
    def cutoff(self) -> float:
        return float(self.radius)

    def validate(self, scene, where: str) -> None:
        _positive(self, where, "radius", "separation_radius",
                  "speed_relaxation", "max_speed")
        for k in ("cohesion", "alignment", "separation", "min_speed"):
            if not getattr(self, k) >= 0:
                raise SceneError.at(f"{where}.{k}", "must be >= 0.")
        if not self.separation_radius <= self.radius:
            raise SceneError.at(f"{where}.separation_radius",
                                "must be <= radius (the list's reach).")
        if not self.min_speed < self.max_speed:
            raise SceneError.at(f"{where}.min_speed",
                                "must be below max_speed.")
        check_reach(scene, self.cutoff, f"{where}.radius")

    def term(self, ctx: Context) -> Term:
        displacement = ctx.displacement
        r2 = self.radius ** 2
        rs2 = self.separation_radius ** 2

        def boids(R, V, nbrs, rho):
            n = R.shape[0]
            pairs = _sph.list_pairs(nbrs, n)
            c = jnp.minimum(pairs.centre, n - 1)
            o = jnp.minimum(pairs.other, n - 1)
            # x_j - x_i, from i's point of view.
            dx = jax.vmap(displacement)(R[o].reshape(-1, R.shape[1]),
                                        R[c].reshape(-1, R.shape[1]))
            dx = dx.reshape(pairs.centre.shape + (R.shape[1],))
            d2 = jnp.sum(dx * dx, axis=-1)
            seen = pairs.valid & (d2 < r2)
            near = pairs.valid & (d2 < rs2)
            one = jnp.ones(pairs.centre.shape + (1,), R.dtype)

            def total(weight, to_centre, to_other):
                w = weight[..., None]
                return _sph.sum_pairs(jnp.where(w, to_centre, 0),
                                       jnp.where(w, to_other, 0), pairs,
                                       nbrs, n)
            count = total(seen, one, one)[:, 0]
            dv = V[o] - V[c]
            mean_dx = total(seen, dx, -dx) / jnp.maximum(count, 1)[:, None]
            mean_dv = total(seen, dv, -dv) / jnp.maximum(count, 1)[:, None]
            push = -dx / jnp.maximum(d2, 1e-12)[..., None]
            sep = total(near, push, -push)
            speed = jnp.linalg.norm(V, axis=1, keepdims=True)
            clamped = jnp.clip(speed, self.min_speed, self.max_speed)
            v_star = V * clamped / jnp.maximum(speed, 1e-12)
            return (self.cohesion * mean_dx + self.alignment * mean_dv
                    + self.separation * sep
                    + (v_star - V) / self.speed_relaxation)
        return Term(accel=boids, notes=(
            f"boids: R={self.radius}, R_s={self.separation_radius}, "
            f"w_c={self.cohesion}, w_a={self.alignment}, "
            f"w_s={self.separation}, speed in [{self.min_speed}, "
            f"{self.max_speed}], tau={self.speed_relaxation}",))
