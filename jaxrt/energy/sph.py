"""Smoothed-particle hydrodynamics on neighbour lists (2D and 3D).

* Kernels: `CubicSpline`, `QuinticSpline`, `WendlandC2`, `WendlandC4`, frozen
  dataclasses (pytrees: ``h`` is a leaf, ``dim`` is static) with ``w(r)``,
  ``grad_w(r)`` and ``cutoff``; `kernel` makes one by name.
* `density`: summation density, self term included.
* `Tait`: weakly compressible equation of state.
* `acceleration`: symmetric pressure term and Monaghan's artificial
  viscosity.

All of it is differentiable with respect to positions, velocities, ``h``,
masses and the equation of state's parameters.

Neighbour lists. Any jax-md layout works (Dense, Sparse, OrderedSparse, from
`jaxrt.neighbor_list` or jax-md), with or without ``mask_self``: self pairs
in the list are ignored and the self term ``m_i W(0)`` is always added
analytically, because OrderedSparse lists never hold self pairs. The list's
cutoff must be at least ``kernel.cutoff``; pairs it lacks are silently
missing (the list object does not record its cutoff, so this cannot be
checked here).

Conventions: for a pair (i, j), ``r_ij = R_i - R_j`` (jax-md's displacement
``d(R_i, R_j)``), ``r = |r_ij|`` and ``grad_i W_ij = grad_w(r) r_ij / r``.

Bad input raises `ValueError` when the value is known (outside ``jit``).
Under ``jit`` a value check cannot raise, so bad values poison the result
with NaN instead of giving a plausible wrong answer: a kernel with ``h <= 0``
returns NaN, `Tait.pressure` of a negative density returns NaN. Shape
errors (``mass``, ``rho`` of the wrong length) always raise. An unknown
keyword argument raises ``TypeError`` naming it and the accepted ones.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Callable, ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax_md import partition

from jaxrt.energy.checks import check_positive, concrete
from jaxrt.layouts.edges import edge_sum, materialized_in_reverse
from jaxrt.energy.keywords import reject_unknown

Array = jax.Array


# ---------------------------------------------------------------------------
# Kernels


@dataclasses.dataclass(frozen=True)
class _Kernel:
    """A radial SPH kernel ``W(r; h) = sigma_d / h**dim * f(r / h)``.

    Attributes:
      h: float scalar > 0, the smoothing length (a pytree leaf: may be traced
        and differentiated).
      dim: 2 or 3 (static).
    """

    h: Array
    dim: int = dataclasses.field(default=3, metadata=dict(static=True))

    # Set by each kernel: support radius in units of h, f(q), and the
    # normalisation sigma_d per dimension.
    support: ClassVar[float]
    _normalisation: ClassVar[dict[int, float]]

    @staticmethod
    def _shape(q: Array) -> Array:
        raise NotImplementedError

    def __post_init__(self):
        if self.dim not in self._normalisation:
            raise ValueError(
                f"dim={self.dim!r} is not supported by "
                f"{type(self).__name__}; use one of "
                f"{sorted(self._normalisation)}.")
        check_positive("h", self.h,
                       "Pass the smoothing length, e.g. 1.2-1.3 times the "
                       "particle spacing.")

    @property
    def normalisation(self) -> float:
        """``sigma_d`` of ``W = sigma_d / h**dim * f(r / h)`` (a float)."""
        return self._normalisation[self.dim]

    @property
    def cutoff(self) -> Array:
        """Support radius ``support * h``: ``W(r) = 0`` for ``r >= cutoff``."""
        return self.support * self.h

    def w(self, r: Array) -> Array:
        """Kernel value.

        Args:
          r: float, any shape: distances >= 0.
        Returns:
          ``W(r)``, shape of ``r``, dtype of ``r`` promoted with ``h``; NaN
          everywhere if ``h <= 0`` (only reachable under ``jit``).
        """
        h = self.h
        q = r / h
        value = self._normalisation[self.dim] / h ** self.dim * self._shape(q)
        # The clamped polynomials leave ~1e-79 of rounding near q = support;
        # cut at r < support * h, the very expression of `cutoff` (r / h
        # can round below support at r = cutoff).
        value = jnp.where(r < self.support * h, value, 0)
        return jnp.where(h > 0, value, jnp.nan)

    def grad_w(self, r: Array) -> Array:
        """Radial derivative ``dW/dr``.

        Args:
          r: float, any shape: distances >= 0.
        Returns:
          ``dW/dr``, shape of ``r`` (<= 0; zero at ``r = 0`` and beyond the
          support). The vector gradient is ``grad_w(r) * r_ij / r``.
        """
        return jax.jvp(self.w, (r,), (jnp.ones_like(r),))[1]


def _register(cls):
    return jax.tree_util.register_dataclass(cls)


# Clamped powers keep each spline one expression: max(a - q, 0)**k is
# C^(k-1) at q = a, so no piecewise where (and no NaN-prone branch) is needed.


@_register
@dataclasses.dataclass(frozen=True)
class CubicSpline(_Kernel):
    """Monaghan's M4 cubic spline, support ``2h``.

    ``f(q) = (2 - q)^3 / 4 - (1 - q)^3`` on [0, 1), ``(2 - q)^3 / 4`` on
    [1, 2); ``sigma_2 = 10 / (7 pi)``, ``sigma_3 = 1 / pi``.
    """

    support: ClassVar[float] = 2.0
    _normalisation: ClassVar[dict[int, float]] = {
        2: 10.0 / (7.0 * math.pi), 3: 1.0 / math.pi}

    @staticmethod
    def _shape(q):
        a = jnp.maximum(2 - q, 0)
        b = jnp.maximum(1 - q, 0)
        return a ** 3 / 4 - b ** 3


@_register
@dataclasses.dataclass(frozen=True)
class QuinticSpline(_Kernel):
    """Morris' M6 quintic spline, support ``3h``.

    ``f(q) = (3-q)^5 - 6 (2-q)^5 + 15 (1-q)^5`` with each term clamped at 0;
    ``sigma_2 = 7 / (478 pi)``, ``sigma_3 = 1 / (120 pi)``.
    """

    support: ClassVar[float] = 3.0
    _normalisation: ClassVar[dict[int, float]] = {
        2: 7.0 / (478.0 * math.pi), 3: 1.0 / (120.0 * math.pi)}

    @staticmethod
    def _shape(q):
        a = jnp.maximum(3 - q, 0)
        b = jnp.maximum(2 - q, 0)
        c = jnp.maximum(1 - q, 0)
        return a ** 5 - 6 * b ** 5 + 15 * c ** 5


@_register
@dataclasses.dataclass(frozen=True)
class WendlandC2(_Kernel):
    """Wendland's C2 kernel, support ``2h``.

    ``f(q) = (1 - q/2)^4 (2q + 1)``; ``sigma_2 = 7 / (4 pi)``,
    ``sigma_3 = 21 / (16 pi)``. Positive definite in 2D and 3D only.
    """

    support: ClassVar[float] = 2.0
    _normalisation: ClassVar[dict[int, float]] = {
        2: 7.0 / (4.0 * math.pi), 3: 21.0 / (16.0 * math.pi)}

    @staticmethod
    def _shape(q):
        a = jnp.maximum(1 - q / 2, 0)
        return a ** 4 * (2 * q + 1)


@_register
@dataclasses.dataclass(frozen=True)
class WendlandC4(_Kernel):
    """Wendland's C4 kernel, support ``2h``.

    ``f(q) = (1 - q/2)^6 (35/12 q^2 + 3q + 1)``; ``sigma_2 = 9 / (4 pi)``,
    ``sigma_3 = 495 / (256 pi)``.
    """

    support: ClassVar[float] = 2.0
    _normalisation: ClassVar[dict[int, float]] = {
        2: 9.0 / (4.0 * math.pi), 3: 495.0 / (256.0 * math.pi)}

    @staticmethod
    def _shape(q):
        a = jnp.maximum(1 - q / 2, 0)
        return a ** 6 * (35 * q * q / 12 + 3 * q + 1)


KERNELS: dict[str, type[_Kernel]] = {
    "cubic_spline": CubicSpline,
    "quintic_spline": QuinticSpline,
    "wendland_c2": WendlandC2,
    "wendland_c4": WendlandC4,
}

Kernel = _Kernel


def kernel(name: str, h: Array, *, dim: int) -> Kernel:
    """Make a kernel by name.

    Args:
      name: one of ``KERNELS`` (``"cubic_spline"``, ``"quintic_spline"``,
        ``"wendland_c2"``, ``"wendland_c4"``).
      h: float scalar > 0, the smoothing length.
      dim: 2 or 3.
    """
    if name not in KERNELS:
        raise ValueError(f"kernel name {name!r} is not known; choose one of "
                         f"{sorted(KERNELS)}.")
    return KERNELS[name](h, dim=dim)


# ---------------------------------------------------------------------------
# Equation of state


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Tait:
    """Tait's equation of state ``P = B ((rho / rho0)**gamma - 1)``,
    ``B = rho0 c0**2 / gamma``.

    All fields are pytree leaves (differentiable).

    Attributes:
      rho0: float scalar > 0, reference density.
      c0: float scalar > 0, sound speed at ``rho0`` (weakly compressible:
        about 10x the largest flow speed).
      gamma: float scalar > 0, stiffness exponent (7 for water).
    """

    rho0: Array
    c0: Array
    gamma: Array = 7.0

    def __post_init__(self):
        for name in ("rho0", "c0", "gamma"):
            check_positive(name, getattr(self, name),
                           "The Tait equation of state needs positive "
                           "parameters.")

    def pressure(self, rho: Array) -> Array:
        """Pressure.

        Args:
          rho: float, any shape: densities >= 0.
        Returns:
          ``P(rho)``, shape of ``rho``; NaN where ``rho < 0`` (only reachable
          under ``jit``; eagerly a negative density raises).
        """
        check_density(rho)
        b = self.rho0 * self.c0 ** 2 / self.gamma
        p = b * ((rho / self.rho0) ** self.gamma - 1)
        return jnp.where(rho >= 0, p, jnp.nan)

    def sound_speed(self, rho: Array) -> Array:
        """Local sound speed ``sqrt(dP/drho) = c0 (rho/rho0)**((gamma-1)/2)``.

        Args:
          rho: float, any shape: densities >= 0.
        """
        check_density(rho)
        c = self.c0 * (rho / self.rho0) ** ((self.gamma - 1) / 2)
        return jnp.where(rho >= 0, c, jnp.nan)


def check_density(rho) -> None:
    v = concrete(rho)
    if v is not None and np.any(v < 0):
        raise ValueError(
            f"rho has negative entries (min {v.min()}); densities must be "
            ">= 0. Summation densities are never negative: check the masses "
            "and the kernel's h.")


# ---------------------------------------------------------------------------
# Pair sums over any layout


class ListPairs(NamedTuple):
    centre: Array  # int, (N, cap) for Dense, (E,) for Sparse
    other: Array
    valid: Array   # bool, same shape: a real pair, not padding, not i == i


def list_pairs(neighbor: partition.NeighborList, n: int) -> ListPairs:
    idx = neighbor.idx
    if partition.is_sparse(neighbor.format):
        # jax-md's smap treats idx[0] as the particle a pair belongs to.
        centre, other = idx[0], idx[1]
    else:
        centre = jnp.broadcast_to(
            jnp.arange(n, dtype=idx.dtype)[:, None], idx.shape)
        other = idx
    valid = (centre < n) & (other < n) & (centre != other)
    return ListPairs(centre, other, valid)


def sum_pairs(to_centre: Array, to_other: Array, pairs: ListPairs,
               neighbor: partition.NeighborList, n: int) -> Array:
    """Add per-pair contributions onto particles.

    Args:
      to_centre: float ``pairs.shape + trailing``, added to the centre.
      to_other: same shape, added to the other particle; only read for
        OrderedSparse, where each unordered pair is stored once (Dense and
        Sparse hold both directions, and the reverse pair adds it).
    Returns:
      float ``(n,) + trailing``.
    """
    trailing = (1,) * (to_centre.ndim - pairs.valid.ndim)
    valid = pairs.valid.reshape(pairs.valid.shape + trailing)
    to_centre = jnp.where(valid, to_centre, 0)
    if not partition.is_sparse(neighbor.format):
        return jnp.sum(to_centre, axis=1)
    # Padding pairs carry index n: outside the segment range, hence dropped.
    # An SPH step runs forward alone: the barrier in reverse mode only.
    out = edge_sum(to_centre, pairs.centre, n, forward_barrier=False)
    if neighbor.format is partition.OrderedSparse:
        out = out + edge_sum(jnp.where(valid, to_other, 0), pairs.other, n,
                             forward_barrier=False)
    return out


def _safe_norm(dr: Array) -> tuple[Array, Array]:
    """``|dr|`` and ``dr / |dr|``, both with finite gradients at ``dr = 0``.

    Args:
      dr: float ``(..., dim)``.
    Returns:
      float ``(...)`` and ``(..., dim)`` (the unit vector is 0 where r = 0).
    """
    r2 = jnp.sum(dr * dr, axis=-1)
    nonzero = r2 > 0
    # sqrt'(0) = inf: take the root of a safe value, then discard it.
    r = jnp.sqrt(jnp.where(nonzero, r2, 1))
    unit = jnp.where(nonzero[..., None], dr / r[..., None], 0)
    return jnp.where(nonzero, r, 0), unit


def per_particle(name: str, value, n: int):
    shape = np.shape(value)
    if shape not in ((), (n,)):
        raise ValueError(f"{name} has shape {shape}; pass a scalar or one "
                         f"value per particle, shape ({n},).")
    return jnp.asarray(value) if shape else value


def _gather(value, index):
    return value[index] if np.ndim(value) else value


def _column(x):
    """Per-pair values ``(...)`` as ``(..., 1)`` to scale vectors; scalars
    unchanged."""
    return x[..., None] if np.ndim(x) else x


def _displacement_vectors(displacement: Callable, R: Array,
                          pairs: ListPairs) -> Array:
    ends = R[pairs.centre.reshape(-1)], R[pairs.other.reshape(-1)]
    if pairs.centre.ndim == 1:  # an edge layout (_edges)
        ends = materialized_in_reverse(ends)
    return jax.vmap(displacement)(*ends).reshape(
        pairs.centre.shape + (R.shape[-1],))


def check_displacement(displacement: Callable, dim: int) -> None:
    probe = jax.ShapeDtypeStruct((dim,), jnp.float32)
    shape = jax.eval_shape(displacement, probe, probe).shape
    if shape != (dim,):
        raise ValueError(
            f"displacement must return a ({dim},) vector, got shape {shape}: "
            "SPH forces need directions, so pass a jax-md displacement "
            "function (space.free() or space.periodic(...)[0]), not a "
            "metric.")


def check_kernel_dim(kernel: Kernel, R: Array) -> None:
    if R.ndim != 2 or R.shape[1] != kernel.dim:
        raise ValueError(f"R has shape {R.shape} but the kernel has "
                         f"dim={kernel.dim}: pass (N, {kernel.dim}) positions "
                         "or a kernel of the right dim.")


# ---------------------------------------------------------------------------
# Density


def density(displacement: Callable, kernel: Kernel, *,
            mass: Array = 1.0) -> Callable[..., Array]:
    """Summation density ``rho_i = m_i W(0) + sum_j m_j W(|r_ij|)``.

    Args:
      displacement: jax-md displacement function ``d(Ra, Rb) -> (dim,)``.
      kernel: a `Kernel` (its ``dim`` must match the positions).
      mass: float scalar or ``(N,)``.

    Returns:
      ``density_fn(R, neighbor, *, h=None, mass=None) -> (N,)`` with ``R``
      float ``(N, dim)`` and ``neighbor`` a jax-md `NeighborList` in any
      layout, built with a cutoff >= ``kernel.cutoff``. ``h`` and ``mass``,
      when given, replace the factory's (may be traced and differentiated).
      The result has the dtype of ``R`` promoted with ``h`` and ``mass``.
    """
    check_displacement(displacement, kernel.dim)
    default_mass = mass

    def density_fn(R: Array, neighbor: partition.NeighborList, *,
                   h: Array | None = None, mass: Array | None = None,
                   **unknown) -> Array:
        # **unknown only to name a typo and the accepted keywords (Python's
        # own TypeError names neither the fix nor the alternatives).
        reject_unknown("density_fn", unknown, ("h", "mass"))
        k = kernel if h is None else dataclasses.replace(kernel, h=h)
        check_kernel_dim(k, R)
        n = R.shape[0]
        m = per_particle("mass", default_mass if mass is None else mass, n)
        pairs = list_pairs(neighbor, n)
        r, _ = _safe_norm(_displacement_vectors(displacement, R, pairs))
        w = k.w(r)
        w0 = k.w(jnp.zeros((), R.dtype))
        rho = sum_pairs(_gather(m, pairs.other) * w,
                         _gather(m, pairs.centre) * w, pairs, neighbor, n)
        return rho + m * w0

    return density_fn


# ---------------------------------------------------------------------------
# Accelerations


class Acceleration(NamedTuple):
    """What `acceleration` returns.

    Attributes:
      pressure: float ``(N, dim)``, ``-sum_j m_j (P_i/rho_i^2 + P_j/rho_j^2)
        grad_i W_ij``.
      viscosity: float ``(N, dim)``, ``-sum_j m_j Pi_ij grad_i W_ij``.
      density: float ``(N,)``, the densities used.
    """

    pressure: Array
    viscosity: Array
    density: Array

    @property
    def total(self) -> Array:
        return self.pressure + self.viscosity


def acceleration(displacement: Callable, kernel: Kernel, eos: Tait, *,
                 mass: Array = 1.0, alpha: Array = 0.1, beta: Array = 0.0,
                 epsilon: float = 0.01) -> Callable[..., Acceleration]:
    """Symmetric SPH pressure force and Monaghan's artificial viscosity.

    ``dv_i/dt = -sum_j m_j (P_i/rho_i^2 + P_j/rho_j^2 + Pi_ij) grad_i W_ij``
    with ``Pi_ij = (-alpha c_ij mu_ij + beta mu_ij^2) / rho_ij`` where
    ``v_ij . r_ij < 0`` (approaching) and 0 otherwise,
    ``mu_ij = h v_ij . r_ij / (r^2 + epsilon h^2)``, ``c_ij`` and ``rho_ij``
    the pair's mean sound speed and density. Each pair term is antisymmetric,
    so ``sum_i m_i dv_i/dt = 0`` (momentum is conserved) up to rounding.

    Args:
      displacement: jax-md displacement function ``d(Ra, Rb) -> (dim,)``.
      kernel: a `Kernel`.
      eos: a `Tait` equation of state (also gives the sound speed).
      mass: float scalar or ``(N,)``.
      alpha, beta: float scalars >= 0, viscosity coefficients.
      epsilon: float, keeps ``mu`` finite as ``r -> 0``.

    Returns:
      ``accel_fn(R, V, neighbor, *, rho=None, pressure=None, h=None,
      mass=None, eos=None, alpha=None, beta=None) -> Acceleration``.
      ``R``, ``V``: float ``(N, dim)``. ``rho``: float ``(N,)``; by default
      the summation `density`. ``pressure``: float ``(N,)``; by default
      ``eos.pressure(rho)`` (pass your own, e.g. clipped at 0 for a free
      surface). The other keywords replace the factory's values and may be
      traced. ``neighbor``: any layout, cutoff >= ``kernel.cutoff``.
    """
    for name, value in (("alpha", alpha), ("beta", beta)):
        v = concrete(value)
        if v is not None and (v.ndim or v < 0):
            raise ValueError(f"{name} must be a scalar >= 0; got {value}.")
    check_displacement(displacement, kernel.dim)
    defaults = dict(mass=mass, eos=eos, alpha=alpha, beta=beta)
    density_fn = density(displacement, kernel, mass=mass)

    def accel_fn(R: Array, V: Array, neighbor: partition.NeighborList, *,
                 rho: Array | None = None, pressure: Array | None = None,
                 h: Array | None = None, mass: Array | None = None,
                 eos: Tait | None = None, alpha: Array | None = None,
                 beta: Array | None = None, **unknown) -> Acceleration:
        reject_unknown("accel_fn", unknown, ("rho", "pressure", "h", "mass",
                                             "eos", "alpha", "beta"))
        k = kernel if h is None else dataclasses.replace(kernel, h=h)
        check_kernel_dim(k, R)
        if V.shape != R.shape:
            raise ValueError(f"V has shape {V.shape} but R has {R.shape}; "
                             "pass one velocity per particle.")
        n = R.shape[0]
        m = per_particle("mass", defaults["mass"] if mass is None else mass,
                          n)
        state = defaults["eos"] if eos is None else eos
        a = defaults["alpha"] if alpha is None else alpha
        b = defaults["beta"] if beta is None else beta
        if rho is None:
            rho = density_fn(R, neighbor, h=k.h, mass=m)
        else:
            check_density(rho)
        rho = per_particle("rho", rho, n)
        if pressure is None:
            pressure = state.pressure(rho)
        pressure = per_particle("pressure", pressure, n)
        c = state.sound_speed(rho)

        pairs = list_pairs(neighbor, n)
        dr = _displacement_vectors(displacement, R, pairs)
        r, unit = _safe_norm(dr)
        grad_w = k.grad_w(r)[..., None] * unit  # grad_i W_ij
        ci, cj = pairs.centre, pairs.other
        mi, mj = _gather(m, ci), _gather(m, cj)

        p_term = pressure[ci] / rho[ci] ** 2 + pressure[cj] / rho[cj] ** 2
        p_pair = p_term[..., None] * grad_w

        dv = V[ci] - V[cj]
        vr = jnp.sum(dv * dr, axis=-1)
        hh = k.h
        mu = hh * vr / (r * r + epsilon * hh * hh)
        c_mean = (c[ci] + c[cj]) / 2
        rho_mean = (rho[ci] + rho[cj]) / 2
        pi = jnp.where(vr < 0, (-a * c_mean * mu + b * mu * mu) / rho_mean, 0)
        v_pair = pi[..., None] * grad_w

        # grad_j W_ji = -grad_i W_ij: the other particle gets the opposite
        # sign (only used for OrderedSparse).
        mi, mj = _column(mi), _column(mj)
        acc_p = sum_pairs(-mj * p_pair, mi * p_pair, pairs, neighbor, n)
        acc_v = sum_pairs(-mj * v_pair, mi * v_pair, pairs, neighbor, n)
        return Acceleration(acc_p, acc_v, rho)

    return accel_fn
