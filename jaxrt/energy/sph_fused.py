"""SPH without a neighbour list: summation density, pressure and viscosity
from a walk over the cell grid (issue #18), differentiable to first order.

`density_fused` and `acceleration_fused` take the arguments of
`jaxrt.energy.sph.density` and `jaxrt.energy.sph.acceleration` plus the box,
and return functions with the same keywords and results, minus the
neighbour list::

    rho = sph.density(disp, kernel, mass=m)(R, nbrs)
    rho = density_fused(disp, box, kernel, mass=m)(R)

    acc = sph.acceleration(disp, kernel, eos, mass=m, alpha=0.1)(R, V, nbrs)
    acc = acceleration_fused(disp, box, kernel, eos, mass=m, alpha=0.1)(R, V)

Backends (``backend=``):

* ``"cell"``: `jaxrt.cell_list`'s sorted grid, recomputed at every call
  (`jaxrt.energy.fused.cell_runs`): every particle walks the runs of sorted
  particles that hold its stencil cells, one slot of every run per step of
  a loop as long as the longest run (`jaxrt.energy.fused.walk_runs`), and
  sums its own terms. Each pair is met from both sides: no scatter, and
  nothing of size N x k is stored. Pure JAX, the same program on CPU and
  GPU. `acceleration_fused` sorts once and walks twice (densities, then
  forces).
* ``"brute"``: all pairs in row blocks, O(N^2); the reference.

Cost. A walk evaluates, per particle, one candidate of each stencil row (3
in 2D, 9 in 3D) per step of a loop as long as the longest run (2.25 x the
support along x): about 2x (2D) and 5x (3D) the pairs within the support,
each pair from both sides, at every call, where a list path reads rows of
support + skin rebuilt every few steps. On a shared 2-core CPU
(`benchmarks/sph_step.py`, water box, float32, ms per step) the list-free
step took 6.1 at N = 10^4 in 2D against 4.4 (jaxrt cell list, Dense) and
2.9 (OrderedSparse), 24.8 against 19.1 / 17.4 at 3·10^4, and 449 against
120 / 123 in 3D at 27000: slower on the CPU; its case is the GPU (#18).

Derivatives. Each walk is a `jax.custom_vjp` (reverse mode through a loop
of dynamic length is impossible): its backward pass is another walk over
the same cells in which every particle, for each candidate, takes the VJP
of the pair term from its own side *and* of the mirrored term (the pair
seen from the other particle, with that particle's cotangent), so that it
collects everything it owes without a scatter. Positions, velocities,
``h``, masses, densities, pressures and the equation of state's
parameters get gradients (the EOS and the self term are plain JAX around
the walks). Only first order: a second derivative raises
`jaxrt.energy.HigherOrderError`; forward mode (``jax.jvp``) is refused by
JAX. Use the list path (`jaxrt.energy.sph`) for Hessians.

Conventions are `jaxrt.energy.sph`'s: ``r_ij = R_i - R_j``, the self term
``m_i W(0)`` in the density, the same kernels and `Tait`. Differences:

* Everything is computed in R's dtype (masses, ``h``, the EOS parameters
  are cast to it); the list path promotes.
* ``h`` given at call time may be smaller than the factory kernel's, never
  larger: the grid's cells are sized by the factory's support.
* Boxes: free space, or orthorhombic with any axes periodic; the support
  must stay below half of every periodic side. ``displacement`` is probed
  for agreement with the box (the walk computes minimum images itself).

Bad input raises `ValueError` when its value is known (outside ``jit``):
a non-finite position (`jaxrt.energy.FusedInputError`), ``h`` above the
factory's, negative densities, a kernel or EOS with non-positive
parameters, arrays of the wrong shape (those always raise). Under ``jit``
the value checks cannot raise, and the results are NaN instead: all of
them for a non-finite position or too large an ``h``. An unknown keyword
raises ``TypeError`` naming it and the accepted ones.
"""
from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxrt.energy import sph as _sph
from jaxrt.energy._checks import concrete
from jaxrt.energy._keywords import reject_unknown
from jaxrt.energy.fused import (FusedInputError, _Params,
                                _periodicity, _sides, _static_params,
                                cell_runs, first_order_only, walk_runs)

Array = jax.Array

BACKENDS = ("cell", "brute")

_HIGHER_ORDER = (
    "density_fused / acceleration_fused are differentiable once (their "
    "VJP is a second walk over the cells); second derivatives (jax.hessian, "
    "gradients of gradients) are not available. Use jaxrt.energy.sph.density"
    " / acceleration on a neighbour list (jaxrt.neighbor_list) for those.")
_first_order_only = first_order_only(_HIGHER_ORDER)


# ---------------------------------------------------------------------------
# Per-particle data as one table, particles on the minor axis: a candidate
# costs one gather of its row, and every pair term is an array (K, M) whose
# long axis M (the particles) the CPU vectorises ((M, K) with K = 3 stencil
# rows did not vectorise: 2-3x slower).


def _pack(data: dict) -> tuple[Array, tuple]:
    """dict of ``(N,)`` / ``(N, k)`` arrays -> float ``(F, N)`` and its
    layout ``((name, first, stop, trailing), ...)``."""
    rows, layout, at = [], [], 0
    for name, v in data.items():
        width = int(np.prod(v.shape[1:], dtype=int))
        rows.append(v.reshape(v.shape[0], width).T)
        layout.append((name, at, at + width, v.shape[1:]))
        at += width
    return jnp.concatenate(rows, axis=0), tuple(layout)


def _unpack(table: Array, layout: tuple) -> dict:
    """Table ``(F, ...)`` -> dict of ``(...)`` (scalars) / ``(k, ...)``
    (vectors: components first)."""
    return {name: table[a] if trailing == () else
            table[a:b].reshape(trailing + table.shape[1:])
            for name, a, b, trailing in layout}


def _components_last(x: Array, layout_trailing: tuple) -> Array:
    """Per-particle ``(k..., N)`` -> the caller's ``(N, k...)``."""
    return x if not layout_trailing else jnp.moveaxis(x, -1, 0)


def _masked_sum(t: Array, keep: Array) -> Array:
    """Sum over the candidate axis (-2) of per-pair ``t`` ``(..., K, M)``
    where ``keep`` ``(K, M)``."""
    t = jnp.broadcast_to(t, jnp.broadcast_shapes(t.shape, keep.shape))
    return jnp.sum(jnp.where(keep, t, 0), axis=-2)


def _inner(g: Array, t: Array) -> Array:
    """Per-pair ``<g, t>`` over the leading component axes."""
    return jnp.sum(g * t, axis=tuple(range(t.ndim - 2))) if t.ndim > 2 \
        else g * t


def _norm(d: Array) -> tuple[Array, Array]:
    """`jaxrt.energy.sph._safe_norm` with components first: ``d`` float
    ``(dim, ...)`` -> ``|d|`` ``(...)`` and the unit vector ``(dim, ...)``,
    0 where ``d = 0``, both with finite gradients there."""
    r2 = jnp.sum(d * d, axis=0)
    nonzero = r2 > 0
    r = jnp.sqrt(jnp.where(nonzero, r2, 1))
    unit = jnp.where(nonzero, d / r, 0)
    return jnp.where(nonzero, r, 0), unit


def _min_image_first(d: Array, grid: _Params) -> Array:
    """`jaxrt.energy.fused._min_image` with components first."""
    shape = (len(grid.side),) + (1,) * (d.ndim - 1)
    side = jnp.asarray(grid.side, d.dtype).reshape(shape)
    wrapped = jnp.mod(d + side * 0.5, side) - side * 0.5
    return jnp.where(np.reshape(grid.periodic, shape), wrapped, d)


# ---------------------------------------------------------------------------
# The engine: out_i = sum_{j != i} pair(x_i, x_j, r_ij, theta).



def _unroll() -> int:
    """Slots per loop step of the forward walks (`walk_runs`): on GPUs a
    loop step costs a device sync (the trip count is read back), so four
    slots a step; on the CPU unrolling measured no faster. The backward
    walks, heavier to compile, take one slot a step."""
    return 1 if jax.default_backend() == "cpu" else 4


@dataclasses.dataclass(frozen=True)
class _PairSum:
    """A per-particle pair sum with its VJP, over a backend's traversal.

    ``pair(mine, other, d, theta)``: ``mine`` / ``other`` dicts of the
    per-particle data of the pair's two particles, components first
    (scalars ``(K, M)``-broadcastable, vectors ``(k, K, M)``: M centres, K
    candidates each), ``d`` float ``(dim, K, M)`` the minimum image of
    ``R_mine - R_other``, ``theta`` dict of scalars (broadcastable to
    ``(1, M)``); returns a tuple of per-pair terms ``(..., K, M)``. It must
    vanish, with all its derivatives, beyond the grid's bound (the walk
    meets only pairs within it, and a pair beyond may be met from one side
    only). The data must hold ``"R"``.
    """

    pair: Callable
    grid: _Params
    backend: str
    block: int | None = None

    def cells(self, R: Array):
        """The sorted grid of R (None for brute), shared by the walks of
        one configuration: ``(order, runs)``, runs ``(R, N)``. With
        ``order`` None, the data are already in the sorted order (and the
        sums come back in it)."""
        if self.backend == "brute":
            return None
        order, runs = cell_runs(jax.lax.stop_gradient(R), self.grid)
        return order, type(runs)(*(x.T for x in runs))

    def traverse(self, table: Array, cells, slot: Callable, acc,
                 unroll: int = 1):
        """``acc += slot(mine, other, keep)`` over all candidates.

        ``table``: float ``(F, N)``; ``slot`` gets columns ``(F, 1, M)`` and
        ``(F, K, M)`` (or ``(F, K, 1)``), bool ``keep`` ``(K, M)``, and
        returns a pytree of per-particle ``(..., M)`` terms; ``acc``: the
        pytree of their ``(..., N)`` sums, in the caller's order.
        """
        if cells is None:
            return self._brute(table, slot, acc)
        order, runs = cells
        if order is not None:
            table = table[:, order]
        mine = table[:, None, :]
        # Candidates are gathered as rows of the transposed table (one
        # contiguous slice each, as GPUs like it; on the CPU it measured as
        # fast as gathering strided columns), then turned particles-minor.
        rows = table.T

        def visit(j, keep, acc):
            other = jnp.moveaxis(rows[j], -1, 0)
            return jax.tree_util.tree_map(jnp.add, acc,
                                          slot(mine, other, keep))

        zeros = jax.tree_util.tree_map(jnp.zeros_like, acc)
        out = walk_runs(runs, visit, zeros, transposed=True, unroll=unroll)
        if order is not None:
            out = jax.tree_util.tree_map(
                lambda o: jnp.zeros_like(o).at[..., order].set(o), out)
        return jax.tree_util.tree_map(jnp.add, acc, out)

    def _brute(self, table, slot, acc):
        n = table.shape[1]
        block = self.block or max(1, min(n, 2 ** 17 // max(n, 1)))
        n_blocks = -(-n // block)
        cols = jnp.arange(n)

        def rows(start):
            idx = start + jnp.arange(block)
            valid = idx < n
            safe = jnp.where(valid, idx, 0)
            keep = valid[None, :] & (safe[None, :] != cols[:, None])
            return slot(table[:, safe][:, None, :], table[:, :, None], keep)

        out = jax.lax.map(rows, jnp.arange(n_blocks) * block)
        return jax.tree_util.tree_map(
            lambda a, o: a + jnp.moveaxis(o, 0, -2).reshape(
                o.shape[1:-1] + (n_blocks * block,))[..., :n], acc, out)

    # The sums and their VJP.

    def _forward(self, data, theta, cells):
        table, layout = _pack(data)
        grid = self.grid

        def slot(mine_cols, other_cols, keep):
            mine, other = _unpack(mine_cols, layout), _unpack(other_cols,
                                                              layout)
            d = _min_image_first(mine["R"] - other["R"], grid)
            return tuple(_masked_sum(t, keep)
                         for t in self.pair(mine, other, d, theta))

        n = table.shape[1]
        shapes = jax.eval_shape(lambda: slot(table[:, None, :1],
                                             table[:, :1, None],
                                             jnp.ones((1, 1), bool)))
        acc = tuple(jnp.zeros(s.shape[:-1] + (n,), s.dtype) for s in shapes)
        out = self.traverse(table, cells, slot, acc, unroll=_unroll())
        return tuple(jnp.moveaxis(o, -1, 0) for o in out)

    def _backward(self, data, theta, cells, g):
        table, layout = _pack(data)
        g_table, g_layout = _pack({str(i): t for i, t in enumerate(g)})
        width = table.shape[0]
        both = jnp.concatenate([table, g_table.astype(table.dtype)], axis=0)
        grid, pair = self.grid, self.pair

        def slot(mine_cols, other_cols, keep):
            xm = _unpack(mine_cols[:width], layout)
            xo = _unpack(other_cols[:width], layout)
            gm = _unpack(mine_cols[width:], g_layout)
            go = _unpack(other_cols[width:], g_layout)
            centres = mine_cols.shape[-1]
            th = {k: jnp.broadcast_to(v, (1, centres))
                  for k, v in theta.items()}

            def phi(xm, th):
                # i's own terms (i, j) with i's cotangent, and the mirrored
                # terms (j, i) with j's: every derivative that lands on i,
                # collected by i. theta's: from i's own terms only (the
                # mirrored ones are counted when j is the centre).
                t_ij = pair(xm, xo, _min_image_first(xm["R"] - xo["R"], grid),
                            th)
                t_ji = pair(xo, xm, _min_image_first(xo["R"] - xm["R"], grid),
                            jax.lax.stop_gradient(th))
                total = sum(_inner(gm[str(k)], a) + _inner(go[str(k)], b)
                            for k, (a, b) in enumerate(zip(t_ij, t_ji)))
                total = jnp.broadcast_to(total, keep.shape)
                return jnp.sum(jnp.where(keep, total, 0))

            dx, dth = jax.grad(phi, argnums=(0, 1))(xm, th)
            return ({k: v[..., 0, :] for k, v in dx.items()},
                    {k: v[0] for k, v in dth.items()})

        n = table.shape[1]
        acc = ({name: jnp.zeros(trailing + (n,), table.dtype)
                for name, _, _, trailing in layout},
               {k: jnp.zeros((n,), table.dtype) for k in theta})
        d_data, d_theta = self.traverse(both, cells, slot, acc)
        d_data = {name: _components_last(d_data[name], trailing).astype(
            data[name].dtype) for name, _, _, trailing in layout}
        d_theta = {k: jnp.sum(v).astype(jnp.result_type(theta[k]))
                   for k, v in d_theta.items()}
        return d_data, d_theta

    def make(self) -> Callable:
        """``sums(data, theta, cells) -> tuple of (N, ...)``, with its VJP
        (data: dict of float ``(N, ...)`` in one dtype; theta: dict of
        float scalars; cells: from `cells`, not differentiated)."""

        @jax.custom_vjp
        def sums(data, theta, cells):
            return self._forward(data, theta, cells)

        def forward(data, theta, cells):
            data, theta = _first_order_only((data, theta))
            return self._forward(data, theta, cells), (data, theta, cells)

        def backward(res, g):
            data, theta, cells = res
            d_data, d_theta = self._backward(data, theta, cells, g)
            return d_data, d_theta, None

        sums.defvjp(forward, backward)
        return sums


# ---------------------------------------------------------------------------
# The SPH pair terms: `jaxrt.energy.sph`'s, per ordered pair (i, j), with
# vector components first.


def _density_pair(kernel: _sph.Kernel) -> Callable:
    cls, dim = type(kernel), kernel.dim

    def pair(mine, other, d, theta):
        r, _ = _norm(d)
        return (other["m"] * cls(theta["h"], dim=dim).w(r),)
    return pair


def _acceleration_pair(kernel: _sph.Kernel, epsilon: float) -> Callable:
    cls, dim = type(kernel), kernel.dim

    def pair(mine, other, d, theta):
        hh, a, b = theta["h"], theta["alpha"], theta["beta"]
        r, unit = _norm(d)
        grad_w = cls(hh, dim=dim).grad_w(r) * unit
        # q = P / rho**2 per particle: the list path's per-pair expression,
        # bit for bit, computed once per particle.
        p_pair = (mine["q"] + other["q"]) * grad_w
        vr = jnp.sum((mine["V"] - other["V"]) * d, axis=0)
        mu = hh * vr / (r * r + epsilon * hh * hh)
        c_mean = (mine["c"] + other["c"]) / 2
        rho_mean = (mine["rho"] + other["rho"]) / 2
        pi = jnp.where(vr < 0, (-a * c_mean * mu + b * mu * mu) / rho_mean, 0)
        mj = other["m"]
        return (-mj * p_pair, -mj * (pi * grad_w))
    return pair


# ---------------------------------------------------------------------------
# Factories


def _grid(displacement, box, kernel: _sph.Kernel, periodic, backend):
    """The walk's static geometry (`_Params`, ``dim`` entries) and the
    factory kernel's support, checked."""
    if backend not in BACKENDS:
        raise ValueError(f"backend={backend!r} is not known; choose one of "
                         f"{BACKENDS}.")
    if not isinstance(kernel, _sph.Kernel):
        raise TypeError(f"kernel must be a jaxrt.energy.sph kernel (e.g. "
                        f"sph.kernel('cubic_spline', h, dim=2)); got "
                        f"{type(kernel).__name__}.")
    h = concrete(kernel.h)
    if h is None or h.ndim:
        raise ValueError("kernel.h must be a concrete scalar at construction "
                         "(it sizes the cells); pass a traced h= to the "
                         "returned function instead.")
    _sph._check_displacement(displacement, kernel.dim)
    from jaxrt.rt.periodic import cutoff_fits
    dim = kernel.dim
    cutoff = float(kernel.support * float(h))
    sides = _sides(box, dim)
    axes = _periodicity(displacement, sides, dim, periodic)
    for a, (side, p) in enumerate(zip(sides if sides is not None else
                                      (np.inf,) * dim, axes)):
        if p and not cutoff_fits(cutoff, side):
            raise ValueError(
                f"the kernel's support {cutoff:g} (support x h) must be below "
                f"half the periodic box side {side:g} on axis {a} (each pair "
                "counts through its nearest image only); use a larger box or "
                "a smaller h.")
    p = _static_params(displacement, box, axes, dim, 0.0, cutoff, cutoff)
    grid = _Params(0.0, cutoff, cutoff, p.periodic[:dim], p.side[:dim])
    return grid, float(h)


def _positions(R, kernel: _sph.Kernel) -> Array:
    R = jnp.asarray(R)
    if not jnp.issubdtype(R.dtype, jnp.floating):
        raise ValueError(f"R must be a float array; got dtype {R.dtype}.")
    _sph._check_kernel_dim(kernel, R)
    return R


def _check_h(h, h0: float) -> None:
    v = concrete(h)
    if v is not None and np.any(v > h0):
        raise ValueError(
            f"h={float(v):g} is larger than the factory kernel's h={h0:g}, "
            "which sizes the cells (pairs beyond its support would be "
            "missed); build the function with the largest h you will pass.")


def _column(value, n: int, dtype) -> Array:
    """Scalar or ``(n,)`` -> ``(n,)`` in ``dtype``."""
    return jnp.broadcast_to(jnp.asarray(value, dtype), (n,))


def _poison(outputs, R, h, h0: float):
    """NaN everywhere for non-finite positions or h above the factory's
    (the checks that cannot raise under jit)."""
    bad = ~jnp.all(jnp.isfinite(R)) | jnp.any(h > h0)
    return tuple(jnp.where(bad, jnp.nan, o) for o in outputs)


def _raise_if_bad(result, R) -> None:
    """Outside a trace: a NaN result from non-finite positions raises."""
    if isinstance(result, jax.core.Tracer):
        return
    if not bool(jnp.all(jnp.isfinite(result))) and not bool(
            jnp.all(jnp.isfinite(R))):
        raise FusedInputError("R has NaN or infinite entries: the SPH sums "
                              "are NaN. Find where the simulation blew up "
                              "(time step, pressure).")


def _density_core(engine_sums, engine: _PairSum, kernel, h0: float):
    """``rho(R, h, m, cells)`` in R's dtype, self term included."""

    def rho(R, h, m, cells):
        dtype, n = R.dtype, R.shape[0]
        h = jnp.asarray(h, dtype)
        m = _column(m, n, dtype)
        k = type(kernel)(h, dim=kernel.dim)
        (total,) = engine_sums(dict(R=R, m=m), dict(h=h), cells)
        out = total + m * k.w(jnp.zeros((), dtype))
        return _poison((out,), R, h, h0)[0]
    return rho


def density_fused(displacement: Callable, box, kernel: _sph.Kernel, *,
                  mass: Array = 1.0, backend: str = "cell",
                  periodic=None) -> Callable[..., Array]:
    """Summation density ``rho_i = m_i W(0) + sum_j m_j W(|r_ij|)`` with no
    neighbour list (`jaxrt.energy.sph.density`'s, to rounding).

    Args:
      displacement: jax-md displacement function ``d(Ra, Rb) -> (dim,)``
        (probed, not called on the particles).
      box: None (free space), a scalar or ``(dim,)`` sides (orthorhombic).
      kernel: a `jaxrt.energy.sph` kernel with a concrete ``h``, which
        sizes the cells (its ``dim`` must match the positions).
      mass: float scalar or ``(N,)``.
      backend: ``"cell"`` (list-free walk) or ``"brute"`` (all pairs).
      periodic: bool or one per axis; None infers it from ``displacement``.

    Returns:
      ``density_fn(R, *, h=None, mass=None) -> (N,)``: ``R`` float32 or
      float64 ``(N, dim)``; ``h`` float scalar ``<=`` the kernel's, and
      ``mass`` scalar or ``(N,)``, replace the factory's (may be traced and
      differentiated). The result is in R's dtype; ``jax.grad`` through it
      runs a second walk (first order only).
    """
    grid, h0 = _grid(displacement, box, kernel, periodic, backend)
    engine = _PairSum(_density_pair(kernel), grid, backend)
    core = _density_core(engine.make(), engine, kernel, h0)
    default_mass = mass

    @jax.jit
    def compute(R, h, m):
        return core(R, h, m, engine.cells(R))

    def density_fn(R: Array, *, h: Array | None = None,
                   mass: Array | None = None, **unknown) -> Array:
        reject_unknown("density_fn", unknown, ("h", "mass"))
        R = _positions(R, kernel)
        k = kernel if h is None else dataclasses.replace(kernel, h=h)
        _check_h(k.h, h0)
        m = _sph._per_particle("mass", default_mass if mass is None else mass,
                               R.shape[0])
        rho = compute(R, k.h, m)
        _raise_if_bad(rho, R)
        return rho

    return density_fn


def acceleration_fused(displacement: Callable, box, kernel: _sph.Kernel,
                       eos: _sph.Tait, *, mass: Array = 1.0,
                       alpha: Array = 0.1, beta: Array = 0.0,
                       epsilon: float = 0.01, backend: str = "cell",
                       periodic=None) -> Callable[..., _sph.Acceleration]:
    """Symmetric SPH pressure force and Monaghan's artificial viscosity with
    no neighbour list (`jaxrt.energy.sph.acceleration`'s, to rounding).

    ``dv_i/dt = -sum_j m_j (P_i/rho_i^2 + P_j/rho_j^2 + Pi_ij) grad_i W_ij``;
    see `jaxrt.energy.sph.acceleration` for ``Pi_ij``.

    Args:
      displacement, box, kernel, backend, periodic: as `density_fused`.
      eos: a `jaxrt.energy.sph.Tait` equation of state.
      mass: float scalar or ``(N,)``.
      alpha, beta: float scalars >= 0, viscosity coefficients.
      epsilon: float, keeps ``mu`` finite as ``r -> 0`` (static).

    Returns:
      ``accel_fn(R, V, *, rho=None, pressure=None, h=None, mass=None,
      eos=None, alpha=None, beta=None) -> jaxrt.energy.sph.Acceleration``
      (``pressure``, ``viscosity`` float ``(N, dim)``, ``density`` ``(N,)``,
      all in R's dtype). ``R``, ``V``: float ``(N, dim)``. ``rho``: float
      ``(N,)``; by default the summation density, from the same sorted
      grid as the forces (one sort, two walks). ``pressure``: float
      ``(N,)``; by default ``eos.pressure(rho)``. The other keywords
      replace the factory's values and may be traced and differentiated
      (``h`` at most the kernel's). ``jax.grad`` through any output runs
      second walks (first order only).
    """
    for name, value in (("alpha", alpha), ("beta", beta)):
        v = concrete(value)
        if v is not None and (v.ndim or v < 0):
            raise ValueError(f"{name} must be a scalar >= 0; got {value}.")
    grid, h0 = _grid(displacement, box, kernel, periodic, backend)
    density_engine = _PairSum(_density_pair(kernel), grid, backend)
    rho_core = _density_core(density_engine.make(), density_engine, kernel,
                             h0)
    engine = _PairSum(_acceleration_pair(kernel, float(epsilon)), grid,
                      backend)
    sums = engine.make()
    defaults = dict(mass=mass, eos=eos, alpha=alpha, beta=beta)

    @jax.jit
    def compute(R, V, rho, pressure, h, m, state, a, b):
        dtype, n = R.dtype, R.shape[0]
        h = jnp.asarray(h, dtype)
        m = _column(m, n, dtype)
        V = V.astype(dtype)
        cells = engine.cells(R)
        given = [None if x is None else _column(x, n, dtype)
                 for x in (rho, pressure)]
        if cells is not None:
            # Both walks in the sorted order: the densities feed the second
            # walk without a round trip through the caller's order.
            order, runs = cells
            R, V, m = R[order], V[order], m[order]
            given = [None if x is None else x[order] for x in given]
            cells = (None, runs)
        rho, pressure = given
        if rho is None:
            rho = rho_core(R, h, m, cells)
        if pressure is None:
            pressure = state.pressure(rho)
        c = state.sound_speed(rho).astype(dtype)
        data = dict(R=R, V=V, rho=rho, q=pressure / rho ** 2, c=c, m=m)
        theta = dict(h=h, alpha=jnp.asarray(a, dtype),
                     beta=jnp.asarray(b, dtype))
        acc_p, acc_v = _poison(sums(data, theta, cells), R, h, h0)
        out = _sph.Acceleration(acc_p, acc_v, rho)
        if cells is not None:
            inverse = jnp.zeros((n,), jnp.int32).at[order].set(
                jnp.arange(n, dtype=jnp.int32))
            out = jax.tree_util.tree_map(lambda x: x[inverse], out)
        return out

    def accel_fn(R: Array, V: Array, *, rho: Array | None = None,
                 pressure: Array | None = None, h: Array | None = None,
                 mass: Array | None = None, eos: _sph.Tait | None = None,
                 alpha: Array | None = None, beta: Array | None = None,
                 **unknown) -> _sph.Acceleration:
        reject_unknown("accel_fn", unknown, ("rho", "pressure", "h", "mass",
                                             "eos", "alpha", "beta"))
        R = _positions(R, kernel)
        V = jnp.asarray(V)
        if V.shape != R.shape:
            raise ValueError(f"V has shape {V.shape} but R has {R.shape}; "
                             "pass one velocity per particle.")
        k = kernel if h is None else dataclasses.replace(kernel, h=h)
        _check_h(k.h, h0)
        n = R.shape[0]
        m = _sph._per_particle("mass", defaults["mass"] if mass is None
                               else mass, n)
        if rho is not None:
            _sph._check_density(rho)
            rho = _sph._per_particle("rho", rho, n)
        if pressure is not None:
            pressure = _sph._per_particle("pressure", pressure, n)
        out = compute(R, V, rho, pressure, k.h, m,
                      defaults["eos"] if eos is None else eos,
                      defaults["alpha"] if alpha is None else alpha,
                      defaults["beta"] if beta is None else beta)
        _raise_if_bad(out.pressure, R)
        return out

    return accel_fn
