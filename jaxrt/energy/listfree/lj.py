"""Lennard-Jones without a neighbour list: energy, forces and parameter
derivatives from one traversal (seed 003 §3.2, ORCS), differentiable to
first order.

`lennard_jones_fused` returns ``energy_fn(R, **params)`` with the energy of
`jax_md.energy.lennard_jones_neighbor_list` (and of jaxrt's
`jaxrt.energy.lennard_jones_neighbor_list`, ``truncation="smooth"``) for
the same arguments, but no list in between: the backend visits every pair
once and returns the sums at once (`FusedSums`). ``jax.grad(energy_fn)``
is ``-F`` from that same visit (a `jax.custom_vjp` whose residuals are the
forces and the parameter derivatives), and ``sigma`` / ``epsilon`` given as
keyword arguments get their gradients the same way, so a training loop can
fit them on energies.

Backends (``backend=``), one protocol (`_Backend.sums`):

* ``"bvh"`` (or a `jaxrt.backends.rt.ffi.Bvh` of options): ORCS-forces on a BVH
  kept per call site and refit or rebuilt by its policy, as the list
  backend does (`jaxrt.backends.rt.orcs`, `jaxrt.backends.rt.ffi.orcs_forces`).
* ``"brute"``: all pairs in pure JAX, in row blocks; the CPU reference and
  the template of the others.
* ``"cell"`` (or a `jaxrt.backends.Cell` of options): jaxrt's sorted cell
  grid (`jaxrt.backends.cell.search`): every particle walks the runs of sorted
  particles that hold its stencil cells and sums its own terms; each pair
  is met from both sides (no scatter), and nothing of size N x k is
  stored. On CUDA one Pallas kernel (`jaxrt.backends.cell.kernel.pair_sums`, a
  thread per particle), elsewhere array programs (`walk_runs`, one slot
  of every run per step of a loop as long as the longest run); ``Cell(
  kernel=...)`` picks one (`CellSums`).

`lennard_jones_perse_step` is ORCS-persé: one leapfrog step ``(R, V) ->
(R', V')`` in a single kernel (``backend="bvh"``), equal radii only.

Conventions, and where they differ from jax-md on purpose:

* As in jax-md's ``lennard_jones_neighbor_list``, ``r_onset`` and
  ``r_cutoff`` are multiples of the factory's ``sigma`` (jax-md multiplies
  them by ``max(sigma)`` at construction, and so does jaxrt's list path);
  a ``sigma=`` given later to the energy function does not move them.
  With ``radii`` (seed 003 §3), pair ``ij`` is cut at ``max(r_i, r_j)``
  and its potential is stretched by ``max(r_i, r_j) / r_cutoff``
  (`jaxrt.energy.lennard_jones_radii`), the list path's rule.
* Everything is in the positions' dtype: Python-float ``sigma`` and
  ``epsilon`` are not downcast to float32 (jax-md's are), and their
  gradients are finite (jax-md's, through padded pairs, are NaN).
* ``sigma`` and ``epsilon`` are scalars here (per-particle or per-species
  values: use the list path). ``radii`` are constants for differentiation
  (their gradient is zero, by ``stop_gradient``).
* Only first derivatives: a second derivative (``jax.hessian``, a gradient
  of forces) raises `HigherOrderError`, and forward mode (``jax.jvp``,
  ``jax.jacfwd``) is refused by JAX. Use
  `jaxrt.energy.lennard_jones_neighbor_list` on a list for those.
* Bad arguments raise at construction, naming the argument. A non-finite
  position or a radius outside ``[0, max(factory radii)]`` makes the energy
  NaN; outside any trace the energy function then raises `FusedInputError`
  naming the cause (`jaxrt.errors` bits).
* Boxes: free space, or orthorhombic boxes with any axes periodic, Cartesian
  coordinates, in 2D or 3D. The cutoff (the largest radius) must stay below
  half of every periodic side.

Past 800 lines: the cell walks shared with `jaxrt.energy.listfree.sph`
(`cell_runs`, `walk_runs`, `Params`) could become a module of their own.
"""
from __future__ import annotations

import dataclasses
import enum
import functools
import sys
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxrt.energy.checks import concrete
from jaxrt.energy.keywords import SIMULATE_KEYWORDS, reject_unknown
from jaxrt.errors import Bits, Error, raise_for

Array = jax.Array

BACKENDS = ("bvh", "brute", "cell")


class FusedSums(NamedTuple):
    """What a backend returns for one configuration, in R's dtype.

    Attributes:
      energy: float scalar, the total energy.
      forces: float ``(N, 3)`` from a backend (zero-padded positions),
        ``(N, dim)`` from ``energy_fn.sums``: ``-dE/dR``.
      d_sigma, d_epsilon: float scalars, ``dE/dsigma`` and ``dE/depsilon``.
      count: float scalar, unordered interacting pairs.
      error: int32 scalar, `InputBit` bits (0: fine).
    """

    energy: Array
    forces: Array
    d_sigma: Array
    d_epsilon: Array
    count: Array
    error: Array


@dataclasses.dataclass(frozen=True)
class Params:
    """Static potential parameters, absolute (already times sigma).

    Attributes:
      r_onset, r_cutoff: the reference potential's switch (radii stretch it).
      bound: the largest pair cut: ``r_cutoff``, or the largest radius.
      periodic: 3 bools; side: 3 floats (1 on free axes).
      dim: the caller's dimension where the backends get positions
        zero-padded to 3 (`_make_energy`): the axes past it are padding,
        all positions equal there (one cell of the grid, `cell_runs`);
        None: every axis is the caller's.
    """

    r_onset: float
    r_cutoff: float
    bound: float
    periodic: tuple
    side: tuple
    dim: int | None = None


class HigherOrderError(Error, TypeError):
    """A second derivative was asked of a fused energy."""


class FusedInputError(Error, ValueError):
    """A fused energy was given non-finite positions or radii out of range."""


_HIGHER_ORDER = (
    "lennard_jones_fused energies are differentiable once (jax.grad gives -F "
    "and the sigma / epsilon gradients from the same traversal); second "
    "derivatives (jax.hessian, gradients of forces, forward mode over "
    "jax.grad) are not available. Use jaxrt.energy.lennard_jones_neighbor_list "
    "on a neighbour list (jaxrt.neighbor_list) for Hessians and force "
    "matching.")


def first_order_only(message: str) -> Callable:
    """An identity whose derivative raises `HigherOrderError(message)`: it
    guards what only a second derivative differentiates (the inputs of a
    forward pass whose VJP is custom, or that VJP's residuals)."""
    @jax.custom_jvp
    def identity(x):
        return x

    @identity.defjvp
    def raise_higher_order(primals, tangents):
        raise HigherOrderError(message)
    return identity


_first_order_only = first_order_only(_HIGHER_ORDER)


# ---------------------------------------------------------------------------
# The pair terms, in JAX (the kernels' twin: `jaxrt.backends.rt.orcs.lj_terms`).


def lj_terms(d2, sigma, epsilon, r_onset, r_cutoff, sigma_base):
    """jax-md's smoothly switched LJ at squared distances ``d2``.

    Args:
      d2: float, any shape; sigma, r_onset, r_cutoff: the pair's values,
        broadcastable; epsilon, sigma_base: the caller's scalars.
    Returns:
      ``(e, g, de_dsigma, de_depsilon)``, shape of ``d2``: energy, force
      factor (``F_i = g (x_i - x_j)``, the true ``-dU/dr / r``; seed 003's
      Eq. 4 drops a factor 2) and derivatives in ``sigma_base`` and
      ``epsilon``. Zero where ``d2 == 0`` or beyond ``r_cutoff``.
    """
    # Squared distances throughout: no square root, one reciprocal (the
    # kernels' issue rate, not memory, bounds them). jax-md takes sqrt(d2)
    # first; the switch is C1 at both ends, so comparing d2 with r_onset^2
    # rather than dr with r_onset moves nothing but rounding.
    positive = d2 > 0
    d2 = jnp.where(positive, d2, 1)
    inverse = 1 / d2
    idr = sigma * sigma * inverse
    idr6 = idr * idr * idr
    idr12 = idr6 * idr6
    lj_unit = 4 * (idr12 - idr6)
    lj = epsilon * lj_unit
    repulsion = 24 * (2 * idr12 - idr6)
    rc2, ro2 = r_cutoff * r_cutoff, r_onset * r_onset
    width = rc2 - ro2
    inverse_cube = 1 / (width * width * width)
    before, inside = d2 < ro2, d2 < rc2
    gap = rc2 - d2
    switch = jnp.where(before, 1, jnp.where(
        inside, gap * gap * (rc2 + 2 * d2 - 3 * ro2) * inverse_cube, 0))
    dswitch = jnp.where(before | ~inside, 0,
                        -6 * gap * (d2 - ro2) * inverse_cube)
    e = switch * lj
    g = switch * epsilon * repulsion * inverse - 2 * dswitch * lj
    ds = switch * epsilon * repulsion / sigma_base
    de = switch * lj_unit
    return tuple(jnp.where(positive, t, 0) for t in (e, g, ds, de))


def _total(x):
    """Sum in float64 where x64 is on (as jax-md's ``high_precision_sum``),
    without its float32-mode warning; in ``x``'s dtype."""
    wide = jax.dtypes.canonicalize_dtype(jnp.float64)
    return jnp.sum(x, dtype=wide).astype(x.dtype)


# ---------------------------------------------------------------------------
# Backends: sums(R3, sigma, epsilon, radii, params) -> FusedSums.


class _Backend:
    """A fused backend: all the pair sums of one configuration.

    ``sums(R3, sigma, epsilon, radii, params)`` with R3 float ``(N, 3)``
    (zero-padded Cartesian positions), sigma and epsilon float scalars in
    R3's dtype, radii float ``(N,)`` or None, ``params`` the static
    `Params`; returns `FusedSums`. ``derivatives=False`` says that
    nothing differentiates in sigma or epsilon: a backend may then leave
    ``d_sigma`` and ``d_epsilon`` at zero and skip their terms;
    ``count=False``, that nobody reads the pair count (the energy's path):
    a backend may then leave it at zero. ``perse``
    (optional) is one fused leapfrog step; backends without one get the
    leapfrog from ``sums``.
    """

    name: str

    def sums(self, R3, sigma, epsilon, radii, params: Params, *,
             derivatives: bool = True, count: bool = True) -> FusedSums:
        raise NotImplementedError

    def perse(self, R3, V3, sigma, epsilon, dt, mass, params: Params):
        """(R', V', energy): a leapfrog step from the forces of `sums`."""
        s = self.sums(R3, sigma, epsilon, None, params)
        V = V3 + (dt / mass) * s.forces
        return _wrap(R3 + dt * V, params), V, s.energy


def _wrap(R3, params: Params):
    """Positions wrapped into the box on periodic axes."""
    side = jnp.asarray(params.side, R3.dtype)
    wrapped = R3 - side * jnp.floor(R3 / side)
    wrapped = jnp.where(wrapped < 0, wrapped + side, wrapped)
    wrapped = jnp.where(wrapped >= side, 0, wrapped)
    return jnp.where(jnp.asarray(params.periodic), wrapped, R3)


def _min_image(d, params: Params):
    """jax-md's ``periodic_displacement`` on periodic axes."""
    side = jnp.asarray(params.side, d.dtype)
    wrapped = jnp.mod(d + side * 0.5, side) - side * 0.5
    return jnp.where(jnp.asarray(params.periodic), wrapped, d)


@dataclasses.dataclass(frozen=True)
class _Brute(_Backend):
    """Every pair, in blocks of ``block`` rows (pure JAX, O(N^2))."""

    block: int | None = None
    name: str = "brute"

    def sums(self, R3, sigma, epsilon, radii, params: Params, *,
             derivatives: bool = True, count: bool = True) -> FusedSums:
        n = R3.shape[0]
        block = self.block or max(1, min(n, 2 ** 21 // max(n, 1)))
        n_blocks = -(-n // block)
        cols = jnp.arange(n)
        rc = jnp.asarray(params.r_cutoff, R3.dtype)

        def rows(start):
            idx = start + jnp.arange(block)
            valid = idx < n
            safe = jnp.where(valid, idx, 0)
            d = _min_image(R3[safe][:, None, :] - R3[None, :, :], params)
            d2 = jnp.sum(d * d, axis=-1)
            cut = (rc if radii is None
                   else jnp.maximum(radii[safe][:, None], radii[None, :]))
            keep = valid[:, None] & (safe[:, None] != cols) & (d2 < cut * cut)
            scale = cut / rc
            e, g, ds, de = lj_terms(jnp.where(keep, d2, 0), sigma * scale,
                                    epsilon, params.r_onset * scale,
                                    rc * scale, sigma)
            forces = jnp.sum(g[..., None] * d, axis=1)
            half = [jnp.sum(t, axis=1) / 2 for t in (e, ds, de)]
            return (forces, *half, jnp.sum(keep, axis=1) / 2)

        out = jax.lax.map(rows, jnp.arange(n_blocks) * block)
        forces, e, ds, de, c = (o.reshape((n_blocks * block,) + o.shape[2:])[:n]
                                for o in out)
        return FusedSums(_total(e), forces,
                         jnp.sum(ds), jnp.sum(de), jnp.sum(c.astype(R3.dtype)),
                         jnp.zeros((), jnp.int32))


CELL_KERNELS = ("auto", "pallas", "xla", "interpret")
# The LJ sums' kernels (the SPH walks' too): the cell walks and the Warp
# engine.
LJ_CELL_KERNELS = CELL_KERNELS + ("warp",)


@dataclasses.dataclass(frozen=True)
class CellSums(_Backend):
    """List-free sums over jaxrt's sorted cell grid (module docstring).

    The grid and its runs are `jaxrt.backends.cell.search`'s (cells ``cutoff / 4``
    wide along x and ``cutoff`` across, coarsened for sparse clouds; small
    periodic boxes alias no cell twice), recomputed at every call, so no
    size is static: each particle walks its runs to their ends.

    ``kernel`` (`jaxrt.backends.Cell`'s option) picks the walk: ``"xla"``,
    array programs (one slot of every particle's runs per step of a loop
    as long as the longest run; pairs decided on the caller's unwrapped
    positions with `_min_image`, the arithmetic of ``backend="brute"``);
    ``"pallas"``, one GPU kernel (`jaxrt.backends.cell.kernel.pair_sums`: a thread
    per particle, its sums in registers, on the grid's wrapped positions;
    on the axes of `run_image_axes` each run's periodic image is added
    once, elsewhere every candidate's difference is rounded to its
    minimum image);
    ``"auto"``, the kernel on CUDA and the array programs elsewhere
    (chosen where the program is lowered); ``"interpret"``, the kernel in
    Pallas' interpreter (tests); ``"warp"``, the Warp engine
    (`jaxrt.energy.listfree.warp_cell`: bin, radix sort, cell table and a
    thread per particle in one JAX call, on CPU or CUDA). They agree to rounding: the switch makes
    every term continuous at the cut, so a pair decided differently by one
    ulp at the cutoff changes nothing.
    """

    kernel: str = "auto"
    name: str = "cell"
    # The kernel's launch (`jaxrt.backends.cell.kernel.pair_sums`): particles and
    # warps per program, and the cluster layout's tile (0: a thread per
    # particle). benchmarks/roofline.py measures the choices.
    # ``unroll`` candidates per step of the thread walk (independent loads
    # in flight), and ``across`` cells per cutoff across x (`cell_runs`).
    # ``runs``: "kernel", the kernel finds each particle's runs from the
    # cell-start table; "stored", it reads the runs computed for every
    # particle beforehand (a pass over N x 2R ints through memory).
    # The same runs and sums either way; "stored" is kept for comparison.
    block: int = 32
    warps: int = 1
    tile: int = 0
    unroll: int = 1
    across: int = 1
    runs: str = "kernel"
    # ``newton``: the thread walk meets each pair once (the upper half of
    # the stencil) and adds the partner's force with an atomic, where no
    # stencil cell across repeats (`run_image_axes`); elsewhere, and in the
    # array walk, every pair is met from both sides as without it. The
    # same sums to rounding (the atomics' order varies). Off by default:
    # on the GPUs measured the atomics cost more than the evaluations they
    # save (docs/benchmarks-notes.md, the list-free step).
    newton: bool = False
    # ``kernel="warp"``: who captures its launches in a CUDA graph
    # (`jaxrt.backends.rt.ffi.cell_lj_sums`: "none", "jax", "warp"), and
    # its stencil's reach in cells along x and across (cells ``bound /
    # reach`` wide; (4, 2) measured fastest on an H200, results/h200/
    # md_step_warp_*).
    graph: str = "none"
    reach: tuple = (4, 2)
    # ``kernel="warp"``: "thread", a thread per particle walks its stencil;
    # "cluster", a thread per cluster of up to ``cluster_size`` particles
    # of one cell walks their common stencil once
    # (`jaxrt.backends.cell.warp_cluster`). The same sums. "native": on
    # CUDA a warp per cluster sharing the candidates by shuffles (the same
    # sums to rounding), elsewhere "cluster".
    walk: str = "thread"
    cluster_size: int = 8

    def __post_init__(self):
        from jaxrt.backends.cell import kernel as _cell_kernel
        if self.kernel not in LJ_CELL_KERNELS:
            raise ValueError(f"backend=Cell(kernel={self.kernel!r}): choose "
                             f"one of {LJ_CELL_KERNELS}.")
        if self.kernel in ("pallas", "interpret") and _cell_kernel.pl is None:
            raise ValueError(f"backend=Cell(kernel={self.kernel!r}): this JAX "
                             "has no Pallas Triton backend; use "
                             "Cell(kernel='xla').")
        if self.newton and self.tile:
            raise ValueError(f"Cell(newton=True, tile={self.tile}): newton "
                             "needs the thread walk (tile=0).")
        if self.walk not in ("thread", "cluster", "native"):
            raise ValueError(f"Cell(walk={self.walk!r}): choose 'thread', "
                             "'cluster' or 'native'.")
        if self.walk != "thread" and self.kernel != "warp":
            raise ValueError(f"Cell(walk={self.walk!r}) is the Warp engine's "
                             f"option; kernel={self.kernel!r} takes "
                             "walk='thread' (or use kernel='warp').")
        if self.cluster_size not in (1, 2, 4, 8, 16):
            raise ValueError(f"Cell(cluster_size={self.cluster_size!r}): "
                             "choose 1, 2, 4, 8 or 16.")
        if self.runs not in ("kernel", "stored"):
            raise ValueError(f"Cell(runs={self.runs!r}): choose 'kernel' or "
                             "'stored'.")
        if self.kernel == "pallas" and jax.default_backend() not in ("gpu",
                                                                     "cuda"):
            raise ValueError(
                "backend=Cell(kernel='pallas') needs a CUDA GPU, and JAX's "
                f"default backend is {jax.default_backend()!r}; use "
                "Cell(kernel='auto') (the kernel where it can run) or 'xla'.")

    def sums(self, R3, sigma, epsilon, radii, params: Params, *,
             derivatives: bool = True, count: bool = True) -> FusedSums:
        from jaxrt.backends.cell import kernel as _cell_kernel
        dtype = R3.dtype
        if self.kernel == "warp":
            from jaxrt.energy.listfree import warp_cell
            forces, e, ds, de, c = warp_cell.walk(
                R3, sigma, epsilon, radii, params, derivatives=derivatives,
                count=count, graph=self.graph, reach=self.reach,
                walk=self.walk, cluster_size=self.cluster_size)
            return FusedSums(_total(e) / 2, forces, jnp.sum(ds) / 2,
                             jnp.sum(de) / 2, jnp.sum(c) / 2,
                             jnp.zeros((), jnp.int32))
        order, runs, images = cell_runs(R3, params, across=self.across)

        def portable():
            return self._walk(R3[order], runs, sigma, epsilon,
                              None if radii is None else radii[order], params,
                              derivatives)

        def kernel(interpret=False):
            return self._kernel_walk(
                images, kernel_runs(runs), jnp.asarray(params.side, dtype),
                sigma, epsilon, radii, order, params, interpret, derivatives,
                count, run_source=self.runs, newton=self.newton,
                block=self.block, warps=self.warps,
                tile=self.tile, unroll=self.unroll)

        if self.kernel == "xla" or (self.kernel == "auto"
                                    and _cell_kernel.pl is None):
            forces, e, ds, de, c = portable()
        elif self.kernel == "auto":
            forces, e, ds, de, c = jax.lax.platform_dependent(
                cuda=kernel, default=portable)
        else:
            forces, e, ds, de, c = kernel(self.kernel == "interpret")
        # Each pair was met from both of its particles.
        return FusedSums(_total(e) / 2,
                         jnp.zeros_like(R3).at[order].set(forces),
                         jnp.sum(ds) / 2, jnp.sum(de) / 2,
                         jnp.sum(c).astype(dtype) / 2,
                         jnp.zeros((), jnp.int32))

    @staticmethod
    def _walk(Ri, runs, sigma, epsilon, cut_i, params: Params,
              derivatives: bool = True):
        """The array-program walk (`walk_runs`): per-particle sums, sorted
        order."""
        n, dtype = Ri.shape[0], Ri.dtype
        rc = jnp.asarray(params.r_cutoff, dtype)

        def visit(j, keep, acc):
            forces, e, ds, de, c = acc
            d = _min_image(Ri[:, None, :] - Ri[j], params)
            d2 = jnp.sum(d * d, axis=-1)
            cut = (rc if cut_i is None
                   else jnp.maximum(cut_i[:, None], cut_i[j]))
            keep = keep & (d2 < cut * cut)
            scale = cut / rc
            te, g, tds, tde = lj_terms(jnp.where(keep, d2, 0),
                                       sigma * scale, epsilon,
                                       params.r_onset * scale, rc * scale,
                                       sigma)
            if derivatives:
                ds = ds + jnp.sum(tds, axis=1)
                de = de + jnp.sum(tde, axis=1)
            return (forces + jnp.sum(g[..., None] * d, axis=1),
                    e + jnp.sum(te, axis=1), ds, de,
                    c + jnp.sum(keep, axis=1, dtype=jnp.int32))

        zeros = jnp.zeros((n,), dtype)
        acc = (jnp.zeros_like(Ri), zeros, zeros, zeros,
               jnp.zeros((n,), jnp.int32))
        forces, e, ds, de, c = walk_runs(runs, visit, acc)
        return forces, e, ds, de, c.astype(dtype)

    @staticmethod
    def _kernel_walk(images: RunImages, runs, side, sigma, epsilon, radii,
                     order, params: Params, interpret: bool,
                     derivatives: bool = True, count: bool = True,
                     run_source: str = "kernel", newton: bool = False,
                     **launch):
        """`jaxrt.backends.cell.kernel.pair_sums` with the LJ terms on the grid's
        own wrapped positions and run images (`cell_runs`): per-particle
        sums, sorted order (``d_sigma`` and ``d_epsilon`` zero unless
        ``derivatives``, the count zero unless ``count``: each sum the
        kernel skips is instructions per candidate saved). ``launch``: its
        launch options (``block``, ``warps``, ``tile``;
        benchmarks/roofline.py tunes them)."""
        from jaxrt.backends.cell import kernel as _cell_kernel
        sorted_cart = images.position
        dtype = sorted_cart.dtype
        r_cutoff, r_onset = params.r_cutoff, params.r_onset
        has_radii = radii is not None

        def terms(d2, valid, scalars, mine, theirs, d):
            sigma, epsilon = scalars[0], scalars[1]
            if has_radii:
                cut = jnp.maximum(mine[0], theirs[0])
                scale = cut / r_cutoff
            else:
                cut, scale = r_cutoff, 1.0
            keep = valid & (d2 < cut * cut)
            e, g, ds, de = lj_terms(jnp.where(keep, d2, 0), sigma * scale,
                                    epsilon, r_onset * scale,
                                    r_cutoff * scale, sigma)
            terms = (e, ds, de) if derivatives else (e,)
            return g, terms + ((keep.astype(d2.dtype),) if count else ())

        # No tangent may reach the kernel: the custom_vjp differentiates.
        sorted_cart, side, sigma, epsilon = jax.lax.stop_gradient(
            (sorted_cart, side, sigma, epsilon))
        # Newton's third law where no stencil cell across repeats.
        newton = newton and all(a or not p for a, p in zip(
            images.axes[1:], params.periodic[1:]))
        forces, sums = _cell_kernel.pair_sums(
            sorted_cart, runs, side, jnp.stack([sigma, epsilon]).astype(dtype),
            () if not has_radii else (radii[order],),
            periodic=params.periodic, pair_terms=terms,
            n_sums=(3 if derivatives else 1) + count, interpret=interpret,
            newton=newton, **images.kernel_options(run_source), **launch)
        if newton:  # each pair's terms once: as the both-sided sums, twice
            sums = 2 * sums
        zero = jnp.zeros_like(sums[0])
        e, ds, de = tuple(sums[:3]) if derivatives else (sums[0], zero, zero)
        return forces, e, ds, de, sums[-1] if count else zero


class Runs(NamedTuple):
    """Each particle's candidates in the cell-sorted order, one column per
    stencil row (`cell_runs`); int32 ``(N, R)`` each, rows in sorted order.

    Slot ``s`` of row ``r`` is sorted particle ``start[r] + s`` for
    ``s < split[r]``, else ``wrapped[r] + s`` (the part of a periodic x row
    that wraps around, shifted so that it continues the first), for
    ``s < length[r]``.
    """

    start: Array
    split: Array
    wrapped: Array
    length: Array


@functools.partial(jax.tree_util.register_dataclass,
                   data_fields=("position", "first", "wrapped", "cell_starts",
                                "cell", "cells"),
                   meta_fields=("axes", "reach"))
@dataclasses.dataclass(frozen=True)
class RunImages:
    """What the kernel walk needs of the grid besides the runs (`cell_runs`):
    the positions the cells were computed from, and the periodic image of
    every run.

    Attributes:
      position: float ``(N, dim)``, sorted order: the positions wrapped
        into ``[0, side]`` on periodic axes exactly as the grid binned them
        (`jaxrt.backends.cell.grid.grid`'s ``mod``; a particle a hair below 0 may
        stand at ``side`` in its top cell). A run's image is only right for
        these: a position wrapped by another rounding could sit a box away
        from its cell.
      first, wrapped: int32 ``(N, R)``, sorted order: image codes of each
        run's first and wrapped parts (`jaxrt.backends.cell.grid.run_images`);
        None where no axis uses them.
      axes: static ``dim`` bools: the axes on which the codes are every
        pair's minimum image, for any positions (`run_image_axes`); the
        walk rounds candidates' differences on the other periodic axes.
      cell_starts, cell, cells: the grid itself (`jaxrt.backends.cell.kernel.
        CellGrid`: cell-start table, sorted cell coordinates, cells per
        axis), from which the kernel can find every run and its image.
      reach: static ``(along x, across)``, the stencil's reach in cells.
    """

    position: Array
    first: Array
    wrapped: Array
    axes: tuple
    cell_starts: Array | None = None
    cell: Array | None = None
    cells: Array | None = None
    reach: tuple = ()

    def kernel_options(self, runs: str = "kernel") -> dict:
        """`jaxrt.backends.cell.kernel.pair_sums`' ``images``, ``image_axes`` and
        ``grid``: with ``runs="kernel"``, the grid (the kernel finds the
        runs), else the stored runs' images."""
        from jaxrt.backends.cell import kernel as _cell_kernel
        if runs == "kernel" and self.cell_starts is not None:
            return dict(images=None, image_axes=self.axes,
                        grid=_cell_kernel.CellGrid(
                            self.cell_starts, self.cell, self.cells,
                            self.reach))
        return dict(images=None if self.first is None
                    else (self.first, self.wrapped), image_axes=self.axes)


def grid_query(params: Params):
    """The `jaxrt.backends.cell.search` query of the fused grid (cutoff: the bound)."""
    from jaxrt.backends.contract import Query
    from jax_md.partition import NeighborListFormat
    return Query(cutoff=params.bound, periodic=tuple(params.periodic),
                 mask_self=True, format=NeighborListFormat.Dense)


def _flat_axes(params: Params) -> tuple[bool, ...]:
    """The padding axes (`Params.dim`)."""
    dim = len(params.side) if params.dim is None else params.dim
    return tuple(a >= dim for a in range(len(params.side)))


def run_image_axes(params: Params, n: int, *, across: int = 1
                   ) -> tuple[bool, ...]:
    """Static: the axes on which the kernel walk over `cell_runs`' grid of
    ``n`` particles adds each run's periodic image once instead of rounding
    every candidate's difference (`jaxrt.backends.cell.grid.image_axes`): periodic
    axes with enough cells that no stencil cell repeats (3 across, 10
    along x, with ``across=1``) for any positions. Where any free axis is
    not padding (`Params.dim`) the grid's coarsening depends on the
    positions: none.

    Returns:
      ``len(params.side)`` bools.
    """
    from jaxrt.backends.cell import grid
    return grid.image_axes(n, params.side, grid_query(params),
                           (grid.REACH[0], across), _flat_axes(params))


def cell_runs(R: Array, params: Params, *, across: int = 1
              ) -> tuple[Array, Runs, RunImages]:
    """The sorted cell grid of `jaxrt.backends.cell.search` (cells ``bound / 4`` along
    x and ``bound / across`` across), recomputed from ``R``: every pair
    closer than ``params.bound`` is in both particles' runs. ``across``:
    finer cells across make ``(2 across + 1)^(dim - 1)`` shorter runs with
    fewer candidates in all.

    Args:
      R: float ``(N, dim)``, Cartesian, unwrapped; ``params.periodic`` and
        ``params.side`` have ``dim`` entries. Padding axes (`Params.dim`)
        are taken as zero.
    Returns:
      int32 ``(N,)`` ``order`` (sorted position -> caller's index), the
      `Runs`, ``(N, R)``, and the `RunImages` (wrapped positions and run
      images, for the kernel walk). Not differentiable; pass R through
      ``stop_gradient`` when it is traced for a derivative.
    """
    from jaxrt.backends.cell import grid
    from jaxrt.backends.contract import Geometry
    dim = R.shape[1]
    flat = _flat_axes(params)
    if any(flat):  # one cell there, whatever the caller padded with
        R = jnp.where(jnp.asarray(flat), 0, R)
    geometry = Geometry(side=jnp.asarray(params.side, R.dtype),
                        scale=jnp.ones((dim,), R.dtype))
    query = grid_query(params)
    # The search's sorted system (`jaxrt.backends.cell.search`), with a
    # faster sort.
    reach = (grid.REACH[0], across)
    # Where the box fixes the grid (periodic, no coarsening), the grid needs
    # no coarsening loop and the cell-start table only as many entries as
    # there are cells (md_step at 10^6: 3.2e5, not the 4e6 of the budget).
    table = grid.static_cells(R.shape[0], params.side, query, reach, flat)
    wrapped, cell, cells = grid.grid(geometry.grid_coordinates(R),
                                     geometry, query, reach,
                                     coarsen=table is None)
    key = grid.key(cell, cells)
    order, sorted_key = sort_by_key(
        key, table or grid.table_size(R.shape[0]))
    cell = cell[order]
    cell_starts = grid.cell_starts(sorted_key, table)
    start1, len1, start2, len2 = grid.runs(
        sorted_key, cell, cells, query, reach, table, cell_starts=cell_starts)
    axes = run_image_axes(params, R.shape[0], across=across)
    # The codes only where some axis uses them (the kernel reads nothing else).
    first = second = None
    if any(axes):
        first, second = grid.run_images(cell, cells, query, reach)
    # Under jit, whichever of the runs and the grid the walk does not read
    # is never computed.
    images = RunImages(wrapped[order], first, second, axes, cell_starts,
                       cell, cells, reach)
    # The wrapped part continues the first in one loop: particles near the
    # x ends have long wrapped parts, so a loop (or a column) of their own
    # would cost as much as the first for every particle.
    return order, Runs(start1, len1, start2 - len1, len1 + len2), images


def kernel_runs(runs: Runs) -> tuple[Array, Array, Array, Array]:
    """`Runs` in the layout of `jaxrt.backends.cell.kernel` (``grid.runs``'s):
    ``(start1, len1, start2, len2)``, the wrapped parts as runs of their
    own."""
    return (runs.start, runs.split, runs.wrapped + runs.split,
            runs.length - runs.split)


def sort_by_key(key: Array, table: int) -> tuple[Array, Array]:
    """(order, sorted key) of int32 keys in ``[0, table)``, ties in any
    order.

    Key and index packed into one unsigned word when they fit (32 bits, or
    64 with x64 on): XLA's CPU sort of one integer operand is several
    times faster than its sort of two operands by a comparator. Otherwise
    the two-operand sort.
    """
    n = key.shape[0]
    index_bits = max(1, (n - 1).bit_length())
    key_bits = max(1, (table - 1).bit_length())
    wide = jax.dtypes.canonicalize_dtype(jnp.uint64)
    word = (jnp.uint32 if index_bits + key_bits <= 32 else
            wide if index_bits + key_bits <= 64 and np.dtype(wide) == np.uint64
            else None)
    if word is None:
        sorted_key, order = jax.lax.sort(
            (key, jnp.arange(n, dtype=jnp.int32)), num_keys=1,
            is_stable=False)
        return order, sorted_key
    packed = jnp.sort((key.astype(word) << index_bits)
                      | jnp.arange(n, dtype=word))
    order = (packed & ((1 << index_bits) - 1)).astype(jnp.int32)
    return order, (packed >> index_bits).astype(jnp.int32)


def walk_runs(runs: Runs, visit: Callable, acc, *, transposed: bool = False,
              unroll: int = 1):
    """``acc = visit(j, keep, acc)`` for every slot of the runs, one slot of
    every run per step of a loop as long as the longest run.

    ``j``: int32, the runs' shape, sorted index of each row's candidate
    (the particle's own index where the run is over); ``keep``: bool, same
    shape, a real candidate that is not the particle itself. Each unordered
    pair within the grid's bound is met from both of its particles;
    ``visit`` adds per-particle terms (no scatter). ``transposed``: the
    runs are ``(R, N)`` (particles on the minor axis, which the CPU
    vectorises), not ``(N, R)``. ``unroll``: slots per loop step (fewer
    steps: each costs a device sync on GPUs; the slots past a run's end are
    masked). The trip count is dynamic, so the loop cannot be
    reverse-differentiated: callers give their own VJP.
    """
    n = runs.start.shape[-1 if transposed else 0]
    me = jnp.arange(n, dtype=jnp.int32)
    me = me[None, :] if transposed else me[:, None]

    def one(slot, acc):
        inside = slot < runs.length
        j = jnp.where(slot < runs.split, runs.start, runs.wrapped) + slot
        j = jnp.where(inside, j, me)
        return visit(j, inside & (j != me), acc)

    def body(step, acc):
        for u in range(unroll):
            acc = one(step * unroll + u, acc)
        return acc

    longest = jnp.max(runs.length, initial=0)
    return jax.lax.fori_loop(0, (longest + unroll - 1) // unroll, body, acc)


class _Bvh(_Backend):
    """ORCS on a kept BVH (`jaxrt.backends.rt.ffi.orcs_forces`, `orcs_perse`); each
    energy function owns its trees (`jaxrt.backends.rt.ffi.TreeOwner`)."""

    name = "bvh"

    def __init__(self, options):
        from jaxrt.backends.rt import ffi
        if options.cluster_size != 1:
            raise ValueError(f"backend=Bvh(cluster_size={options.cluster_size})"
                             ": ORCS casts one box per particle; use "
                             "cluster_size=1.")
        ffi.load_orcs()
        self._ffi = ffi
        self.owner = ffi.TreeOwner(options)

    def _params(self, dtype, sigma, epsilon, params: Params, dt=0.0, mass=1.0):
        from jaxrt.backends.rt import orcs
        values = [None] * orcs.N_PARAMS
        values[orcs.SIGMA], values[orcs.EPSILON] = sigma, epsilon
        values[orcs.R_ONSET], values[orcs.R_CUTOFF] = params.r_onset, params.r_cutoff
        values[orcs.RADIUS_BOUND] = params.bound
        values[orcs.DT], values[orcs.MASS] = dt, mass
        return jnp.stack([jnp.asarray(v, dtype) for v in values])

    def sums(self, R3, sigma, epsilon, radii, params: Params, *,
             derivatives: bool = True, count: bool = True) -> FusedSums:
        dtype = R3.dtype
        reach = jnp.zeros((1,), dtype) if radii is None else radii
        side = jnp.asarray(params.side, dtype)[None, :]
        forces, e, ds, de, c, err = self._ffi.orcs_forces(
            self.owner, R3, side, reach, self._params(dtype, sigma, epsilon, params),
            cutoff=params.bound, periodic=params.periodic,
            has_radii=radii is not None)
        return FusedSums(_total(e), forces,
                         jnp.sum(ds), jnp.sum(de), jnp.sum(c.astype(dtype)),
                         err[..., 0])

    def perse(self, R3, V3, sigma, epsilon, dt, mass, params: Params):
        dtype = R3.dtype
        side = jnp.asarray(params.side, dtype)[None, :]
        x, v, e, _, _ = self._ffi.orcs_perse(
            self.owner, R3, V3.astype(dtype), side,
            self._params(dtype, sigma, epsilon, params, dt, mass),
            cutoff=params.bound, periodic=params.periodic)
        return x, v, _total(e)


def _backend(backend) -> _Backend:
    from jaxrt.backends.cell.search import Cell
    if isinstance(backend, CellSums):  # launch options (tests, benchmarks)
        return backend
    # A Bvh value was made by its module: Warp is loaded only if it was.
    ffi = sys.modules.get("jaxrt.backends.rt.ffi")
    if ffi is not None and isinstance(backend, ffi.Bvh):
        return _Bvh(backend)
    if backend == "bvh":
        from jaxrt.backends.rt import ffi
        return _Bvh(ffi.Bvh())
    if backend == "brute":
        return _Brute()
    if backend == "cell":
        return CellSums()
    if isinstance(backend, Cell):
        if backend.radius_classes is not None:
            raise ValueError(
                f"backend=Cell(radius_classes={backend.radius_classes!r}): "
                "the fused sums walk one grid of the largest radius; leave "
                "radius_classes at None.")
        return CellSums(kernel=backend.kernel)
    raise ValueError(f"backend={backend!r} is not known; choose one of "
                     f"{BACKENDS}, or pass options: jaxrt.backends.Bvh(...) "
                     "or jaxrt.backends.Cell(kernel=...).")


# ---------------------------------------------------------------------------
# Geometry: the box and its periodic axes, from the caller's displacement.


def box_sides(box, dim: int):
    """float64 ``(dim,)`` box sides, or None for free space."""
    if box is None:
        return None
    b = np.asarray(box, np.float64)
    if b.ndim == 2:
        if b.shape != (dim, dim) or np.any(b - np.diag(np.diag(b))):
            raise ValueError("box: lennard_jones_fused takes orthorhombic "
                             "boxes only (a scalar, (dim,) sides or a diagonal "
                             "matrix); use the list path for triclinic boxes.")
        b = np.diag(b)
    b = np.broadcast_to(b, (dim,)) if b.ndim == 0 else b
    if b.shape != (dim,) or not np.all(np.isfinite(b) & (b > 0)):
        raise ValueError(f"box must be finite and > 0, a scalar or ({dim},) "
                         f"sides for {dim}D positions; got {box!r}.")
    return b


def periodicity(displacement, sides, dim: int, periodic) -> tuple:
    """Per-axis periodic flags: given, or inferred by probing
    ``displacement`` as `jaxrt.neighbor_list` does."""
    from jaxrt.lists import metric as _space
    from jaxrt.lists import neighbors
    from jaxrt.backends.contract import MetricSq
    if periodic is not None:
        axes = neighbors.normalise_periodic(periodic, dim)
        if any(axes) and sides is None:
            raise ValueError("periodic axes need box: pass box=L or "
                             "box=(Lx, Ly[, Lz]).")
        return axes
    grid = neighbors.grid_space(sides, dim, False, None)
    metric = MetricSq(neighbors.metric_sq_fn(displacement, dim), {})
    with jax.ensure_compile_time_eval():
        g = np.asarray(_space.gram(metric, grid, jnp.float32))
    free, periodic = neighbors.probe_axes(metric, grid, g)
    axes = neighbors.infer_periodic(free, periodic, sides is not None)
    if axes is None:
        raise neighbors.undetermined_error(free, periodic, sides is not None)
    return axes


def _check_displacement(displacement, params: Params, dim: int) -> None:
    """The displacement must agree with the box and axes the kernels use
    (they compute distances themselves): checked on random pairs."""
    rng = np.random.default_rng(0)
    side = np.asarray(params.side[:dim])
    a, b = (rng.random((16, dim)) * side for _ in range(2))
    with jax.ensure_compile_time_eval():
        d = np.stack([np.asarray(displacement(jnp.asarray(x, jnp.float32),
                                              jnp.asarray(y, jnp.float32)))
                      for x, y in zip(a, b)])
    ours = a - b
    per = np.asarray(params.periodic[:dim])
    ours = np.where(per, ours - side * np.round(ours / side), ours)
    if d.shape != ours.shape or not np.allclose(np.abs(d), np.abs(ours),
                                                atol=1e-4 * side.max()):
        raise ValueError(
            "displacement disagrees with box and periodic (the fused kernels "
            "compute minimum-image displacements in an orthorhombic box "
            f"with sides {tuple(side)} and periodic={tuple(per)}); pass the "
            "box of the displacement function, or periodic= explicitly.")


def static_params(displacement, box, periodic, dim: int, r_onset: float,
                   r_cutoff: float, bound: float) -> Params:
    """The `Params` of ``dim``-D positions, geometry checked."""
    from jaxrt.backends.rt.halfbox import check_cutoff
    if dim not in (2, 3):
        raise ValueError(f"R must be (N, 2) or (N, 3); got dim {dim}.")
    sides = box_sides(box, dim)
    axes = periodicity(displacement, sides, dim, periodic)
    side = tuple(sides) if sides is not None else (1.0,) * dim
    params = Params(r_onset, r_cutoff, bound,
                     tuple(axes) + (False,) * (3 - dim),
                     tuple(float(s) for s in side) + (1.0,) * (3 - dim), dim)
    check_cutoff(bound, params.side, params.periodic)
    _check_displacement(displacement, params, dim)
    return params


def _check_potential(sigma, epsilon, r_onset, r_cutoff):
    """The factory's scalars, checked: (sigma, r_onset, r_cutoff) floats."""
    sigma0 = _scalar("sigma", sigma, positive=True)
    _scalar("epsilon", epsilon, positive=False)
    r_on, r_c = (_scalar(n, v, positive=False) for n, v in
                 (("r_onset", r_onset), ("r_cutoff", r_cutoff)))
    if not 0 <= r_on < r_c:
        raise ValueError(f"r_onset={r_onset} must satisfy 0 <= r_onset < "
                         f"r_cutoff={r_cutoff}.")
    return sigma0, r_on, r_c


# ---------------------------------------------------------------------------
# The energy function.


def _scalar(name: str, value, positive: bool) -> float:
    v = concrete(value)
    if v is None:
        raise ValueError(f"{name} must be concrete (not traced) at "
                         "construction; pass traced values to the energy "
                         "function instead.")
    if v.ndim:
        raise ValueError(
            f"{name} has shape {v.shape}: lennard_jones_fused takes a scalar "
            f"{name}. For per-particle or per-species {name}, use "
            "jaxrt.energy.lennard_jones_neighbor_list on a list.")
    ok = np.isfinite(v) and (v > 0 if positive else v >= 0)
    if not ok:
        raise ValueError(f"{name} must be finite and {'> 0' if positive else '>= 0'}"
                         f"; got {value}.")
    return float(v)


def _check_radii(radii):
    r = concrete(radii)
    if r is None:
        raise ValueError("radii must be concrete at construction: the largest "
                         "sets the boxes and the gamma rays' reach.")
    if r.ndim != 1 or not np.all(np.isfinite(r) & (r >= 0)):
        raise ValueError(f"radii must be a finite, >= 0, float (N,) array; "
                         f"got shape {r.shape}.")
    return float(np.max(r, initial=0.0))


@enum.unique
class InputBit(Bits):
    """Bits of a list-free energy's input check, int32 (the ORCS kernels
    set the same values: `jaxrt.backends.rt.orcs`' ``ERROR_*``)."""
    NONFINITE_POSITION = 1 << 4
    BAD_RADII = 1 << 7


def _input_errors(R, radii, bound: float) -> Array:
    """`InputBit` bits of the inputs (traceable)."""
    bad_r = ~jnp.all(jnp.isfinite(R))
    error = jnp.where(bad_r, int(InputBit.NONFINITE_POSITION), 0)
    if radii is not None:
        ok = jnp.all((radii >= 0) & (radii <= bound))
        error = error | jnp.where(ok, 0, int(InputBit.BAD_RADII))
    return error.astype(jnp.int32)


def _raise_for(error, bound: float) -> None:
    raise_for(int(error), {
        InputBit.NONFINITE_POSITION:
            "R has NaN or infinite entries: the energy is NaN. Find where "
            "the simulation blew up (time step, overlapping particles).",
        InputBit.BAD_RADII:
            f"radii must be finite and in [0, {bound:g}] (the factory's "
            "largest radius sets the search); pass smaller radii or build "
            "the energy with them."}, FusedInputError, "", sep=" ")


def _make_energy(backend: _Backend, params: Params, dim: int) -> Callable:
    """``energy(R, sigma, epsilon, radii)`` with its custom VJP."""

    def padded(R):
        return jnp.pad(R, ((0, 0), (0, 3 - dim)))

    def run(R, sigma, epsilon, radii, derivatives=True):
        s = backend.sums(padded(R), sigma, epsilon, radii, params,
                         derivatives=derivatives, count=False)
        error = s.error | _input_errors(R, radii, params.bound)
        nan = jnp.asarray(jnp.nan, R.dtype)
        poison = error != 0
        return (jnp.where(poison, nan, s.energy),
                (jnp.where(poison, nan, s.forces[:, :dim]),
                 jnp.where(poison, nan, s.d_sigma),
                 jnp.where(poison, nan, s.d_epsilon)))

    @jax.custom_vjp
    def energy(R, sigma, epsilon, radii):
        return run(R, sigma, epsilon, radii)[0]

    def forward(R, sigma, epsilon, radii):
        # Symbolic zeros say whether sigma or epsilon is differentiated: an
        # MD step's forces skip their terms (a third of the kernel's work).
        derivatives = sigma.perturbed or epsilon.perturbed
        R, sigma, epsilon = _first_order_only((R.value, sigma.value,
                                               epsilon.value))
        radii = None if radii is None else radii.value
        e, (forces, ds, de) = run(R, sigma, epsilon, radii, derivatives)
        return e, (forces, ds, de, radii)

    def backward(res, g):
        forces, ds, de, radii = res
        if isinstance(g, jax.custom_derivatives.SymbolicZero):
            g = jnp.zeros((), forces.dtype)
        return (-g * forces, g * ds, g * de,
                None if radii is None else jnp.zeros_like(radii))

    energy.defvjp(forward, backward, symbolic_zeros=True)
    return energy


_ENERGY_KEYWORDS = ("sigma", "epsilon", "radii")


def lennard_jones_fused(displacement: Callable, box, *, sigma: float = 1.0,
                        epsilon: float = 1.0, r_onset: float = 2.0,
                        r_cutoff: float = 2.5, radii: Array | None = None,
                        backend="bvh", periodic=None) -> Callable[..., Array]:
    """Lennard-Jones energy with no neighbour list (ORCS-forces, seed 003
    §3.2.2), the energy of `jax_md.energy.lennard_jones_neighbor_list` with
    these arguments.

    Args:
      displacement: a jax-md displacement function; it is probed (for the
        periodic axes when ``periodic`` is None, and for agreement with the
        box), not called on the particles.
      box: None (free space), a scalar or ``(dim,)`` sides (orthorhombic).
      sigma, epsilon: float scalars, sigma > 0, epsilon >= 0.
      r_onset, r_cutoff: the smooth switch's start and the cutoff, in units
        of ``sigma`` (as jax-md's), ``0 <= r_onset < r_cutoff``.
      radii: None, or float ``(N,)`` per-particle radii (seed 003 §3): pair
        ``ij`` cut at ``max(r_i, r_j)``, the potential stretched by
        ``max(r_i, r_j) / (r_cutoff sigma)``. Their largest bounds the
        radii the energy function may be given.
      backend: ``"bvh"``, ``"brute"``, ``"cell"``, or
        `jaxrt.backends.rt.ffi.Bvh` options (rebuild policy, builder, sorting).
      periodic: bool or one per axis; None infers it from ``displacement``.

    Returns:
      ``energy_fn(R, *, sigma=None, epsilon=None, radii=None)``: R float32
      or float64 ``(N, dim)``, dim 2 or 3; ``sigma`` / ``epsilon`` float
      scalars that replace the factory's (differentiable; the cutoffs stay
      where the factory put them); ``radii`` float ``(N,)`` (only if the
      factory had radii). Returns the float scalar energy in R's dtype;
      jit-compiled; ``jax.grad`` in R gives ``-F``, in sigma and epsilon
      their derivatives, from the same traversal. ``kT=`` (passed on by
      jax_md.simulate) is accepted and dropped; other keywords raise.
      ``energy_fn.sums(R, **params)`` returns the whole `FusedSums`
      (forces, ``dE/dsigma``, ``dE/depsilon``, the number of interacting
      pairs, error bits), for statistics; it is not differentiable.
    """
    sigma0, r_on, r_c = _check_potential(sigma, epsilon, r_onset, r_cutoff)
    bound = r_c * sigma0 if radii is None else _check_radii(radii)
    impl = _backend(backend)
    default = dict(sigma=sigma, epsilon=epsilon, radii=radii)
    by_dim: dict = {}

    def setup(dim: int):
        if dim not in by_dim:
            params = static_params(displacement, box, periodic, dim,
                                    r_on * sigma0, r_c * sigma0, bound)
            energy = _make_energy(impl, params, dim)

            def sums(R, sigma, epsilon, radii):
                s = impl.sums(jnp.pad(R, ((0, 0), (0, 3 - dim))), sigma,
                              epsilon, radii, params)
                error = s.error | _input_errors(R, radii, params.bound)
                return s._replace(forces=s.forces[:, :dim], error=error)

            by_dim[dim] = (jax.jit(energy), jax.jit(sums))
        return by_dim[dim]

    def arguments(R, sigma, epsilon, radii, kwargs):
        """(R, sigma, epsilon, radii) checked and in R's dtype."""
        reject_unknown("energy_fn", kwargs, _ENERGY_KEYWORDS,
                       ignored=SIMULATE_KEYWORDS)
        R = jnp.asarray(R)
        if R.ndim != 2 or not jnp.issubdtype(R.dtype, jnp.floating):
            raise ValueError(f"R must be a float (N, dim) array; got shape "
                             f"{R.shape} and dtype {R.dtype}.")
        if radii is not None and default["radii"] is None:
            raise ValueError("radii was given to the energy function but not "
                             "to the factory: pass radii to "
                             "lennard_jones_fused (its largest sets the search).")
        radii = default["radii"] if radii is None else radii
        if radii is not None:
            radii = jnp.asarray(radii, R.dtype)
            if radii.shape != (R.shape[0],):
                raise ValueError(f"radii has shape {radii.shape}; R has "
                                 f"{R.shape[0]} particles: pass one radius each.")
            radii = jax.lax.stop_gradient(radii)
        p = {k: jnp.asarray(default[k] if v is None else v)
             for k, v in (("sigma", sigma), ("epsilon", epsilon))}
        for k, v in p.items():
            if v.ndim:
                raise ValueError(f"{k} has shape {v.shape}; pass a scalar.")
        return R, p["sigma"].astype(R.dtype), p["epsilon"].astype(R.dtype), radii

    def energy_fn(R: Array, *, sigma=None, epsilon=None, radii=None,
                  **kwargs) -> Array:
        args = arguments(R, sigma, epsilon, radii, kwargs)
        e = setup(args[0].shape[1])[0](*args)
        if not isinstance(e, jax.core.Tracer):
            if not bool(jnp.isfinite(e)):
                _raise_for(_input_errors(args[0], args[3], bound), bound)
        return e

    def sums(R: Array, *, sigma=None, epsilon=None, radii=None,
             **kwargs) -> FusedSums:
        """All the backend's sums at once (`FusedSums`: forces, parameter
        derivatives, interaction count, error bits); not differentiable."""
        args = arguments(R, sigma, epsilon, radii, kwargs)
        return setup(args[0].shape[1])[1](*args)

    energy_fn.sums = sums
    return energy_fn


def lennard_jones_perse_step(displacement: Callable, box, *, dt: float,
                             mass: float = 1.0, sigma: float = 1.0,
                             epsilon: float = 1.0, r_onset: float = 2.0,
                             r_cutoff: float = 2.5, backend="bvh",
                             periodic=None, radii=None) -> Callable:
    """ORCS-persé (seed 003 §3.2.1): one leapfrog step in one kernel.

    ``v(t + dt/2) = v(t - dt/2) + dt F(x(t)) / mass``, ``x(t + dt) = x(t) +
    dt v(t + dt/2)``, wrapped into the box on periodic axes (free axes have
    no wall law: the paper gives none). With the same arguments as
    `lennard_jones_fused`, F is that energy's force. Not differentiable.

    Args:
      dt, mass: float scalars > 0.
      radii: must be None: persé needs equal radii (detection is one-sided
        otherwise); use `lennard_jones_fused` with an integrator.
      others: as `lennard_jones_fused`.
    Returns:
      ``step(R, V) -> (R', V')``, R and V float ``(N, dim)`` (V at the half
      step), in R's dtype; jit-compiled. ``step.energy(R, V)`` also returns
      the energy at R: ``(R', V', E)``.
    """
    if radii is not None:
        raise ValueError("radii: ORCS-persé needs equal radii (seed 003 "
                         "§3.2.3; with different radii each pair is found "
                         "from one side only). Use lennard_jones_fused(..., "
                         "radii=) and an integrator (ORCS-forces).")
    dt = _scalar("dt", dt, positive=True)
    mass = _scalar("mass", mass, positive=True)
    sigma0, r_on, r_c = _check_potential(sigma, epsilon, r_onset, r_cutoff)
    impl = _backend(backend)
    by_dim: dict = {}

    def setup(dim: int):
        if dim not in by_dim:
            params = static_params(displacement, box, periodic, dim,
                                    r_on * sigma0, r_c * sigma0, r_c * sigma0)

            @jax.jit
            def step(R, V):
                pad = ((0, 0), (0, 3 - dim))
                x, v, e = impl.perse(jnp.pad(R, pad), jnp.pad(V, pad),
                                     jnp.asarray(sigma, R.dtype),
                                     jnp.asarray(epsilon, R.dtype), dt, mass,
                                     params)
                return x[:, :dim], v[:, :dim].astype(R.dtype), e

            by_dim[dim] = step
        return by_dim[dim]

    def with_energy(R, V):
        R, V = jnp.asarray(R), jnp.asarray(V)
        if R.ndim != 2 or V.shape != R.shape:
            raise ValueError(f"R and V must both be (N, dim); got {R.shape} "
                             f"and {V.shape}.")
        return setup(R.shape[1])(R, V)

    def step(R, V):
        x, v, _ = with_energy(R, V)
        return x, v

    step.energy = with_energy
    return step
