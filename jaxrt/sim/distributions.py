"""The seed papers' particle distributions, as plain numpy.

* Seed 001 (Algis & Bramas), §5.2: `uniform` — ``N = p·β³`` particles
  uniform in the unit box, cutoff ``1/β``.
* Seed 001, §5.3 and Code 2 (Appendix 9): `sphere_surface` — ``N = p·α³``
  particles uniform on the unit sphere, cutoff for about ``9·p``
  neighbours.
* Seed 003 (Meneses et al.), §4: `lattice`, `disordered`, `cluster` in a
  box of side `BOX_SIDE` = 1000, and the per-particle search radii of
  `radii`: ``"r=1"``, ``"r=160"``, ``"U[1,160]"``, ``"LN[1,330]"``.

Every function returns float64 numpy arrays (cast to float32 for the seeds'
single-precision runs) and is reproducible from its ``seed``.
"""
from __future__ import annotations

import math

import numpy as np

BOX_SIDE = 1000.0
"""Seed 003 §4: "a 3D box of size 10³ × 10³ × 10³"."""

CLUSTER_SIGMA = 25.0
"""Seed 003 §4: the Cluster scene is N(μ = rand, σ = 25)."""

RADIUS_KINDS = ("r=1", "r=160", "U[1,160]", "LN[1,330]")
"""Seed 003 §4's radius distributions, the names `radii` accepts."""


def _check_positive_int(name: str, value) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name} must be a positive int; got {value!r}.")
    return int(value)


def _check_side(side) -> float:
    if not (isinstance(side, (int, float, np.floating, np.integer))
            and math.isfinite(side) and side > 0):
        raise ValueError(f"side must be a finite number > 0; got {side!r}.")
    return float(side)


def uniform(beta: int, p: int, seed: int) -> tuple[np.ndarray, float]:
    """Seed 001 §5.2: uniform particles in the unit box.

    The seed's grid has β³ cells of side ``C = 1/β`` and ``p`` particles per
    cell on average (β ∈ {2, …, 32}, p ∈ {1, …, 32}).

    Args:
      beta: cells per box side, β ≥ 1.
      p: particles per cell, p ≥ 1.
      seed: numpy random seed.
    Returns:
      positions float64 ``(p·β³, 3)`` in ``[0, 1)``, and the cutoff ``1/β``.
    """
    beta = _check_positive_int("beta", beta)
    p = _check_positive_int("p", p)
    n = p * beta ** 3
    return np.random.default_rng(seed).random((n, 3)), 1.0 / beta


def sphere_surface_cutoff(n: int, p: int) -> float:
    """Seed 001 Code 2's cutoff: the angle ``acos(1 − 2·9p/N)`` of the
    spherical cap that holds ``9·p`` of ``N`` uniform points on the unit
    sphere (cap area fraction ``(1 − cos θ)/2``). Used as a Euclidean
    cutoff, as Code 2 does; the chord ``2·sin(θ/2)`` is shorter by
    ``θ³/24``, so the mean count is slightly above ``9·p``.
    """
    expected_neighbours = 9.0 * p
    cosine = 1.0 - 2.0 * expected_neighbours / n
    return math.acos(min(1.0, max(-1.0, cosine)))


def sphere_surface(alpha: int, p: int, seed: int) -> tuple[np.ndarray, float]:
    """Seed 001 §5.3 and Code 2 (Appendix 9): particles on the unit sphere.

    ``theta = 2π·U``, ``phi = acos(1 − 2·U)``: uniform on the sphere.
    About α³ cells of a grid over the sphere are non-empty, ``p`` particles
    per such cell (α ∈ {2, …, 128}).

    Args:
      alpha: the seed's α ≥ 1 (``boxDiv`` in Code 2).
      p: particles per non-empty cell, p ≥ 1.
      seed: numpy random seed.
    Returns:
      positions float64 ``(p·α³, 3)`` with ``|r| = 1`` (centred at the
      origin: shift by ``1 + cutoff`` for a backend that needs ``[0, box)``),
      and the cutoff `sphere_surface_cutoff`.
    """
    alpha = _check_positive_int("alpha", alpha)
    p = _check_positive_int("p", p)
    n = p * alpha ** 3
    rng = np.random.default_rng(seed)
    theta = 2.0 * np.pi * rng.random(n)
    phi = np.arccos(1.0 - 2.0 * rng.random(n))
    positions = np.stack([np.sin(phi) * np.cos(theta),
                          np.sin(phi) * np.sin(theta),
                          np.cos(phi)], axis=1)
    return positions, sphere_surface_cutoff(n, p)


def lattice(n: int, side: float = BOX_SIDE, *, dim: int = 3) -> np.ndarray:
    """Seed 003 §4 Lattice: "grid positions".

    The first ``n`` points, in x-fastest order, of the cubic (``dim`` 2:
    square) grid of ``m = ⌈n^(1/dim)⌉`` points per side with spacing
    ``side / m``, at cell centres (so the periodic images keep the
    spacing). Deterministic: no seed.

    Returns:
      positions float64 ``(n, dim)`` in ``(0, side)``.
    """
    n = _check_positive_int("n", n)
    side = _check_side(side)
    if dim not in (2, 3):
        raise ValueError(f"dim={dim!r}: the lattice is 2D or 3D.")
    per_side = round(n ** (1.0 / dim))
    if per_side ** dim < n:
        per_side += 1
    k = np.arange(n)
    cells = np.stack([(k // per_side ** a) % per_side for a in range(dim)],
                     axis=1)
    return (cells + 0.5) * (side / per_side)


def disordered(n: int, seed: int, side: float = BOX_SIDE) -> np.ndarray:
    """Seed 003 §4 Disordered: uniform random positions.

    Returns:
      positions float64 ``(n, 3)`` in ``[0, side)``.
    """
    n = _check_positive_int("n", n)
    side = _check_side(side)
    return np.random.default_rng(seed).random((n, 3)) * side


def cluster(n: int, seed: int, side: float = BOX_SIDE,
            sigma: float = CLUSTER_SIGMA) -> np.ndarray:
    """Seed 003 §4 Cluster: one normal cloud N(μ = rand, σ = 25).

    The seed gives no more. Read here as: μ uniform in the box kept ``4σ``
    from the walls, so that the cloud is not cut by a wall, and the rare
    points that still fall outside ``[0, side)`` drawn again (a normal
    truncated to the box, the same under wall and periodic boundaries).

    Args:
      sigma: standard deviation per axis, ``0 < 4·sigma < side / 2``.
    Returns:
      positions float64 ``(n, 3)`` in ``[0, side)``.
    """
    n = _check_positive_int("n", n)
    side = _check_side(side)
    if not (math.isfinite(sigma) and 0 < 4 * sigma < side / 2):
        raise ValueError(f"sigma must satisfy 0 < 4·sigma < side/2 = {side / 2}; "
                         f"got {sigma!r}.")
    rng = np.random.default_rng(seed)
    centre = 4 * sigma + rng.random(3) * (side - 8 * sigma)
    positions = centre + sigma * rng.standard_normal((n, 3))
    outside = np.any((positions < 0) | (positions >= side), axis=1)
    while outside.any():
        positions[outside] = centre + sigma * rng.standard_normal((int(outside.sum()), 3))
        outside = np.any((positions < 0) | (positions >= side), axis=1)
    return positions


def radii(kind: str, n: int, seed: int) -> np.ndarray:
    """Seed 003 §4's per-particle search radii.

    Args:
      kind: one of `RADIUS_KINDS`:
        ``"r=1"`` and ``"r=160"`` constant; ``"U[1,160]"`` uniform in
        [1, 160]; ``"LN[1,330]"`` log-normal with μ = 1, σ = 2 (of the
        logarithm) clipped to [1, 330] (the seed says "in the range [1, 330]"
        without saying how; clipping keeps the many small radii the seed
        describes, ~31 % of them at exactly 1).
      n: number of particles.
      seed: numpy random seed (unused by the constant kinds).
    Returns:
      float64 ``(n,)``.
    """
    n = _check_positive_int("n", n)
    rng = np.random.default_rng(seed)
    if kind == "r=1":
        return np.ones(n)
    if kind == "r=160":
        return np.full(n, 160.0)
    if kind == "U[1,160]":
        return rng.uniform(1.0, 160.0, n)
    if kind == "LN[1,330]":
        return np.clip(rng.lognormal(mean=1.0, sigma=2.0, size=n), 1.0, 330.0)
    raise ValueError(f"kind must be one of {RADIUS_KINDS}; got {kind!r}.")
