"""Pair energies on Dense lists whose position gradient needs no scatter.

On a Dense list ``idx`` (``N`` rows, padding index ``N``) a pair energy is

    E(R) = 1/2 * sum_i sum_c u(d(R_i, R_idx[i, c])).

Plain reverse-mode autodiff differentiates through the gather ``R[idx]``,
whose transpose is a scatter-add of ``N * capacity`` vectors: on a GPU that
scatter, not the arithmetic, sets the time of a force evaluation. A neighbour
list is symmetric (``j`` in row ``i`` iff ``i`` in row ``j``) and ``u``
depends on the distance only, so the two ends of each pair contribute equal
halves:

    dE/dR_k = sum_c  d/dR_k u(d(R_k, R_idx[k, c]))      (idx held fixed)

which is a per-row sum over gathered neighbours: no scatter. This module
makes that the JVP of ``E`` (`jax.custom_jvp`), so ``jax.grad``,
`jax_md.quantity.force` and ``simulate.*`` get it unchanged, and the JVP is
itself built from ordinary differentiable ops, so ``jax.hessian`` and
gradients of forces stay exact. Derivatives with respect to the parameters
(``sigma``, ``epsilon``, cutoffs, a ``box=`` for the metric) go through
ordinary forward-mode JAX and are only computed when asked for.

Requirements (true of every list jaxrt and jax-md build): the list holds
both directions of every pair; per-pair parameters are symmetric
(``p[a, b] == p[b, a]``). A ``custom_mask_function`` that removes ``j`` from
row ``i`` but not ``i`` from row ``j`` breaks the first: use the
``gradient="autodiff"`` option of the energy factories then.
"""
from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero
from jax_md import space, util

Array = jax.Array


def row_parameter(value, idx: Array, species: Array | None,
                  combine: Callable | None = None):
    """A pair parameter laid out like the Dense list, as jax-md's ``smap``.

    Args:
      value: float scalar; ``(N,)`` per particle (combined by ``combine``,
        default the arithmetic mean, as jax-md's default); ``(N, N)`` per
        pair; or with ``species`` an ``(S, S)`` matrix.
      idx: int32 ``(N, capacity)`` Dense list.
      species: int ``(N,)`` or None.
      combine: ``combine(value_i, value_j)`` for per-particle values.
    Returns:
      The scalar, or float ``(N, capacity)``.
    """
    value = jnp.asarray(value)
    if value.ndim == 0:
        return value
    if value.ndim == 1:
        if combine is not None:
            return combine(value[:, None], value[idx])
        return 0.5 * (value[:, None] + value[idx])
    if species is None:
        rows = jnp.arange(idx.shape[0], dtype=jnp.int32)[:, None]
        return value[rows, idx]
    return value[species[:, None], species[idx]]


def _pair_energies(pair: Callable, metric: Callable, combine: tuple,
                   centre: Array, neighbour: Array, idx: Array, params: dict,
                   species: Array | None, metric_kwargs: dict) -> Array:
    """``u(d(centre_i, neighbour_ic))`` masked to real entries: float
    ``(N, capacity)``. ``neighbour`` is float ``(N, capacity, dim)``;
    ``combine``: ``(name, fn)`` pairs, how per-particle parameters combine."""
    distance = space.map_neighbor(lambda a, b: metric(a, b, **metric_kwargs))
    dr = distance(centre, neighbour)
    how = dict(combine)
    row_params = {k: row_parameter(v, idx, species, how.get(k))
                  for k, v in params.items()}
    return pair(dr, **row_params) * (idx < centre.shape[0])


def _total(pair, metric, combine, R, idx, params, species, metric_kwargs):
    e = _pair_energies(pair, metric, combine, R, R[idx], idx, params, species,
                       metric_kwargs)
    # The same sum as jax-md's smap, so totals agree bit for bit.
    return util.high_precision_sum(e) / 2


def _instantiate(tangent, primal):
    if isinstance(tangent, SymbolicZero):
        return jnp.zeros(jnp.shape(primal), jnp.result_type(primal))
    return tangent


def _is_zero(tree) -> bool:
    return all(isinstance(t, SymbolicZero) for t in jax.tree.leaves(
        tree, is_leaf=lambda t: isinstance(t, SymbolicZero)))


_dense_total = jax.custom_jvp(_total, nondiff_argnums=(0, 1, 2))


def _dense_total_jvp(pair, metric, combine, primals, tangents):
    R, idx, params, species, metric_kwargs = primals
    dR, _, dparams, _, dkwargs = tangents
    energy = _total(pair, metric, combine, R, idx, params, species,
                    metric_kwargs)
    tangent = jnp.zeros_like(energy)
    if not isinstance(dR, SymbolicZero):
        neighbour = R[idx]

        def row_sums(centre):
            e = _pair_energies(pair, metric, combine, centre, neighbour, idx,
                               params, species, metric_kwargs)
            return jnp.sum(e)

        force = jax.grad(row_sums)(R)  # = dE/dR for a symmetric list
        tangent = tangent + jnp.sum(force * dR).astype(energy.dtype)
    if not (_is_zero(dparams) and _is_zero(dkwargs)):
        dparams = jax.tree.map(_instantiate, dparams, params,
                               is_leaf=lambda t: isinstance(t, SymbolicZero))
        dkwargs = jax.tree.map(_instantiate, dkwargs, metric_kwargs,
                               is_leaf=lambda t: isinstance(t, SymbolicZero))
        _, t = jax.jvp(
            lambda p, k: _total(pair, metric, combine, R, idx, p, species, k),
            (params, metric_kwargs), (dparams, dkwargs))
        tangent = tangent + t
    return energy, tangent


_dense_total.defjvp(_dense_total_jvp, symbolic_zeros=True)


def dense_pair_energy(pair: Callable, metric: Callable, R: Array, idx: Array,
                      params: dict, species: Array | None = None,
                      metric_kwargs: dict | None = None,
                      combine: tuple = ()) -> Array:
    """Total pair energy on a Dense list, with the scatter-free gradient.

    Args:
      pair: ``pair(dr, **params)`` -> energies, elementwise in ``dr``; must be
        finite with a finite gradient at ``dr == 0`` (padding and self
        entries are masked by multiplying by zero).
      metric: ``metric(Ra, Rb, **metric_kwargs)`` -> distance (scalar).
      R: float ``(N, dim)`` positions.
      idx: int32 ``(N, capacity)`` symmetric Dense list, padding ``N``.
      params: name -> float scalar, ``(N,)``, ``(N, N)`` or ``(S, S)`` (see
        `row_parameter`); differentiable.
      species: int ``(N,)`` or None.
      metric_kwargs: extra keyword arrays for ``metric`` (e.g. ``box``);
        differentiable.
      combine: static ``(name, fn)`` pairs: per-particle ``params[name]``
        combine as ``fn(p_i, p_j)`` (symmetric), not the mean.
    Returns:
      float scalar, ``1/2 sum_i sum_c u``, in the dtype of the pair energies.
    """
    return _dense_total(pair, metric, tuple(combine), R, idx, params, species,
                        {} if metric_kwargs is None else metric_kwargs)
