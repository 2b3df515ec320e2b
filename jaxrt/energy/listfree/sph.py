"""SPH without a neighbour list: summation density, pressure and viscosity
from a walk over the cell grid, differentiable to first order.

`density_fused` and `acceleration_fused` take the arguments of
`jaxrt.energy.sph.density` and `jaxrt.energy.sph.acceleration` plus the box,
and return functions with the same keywords and results, minus the
neighbour list::

    rho = sph.density(disp, kernel, mass=m)(R, nbrs)
    rho = density_fused(disp, box, kernel, mass=m)(R)

    acc = sph.acceleration(disp, kernel, eos, mass=m, alpha=0.1)(R, V, nbrs)
    acc = acceleration_fused(disp, box, kernel, eos, mass=m, alpha=0.1)(R, V)

Backends (``backend=``):

* ``"cell"``: `jaxrt.backends.cell.search`'s sorted grid, recomputed at every call
  (`jaxrt.energy.listfree.lj.cell_runs`): every particle walks the runs of sorted
  particles that hold its stencil cells and sums its own terms. Each pair
  is met from both sides: no scatter, and nothing of size N x k is
  stored. On CUDA the walk is one Pallas kernel
  (`jaxrt.backends.cell.kernel.pair_sums`: a thread per particle, its sums in
  registers), elsewhere array programs (`jaxrt.energy.listfree.lj.walk_runs`:
  one slot of every run per step of a loop as long as the longest run);
  ``jaxrt.backends.Cell(kernel=...)`` picks one, as for
  `jaxrt.energy.lennard_jones_fused`: ``"auto"`` (what ``"cell"`` is:
  the kernel where the program is lowered for CUDA, else the arrays),
  ``"pallas"`` (the kernel; an error off CUDA), ``"xla"`` (the arrays
  everywhere), ``"interpret"`` (the kernel in Pallas' interpreter, for
  tests). The pair terms are one definition for both, so they agree to
  rounding (the kernel works on the grid's wrapped positions, adding each
  run's periodic image once where the box proves it right,
  `jaxrt.energy.listfree.lj.run_image_axes`, and rounding to minimum images
  elsewhere; the arrays take minimum images of the caller's).
  `acceleration_fused` sorts once and walks twice (densities, then
  forces); each VJP walks once more, the same way.
* ``Cell(kernel="warp")``: the Warp engine
  (`jaxrt.energy.listfree.warp_cell`, kernels in
  `jaxrt.backends.cell.warp_sph`; CPU or CUDA): the Lennard-Jones
  engine's bin, radix sort, cell table and gather, then a thread per
  sorted particle for each pass. ``accel_fn`` without ``rho`` /
  ``pressure`` is one call (sort, density walk, self term and Tait per
  particle, force walk); with them, and ``density_fn``, one call sorts
  and one more per walk. Its pair terms are the others' written out
  (the kernels' ``f'`` by hand), so the results agree to rounding. Its
  VJPs are the cell walk's (``"auto"``) on the same positions: a
  gradient recomputes the step there. ``jaxrt.energy.listfree.lj.CellSums(
  kernel="warp", reach=..., graph=...)`` sets its stencil and graph
  capture.
* ``"brute"``: all pairs in row blocks, O(N^2); the reference.

Cost. A walk evaluates, per particle, one candidate of each stencil row (3
in 2D, 9 in 3D) per step of a loop as long as the longest run (2.25 x the
support along x): about 2x (2D) and 5x (3D) the pairs within the support,
each pair from both sides, at every call, where a list path reads rows of
support + skin rebuilt every few steps. On the CPU that makes it slower
than a step on a list; its case is the GPU, where the walk is one kernel
(`benchmarks/sph_step.py`; the numbers are in docs/benchmarks.md).

Derivatives. Each walk is a `jax.custom_vjp` (reverse mode through a loop
of dynamic length is impossible): its backward pass is another walk over
the same cells (array programs or kernel, as the forward) in which every
particle, for each candidate, takes the VJP of the pair term from its own
side *and* of the mirrored term (the pair seen from the other particle,
with that particle's cotangent), so that it collects everything it owes
without a scatter; in the kernel each thread differentiates its own
candidate's terms (`jax.vjp` traced into the kernel). Positions, velocities,
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

One module past 800 lines on purpose: one energy's walks, pair terms
and checks.
"""
from __future__ import annotations

import dataclasses
import functools
import operator
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxrt.energy import sph as _sph
from jaxrt.energy.checks import concrete
from jaxrt.energy.keywords import reject_unknown
from jaxrt.energy.listfree.lj import (CELL_KERNELS, CellSums,
                                      FusedInputError, Params, periodicity,
                                      box_sides, static_params, cell_runs,
                                      first_order_only, walk_runs)

Array = jax.Array

BACKENDS = ("cell", "brute")
# The cell walk's programs (``jaxrt.backends.Cell(kernel=...)``).
WALKS = CELL_KERNELS + ("warp",)
# The Warp engine's stencil reach in cells (along x, across), the
# Lennard-Jones engine's default.
WARP_REACH = tuple(CellSums.reach)
_WARP_DEFAULT = (WARP_REACH, "none")

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
# rows did not vectorise, and was slower).


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


def _min_image_first(d: Array, grid: Params) -> Array:
    """`jaxrt.energy.listfree.lj._min_image` with components first."""
    shape = (len(grid.side),) + (1,) * (d.ndim - 1)
    side = jnp.asarray(grid.side, d.dtype).reshape(shape)
    wrapped = jnp.mod(d + side * 0.5, side) - side * 0.5
    return jnp.where(np.reshape(grid.periodic, shape), wrapped, d)


# Vectors in the pair terms: arrays with the components on a leading axis
# in the array walk (the form XLA fuses best), tuples of components in the
# kernel (one value per thread: Triton's tensors are sized in powers of
# two, so no (3, block) stack). The terms are written once, with these.


def _map(f: Callable, *xs):
    """``f`` component by component over vectors (scalars broadcast)."""
    k = next((len(x) for x in xs if isinstance(x, tuple)), None)
    if k is None:
        return f(*xs)
    return tuple(f(*(x[a] if isinstance(x, tuple) else x for x in xs))
                 for a in range(k))


def _components_sum(v):
    """The sum of a vector's components."""
    return (functools.reduce(operator.add, v) if isinstance(v, tuple)
            else jnp.sum(v, axis=0))


def _inner(g, t):
    """Per-pair ``<g, t>`` (scalars, or vectors over their components)."""
    if isinstance(t, tuple):
        return _components_sum(_map(operator.mul, g, t))
    return jnp.sum(g * t, axis=tuple(range(t.ndim - 2))) if t.ndim > 2 \
        else g * t


def _norm(d):
    """`jaxrt.energy.sph._safe_norm` of a vector ``d`` -> ``|d|`` and the
    unit vector, 0 where ``d = 0``, both with finite gradients there."""
    r2 = _components_sum(_map(lambda x: x * x, d))
    nonzero = r2 > 0
    r = jnp.sqrt(jnp.where(nonzero, r2, 1))
    unit = _map(lambda x: jnp.where(nonzero, x / r, 0), d)
    return jnp.where(nonzero, r, 0), unit


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
    per-particle data of the pair's two particles, ``d`` the minimum image
    of ``R_mine - R_other``, ``theta`` a dict of scalars. In the array
    walk scalars are ``(K, M)``-broadcastable (M centres, K candidates
    each) and vectors ``(k, K, M)`` (components first); in the kernel
    scalars are one value per thread and vectors tuples of components.
    Written with `_map` / `_components_sum` / `_norm`, one definition
    serves both. Returns a tuple of per-pair terms (scalars or vectors),
    elementwise in its inputs. It must vanish, with all its derivatives, beyond
    the grid's bound (the walk meets only pairs within it, and a pair
    beyond may be met from one side only). The data must hold ``"R"``.

    ``walk`` (backend ``"cell"``): ``"xla"``, the array walk
    (`walk_runs`); ``"pallas"``, the kernel
    (`jaxrt.backends.cell.kernel.pair_sums`: a thread per particle, its sums in
    registers, on wrapped positions); ``"auto"``, the kernel where the
    program is lowered for CUDA, else the array walk; ``"interpret"``,
    the kernel in Pallas' interpreter (tests). The forward sums and the
    VJP's second walk both take it.
    """

    pair: Callable
    grid: Params
    backend: str
    walk: str = "xla"
    block: int | None = None
    warp: "_WarpPass | None" = None

    def cells(self, R: Array):
        """The sorted grid of R (None for brute), shared by the walks of
        one configuration: ``(order, runs, images)``, runs ``(R, N)``,
        images the kernel's (`jaxrt.energy.listfree.lj.RunImages`, sorted order).
        With ``order`` None, the data are already in the sorted order (and
        the sums come back in it). The Warp engine's: ``(order, sorted,
        None)``, ``sorted`` a `jaxrt.energy.listfree.warp_cell.Sorted`."""
        if self.backend == "brute":
            return None
        if self.walk == "warp":
            state = self.warp.sort(R)
            return state.order, state, None
        order, runs, images = cell_runs(jax.lax.stop_gradient(R), self.grid)
        return order, type(runs)(*(x.T for x in runs)), images

    def _dispatch(self, cells, portable: Callable, kernel: Callable):
        """``portable()`` or ``kernel(interpret)`` as ``walk`` says (the
        array walk for brute, and where this JAX has no Pallas)."""
        from jaxrt.backends.cell import kernel as _cell_kernel
        if (cells is None or self.walk == "xla"
                or (self.walk == "auto" and _cell_kernel.pl is None)):
            return portable()
        if self.walk == "auto":
            return jax.lax.platform_dependent(cuda=kernel, default=portable)
        return kernel(self.walk == "interpret")

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
        order, runs, _ = cells
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

    def _kernel(self, data, theta, cells, extra, terms, n_sums, interpret):
        """`jaxrt.backends.cell.kernel.pair_sums` over the grid's runs.

        ``data``: as `make`'s; ``extra``: more float ``(N,)`` columns, in
        the caller's order; ``terms(scalars, mine, theirs, d, valid)``:
        the kernel's pair terms, ``mine`` / ``theirs`` the data's
        `_Columns` values (R left out: the kernel gives ``d``) followed by
        the extra columns, ``scalars`` theta's values in its key order,
        ``d`` zero where ``valid`` is false; returns ``n_sums`` float
        terms. Returns float ``(n_sums, N)`` sums, caller's order.
        """
        from jaxrt.backends.cell import kernel as _cell_kernel
        from jaxrt.energy.listfree.lj import kernel_runs
        order, runs, images = cells
        dtype = data["R"].dtype
        columns = _Columns(data)
        values = columns.values(data) + [x.astype(dtype) for x in extra]
        if order is not None:
            values = [v[order] for v in values]
        keys = tuple(theta)
        scalars = jnp.stack([jnp.asarray(theta[k], dtype) for k in keys])

        def pair_terms(d2, valid, scalars, mine, theirs, d):
            # Candidates that are not others (the particle itself, slots
            # past a run) see d = 0, where every term and derivative is
            # finite; their terms are dropped.
            d = tuple(jnp.where(valid, x, 0) for x in d)
            out = terms(scalars, mine, theirs, d, valid)
            return (jnp.zeros_like(d2),
                    tuple(jnp.where(valid, t, 0) for t in out))

        # No tangent may reach the kernel: the custom_vjp differentiates.
        values, scalars = jax.lax.stop_gradient((values, scalars))
        grid = self.grid
        # The positions the grid binned (sorted, wrapped by its own
        # rounding), which the runs' images are right for; not data's R.
        _, sums = _cell_kernel.pair_sums(
            images.position, kernel_runs(type(runs)(*(x.T for x in runs))),
            jnp.asarray(grid.side, dtype), scalars, tuple(values),
            periodic=tuple(grid.periodic), pair_terms=pair_terms,
            n_sums=n_sums, interpret=interpret, **images.kernel_options())
        if order is not None:
            sums = jnp.zeros_like(sums).at[:, order].set(sums)
        return sums

    # The sums and their VJP.

    def _warp_forward(self, data, theta, cells):
        """The Warp engine's pass over its sort (`_WarpPass`)."""
        order, state, _ = cells
        if order is not None:
            data = {k: v[order] for k, v in data.items()}
        out = self.warp(jax.lax.stop_gradient(data),
                        jax.lax.stop_gradient(theta), state)
        if order is not None:
            out = tuple(jnp.zeros_like(o).at[order].set(o) for o in out)
        return out

    def _forward(self, data, theta, cells):
        grid, pair = self.grid, self.pair
        if cells is not None and self.walk == "warp":
            return self._warp_forward(data, theta, cells)

        def portable():
            table, layout = _pack(data)

            def slot(mine_cols, other_cols, keep):
                mine = _unpack(mine_cols, layout)
                other = _unpack(other_cols, layout)
                d = _min_image_first(mine["R"] - other["R"], grid)
                return tuple(_masked_sum(t, keep)
                             for t in pair(mine, other, d, theta))

            n = table.shape[1]
            shapes = jax.eval_shape(lambda: slot(table[:, None, :1],
                                                 table[:, :1, None],
                                                 jnp.ones((1, 1), bool)))
            acc = tuple(jnp.zeros(s.shape[:-1] + (n,), s.dtype)
                        for s in shapes)
            out = self.traverse(table, cells, slot, acc, unroll=_unroll())
            return tuple(jnp.moveaxis(o, -1, 0) for o in out)

        def kernel(interpret=False):
            columns = _Columns(data)
            keys = tuple(theta)
            treedef = jax.tree_util.tree_structure(jax.eval_shape(
                lambda: self.pair(*columns.dummy(data), theta)))

            def terms(scalars, mine, theirs, d, valid):
                th = dict(zip(keys, scalars))
                out = pair(columns.rebuild(mine), columns.rebuild(theirs), d,
                           th)
                return jax.tree_util.tree_leaves(out)

            sums = self._kernel(data, theta, cells, (), terms,
                                treedef.num_leaves, interpret)
            out = treedef.unflatten(list(sums))
            return tuple(jnp.stack(t, axis=-1) if isinstance(t, tuple) else t
                         for t in out)

        return self._dispatch(cells, portable, kernel)

    def _backward(self, data, theta, cells, g):
        grid, pair = self.grid, self.pair
        if cells is not None and self.walk == "warp":
            # The Warp walks compute values only: the VJP is the cell
            # walk's ("auto": the Pallas kernel on CUDA, arrays elsewhere)
            # on jaxrt's grid of the same positions, in the data's order.
            other = dataclasses.replace(self, walk="auto", warp=None)
            return other._backward(data, theta, other.cells(data["R"]), g)

        def portable():
            table, layout = _pack(data)
            g_table, g_layout = _pack({str(i): t for i, t in enumerate(g)})
            width = table.shape[0]
            both = jnp.concatenate([table, g_table.astype(table.dtype)],
                                   axis=0)

            def slot(mine_cols, other_cols, keep):
                xm = _unpack(mine_cols[:width], layout)
                xo = _unpack(other_cols[:width], layout)
                gm = _unpack(mine_cols[width:], g_layout)
                go = _unpack(other_cols[width:], g_layout)
                centres = mine_cols.shape[-1]
                th = {k: jnp.broadcast_to(v, (1, centres))
                      for k, v in theta.items()}

                def phi(xm, th):
                    d = _min_image_first(xm["R"] - xo["R"], grid)
                    total = _mirrored(pair, xm, xo, d, th, gm, go)
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
            return ({name: _components_last(d_data[name], trailing)
                     for name, _, _, trailing in layout}, d_theta)

        def kernel(interpret=False):
            columns = _Columns(data)
            gs = {str(i): t for i, t in enumerate(g)}
            g_columns = _Columns(gs, skip=())
            width, keys = columns.width, tuple(theta)

            def terms(scalars, mine, theirs, d, valid):
                xm, xo = (columns.rebuild(x[:width]) for x in (mine, theirs))
                gm, go = (g_columns.rebuild(x[width:]) for x in (mine,
                                                                 theirs))
                # theta per thread: each gets its own derivative.
                th = {k: jnp.broadcast_to(s, valid.shape)
                      for k, s in zip(keys, scalars)}

                def phi(xm, d, th):
                    return _mirrored(pair, xm, xo, d, th, gm, go)

                total, vjp = jax.vjp(phi, xm, d, th)
                dx, dd, dth = vjp(jnp.ones_like(total))
                # d = R_i - R_j: its derivative is R_i's.
                return (columns.values(dx) + list(dd)
                        + [dth[k] for k in keys])

            n_sums = columns.width + len(grid.side) + len(keys)
            sums = self._kernel(data, theta, cells, g_columns.values(gs),
                                terms, n_sums, interpret)
            dx = columns.rebuild(list(sums[:columns.width]))
            dim = len(grid.side)
            dx["R"] = tuple(sums[columns.width:columns.width + dim])
            d_data = {name: (jnp.stack(dx[name], axis=-1)
                             if isinstance(dx[name], tuple) else dx[name])
                      for name in data}
            d_theta = dict(zip(keys, sums[columns.width + dim:]))
            return d_data, d_theta

        d_data, d_theta = self._dispatch(cells, portable, kernel)
        d_data = {name: d_data[name].astype(data[name].dtype)
                  for name in data}
        d_theta = {k: jnp.sum(v).astype(jnp.result_type(theta[k]))
                   for k, v in d_theta.items()}
        return d_data, d_theta

    def make(self) -> Callable:
        """``sums(data, theta, cells) -> tuple of (N, ...)``, with its VJP
        (data: dict of float ``(N,)`` / ``(N, k)`` in one dtype; theta:
        dict of float scalars; cells: from `cells`, not differentiated)."""

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


def _mirrored(pair, xm, xo, d, th, gm, go):
    """What the VJP's walk differentiates, per pair: i's own terms (i, j)
    with i's cotangent, and the mirrored terms (j, i) with j's, so that
    every derivative that lands on i is collected by i. theta's: from i's
    own terms only (the mirrored ones are counted when j is the centre).
    ``d``: the minimum image of ``R_i - R_j``, by components."""
    t_ij = pair(xm, xo, d, th)
    t_ji = pair(xo, xm, _map(operator.neg, d), jax.lax.stop_gradient(th))
    return sum(_inner(gm[str(k)], a) + _inner(go[str(k)], b)
               for k, (a, b) in enumerate(zip(t_ij, t_ji)))


class _Columns:
    """A data dict as ``(N,)`` columns, vectors by component (the kernel
    takes per-particle values as flat arrays), and back.

    ``skip``: names left out (``"R"``: the kernel gives ``d`` instead).
    """

    def __init__(self, data: dict, skip=("R",)):
        self.spec = tuple((name, None if v.ndim == 1 else v.shape[1])
                          for name, v in data.items() if name not in skip)
        self.width = sum(1 if k is None else k for _, k in self.spec)

    def values(self, data: dict) -> list:
        """float ``(N,)`` columns of ``(N,)`` / ``(N, k)`` data, or the
        flat values of a `rebuild` dict, in the columns' order."""
        out = []
        for name, k in self.spec:
            v = data[name]
            out.extend([v] if k is None else list(v) if isinstance(v, tuple)
                       else [v[:, a] for a in range(k)])
        return out

    def rebuild(self, values) -> dict:
        """Columns (or any per-column values) -> dict of values and
        component tuples."""
        out, at = {}, 0
        for name, k in self.spec:
            out[name] = (values[at] if k is None
                         else tuple(values[at:at + k]))
            at += 1 if k is None else k
        return out

    def dummy(self, data: dict):
        """``(mine, other, d)`` scalars shaped as a thread's, for tracing
        the pair's output structure."""
        dtype = data["R"].dtype
        x = self.rebuild([jnp.zeros((), dtype)] * self.width)
        d = tuple(jnp.zeros((), dtype) for _ in range(data["R"].shape[1]))
        return x, x, d


# ---------------------------------------------------------------------------
# The Warp engine's passes (``Cell(kernel="warp")``).


@dataclasses.dataclass(frozen=True)
class _WarpPass:
    """One pass of `jaxrt.energy.listfree.warp_cell`'s SPH walks over its
    sort: ``which`` ``"density"`` (`_density_pair`'s sums) or ``"forces"``
    (`_acceleration_pair`'s), the kernel by name, the grid padded to 3
    axes (`Params.dim` the caller's), the stencil's ``reach``."""

    which: str
    kind: str
    params: Params
    reach: tuple
    support: float
    epsilon: float = 0.0

    @classmethod
    def make(cls, which: str, kernel: _sph.Kernel, grid: Params,
             reach: tuple, epsilon: float = 0.0) -> "_WarpPass":
        from jaxrt.backends.cell import warp_sph
        kind = {c: n for n, c in _sph.KERNELS.items()}.get(type(kernel))
        if kind not in warp_sph.KINDS:
            raise ValueError(
                f"backend=Cell(kernel='warp') has no {type(kernel).__name__}"
                f" kernel; use one of jaxrt.energy.sph.KERNELS "
                f"({warp_sph.KINDS}), or Cell(kernel='auto').")
        dim = len(grid.side)
        params = Params(grid.r_onset, grid.r_cutoff, grid.bound,
                        tuple(grid.periodic) + (False,) * (3 - dim),
                        tuple(grid.side) + (1.0,) * (3 - dim), dim)
        return cls(which, kind, params, tuple(reach), float(kernel.support),
                   float(epsilon))

    def sort(self, R: Array):
        from jaxrt.energy.listfree import warp_cell
        return warp_cell.sort(_pad3(R), self.params, self.reach)

    def constants(self, theta: dict, dtype, dim: int,
                  eos: _sph.Tait | None = None) -> Array:
        """`jaxrt.backends.cell.warp_sph`'s params ``(N_PARAMS,)`` in
        ``dtype``: theta's ``h`` (``alpha``, ``beta``: 0 if absent) and,
        for a whole step, the self term and ``eos``' constants."""
        from jaxrt.backends.cell import warp_sph
        h = jnp.asarray(theta["h"], dtype)
        values = [0] * warp_sph.N_PARAMS
        values[warp_sph.H] = h
        # `jaxrt.energy.sph.Kernel.w`'s expressions, evaluated once.
        values[warp_sph.SUPPORT] = self.support * h
        values[warp_sph.NORM_W] = _sph.KERNELS[self.kind](
            1.0, dim=dim).normalisation / h ** dim
        values[warp_sph.ALPHA] = theta.get("alpha", 0)
        values[warp_sph.BETA] = theta.get("beta", 0)
        values[warp_sph.EPSILON] = self.epsilon
        if eos is not None:
            values[warp_sph.W0] = _sph.KERNELS[self.kind](h, dim=dim).w(
                jnp.zeros((), dtype))
            values[warp_sph.RHO0] = eos.rho0
            values[warp_sph.C0] = eos.c0
            values[warp_sph.GAMMA] = eos.gamma
            # `jaxrt.energy.sph.Tait.pressure`'s B.
            values[warp_sph.B] = eos.rho0 * eos.c0 ** 2 / eos.gamma
        return jnp.stack([jnp.asarray(v, dtype) for v in values])

    def __call__(self, data: dict, theta: dict, state) -> tuple:
        """The pass's sums, sorted order (``data`` sorted as ``state``)."""
        from jaxrt.energy.listfree import warp_cell
        R = data["R"]
        dtype, dim = R.dtype, R.shape[1]
        constants = self.constants(theta, dtype, dim)
        if self.which == "density":
            return (warp_cell.sph_density(state, self.params, self.reach,
                                          self.kind, constants, data["m"]),)
        pressure, viscosity = warp_cell.sph_forces(
            state, self.params, self.reach, self.kind, constants,
            _pad3(data["V"]), data["m"], data["rho"], data["q"], data["c"])
        return pressure[:, :dim], viscosity[:, :dim]


def _warp_step(warp: _WarpPass, reference: Callable, h0: float,
               graph: str) -> Callable:
    """``step(R, V, h, m, eos, alpha, beta) -> Acceleration``: a whole
    step's sums in one Warp call (`jaxrt.energy.listfree.warp_cell.sph_step`:
    the sort, densities, Tait, forces), in R's dtype, ``m`` ``(N,)``. Its
    VJP is ``reference``'s (the same step on the cell walk, recomputed:
    the Warp kernels compute values only)."""
    from jaxrt.energy.listfree import warp_cell

    def values(R, V, h, m, eos, a, b):
        dtype, dim = R.dtype, R.shape[1]
        constants = warp.constants(dict(h=h, alpha=a, beta=b), dtype, dim,
                                   eos)
        pressure, viscosity, rho = warp_cell.sph_step(
            _pad3(R), _pad3(V.astype(dtype)), m, warp.params, warp.reach,
            warp.kind, constants, graph)
        out = _poison((pressure[:, :dim], viscosity[:, :dim], rho), R,
                      jnp.asarray(h, dtype), h0)
        return _sph.Acceleration(*out)

    @jax.custom_vjp
    def step(R, V, h, m, eos, a, b):
        return values(R, V, h, m, eos, a, b)

    def forward(*args):
        args = _first_order_only(args)
        return values(*args), args

    def backward(args, g):
        def plain(R, V, h, m, eos, a, b):
            return reference(R, V, None, None, h, m, eos, a, b)
        return jax.vjp(plain, *args)[1](g)

    step.defvjp(forward, backward)
    return step


def _pad3(x: Array) -> Array:
    """``(N, dim)`` -> ``(N, 3)``, zeros on the padding axes."""
    return jnp.pad(x, ((0, 0), (0, 3 - x.shape[1])))


# ---------------------------------------------------------------------------
# The SPH pair terms: `jaxrt.energy.sph`'s, per ordered pair (i, j); vectors
# through `_map` (one definition for the array walk and the kernel).


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
        dw = cls(hh, dim=dim).grad_w(r)
        grad_w = _map(lambda u: dw * u, unit)
        # q = P / rho**2 per particle: the list path's per-pair expression,
        # bit for bit, computed once per particle.
        q = mine["q"] + other["q"]
        vr = _components_sum(_map(lambda vi, vj, x: (vi - vj) * x,
                                  mine["V"], other["V"], d))
        mu = hh * vr / (r * r + epsilon * hh * hh)
        c_mean = (mine["c"] + other["c"]) / 2
        rho_mean = (mine["rho"] + other["rho"]) / 2
        pi = jnp.where(vr < 0, (-a * c_mean * mu + b * mu * mu) / rho_mean, 0)
        mj = other["m"]
        return (_map(lambda gw: -mj * (q * gw), grad_w),
                _map(lambda gw: -mj * (pi * gw), grad_w))
    return pair


# ---------------------------------------------------------------------------
# Factories


def _traversal(backend) -> tuple[str, str, tuple]:
    """``backend=`` -> ``(name, walk, (reach, graph))`` of `_PairSum` (the
    Warp engine's stencil reach and graph capture, `_WarpPass`), as
    `jaxrt.energy.listfree.lj._backend` parses the LJ energy's: ``"cell"`` is
    ``Cell(kernel="auto")``; a `jaxrt.backends.Cell` picks the walk (its
    own checks reject an unknown ``kernel``; `jaxrt.energy.listfree.lj.CellSums`'s,
    a kernel this JAX or device cannot run)."""
    from jaxrt.backends.cell import search as cell_list
    if isinstance(backend, cell_list.Cell):
        if backend.radius_classes is not None:
            raise ValueError(
                f"backend=Cell(radius_classes={backend.radius_classes!r}): "
                "the SPH walks use one grid of the kernel's support; leave "
                "radius_classes at None.")
        return "cell", CellSums(kernel=backend.kernel).kernel, _WARP_DEFAULT
    if isinstance(backend, CellSums) and backend.kernel == "warp":
        # The Warp engine's stencil and graph capture (benchmarks tune them).
        return "cell", "warp", (tuple(backend.reach), backend.graph)
    if isinstance(backend, str) and backend in BACKENDS:
        return backend, "auto" if backend == "cell" else "xla", _WARP_DEFAULT
    raise ValueError(f"backend={backend!r} is not known; choose one of "
                     f"{BACKENDS}, or jaxrt.backends.Cell(kernel=...) with "
                     f"kernel one of {WALKS} (the cell walk's "
                     "program: 'xla' array programs, 'pallas' the CUDA "
                     "kernel, 'auto' the kernel on CUDA and the arrays "
                     "elsewhere, 'interpret' the kernel in Pallas' "
                     "interpreter, 'warp' the Warp engine).")


def _grid(displacement, box, kernel: _sph.Kernel, periodic):
    """The walk's static geometry (`Params`, ``dim`` entries) and the
    factory kernel's support, checked."""
    if not isinstance(kernel, _sph.Kernel):
        raise TypeError(f"kernel must be a jaxrt.energy.sph kernel (e.g. "
                        f"sph.kernel('cubic_spline', h, dim=2)); got "
                        f"{type(kernel).__name__}.")
    h = concrete(kernel.h)
    if h is None or h.ndim:
        raise ValueError("kernel.h must be a concrete scalar at construction "
                         "(it sizes the cells); pass a traced h= to the "
                         "returned function instead.")
    _sph.check_displacement(displacement, kernel.dim)
    from jaxrt.backends.rt.halfbox import cutoff_fits
    dim = kernel.dim
    cutoff = float(kernel.support * float(h))
    sides = box_sides(box, dim)
    axes = periodicity(displacement, sides, dim, periodic)
    for a, (side, p) in enumerate(zip(sides if sides is not None else
                                      (np.inf,) * dim, axes)):
        if p and not cutoff_fits(cutoff, side):
            raise ValueError(
                f"the kernel's support {cutoff:g} (support x h) must be below "
                f"half the periodic box side {side:g} on axis {a} (each pair "
                "counts through its nearest image only); use a larger box or "
                "a smaller h.")
    p = static_params(displacement, box, axes, dim, 0.0, cutoff, cutoff)
    grid = Params(0.0, cutoff, cutoff, p.periodic[:dim], p.side[:dim])
    return grid, float(h)


def _positions(R, kernel: _sph.Kernel) -> Array:
    R = jnp.asarray(R)
    if not jnp.issubdtype(R.dtype, jnp.floating):
        raise ValueError(f"R must be a float array; got dtype {R.dtype}.")
    _sph.check_kernel_dim(kernel, R)
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
                  mass: Array = 1.0, backend="cell",
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
      backend: ``"cell"`` (list-free walk), ``"brute"`` (all pairs), or
        ``jaxrt.backends.Cell(kernel=...)``: the cell walk as the CUDA
        kernel (``"pallas"``), as array programs (``"xla"``), the kernel
        on CUDA and the arrays elsewhere (``"auto"``, what ``"cell"``
        is), the kernel in Pallas' interpreter (``"interpret"``,
        tests), or the Warp engine (``"warp"``, module docstring). All
        agree to rounding.
      periodic: bool or one per axis; None infers it from ``displacement``.

    Returns:
      ``density_fn(R, *, h=None, mass=None) -> (N,)``: ``R`` float32 or
      float64 ``(N, dim)``; ``h`` float scalar ``<=`` the kernel's, and
      ``mass`` scalar or ``(N,)``, replace the factory's (may be traced and
      differentiated). The result is in R's dtype; ``jax.grad`` through it
      runs a second walk (first order only).
    """
    name, walk, (reach, _) = _traversal(backend)
    grid, h0 = _grid(displacement, box, kernel, periodic)
    warp = (_WarpPass.make("density", kernel, grid, reach)
            if walk == "warp" else None)
    engine = _PairSum(_density_pair(kernel), grid, name, walk, warp=warp)
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
        m = _sph.per_particle("mass", default_mass if mass is None else mass,
                               R.shape[0])
        rho = compute(R, k.h, m)
        _raise_if_bad(rho, R)
        return rho

    return density_fn


def _cell_step(engine: _PairSum, rho_core: Callable, h0: float) -> Callable:
    """``step(R, V, rho, pressure, h, m, eos, alpha, beta) ->
    Acceleration`` on ``engine``'s walks (``rho`` / ``pressure`` None:
    the summation densities by ``rho_core``, Tait's pressures): one sort,
    both walks in its order."""
    sums = engine.make()

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
            order, runs, images = cells
            R, V, m = R[order], V[order], m[order]
            given = [None if x is None else x[order] for x in given]
            cells = (None, runs, images)
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
    return compute


def acceleration_fused(displacement: Callable, box, kernel: _sph.Kernel,
                       eos: _sph.Tait, *, mass: Array = 1.0,
                       alpha: Array = 0.1, beta: Array = 0.0,
                       epsilon: float = 0.01, backend="cell",
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
    name, walk, (reach, graph) = _traversal(backend)
    grid, h0 = _grid(displacement, box, kernel, periodic)
    warps = ((_WarpPass.make("density", kernel, grid, reach),
              _WarpPass.make("forces", kernel, grid, reach, float(epsilon)))
             if walk == "warp" else (None, None))
    density_engine = _PairSum(_density_pair(kernel), grid, name, walk,
                              warp=warps[0])
    rho_core = _density_core(density_engine.make(), density_engine, kernel,
                             h0)
    engine = _PairSum(_acceleration_pair(kernel, float(epsilon)), grid,
                      name, walk, warp=warps[1])
    defaults = dict(mass=mass, eos=eos, alpha=alpha, beta=beta)
    cell_step = _cell_step(engine, rho_core, h0)
    whole_step = None
    if walk == "warp":
        # Densities, Tait and forces in one Warp call where the densities
        # and pressures are the step's own; the cell walk ("auto") gives
        # its VJP.
        plain = dataclasses.replace(density_engine, walk="auto", warp=None)
        whole_step = _warp_step(warps[1], _cell_step(
            dataclasses.replace(engine, walk="auto", warp=None),
            _density_core(plain.make(), plain, kernel, h0), h0), h0, graph)

    @jax.jit
    def compute(R, V, rho, pressure, h, m, state, a, b):
        if whole_step is not None and rho is None and pressure is None:
            dtype, n = R.dtype, R.shape[0]
            return whole_step(R, V, jnp.asarray(h, dtype), _column(m, n, dtype),
                              state, jnp.asarray(a, dtype),
                              jnp.asarray(b, dtype))
        return cell_step(R, V, rho, pressure, h, m, state, a, b)

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
        m = _sph.per_particle("mass", defaults["mass"] if mass is None
                               else mass, n)
        if rho is not None:
            _sph.check_density(rho)
            rho = _sph.per_particle("rho", rho, n)
        if pressure is not None:
            pressure = _sph.per_particle("pressure", pressure, n)
        out = compute(R, V, rho, pressure, k.h, m,
                      defaults["eos"] if eos is None else eos,
                      defaults["alpha"] if alpha is None else alpha,
                      defaults["beta"] if beta is None else beta)
        _raise_if_bad(out.pressure, R)
        return out

    return accel_fn
