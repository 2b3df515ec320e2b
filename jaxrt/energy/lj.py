"""Lennard-Jones energies on neighbour lists, jit-able and differentiable.

The pair sum is jax-md's own (`jax_md.smap.pair_neighbor_list`) and so is
the smooth switch (`jax_md.energy.multiplicative_isotropic_cutoff`), so with ``truncation="smooth"`` the energy equals
`jax_md.energy.lennard_jones_neighbor_list` on the same list. jaxrt adds:

* three truncations: ``"truncated"`` (plain cut at ``r_cutoff``),
  ``"shifted"`` (cut and shifted so that ``E(r_cutoff) = 0``) and
  ``"smooth"`` (jax-md's C1 switch between ``r_onset`` and ``r_cutoff``);
* per-particle energies for every layout, OrderedSparse included (each
  pair's energy split half and half between its two particles);
* ``sigma``, ``epsilon``, ``r_onset`` and ``r_cutoff`` as keyword arguments of
  the energy function, so `jax.grad` can differentiate with respect to them;
* gradients that stay finite when two particles coincide (padding entries
  and self pairs included), by the double-``where`` trick instead of
  jax-md's ``nan_to_num``;
* clear errors for malformed ``species`` / ``sigma`` / ``epsilon``;
* per-particle radii (``radii=``, seed 003 §3): pair ``ij`` is cut at
  ``r_c,ij = max(r_i, r_j)`` (the lists' rule), and its potential is the
  factory's stretched by ``s_ij = r_c,ij / r_cutoff``: ``sigma_ij = sigma
  s_ij``, ``r_onset,ij = r_onset s_ij`` (`lennard_jones_radii`).

Forces are ``-jax.grad(energy_fn)`` (e.g. `jax_md.quantity.force`).

Differences from jax-md, on purpose:

* Python-float parameters stay weakly typed, so a float64 system stays
  float64 (jax-md casts Python floats to float32).
* Two particles at exactly the same position contribute zero energy and zero
  force (jax-md: zero energy, NaN-free only by accident of ``nan_to_num``).
  Nearly coincident particles give ``+inf`` energy once ``(sigma/r)**12``
  overflows (``r < sigma * 1e-3.2`` in float32); jax-md replaces that with
  the largest float and a zero force, which hides the overlap.
* A NaN or infinite position makes the energy NaN: the pair functions'
  masks (and jax-md's switch) treat a NaN distance as one past the cutoff,
  which would drop that particle's pairs from the sum silently.
* Keyword arguments of the energy function other than the LJ parameters
  go to the displacement function only (e.g. ``box=`` for a changing box),
  and only those it reads: its named parameters, plus ``box``, ``new_box``
  and ``perturbation`` when it takes ``**kwargs`` as jax_md.space's do.
  ``kT`` (which jax_md.simulate's Nose-Hoover integrators pass on) is
  accepted and dropped. Anything else (a typo such as ``sigmaa=``) raises
  ``TypeError`` (jax-md's displacements take ``**unused`` and would drop it
  silently).
"""
from __future__ import annotations

import functools
import math
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax_md import energy as jmd_energy
from jax_md import partition, smap, space

from jaxrt.energy.checks import concrete
from jaxrt.layouts.edges import edge_sum, materialized_metric
from jaxrt.energy.keywords import (SIMULATE_KEYWORDS, displacement_keywords,
                                    reject_unknown)
from jaxrt.energy.rows import dense_pair_energy

Array = jax.Array

TRUNCATIONS = ("smooth", "shifted", "truncated")
GRADIENTS = ("rows", "autodiff")


def lennard_jones(dr: Array, sigma: Array = 1.0, epsilon: Array = 1.0
                  ) -> Array:
    """``4 epsilon ((sigma/dr)**12 - (sigma/dr)**6)``, finite at ``dr == 0``.

    Args:
      dr: float, any shape: distances.
      sigma, epsilon: float scalars or arrays broadcastable to ``dr``.
    Returns:
      Energies, shape and dtype of ``dr`` (promoted with the parameters).
      Zero, with a zero gradient, where ``dr == 0``. NaN where ``sigma <= 0``
      or ``epsilon < 0``: those are only reachable under ``jit`` (eagerly
      the factories raise), and LJ's even powers would otherwise make
      ``-sigma`` act as ``sigma`` without a trace.
    """
    positive = dr > 0
    # The discarded branch must be finite too, or its NaN leaks into the
    # gradient through the where (0 * inf).
    safe = jnp.where(positive, dr, 1)
    # Same arithmetic as jax_md.energy.lennard_jones, so values match it bit
    # for bit.
    idr = sigma / safe
    idr = idr * idr
    idr6 = idr * idr * idr
    idr12 = idr6 * idr6
    e = jnp.where(positive, 4 * epsilon * (idr12 - idr6), 0)
    return jnp.where((sigma > 0) & (epsilon >= 0), e, jnp.nan)


def lennard_jones_truncated(dr: Array, sigma: Array = 1.0,
                            epsilon: Array = 1.0, *, r_onset: Array,
                            r_cutoff: Array, truncation: str = "smooth"
                            ) -> Array:
    """Lennard-Jones with a cutoff.

    Args:
      dr: float, any shape: distances.
      sigma, epsilon: float scalars or arrays broadcastable to ``dr``.
      r_onset: float scalar, where the smooth switch starts (absolute
        distance; only read for ``truncation="smooth"``).
      r_cutoff: float scalar, absolute cutoff distance.
      truncation: ``"smooth"`` (jax-md's C1 switch ``S(r)`` times LJ),
        ``"shifted"`` (``E(r) - E(r_cutoff)`` below the cutoff) or
        ``"truncated"`` (``E(r)`` below the cutoff).
    Returns:
      Energies, shape of ``dr``; zero for ``dr >= r_cutoff``.
    """
    # jax-md's switch squares the cutoffs with a float32 exponent, which
    # turns Python floats into float32 even for float64 positions: give
    # them the positions' dtype first.
    dtype = jnp.result_type(dr, r_onset, r_cutoff)
    r_onset = jnp.asarray(r_onset, dtype)
    r_cutoff = jnp.asarray(r_cutoff, dtype)
    if truncation == "smooth":
        # Called here rather than once per factory so that r_onset and
        # r_cutoff may be traced (and differentiated).
        switched = jmd_energy.multiplicative_isotropic_cutoff(
            lennard_jones, r_onset, r_cutoff)
        return switched(dr, sigma, epsilon)
    e = lennard_jones(dr, sigma, epsilon)
    if truncation == "shifted":
        e = e - lennard_jones(r_cutoff, sigma, epsilon)
    elif truncation != "truncated":
        raise ValueError(_truncation_error(truncation))
    # dr == r_cutoff falls outside, matching the strict `<` of the lists;
    # coincident particles stay at zero (not -E(r_cutoff)) as in "smooth".
    return jnp.where((dr > 0) & (dr < r_cutoff), e, 0)


def lennard_jones_radii(dr: Array, sigma: Array = 1.0, epsilon: Array = 1.0,
                        radius: Array = 1.0, *, r_onset: Array,
                        r_cutoff: Array, truncation: str = "smooth") -> Array:
    """`lennard_jones_truncated` stretched to a pair's radius.

    Seed 003 §3 cuts pair ``ij`` at ``radius = max(r_i, r_j)`` and leaves
    sigma unspecified; here the whole potential scales with the cut:
    ``s = radius / r_cutoff``, sigma ``sigma s``, onset ``r_onset s``, cut
    ``radius`` (with the defaults sigma = 1, r_cutoff = 2.5: ``sigma_ij =
    max(r_i, r_j) / 2.5``, the usual cut at 2.5 sigma). epsilon is not
    scaled.

    Args:
      dr: float, any shape: distances.
      sigma, epsilon, radius: float, broadcastable to ``dr``; ``radius`` is
        the pair's ``max(r_i, r_j)`` (zero: no interaction).
      r_onset, r_cutoff: float scalars, the reference potential's.
    Returns:
      Energies, shape of ``dr``; zero for ``dr >= radius``.
    """
    positive = radius > 0
    scale = jnp.where(positive, radius, r_cutoff) / r_cutoff
    e = lennard_jones_truncated(dr, sigma * scale, epsilon,
                                r_onset=r_onset * scale,
                                r_cutoff=r_cutoff * scale,
                                truncation=truncation)
    return jnp.where(positive, e, 0)


# One pair function per truncation, made once: the row-gradient path keys
# its custom JVP on the function object.
_PAIRS = {t: functools.partial(lennard_jones_truncated, truncation=t)
          for t in TRUNCATIONS}
_RADII_PAIRS = {t: functools.partial(lennard_jones_radii, truncation=t)
                for t in TRUNCATIONS}
# The pair's radius is max(r_i, r_j), not jax-md's default mean.
_RADIUS_COMBINE = (("radius", jnp.maximum),)


# The energy function's own keywords (lennard_jones_pair_neighbor_list).
_ENERGY_KEYWORDS = ("sigma", "epsilon", "r_onset", "r_cutoff", "species",
                    "radii")


def _truncation_error(truncation) -> str:
    return (f"truncation={truncation!r} is not known; choose one of "
            f"{TRUNCATIONS}.")


def _check_parameter(name: str, value, species) -> None:
    """Shapes (and, when known, signs) of sigma / epsilon against species."""
    v = concrete(value)
    shape = tuple(np.shape(value)) if v is None else v.shape
    if species is None:
        if len(shape) > 2:
            raise ValueError(
                f"{name} has shape {shape}; without species it must be a "
                "scalar, a per-particle (N,) array or a per-pair (N, N) "
                "matrix.")
    else:
        if len(shape) not in (0, 2) or (len(shape) == 2
                                        and shape[0] != shape[1]):
            raise ValueError(
                f"{name} has shape {shape} but species was given: pass a "
                f"scalar or a square (S, S) matrix {name}[a, b] for each pair "
                "of species a, b (per-particle vectors are not combined "
                "with species).")
        if len(shape) == 2:
            s = concrete(species)
            if s is not None and s.size and int(s.max()) >= shape[0]:
                raise ValueError(
                    f"species has values up to {int(s.max())} but {name} is "
                    f"{shape[0]}x{shape[0]}: make {name} (S, S) with "
                    f"S > max(species) = {int(s.max())}.")
    if v is not None:
        if not np.all(np.isfinite(v)):
            raise ValueError(f"{name} has non-finite entries; pass finite "
                             "values.")
        if name == "sigma" and np.any(v <= 0):
            raise ValueError(f"sigma must be > 0 everywhere; got min "
                             f"{v.min()}.")
        if np.any(v < 0):
            raise ValueError(f"{name} must be >= 0 everywhere (0 switches a "
                             f"pair off); got min {v.min()}.")
        if v.ndim == 2 and not np.allclose(v, v.T):
            raise ValueError(
                f"{name} is not symmetric: {name}[a, b] must equal "
                f"{name}[b, a] (an asymmetric matrix gives different energies "
                "for Dense / Sparse and OrderedSparse lists); symmetrise it, "
                f"e.g. ({name} + {name}.T) / 2.")


def _check_radii(radii, n: int | None = None) -> None:
    """Shape (and, when concrete, values) of per-particle radii."""
    shape = np.shape(radii)
    if len(shape) != 1 or (n is not None and shape[0] != n):
        want = "(N,)" if n is None else f"({n},)"
        raise ValueError(f"radii must be a float {want} array, one radius per "
                         f"particle; got shape {shape}.")
    r = concrete(radii)
    if r is not None and not np.all(np.isfinite(r) & (r >= 0)):
        raise ValueError("radii must be finite and >= 0.")


def _check_species(species) -> None:
    if species is None:
        return
    shape = np.shape(species)
    dtype = getattr(species, "dtype", np.asarray(species).dtype)
    if len(shape) != 1 or not jnp.issubdtype(dtype, jnp.integer):
        raise ValueError(
            f"species must be an integer (N,) array; got shape {shape} and "
            f"dtype {dtype}. Pass one integer type per particle.")
    s = concrete(species)
    if s is not None and s.size and s.min() < 0:
        raise ValueError("species has negative entries; use 0, 1, ..., S-1.")


def _check_cutoffs(r_onset, r_cutoff, truncation) -> None:
    rc = concrete(r_cutoff)
    if rc is not None and (rc.ndim or not rc > 0 or not np.isfinite(rc)):
        raise ValueError(f"r_cutoff must be a finite scalar > 0; got "
                         f"{r_cutoff}.")
    ro = concrete(r_onset)
    if truncation == "smooth" and ro is not None and rc is not None:
        if ro.ndim or not 0 <= ro < rc:
            raise ValueError(
                f"r_onset={r_onset} must be a scalar with 0 <= r_onset < "
                f"r_cutoff={r_cutoff}: the smooth switch divides by "
                "r_cutoff**2 - r_onset**2.")


def _check_overrides(p: dict, species, n: int) -> None:
    """Shapes of the energy function's ``sigma`` and ``epsilon`` (in ``p``)
    against ``species`` (int ``(N,)`` or None) and ``n`` particles."""
    if species is not None and species.shape[0] != n:
        raise ValueError(f"species has {species.shape[0]} entries but R "
                         f"has {n} particles; pass one type per particle.")
    for name in ("sigma", "epsilon"):
        # Overrides are usually being differentiated (and finite
        # differences perturb them asymmetrically), so only their shapes
        # are checked, never their values.
        shape = np.shape(p[name])
        if species is not None and shape and (
                len(shape) != 2 or shape[0] != shape[1]):
            raise ValueError(
                f"{name} has shape {shape} but species was given: pass a "
                f"scalar or a square (S, S) matrix.")
        s = None if species is None else concrete(species)
        if len(shape) == 2 and s is not None and s.size and (
                int(s.max()) >= shape[0]):
            raise ValueError(
                f"species has values up to {int(s.max())} but {name} is "
                f"{shape[0]}x{shape[0]}: make {name} (S, S) with "
                f"S > max(species).")
        if species is None and len(shape) >= 1 and shape[0] != n:
            raise ValueError(
                f"{name} has shape {shape} but R has {n} particles: "
                f"per-particle {name} must be (N,) or (N, N).")


def lennard_jones_pair_neighbor_list(
    displacement_or_metric: Callable,
    *,
    species: Array | None = None,
    sigma: Array = 1.0,
    epsilon: Array = 1.0,
    r_onset: Array = 2.0,
    r_cutoff: Array = 2.5,
    truncation: str = "smooth",
    per_particle: bool = False,
    gradient: str = "rows",
    radii: Array | None = None,
) -> Callable[..., Array]:
    """Lennard-Jones energy on any jax-md neighbour list (absolute units).

    Unlike jax-md's convenience wrapper, ``r_onset`` and ``r_cutoff`` here are
    absolute distances (not multiples of ``max(sigma)``). The list must have
    been built with a cutoff of at least ``r_cutoff``; pairs it lacks are
    silently missing from the sum.

    Args:
      displacement_or_metric: jax-md displacement or metric function.
      species: int ``(N,)`` particle types, or None.
      sigma, epsilon: float scalar; without species also ``(N,)`` per
        particle (combined by the arithmetic mean, as jax-md does) or
        ``(N, N)``; with species a symmetric ``(S, S)`` matrix,
        ``S > max(species)``. ``sigma > 0``, ``epsilon >= 0``.
      r_onset: float scalar, start of the smooth switch (``"smooth"`` only).
      r_cutoff: float scalar > r_onset.
      truncation: ``"smooth"``, ``"shifted"`` or ``"truncated"`` (see
        `lennard_jones_truncated`).
      per_particle: return ``(N,)`` energies (each pair split half and half
        between its particles) instead of the total.
      gradient: how the total energy on a *Dense* list is differentiated
        with respect to positions. ``"rows"`` (default): each particle's
        force is summed from its own row, no scatter (`jaxrt.energy.rows`;
        several times faster on a GPU; needs the list to hold both
        directions of every pair, as every jaxrt and jax-md list does).
        ``"autodiff"``: plain reverse mode through the gather (use it with a
        ``custom_mask_function`` that masks one direction only). Other
        layouts and ``per_particle`` always use ``"autodiff"``.
      radii: None, or float ``(N,)`` per-particle radii (seed 003 §3): pair
        ``ij`` is cut at ``r_c,ij = max(r_i, r_j)`` and its potential is
        stretched by ``s_ij = r_c,ij / r_cutoff``, so ``sigma_ij = sigma
        s_ij`` and ``r_onset,ij = r_onset s_ij`` (`lennard_jones_radii`).
        Use a list built with the same ``radii=`` (and ``r_cutoff >=
        max(radii)``).

    Returns:
      ``energy_fn(R, neighbor, *, sigma=None, epsilon=None, r_onset=None,
      r_cutoff=None, species=None, radii=None, **metric_kwargs)``. ``R`` is float
      ``(N, dim)``, ``neighbor`` a jax-md `NeighborList` in any layout. The
      keyword parameters, when given, replace the factory's (same shapes,
      may be traced: differentiate with respect to them; only their shapes
      are checked); ``species`` (int ``(N,)``) only if the factory had
      species. ``metric_kwargs`` (e.g. ``box=`` for
      ``space.periodic_general``) go to the displacement function only; a
      name it does not read raises ``TypeError`` (module docstring).
      Returns a scalar, or ``(N,)`` with ``per_particle``, in the dtype of
      ``R`` promoted with the parameters.

    Under ``jit`` the value checks cannot run: a ``species`` entry beyond
    ``sigma``'s size silently reads the last row (JAX clamps gathers),
    ``sigma <= 0`` or ``epsilon < 0`` gives NaN energies, and
    ``r_onset >= r_cutoff`` gives NaN gradients with respect to the cutoffs.
    Shape errors always raise.
    """
    _check_factory(truncation, gradient, species, sigma, epsilon, r_onset,
                   r_cutoff, radii)
    metric = space.canonicalize_displacement_or_metric(displacement_or_metric)
    metric_keywords = displacement_keywords(displacement_or_metric)
    defaults = dict(sigma=sigma, epsilon=epsilon, r_onset=r_onset,
                    r_cutoff=r_cutoff)
    default_species = species
    default_radii = radii

    def energy_fn(R: Array, neighbor: partition.NeighborList, *,
                  sigma: Array | None = None, epsilon: Array | None = None,
                  r_onset: Array | None = None, r_cutoff: Array | None = None,
                  species: Array | None = None, radii: Array | None = None,
                  **metric_kwargs) -> Array:
        # Names are static, so this raises at trace time under jit too.
        reject_unknown("energy_fn", metric_kwargs, _ENERGY_KEYWORDS,
                       metric_keywords, SIMULATE_KEYWORDS)
        metric_kwargs = {k: v for k, v in metric_kwargs.items()
                         if k in metric_keywords}
        given = dict(sigma=sigma, epsilon=epsilon, r_onset=r_onset,
                     r_cutoff=r_cutoff)
        n = R.shape[0]
        p, species, radii = _call_parameters(
            given, defaults, species, default_species, radii, default_radii,
            n)
        pairs, pair_params, combine = _PAIRS, {}, ()
        if radii is not None:
            _check_radii(radii, n)
            pairs, combine = _RADII_PAIRS, _RADIUS_COMBINE
            pair_params = {"radius": jnp.asarray(radii)}

        # A NaN or infinite position is never a silent zero: the pair
        # functions and the switch mask a NaN distance like one past the
        # cutoff, so the particle's pairs would simply vanish from the sum.
        # 0 * sum(R) is 0 for finite R (with a zero gradient) and NaN
        # otherwise.
        poison = 0 * jnp.sum(R)
        if (neighbor.format is partition.Dense and not per_particle
                and gradient == "rows"):
            return poison + dense_pair_energy(
                pairs[truncation], metric, R, neighbor.idx,
                {"sigma": p["sigma"], "epsilon": p["epsilon"],
                 "r_onset": p["r_onset"], "r_cutoff": p["r_cutoff"],
                 **pair_params},
                species, metric_kwargs, combine)

        out = _mapped_energy(pairs[truncation], metric, R, neighbor, p,
                             pair_params, combine, species, per_particle,
                             metric_kwargs)
        return out + poison.astype(out.dtype)

    return energy_fn


def _check_factory(truncation, gradient, species, sigma, epsilon, r_onset,
                   r_cutoff, radii) -> None:
    """`lennard_jones_pair_neighbor_list`'s arguments, checked."""
    if truncation not in TRUNCATIONS:
        raise ValueError(_truncation_error(truncation))
    if gradient not in GRADIENTS:
        raise ValueError(f"gradient={gradient!r} is not known; choose one of "
                         f"{GRADIENTS}.")
    _check_species(species)
    _check_parameter("sigma", sigma, species)
    _check_parameter("epsilon", epsilon, species)
    _check_cutoffs(r_onset, r_cutoff, truncation)
    if radii is not None:
        _check_radii(radii)


def _call_parameters(given: dict, defaults: dict, species, default_species,
                     radii, default_radii, n: int):
    """An energy function's parameters: those ``given`` to the call (None:
    not given) over the factory's ``defaults``, and its species and radii,
    checked. Returns ``(params, species, radii)``."""
    p = {k: defaults[k] if v is None else v for k, v in given.items()}
    if species is None:
        species = default_species
    elif default_species is None:
        raise ValueError(
            "species was given to the energy function but not to the "
            "factory: pass species (and (S, S) sigma / epsilon) to "
            "lennard_jones_pair_neighbor_list.")
    else:
        _check_species(species)
    _check_overrides(p, species, n)
    if radii is None:
        radii = default_radii
    elif default_radii is None:
        raise ValueError(
            "radii was given to the energy function but not to the "
            "factory: pass radii to lennard_jones_pair_neighbor_list.")
    return p, species, radii


def _mapped_energy(pair_fn: Callable, metric: Callable, R: Array,
                   neighbor: partition.NeighborList, p: dict,
                   pair_params: dict, combine, species, per_particle: bool,
                   metric_kwargs: dict) -> Array:
    """The energy through jax-md's ``smap.pair_neighbor_list`` on any
    layout: a scalar, or float ``(N,)`` with ``per_particle``."""
    n = R.shape[0]
    pair = functools.partial(pair_fn, r_onset=p["r_onset"],
                             r_cutoff=p["r_cutoff"])
    # jax-md's smap combines per-particle parameters given as (fn, value).
    pair_params = {k: (dict(combine)[k], v) for k, v in pair_params.items()}
    ordered = neighbor.format is partition.OrderedSparse
    if not per_particle:
        reduce_axis = None
    elif ordered:
        reduce_axis = ()  # jax-md refuses; reduced below
    else:
        reduce_axis = (1,)
    # ignore_unused_parameters: metric_kwargs (e.g. box=) reach the
    # displacement only, never the pair function.
    # Edge layouts: the gathered ends written out first
    # (`jaxrt.layouts.edges`).
    edge_metric = (materialized_metric(metric)
                   if partition.is_sparse(neighbor.format) else metric)
    mapped = smap.pair_neighbor_list(
        pair, edge_metric, species=species, reduce_axis=reduce_axis,
        ignore_unused_parameters=True, sigma=p["sigma"],
        epsilon=p["epsilon"], **pair_params)
    out = mapped(R, neighbor, **metric_kwargs)
    if per_particle and ordered:
        # Each unordered pair appears once: give half to each end. The
        # padding index n falls outside segment_sum's range and is
        # dropped (its energies are zero anyway).
        out = (edge_sum(out, neighbor.idx[0], n)
               + edge_sum(out, neighbor.idx[1], n)) / 2
    return out


def lennard_jones_neighbor_list(
    displacement_or_metric: Callable,
    box_size,
    *,
    species: Array | None = None,
    sigma: Array = 1.0,
    epsilon: Array = 1.0,
    r_onset: float = 2.0,
    r_cutoff: float = 2.5,
    dr_threshold: float = 0.5,
    per_particle: bool = False,
    fractional_coordinates: bool = False,
    format: partition.NeighborListFormat = partition.OrderedSparse,
    truncation: str = "smooth",
    gradient: str = "rows",
    neighbor_list_fn: Callable | None = None,
    radii: Array | None = None,
    **neighbor_kwargs,
) -> tuple[partition.NeighborListFns, Callable[..., Array]]:
    """Drop-in for `jax_md.energy.lennard_jones_neighbor_list`.

    As in jax-md, ``r_onset`` and ``r_cutoff`` are in units of
    ``max(sigma)``, fixed when this is called: passing a different ``sigma``
    to the energy function later does not move the cutoff. The energy
    function's own ``r_onset`` / ``r_cutoff`` keywords are absolute distances
    (see `lennard_jones_pair_neighbor_list`).

    Args:
      displacement_or_metric: jax-md displacement or metric function.
      box_size: the box, as for the neighbour list.
      species, sigma, epsilon, truncation, per_particle, gradient: as in
        `lennard_jones_pair_neighbor_list`; ``sigma`` must be concrete here
        (it sets the cutoff).
      r_onset, r_cutoff: multiples of ``max(sigma)``.
      dr_threshold: the list's skin.
      fractional_coordinates: forwarded to the neighbour list only (the
        displacement function already knows it).
      format: the list layout.
      neighbor_list_fn: the list factory; default `jaxrt.neighbor_list`
        (``backend="auto"``). Give ``functools.partial(jaxrt.neighbor_list,
        backend=...)`` or ``jax_md.partition.neighbor_list``.
      radii: None, or float ``(N,)`` per-particle radii, given to both the
        list (whose ``r_cutoff`` is then ``max(radii)``) and the energy
        (`lennard_jones_pair_neighbor_list`: pairs cut at ``max(r_i, r_j)``,
        the potential stretched from the reference cut ``r_cutoff``).
      neighbor_kwargs: forwarded to ``neighbor_list_fn`` (jaxrt rejects
        names it does not know).

    Returns:
      ``(neighbor_fn, energy_fn)`` as in jax-md.
    """
    if neighbor_list_fn is None:
        from jaxrt.lists.neighbors import neighbor_list as neighbor_list_fn
    s = concrete(sigma)
    if s is None:
        raise ValueError("sigma must be concrete (not traced) here: it sets "
                         "the cutoff of the neighbour list. Pass traced "
                         "values to the energy function instead.")
    _check_parameter("sigma", sigma, species)
    scale = float(np.max(s))
    # Array sigma keeps its dtype; a Python float stays weak (no downcast).
    scale_like = jnp.max(sigma) if isinstance(sigma, jax.Array) else scale
    if not (float(r_cutoff) > 0 and math.isfinite(float(r_cutoff))):
        raise ValueError(f"r_cutoff must be finite and > 0; got {r_cutoff}.")
    list_cutoff = float(r_cutoff) * scale
    if radii is not None:
        _check_radii(radii)
        r = concrete(radii)
        if r is None:
            raise ValueError("radii must be concrete here: the largest sets "
                             "the neighbour list's cutoff.")
        list_cutoff = float(np.max(r, initial=0.0))
        neighbor_kwargs["radii"] = radii
    neighbor_fn = neighbor_list_fn(
        displacement_or_metric, box_size, list_cutoff,
        dr_threshold, fractional_coordinates=fractional_coordinates,
        format=format, **neighbor_kwargs)
    energy_fn = lennard_jones_pair_neighbor_list(
        displacement_or_metric, species=species, sigma=sigma, epsilon=epsilon,
        r_onset=r_onset * scale_like, r_cutoff=r_cutoff * scale_like,
        truncation=truncation, per_particle=per_particle, gradient=gradient,
        radii=radii)
    return neighbor_fn, energy_fn
