"""What the caller's ``displacement_or_metric`` measures, as the grids need it.

jax-md hands a neighbour list a function ``d(Ra, Rb)`` and a box, and never
checks that the two agree. The grids of jaxrt's backends bin positions, so
they need to know how far apart in position space two neighbours can be.
This module models the caller's metric as

    d(Ra, Rb)**2 = q^T G q,   q = wrap(T Ra - T Rb)

with ``T`` a static linear map to the grid's space (the identity, or the
inverse of a triclinic box for Cartesian positions), ``wrap`` the minimum
image on periodic axes of period ``P`` (in that space), and ``G`` the
metric's Gram matrix, read off the metric itself at short displacements
(exact for jax-md's spaces, whose ``d**2`` is a quadratic form; `gram`). So fractional coordinates, triclinic boxes, scaled or
anisotropic metrics and a box passed to ``allocate`` / ``update`` are all
one case, and the model is checked against the metric before it is trusted:

* at ``allocate`` on sampled pairs (`sample_deviation`): a metric the model
  does not fit is either decided pair by pair by the metric (when it is
  never shorter than the model, so the grid still holds every neighbour) or
  refused;
* on every rebuild under ``jit``, on the particles at the extremes of each
  axis (`extremes_disagree`): this is what catches a periodic displacement
  given with ``box=None``, whose short distances look free.

Height: a neighbour within ``c`` lies within ``c / h_a`` of the particle
along axis ``a`` of the grid's space, with ``h_a = 1 / sqrt((G^-1)_aa)``
(Cauchy-Schwarz on ``q_a = e_a^T G^-1/2 G^1/2 q``); for a diagonal ``G``,
``h_a = sqrt(G_aa)``. ``P_a h_a`` is the periodic cell's height across
axis ``a``. A cutoff of half of it or more is a small box (`cutoff_fits`):
the grid then holds every particle whose image under the metric's wrap is
within the cutoff (its cells are no narrower than the cutoff, or the
stencil spans the whole axis), and `jaxrt.neighbor_list` lists it on the
backends that can (``small_boxes``).
"""
from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxrt import platforms

# Off-diagonal Gram entries below this (relative) count as zero.
_DIAGONAL_TOLERANCE = 2.0 ** -20
# Model and metric may differ by rounding: this much relative, plus ulps of
# the largest coordinate. XLA's GPU arithmetic (contracted multiply-adds,
# its division and square root) made them differ by up to ~30 ulps on the
# H200, where the CPU agreed to a few. A metric that departs from its
# quadratic model by less than this is taken as the model (the cell list
# then decides only pairs within 2**-18 of the cutoff by the metric).
_AGREE_RELATIVE = 2.0 ** -16
_AGREE_ULPS = 64
# A box is small unless the cutoff is this far (relatively) below half a
# periodic height: the ray-traced backends' margin
# (`jaxrt.backends.rt.halfbox.CUTOFF_MARGIN`), so that the front refuses for them
# exactly the boxes they cannot serve.
CUTOFF_MARGIN = 2.0 ** -16
# The largest relative shortfall of the metric under its model that the
# grid absorbs by searching that much farther (TF32 rounding is 2**-11).
MAX_SLACK = 2.0 ** -7
# Pairs sampled at allocate: particles adjacent along each axis (most of
# them near one another) and random ones (most far apart).
_ADJACENT_SAMPLES = 4096
_RANDOM_SAMPLES = 2048
# From this many particles `sample_pairs` sorts on an accelerator where the
# positions live (smaller sorts cost less on the host than a compile).
_DEVICE_SORT_MIN = 1 << 16


@dataclasses.dataclass(frozen=True, eq=False)
class Space:
    """The static part of the model, fixed by `jaxrt.neighbor_list`'s arguments.

    Attributes:
      periodic: one bool per axis.
      period: float64 ``(dim,)``, ``P``: the period of each axis in the
        grid's space (box sides for Cartesian positions in an orthorhombic
        box, 1 for fractional coordinates or a triclinic box, 1 where free).
      transform: float64 ``(dim, dim)`` ``T`` (grid coordinates ``q = T p``
        for positions ``p``), or None for the identity.
    """

    periodic: tuple[bool, ...]
    period: np.ndarray
    transform: np.ndarray | None = None

    @property
    def dim(self) -> int:
        return len(self.periodic)

    def _value(self) -> tuple:
        transform = (None if self.transform is None else
                     np.asarray(self.transform, np.float64).tobytes())
        return (self.periodic,
                np.asarray(self.period, np.float64).tobytes(), transform)

    # Equal by value: a `Space` is static in jitted programs, and two
    # `jaxrt.neighbor_list` factories with equal arguments must meet one
    # another's compiled programs (the arrays make the default eq fail).
    def __eq__(self, other) -> bool:
        return isinstance(other, Space) and self._value() == other._value()

    def __hash__(self) -> int:
        return hash(self._value())

    def to_grid(self, position):
        """Grid coordinates ``q`` of float ``(..., dim)`` positions."""
        if self.transform is None:
            return position
        return apply(jnp.asarray(self.transform, position.dtype), position)

    def from_grid(self, q):
        if self.transform is None:
            return q
        return apply(jnp.asarray(np.linalg.inv(self.transform), q.dtype), q)

    def wrap(self, dq):
        """Grid displacements ``dq`` (float ``(..., dim)``) wrapped into
        ``[-P/2, P/2)`` on periodic axes, with jax-md's arithmetic (its
        ``space.periodic_displacement``): a difference of exactly half a
        period goes to ``-P/2`` as jax-md's does. In a triclinic box the two
        ways differ in length, and lattices in fractional coordinates have
        such differences (a rounding wrap made the model longer than
        jax-md's metric there, and the check refused the list)."""
        if not any(self.periodic):
            return dq
        p = jnp.asarray(np.where(self.periodic, self.period, 1.0), dq.dtype)
        on = jnp.asarray(self.periodic)
        return jnp.where(on, jnp.mod(dq + 0.5 * p, p) - 0.5 * p, dq)


def apply(matrix, vectors):
    """``matrix @ v`` for float ``(..., dim)`` vectors, elementwise in the
    vectors' dtype: a matrix product on a GPU may round its float32 inputs
    to TF32 (10 bits), far coarser than the checks here allow."""
    return jnp.sum(matrix * vectors[..., None, :], axis=-1)


# The model's functions are jitted (``space`` static, equal by value):
# called eagerly at allocate, op by op, their dozens of tiny programs each
# compiled on its own, most of a cold allocate's extra time.
@functools.partial(jax.jit, static_argnames=("space", "dtype"))
def gram(metric_sq, space: Space, dtype):
    """``G``: float ``(dim, dim)`` in ``dtype``, the Gram matrix of
    ``metric_sq`` (`jaxrt.backends.MetricSq`) in grid coordinates. Traceable
    (a box passed to ``update`` changes it under ``jit``).

    From values of the metric, not its derivatives: jax-md's fractional
    spaces give ``transform`` a custom JVP (forces in real space), so
    autodiff sees the identity. Steps are powers of two well inside half a
    period (and below the gap between L/2 and the next power of two), so
    that jax-md's wrap and a box side times a step are exact:
    a Cartesian metric gives the identity and a fractional orthorhombic one
    the squared sides, bit for bit.
    """
    dim = space.dim
    period = np.asarray(space.period, np.float64)
    # jax-md's space.periodic wraps as mod(d + L/2, L) - L/2, exact only
    # while L/2 + step stays below the next power of two (L = 3.9764 with
    # a step of 1/32 rounded, and its box looked sheared by 4e-6).
    half = period / 2
    gap = 2.0 ** np.ceil(np.log2(half)) - half
    limit = np.where(gap > 0, np.minimum(period / 64, gap / 2), period / 64)
    steps = 2.0 ** np.floor(np.log2(limit))
    origin = jnp.zeros((dim,), dtype)

    def squared(q):
        return metric_sq(space.from_grid(jnp.asarray(q, dtype)), origin)

    unit = np.diag(steps)
    rows = []
    for a in range(dim):
        row = []
        for b in range(dim):
            if a == b:
                row.append(squared(unit[a]) / (steps[a] * steps[a]))
            else:  # polarisation: exact zero for an orthorhombic box
                row.append((squared(unit[a] + unit[b])
                            - squared(unit[a] - unit[b]))
                           / (4 * steps[a] * steps[b]))
        rows.append(jnp.stack(row))
    return jnp.stack(rows).astype(dtype)


@functools.partial(jax.jit, static_argnames=("space",))
def lengths_from_origin(metric_sq, space: Space, q):
    """float ``(M,)``: the distances ``metric_sq`` gives from the origin
    to the grid points ``q`` (float ``(M, dim)``), in one program."""
    origin = jnp.zeros(q.shape[1:], q.dtype)
    return jnp.sqrt(jax.vmap(lambda r: metric_sq(origin, r))(
        space.from_grid(q)))


def _jaxlib_version() -> tuple[int, ...]:
    """``jaxlib``'s release as integers (``(0, 10, 1)``)."""
    import jaxlib
    parts = []
    for part in jaxlib.__version__.split(".")[:3]:
        if not part.isdigit():
            break
        parts.append(int(part))
    return tuple(parts)


# XLA's options for the programs a CPU runs eagerly (``allocate``'s and
# an eager ``update``'s): its older fusion emitters compile the search's
# gather- and bit-heavy programs in a half to three quarters of the time
# of its newer (MLIR) ones, and their code runs as fast or faster.
# An XLA without them refuses the option at compile time: it is given only
# to the versions where it was measured (``jaxlib`` 0.10.x); others keep
# XLA's defaults (slower compiles, the same programs' results).
CPU_COMPILE_OPTIONS = ({"xla_cpu_use_fusion_emitters": False}
                       if (0, 10, 1) <= _jaxlib_version() < (0, 11) else {})
# XLA's options for programs that run once or a few times (``allocate``'s
# measuring, an eager call's program) at small N on a CPU: the backend's
# optimisation off compiles several times faster (a first ``allocate``'s
# largest cost) and runs ~10x slower. ``jit`` by the caller is unaffected.
QUICK_COMPILE_OPTIONS = {**CPU_COMPILE_OPTIONS,
                         "xla_backend_optimization_level": 0}


def concrete(fn, *args, **kwargs):
    """``fn(*args, **kwargs)`` as concrete arrays: a jitted ``fn`` called
    as one compiled program where no trace is under way, and evaluated at
    trace time (``jax.ensure_compile_time_eval``: op by op, each op
    compiled on its own, dozens of programs) only under a trace. On a
    CPU the model's programs (run once per ``allocate``) are compiled for
    compile speed (`QUICK_COMPILE_OPTIONS`)."""
    if platforms.under_trace():
        with jax.ensure_compile_time_eval():
            return fn(*args, **kwargs)
    if fn in _QUICK and _on_cpu_only(args, kwargs):
        fn = _QUICK[fn]
    return fn(*args, **kwargs)


def _off_diagonal(g, xp):
    """Does the Gram matrix have off-diagonal entries (bool)? ``xp`` is
    numpy (eager: no program to compile) or jax.numpy (traced)."""
    d = xp.sqrt(xp.abs(xp.diagonal(g)))
    off = xp.abs(g - xp.diag(xp.diagonal(g)))
    return xp.any(off > _DIAGONAL_TOLERANCE * d[:, None] * d[None, :])


def is_diagonal(g) -> bool:
    """Eager: is the (concrete) Gram matrix diagonal?"""
    return not bool(_off_diagonal(np.asarray(g, np.float64), np))


def off_diagonal(g):
    """Traced: does the Gram matrix have off-diagonal entries (bool scalar)?"""
    return _off_diagonal(g, jnp)


@functools.partial(jax.jit, static_argnames=("diagonal",))
def heights(g, diagonal: bool):
    """``h``: float ``(dim,)``, metric length per unit grid step across each
    axis (module docstring). ``diagonal`` (static) takes the exact
    ``sqrt(G_aa)``, which equals the box side for jax-md's fractional
    coordinates bit for bit."""
    if diagonal:
        return jnp.sqrt(jnp.diagonal(g))
    cofactor = _cofactor_diagonal(g)
    det = jnp.sum(g[0] * jnp.stack([cofactor[0]] + [
        _cofactor(g, 0, b) for b in range(1, g.shape[0])]))
    return jnp.sqrt(det / cofactor)


def _cofactor(g, a: int, b: int):
    """Cofactor ``C_ab`` of a 2x2 or 3x3 ``g`` (a != b)."""
    if g.shape[0] == 2:
        return -g[1 - a, 1 - b]
    rows = [r for r in range(3) if r != a]
    cols = [c for c in range(3) if c != b]
    minor = (g[rows[0], cols[0]] * g[rows[1], cols[1]]
             - g[rows[0], cols[1]] * g[rows[1], cols[0]])
    return minor if (a + b) % 2 == 0 else -minor


def _cofactor_diagonal(g):
    """float ``(dim,)``: the diagonal cofactors of ``g`` (dim <= 3), written
    out (``(G^-1)_aa = C_aa / det G``) rather than a GPU solver's inverse."""
    dim = g.shape[0]
    if dim == 1:
        return jnp.ones((1,), g.dtype)
    if dim == 2:
        return jnp.stack([g[1, 1], g[0, 0]])
    return jnp.stack([g[b, b] * g[c, c] - g[b, c] * g[c, b]
                      for b, c in ((1, 2), (0, 2), (0, 1))])


def model_sq(qa, qb, g, space: Space):
    """The model's squared distance of grid coordinates ``qa``, ``qb``
    (float ``(..., dim)``)."""
    dq = space.wrap(qa - qb)
    return jnp.sum(dq * apply(g, dq), axis=-1)


def _tolerance(q, h, space: Space):
    """Absolute distance tolerance (float scalar): rounding of coordinates."""
    scale = jnp.max(jnp.abs(q) * h, initial=0.0)
    if any(space.periodic):
        scale = scale + jnp.max(jnp.where(jnp.asarray(space.periodic),
                                          jnp.asarray(space.period, q.dtype) * h,
                                          0.0))
    return _AGREE_ULPS * jnp.finfo(q.dtype).eps * scale


@functools.partial(jax.jit, static_argnames=("space", "slack"))
def _deviation(position, i, j, metric_sq, g, h, space: Space,
               slack=0.0):
    """Signed excess of metric over model distance on pairs ``(i, j)``,
    in units of the allowed rounding (|x| <= 1: they agree), the model
    shortened by the relative ``slack`` first. float ``(M,)``."""
    q = space.to_grid(position)
    m = jnp.sqrt(jnp.maximum(jax.vmap(metric_sq)(position[i], position[j]), 0))
    d = jnp.sqrt(jnp.maximum(model_sq(q[i], q[j], g, space), 0))
    allowed = _AGREE_RELATIVE * jnp.maximum(m, d) + _tolerance(q, h, space)
    return (m - (1.0 - slack) * d) / allowed, m, d, allowed


def extreme_pairs(position, space: Space):
    """int32 ``(dim,)`` twice: per axis, the particles with the smallest and
    largest grid coordinate (the pair a wrong periodicity shortens most)."""
    q = space.to_grid(position)
    q = jnp.where(jnp.isfinite(q), q, 0.0)
    return (jnp.argmin(q, axis=0).astype(jnp.int32),
            jnp.argmax(q, axis=0).astype(jnp.int32))


def extremes_disagree(position, metric_sq, g, h, space: Space,
                      lower_bound_only: bool, slack: float = 0.0):
    """Traced check: does the metric disagree with the model on the extreme
    pairs (bool scalar)? With ``lower_bound_only`` (the metric decides every
    pair), only a metric shorter than ``1 - slack`` times the model is a
    disagreement."""
    i, j = extreme_pairs(position, space)
    dev = _deviation(position, i, j, metric_sq, g, h, space, slack)[0]
    bad = dev < -1 if lower_bound_only else jnp.abs(dev) > 1
    return jnp.any(bad | ~jnp.isfinite(dev))


def sample_pairs(position, space: Space) -> tuple[np.ndarray, np.ndarray]:
    """Eager: int ``(M,)`` twice, pairs to test the model on: the extremes
    of each axis, neighbours in the order along each axis, random pairs."""
    q = space.to_grid(jnp.asarray(position))
    n, dim = q.shape
    take = np.linspace(0, n - 2, min(_ADJACENT_SAMPLES // dim,
                                     max(n - 1, 0))).astype(int)
    if n >= _DEVICE_SORT_MIN and _on_accelerator(q):
        lowest, highest, before, after = _axis_samples_on_device(q, take)
    else:
        lowest, highest, before, after = _axis_samples_on_host(q, take)
    rng = np.random.default_rng(0)
    # The extremes are the pairs `extremes_disagree` checks under jit
    # (first occurrences).
    i = np.concatenate([lowest, *before, rng.integers(0, n, _RANDOM_SAMPLES)])
    j = np.concatenate([highest, *after, rng.integers(0, n, _RANDOM_SAMPLES)])
    keep = i != j
    return i[keep], j[keep]


def _on_accelerator(x) -> bool:
    return any(d.platform != "cpu" for d in x.devices())


def _on_cpu_only(*args) -> bool:
    """Would an eager program of ``args`` run on a CPU (JAX's default
    device a CPU and no array of them elsewhere)?"""
    if jax.default_backend() != "cpu":
        return False
    return not any(isinstance(x, jax.Array) and not isinstance(
        x, jax.core.Tracer) and _on_accelerator(x)
        for x in jax.tree_util.tree_leaves(args))


def on_accelerator(x) -> bool:
    """Does the array ``x`` live on a device other than a CPU?"""
    return _on_accelerator(x)


def _axis_samples_on_host(q, take):
    """Per axis of ``q`` (float ``(N, dim)``): the first argmin and argmax,
    and the particles at ranks ``take`` and ``take + 1`` (int ``(M,)``) of
    its order, sorted by NumPy (quicksort: ties in either order)."""
    columns = np.ascontiguousarray(np.asarray(q).T)
    orders = [np.argsort(c) for c in columns]
    return ([int(np.argmin(c)) for c in columns],
            [int(np.argmax(c)) for c in columns],
            [o[take] for o in orders], [o[take + 1] for o in orders])


def _axis_samples_on_device(q, take):
    """`_axis_samples_on_host`, sorted where ``q`` lives (ties in index
    order): at millions of particles the host's sorts were most of an
    `allocate` with a GPU (docs/benchmarks-notes.md); only the samples come
    back."""
    order = jnp.argsort(q, axis=0, stable=True)
    dim = q.shape[1]
    picked = np.asarray(order[np.concatenate([take, take + 1])])
    return (np.asarray(jnp.argmin(q, axis=0)), np.asarray(jnp.argmax(q, axis=0)),
            [picked[:len(take), a] for a in range(dim)],
            [picked[len(take):, a] for a in range(dim)])


def sample_deviation(position, metric_sq, g, h, space: Space):
    """Eager: ``(deviation, slack, i, j)``: the sampled pairs' deviations
    (float64 ``(M,)``, `_deviation`), the relative slack the grid needs
    (`MAX_SLACK` or less, or None when the metric is shorter than that
    allows) and the pairs."""
    i, j = sample_pairs(position, space)
    if len(i) == 0:
        return np.zeros(0), 0.0, i, j
    dev, m, d, allowed = (np.asarray(x, np.float64) for x in concrete(
        _deviation, jnp.asarray(position), jnp.asarray(i), jnp.asarray(j),
        metric_sq, g, h, space))
    # How much shorter than the model the metric is, beyond rounding:
    # twice that (a sample is not every pair) lets the grid hold every
    # neighbour of a metric that is noisy, e.g. jax-md's periodic_general,
    # whose matrix product a GPU rounds to TF32 by default.
    short = np.max((d - m - allowed) / np.maximum(d, 1e-30), initial=0.0)
    slack = 0.0 if short <= 0 else 2.0 * short
    return dev, (slack if slack <= MAX_SLACK else None), i, j


def cutoff_fits(cutoff: float, height_times_period):
    """Traced: is ``cutoff`` below half of the periodic height (with the
    margin), i.e. not a small box? ``height_times_period``: float
    ``(dim,)``, one answer per axis (the caller ignores free axes)."""
    return cutoff < 0.5 * (1.0 - CUTOFF_MARGIN) * height_times_period


def _quick_twin(fn, static: tuple[str, ...]):
    return jax.jit(fn.__wrapped__, static_argnames=static,
                   compiler_options=QUICK_COMPILE_OPTIONS)


# `concrete`'s programs compiled for compile speed, by the jitted function.
_QUICK = {
    gram: _quick_twin(gram, ("space", "dtype")),
    lengths_from_origin: _quick_twin(lengths_from_origin, ("space",)),
    heights: _quick_twin(heights, ("diagonal",)),
    _deviation: _quick_twin(_deviation, ("space", "slack")),
}
