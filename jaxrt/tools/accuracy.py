"""What accuracy costs in time: sweep the knobs that trade one for the other.

``jaxrt accuracy [SCENE] --out DIR [--quick]`` (`jaxrt.cli`) calls `run`.
On a scene (`SCENES`: the LJ fluid by default; ``lj-fluid-2d``, the LJ
fluid in 2D, where the Delaunay backend runs; the dam break for SPH, 2D
too) it varies one knob at a time away from the scene's own setting (the
*base*) and measures,
for each value, the time per step and its errors against a float64
reference of the same scene. Outputs in ``DIR``: ``accuracy.csv`` (one row
per knob value), ``<knob>.png`` (each error against the time per step, the
Pareto front drawn) and ``summary.md`` (sentences computed from the rows).

One function per concern:

* knobs as data: `Knob` (a name, its `Value`\\s, the scenes and
  dimensions it applies to, whether it is available here) and `KNOBS`; a
  `Value` maps a `Scene` to a `Scene` (every knob is a scene field, a
  backend option, or an effect in place of the LJ: `LJFused`, `LJPairs`)
  and may run in some dimensions only (Delaunay 2D, `jaxrt.pairs` 3D) or
  only where it can (the Pallas kernels: CUDA GPUs);
* a knob may need a scene of its own (`Knob.own_scene`): per-particle
  cutoff radii (the ``radii`` knob: one grid of the largest radius,
  ``Cell(radius_classes=)``, the BVH, the fused LJ with ``radii=``) run on
  `polydisperse` (`jaxrt.sim.lj_polydisperse`, ``jaxrt.sim.LJ(radii=)``:
  pair ``ij`` cut at ``max(r_i, r_j)``, the list built with those radii),
  against that scene's own float64 reference, its pairs checked at
  ``max(r_i, r_j)`` (`brute_pairs` ``radii=``);
* the reference: `equilibrate` (float64), `reference_forces` (float64,
  brute force), `measure` of the float64 scene itself (continuing the
  equilibration, its list by the scene's backend, ``cell``);
* the error measures, each a pure function of arrays (tested by hand):
  `force_rms_rel`, `energy_drift`, `brute_pairs` / `pairs_missed`, `rdf` /
  `rdf_difference`, `position_rms`;
* timing: `measure` times the jitted chunks of the run itself, the first
  (compiling) chunk excluded, every chunk synchronised
  (`jax.block_until_ready`), the median over chunks reported;
* `pareto_front`, `write_csv`, `plot_knob`, `write_summary`.

Definitions (the CSV's columns):

* ``time_per_step_ms``: median over the run's chunks (``chunk`` steps in one
  jitted ``lax.scan`` each; list updates, forces, integrator) of the chunk's
  wall time / ``chunk``; the first chunk (compilation) and any chunk redone
  after a list overflow are excluded. ``time_min_ms`` / ``time_max_ms``: the
  extremes of the same samples. ``time_per_tau_ms``: ``time_per_step_ms /
  dt``, per unit of simulated time (what the summary ranks by, so that a
  longer time step counts for what it saves).
* ``force_rms_rel``: ``sqrt(mean |F - F_ref|^2) / sqrt(mean |F_ref|^2)`` at
  the equilibrated configuration, where ``F_ref`` is the float64 brute-force
  force of the *scene's own* potential (so it isolates precision and list
  effects); ``force_rms_rel_full``: the same against float64 LJ cut plainly
  at ``r_ref`` (the longest cutoff the box allows, at most 5 sigma): the
  error of the truncation itself (none with cutoff radii: each pair has
  its own stretched potential). (SPH: accelerations.)
* ``drift_per_particle_1e4``: the least-squares slope of
  ``(E(t) - E(t_1)) / N`` against the step number, times 10^4: energy drift
  per particle per 10^4 steps of the setting's own Hamiltonian, NVE;
  ``drift_se``: its standard error from 10 block means (`energy_drift`);
  ``max_abs_dE_per_particle``: ``max |E(t) - E(t_1)| / N`` over the run
  (the energy excursion, robust in short runs: it scales as dt^2).
  Empty for non-conservative scenes (dam break).
* ``pairs_missed``: after every chunk, the pairs within the interaction
  cutoff (with radii: ``max(r_i, r_j)``) at the current positions (float64
  brute force, minimum image on periodic axes) that the list in use lacks (or, for `LJPairs`, the pairs
  `jaxrt.pairs` finds at those positions), summed over the checks
  (``pairs_checked``: the brute-force pairs over the same checks; ``k``:
  mean neighbours within the cutoff per particle); ``missed_depth_ulps``:
  the deepest missed pair's distance inside its cut, in ulps of the
  distances' scale (`missed_depth_ulps`): up to `ROUNDING_ULPS` a search in
  float32 decides by rounding, as jax-md's metric does; deeper, the list is
  wrong.
* ``rdf_l2`` / ``rdf_linf``: ``sqrt(sum (g - g_ref)^2 dr)`` and
  ``max |g - g_ref|`` of the radial distribution functions over the run's
  chunk-end frames, on the fixed grid ``dr`` up to ``r_max`` (periodic
  scenes only); ``rdf_noise`` in the summary: the same between the two
  halves of the reference run (each half from half the frames, so about
  √2 above the noise of a setting against the reference), the floor
  below which a difference means nothing.
* ``position_rms``: RMS distance between the setting's final positions and
  the reference's (chaotic for the LJ fluid, so a measure of divergence).
* ``rebuilds``: list rebuilds over the run; ``triangulation_rebuilds``
  (Delaunay lists): rebuilds of the triangulation from scratch (Qhull on
  the host) where its maintenance by flips gave up.
"""
from __future__ import annotations

import csv
import dataclasses
import datetime
import importlib.util
import math
import os
import pathlib
import platform
import subprocess
import time
import warnings
from typing import Callable, NamedTuple, Sequence

import numpy as np

from jaxrt.sim.effects import LJFields

# ---------------------------------------------------------------------------
# Provenance: benchmarks/_harness.py's, when the repository is here.


def _harness():
    """``benchmarks/_harness.py`` as a module, or None outside a checkout."""
    path = pathlib.Path(__file__).resolve().parents[2] / "benchmarks" / \
        "_harness.py"
    if not path.exists():
        return None
    spec = importlib.util.spec_from_file_location("_jaxrt_bench_harness", path)
    mod = importlib.util.module_from_spec(spec)
    try:
        spec.loader.exec_module(mod)
    except Exception:  # noqa: BLE001 - provenance is best effort
        return None
    return mod


def provenance() -> dict:
    """The harness's provenance columns (device, versions, git sha, date)."""
    h = _harness()
    if h is not None:
        return {**h.host_provenance(), **h.device_provenance()}
    import jax
    dev = jax.devices()[0]
    try:
        sha = os.environ.get("GIT_SHA") or subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True,
            text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        sha = "unknown"
    return {"device": f"{dev.platform}:{dev.device_kind}",
            "device_kind": dev.device_kind, "host": platform.node(),
            "jax": jax.__version__, "python": platform.python_version(),
            "git_sha": sha or "unknown",
            "date": datetime.datetime.now(datetime.timezone.utc)
            .isoformat(timespec="seconds")}


PROVENANCE = ("device", "device_kind", "device_slug", "host", "jax", "jaxlib",
              "jax_md", "warp", "python", "git_sha", "date")

# ---------------------------------------------------------------------------
# Effects the knobs put in a scene in place of its LJ (list-free: each runs
# its own search, so ``pairwise = False`` and the scene builds no list)


def _lj_r_onset(effect) -> float:
    return 0.8 * effect.r_cutoff if effect.r_onset is None else \
        effect.r_onset


@dataclasses.dataclass(frozen=True)
class LJFused(LJFields):
    """The LJ effect on the list-free fused energy
    (`jaxrt.energy.lennard_jones_fused`): ``pairwise = False``, so the
    compiled scene builds no list. ``backend``: the fused energy's search,
    a name (``"cell"``: the portable one, its kernel as ``"cell"`` picks
    it) or an options object passed through as it is (a
    `jaxrt.backends.Cell` for the cell search's kernel, where the fused
    energy takes one). The fused energy is jax-md's smooth switch only;
    other truncations are refused (the knob runs on the smooth base
    scene). ``radii``: per-particle cutoff radii as `jaxrt.sim.LJ`'s (pair
    ``ij`` cut at ``max(r_i, r_j)``, the potential stretched), passed to
    the fused energy's ``radii=``."""

    backend: object = "cell"
    kind = "lj_fused"
    pairwise = False

    @property
    def search(self) -> str:
        """The search, for the CSV's ``backend`` column."""
        b = self.backend
        if not isinstance(b, str):
            newton = "+newton" if getattr(b, "newton", False) else ""
            b = f"{b.name}[{getattr(b, 'kernel', '?')}{newton}]"
        return f"fused {b} (no list)"

    def validate(self, scene, where: str) -> None:
        from jaxrt.sim import SceneError
        if self.truncation != "smooth":
            raise SceneError.at(f"{where}.truncation", "the fused energy is "
                                "the smooth switch only; use 'smooth'.")
        if np.ndim(self.sigma) or np.ndim(self.epsilon):
            raise SceneError.at(f"{where}.sigma", "the fused energy takes "
                                "scalar sigma and epsilon.")
        if self.radii is not None:
            from jaxrt.sim.effects import check_cutoff_radii
            check_cutoff_radii(self, scene, where)

    def term(self, ctx):
        import jaxrt.energy
        from jaxrt.sim import Term
        box = np.asarray(ctx.scene.box.size, float)
        sigma = float(self.sigma)
        # The fused factory takes r_onset / r_cutoff in units of sigma, as
        # jax-md's does; the scene's are absolute.
        # Its radii stretch the potential by max(r_i, r_j) / (r_cutoff
        # sigma), r_cutoff in units of sigma: the list LJ's rule.
        radii = (None if self.radii is None
                 else np.asarray(self.radii, np.float64))
        energy = jaxrt.energy.lennard_jones_fused(
            ctx.displacement, box, sigma=sigma, epsilon=float(self.epsilon),
            r_onset=_lj_r_onset(self) / sigma, r_cutoff=self.r_cutoff / sigma,
            backend=self.backend, periodic=ctx.scene.box.periodic,
            radii=radii)

        def lj_fused(R, nbrs):
            return energy(R)
        return Term(energy=lj_fused, notes=(
            f"list-free fused LJ (backend {self.backend!r})",))


@dataclasses.dataclass(frozen=True)
class LJPairs(LJFields):
    """The LJ effect on pairs from `jaxrt.pairs` (a full list with lattice
    shifts, ``(i, j, S)`` and ``(j, i, -S)``, the pair list of the ML
    potentials), searched every step at ``r_cutoff`` itself: no skin and
    nothing kept between steps. Under ``jit`` the search needs a static
    capacity: ``capacity_margin`` times the pairs at the scene's own
    positions (`jaxrt.pairs_sizes`) plus 64. A search past it makes the
    energy and the forces NaN (the run then stops at non-finite
    positions): never a silent loss of pairs. Same potential as
    `jaxrt.sim.LJ` (`jaxrt.energy.lj.lennard_jones_truncated`), scalar
    sigma and epsilon; 3D (`jaxrt.pairs` is)."""

    capacity_margin: float = 1.25
    kind = "lj_pairs"
    pairwise = False
    search = "jaxrt.pairs (no list)"

    @property
    def cutoff(self) -> float:
        return float(self.r_cutoff)

    def validate(self, scene, where: str) -> None:
        from jaxrt.sim import SceneError
        if scene.particles.dim != 3:
            raise SceneError.at(where, "jaxrt.pairs takes 3D positions; "
                                f"this scene is {scene.particles.dim}D.")
        if np.ndim(self.sigma) or np.ndim(self.epsilon):
            raise SceneError.at(f"{where}.sigma", "scalar sigma and epsilon "
                                "only (no species).")
        r = scene.particles.radius
        if r is not None and np.ptp(r) > 0:
            raise SceneError.at(where, "no per-particle radii.")
        if self.radii is not None:
            raise SceneError.at(f"{where}.radii", "jaxrt.pairs searches one "
                                "cutoff; no per-particle cutoff radii (the "
                                "LJ on a list or the fused LJ take them).")

    def searcher(self, scene) -> Callable:
        """``search(R) -> jaxrt.Pairs`` for ``R`` float ``(N, 3)``, jitted,
        its capacity and reach static (`jaxrt.pairs` under ``jit``)."""
        import jax
        import jaxrt
        box = scene.box
        cell = np.asarray(box.size, np.float64)
        pbc = tuple(box.periodic)
        sizes = jaxrt.pairs_sizes(np.asarray(scene.particles.positions),
                                  self.r_cutoff, cell=cell, pbc=pbc)
        capacity = int(self.capacity_margin * sizes.capacity) + 64

        @jax.jit
        def search(R):
            return jaxrt.pairs(R, self.r_cutoff, cell=cell.astype(R.dtype),
                               pbc=pbc, capacity=capacity,
                               max_shift=sizes.max_shift)
        search.cell = cell
        return search

    def term(self, ctx):
        import jax.numpy as jnp
        from jaxrt.energy.lj import lennard_jones_truncated
        from jaxrt.sim import Term
        search = self.searcher(ctx.scene)
        r_c, r_on = float(self.r_cutoff), _lj_r_onset(self)
        sigma, epsilon = float(self.sigma), float(self.epsilon)

        def lj_pairs(R, nbrs):
            p = search(R)
            valid = p.valid
            # Padded entries sit at the cutoff (zero energy, finite
            # gradient), not at 0 where LJ is infinite.
            dr = jnp.where(valid, p.distances(R, search.cell.astype(R.dtype)),
                           r_c)
            e = lennard_jones_truncated(dr, sigma, epsilon, r_onset=r_on,
                                        r_cutoff=r_c,
                                        truncation=self.truncation)
            # Each pair is listed both ways; an overflow poisons the energy
            # and, through the product, every force.
            u = 0.5 * jnp.sum(jnp.where(valid, e, 0.0))
            return u * jnp.where(p.overflow, jnp.nan, 1.0).astype(u.dtype)
        return Term(energy=lj_pairs, notes=(
            f"LJ on jaxrt.pairs, searched every step at {r_c:g}",))

    def pair_checker(self, scene) -> Callable:
        """``codes(position)``: the sorted pair codes ``i * n + j`` (i < j)
        that this effect's search finds at ``position`` (float64 ``(N,
        3)``, searched in the scene's dtype, as in the run), for
        `pairs_missed`; raises if the search overflowed."""
        import jax.numpy as jnp
        search = self.searcher(scene)
        n = scene.particles.n

        def codes(position):
            p = search(jnp.asarray(position, scene.dtype))
            if bool(p.overflow):
                raise RuntimeError("jaxrt.pairs overflowed its capacity")
            c = int(p.count)
            i = np.asarray(p.i)[:c].astype(np.int64)
            j = np.asarray(p.j)[:c].astype(np.int64)
            keep = i < j
            return np.unique(i[keep] * n + j[keep])
        return codes



# ---------------------------------------------------------------------------
# Knobs as data


def _always() -> bool:
    return True


@dataclasses.dataclass(frozen=True)
class Value:
    """One value of a knob: ``label`` (the CSV's ``value``) and ``apply``
    (base scene -> the scene of this value); ``dims``: the scene
    dimensions it runs in (Delaunay: 2D only); ``available``: whether it
    can run in this installation (the Pallas kernels: CUDA only)."""

    label: str
    apply: Callable
    dims: tuple[int, ...] = (2, 3)
    available: Callable[[], bool] = _always


@dataclasses.dataclass(frozen=True)
class Knob:
    """A knob: ``name``, its ``values``, the labels ``quick`` sweeps, the
    scene kinds it applies to (``"lj"``, ``"sph"``), the scene dimensions
    (``dims``) and whether it is ``available`` in this installation."""

    name: str
    values: tuple[Value, ...]
    quick: tuple[str, ...]
    scenes: tuple[str, ...] = ("lj", "sph")
    available: Callable[[], bool] = _always
    what: str = ""
    judge: str = "pairs_missed"
    """The error column the summary judges the knob's values by."""
    dims: tuple[int, ...] = (2, 3)
    own_scene: Callable | None = None
    """None, or ``own_scene(base, plan) -> Scene``: the knob's own base
    scene (float32, backend explicit) built from the sweep's ``base`` at
    the plan's size, in place of it: the knob's values apply to it and its
    reference is its own float64 run (`run`). For knobs that need what the
    sweep's scenes lack (per-particle radii: `polydisperse`)."""

    def base_for(self, base, plan: "Plan"):
        """The scene this knob's values apply to (`own_scene`)."""
        return base if self.own_scene is None else self.own_scene(base, plan)

    def selected(self, quick: bool, dim: int | None = None
                 ) -> tuple[Value, ...]:
        """The values a sweep runs: the ``quick`` ones if ``quick``, those
        that run in ``dim`` dimensions (any if None) and are available."""
        return tuple(v for v in self.values
                     if (not quick or v.label in self.quick)
                     and (dim is None or dim in v.dims) and v.available())


def _replace_neighbors(scene, **kw):
    return dataclasses.replace(scene, neighbors=dataclasses.replace(
        scene.neighbors, **kw))


def _with_dtype(dtype: str):
    return lambda s: dataclasses.replace(s, dtype=dtype)


_BY_OBJECT = ("bvh", "spheres", "squares")
"""Backends a knob passes as objects: then "bvh" is Bvh(policy="drift")'s
run, found again under its options (a setting two knobs reach runs once,
`_key`)."""


def _with_backend(backend, dtype: str | None = None):
    def apply(s):
        b = backend
        if b in _BY_OBJECT:
            from jaxrt.backends import resolve
            b = resolve(b)
        s = _replace_neighbors(s, backend=b)
        return dataclasses.replace(s, dtype=dtype) if dtype else s
    return apply


def _with_lj(truncation: str, cutoff: float):
    def apply(s):
        from jaxrt.sim import LJ
        effects = tuple(
            dataclasses.replace(e, truncation=truncation, r_cutoff=cutoff,
                                r_onset=0.8 * cutoff)
            if isinstance(e, LJ) else e for e in s.effects)
        return dataclasses.replace(s, effects=effects)
    return apply


def _with_skin(factor: float):
    """Skin as a multiple of the scene's own skin."""
    return lambda s: _replace_neighbors(s, skin=s.neighbors.skin * factor)


def _with_dt(factor: float):
    """Time step as a multiple of the scene's own."""
    return lambda s: dataclasses.replace(s, integrator=dataclasses.replace(
        s.integrator, dt=s.integrator.dt * factor))


def _with_bvh_policy(policy: str):
    def apply(s):
        from jaxrt.backends import Bvh
        return _replace_neighbors(s, backend=Bvh(policy=policy))
    return apply


DELAUNAY_CAPACITY = 2.0
"""The Delaunay lists' capacity_multiplier (the boids scene's): its vertex
degree and BFS frontier buffers are sized at ``allocate``, and a liquid's
fluctuate past 1.25 times that within a chunk (measured: the 2D LJ fluid
overflowed twice in a row at 1.25 and 1.5)."""


def _with_delaunay(max_flip_rounds: int = 64, max_splits: int = 32):
    """Delaunay with these options, in float64 (its predicates are float64:
    it refuses float32 positions), `DELAUNAY_CAPACITY`."""
    def apply(s):
        from jaxrt.backends import Delaunay
        s = _replace_neighbors(s, backend=Delaunay(
            max_flip_rounds=max_flip_rounds, max_splits=max_splits),
            capacity_multiplier=DELAUNAY_CAPACITY)
        return dataclasses.replace(s, dtype="float64")
    return apply


def _with_cell_kernel(kernel: str):
    def apply(s):
        from jaxrt.backends import Cell
        return _replace_neighbors(s, backend=Cell(kernel=kernel))
    return apply


def _warp() -> bool:
    import jaxrt
    return "bvh" in jaxrt.available_backends()


def _has_fused() -> bool:
    import jaxrt.energy
    return hasattr(jaxrt.energy, "lennard_jones_fused")


def _pallas_here() -> bool:
    """Whether the cell list's Pallas kernel can run here: a CUDA GPU and a
    JAX with Pallas' Triton backend (`jaxrt._cell_kernel`). Pallas'
    interpreter runs anywhere but is far too slow for a sweep."""
    import jax
    from jaxrt.backends.cell import kernel as _cell_kernel
    return (jax.default_backend() in ("gpu", "cuda")
            and _cell_kernel.plgpu is not None)


def _fused_takes(backend) -> bool:
    """Whether `jaxrt.energy.lennard_jones_fused` accepts ``backend`` (a
    `jaxrt.backends.Cell` for its cell search: not before the fused cell
    kernel lands), probed on a small periodic box."""
    if not _has_fused():
        return False
    from jax_md import space
    import jaxrt.energy
    try:
        jaxrt.energy.lennard_jones_fused(space.periodic(10.0)[0], 10.0,
                                         backend=backend)
    except (TypeError, ValueError):
        return False
    return True


def _fused_cell(kernel: str) -> Callable[[], bool]:
    """``available`` of the fused energy on ``Cell(kernel=kernel)``: a GPU
    where the kernel runs (on a CPU "auto" is "xla", the plain ``fused``
    value) and a fused energy that takes a `Cell`."""
    def available() -> bool:
        from jaxrt.backends import Cell
        return _pallas_here() and _fused_takes(Cell(kernel=kernel))
    return available


def _lj_as(cls, **options):
    """``apply``: the scene with its LJ effect replaced by ``cls`` (an
    effect of the same fields and ``options``, e.g. `LJFused`, `LJPairs`)."""
    def apply(s):
        from jaxrt.sim import LJ
        effects = tuple(cls(**{f.name: getattr(e, f.name) for f in
                               dataclasses.fields(e)}, **options)
                        if isinstance(e, LJ) else e for e in s.effects)
        return dataclasses.replace(s, effects=effects)
    return apply


def _list_free(backend="cell"):
    """The scene with its LJ effect replaced by the list-free fused energy
    (`LJFused`, its search ``backend``): no neighbour list at all."""
    return _lj_as(LJFused, backend=backend)


def _fused_kernel(kernel: str):
    def apply(s):
        from jaxrt.backends import Cell
        return _list_free(Cell(kernel=kernel))(s)
    return apply


def _fused_newton(s):
    """The fused walk meeting each pair once (`Cell(newton=True)` of the
    fused energy's own backend; "auto": the kernel where it runs, which is
    where this value runs)."""
    from jaxrt.energy.listfree.lj import CellSums
    return _list_free(CellSums(kernel="auto", newton=True))(s)


def _same(s):
    return s


POLYDISPERSE_DENSITY = 0.45
"""The radii knob's number density (`polydisperse`), where the box fits."""


def polydisperse(base, plan: "Plan"):
    """The radii knob's scene: `jaxrt.sim.lj_polydisperse` (1 % of the
    particles of cutoff radius 6 in a fluid of radius 2.5: two radius
    classes) with ``base``'s particle count and dimension, float32, backend
    ``cell``, at `POLYDISPERSE_DENSITY`, or lower where that box would be
    shorter than twice the largest radius plus the skin (small ``n``, in
    tests: the minimum image needs it)."""
    del plan  # the size is the base's (the plan's n, QUICK or FULL)
    from jaxrt import sim
    p = base.particles
    # Box side >= 2 (6.0 + skin 0.3) + 0.2 of margin.
    density = min(POLYDISPERSE_DENSITY, p.n / 12.8 ** p.dim)
    return dataclasses.replace(
        sim.lj_polydisperse(n=p.n, density=density, dim=p.dim,
                            backend="cell"), dtype="float32")


def _with_radius_classes(classes: int | None):
    """The cell list with ``radius_classes`` (1: one grid of the largest
    radius; None: as many classes as the radii need)."""
    def apply(s):
        from jaxrt.backends import Cell
        return _replace_neighbors(s, backend=Cell(radius_classes=classes))
    return apply


def _eps(e: int) -> Value:
    def apply(s):
        from jaxrt.backends import Spheres
        return _replace_neighbors(s, backend=Spheres(epsilon_relative=2.0 ** -e))
    return Value(f"2^-{e}", apply)


def _flips(rounds: int, splits: int) -> Value:
    return Value(f"rounds {rounds}, splits {splits}",
                 _with_delaunay(rounds, splits), dims=(2,))


KNOBS: tuple[Knob, ...] = (
    Knob("dtype", (Value("float32", _with_dtype("float32")),
                   Value("float64", _with_dtype("float64"))),
         quick=("float32", "float64"),
         what="positions, velocities and forces in float32 or float64 (the "
              "code offers no mixed precision)", judge="force_rms_rel"),
    Knob("truncation", tuple(
        Value(f"{t} {c:g}", _with_lj(t, c))
        for t in ("truncated", "shifted", "smooth") for c in (2.5, 3.0, 4.0)),
         quick=("truncated 2.5", "shifted 2.5", "smooth 2.5", "smooth 4"),
         scenes=("lj",),
         what="LJ truncation and cutoff in sigma (smooth: switch from "
              "0.8 r_c to r_c)", judge="force_rms_rel_full"),
    Knob("skin", tuple(Value(f"x{f:g}", _with_skin(f))
                       for f in (0.0, 1 / 3, 2 / 3, 1.0, 5 / 3)),
         quick=("x0.333333", "x1", "x1.66667"),
         what="the list's skin (dr_threshold) as a multiple of the scene's"),
    Knob("dt", tuple(Value(f"x{f:g}", _with_dt(f))
                     for f in (0.25, 0.5, 1.0, 2.0)),
         quick=("x0.5", "x1", "x2"),
         what="the time step as a multiple of the scene's",
         judge="max_abs_dE_per_particle"),
    Knob("format", tuple(Value(f, lambda s, f=f: _replace_neighbors(
        s, format=f)) for f in ("Dense", "Sparse", "OrderedSparse")),
         quick=("Dense", "OrderedSparse"),
         what="the neighbour list's layout"),
    Knob("backend", tuple(Value(b, _with_backend(b)) for b in
                          ("brute", "cell", "bvh", "spheres", "squares"))
         + (Value("delaunay", _with_delaunay(), dims=(2,)),),
         quick=("brute", "cell", "bvh", "spheres", "delaunay"),
         what="the search (all exact: differences are rounding only); "
              "delaunay (2D scenes only) runs in float64, as its predicates "
              "need (it refuses float32), so its like-for-like is `dtype = "
              "float64`, the cell list in float64 (and with capacity "
              "multiplier 2, the head-room its degree and frontier buffers "
              "need)"),
    Knob("cell-kernel", tuple(Value(k, _with_cell_kernel(k))
                              for k in ("auto", "xla", "pallas")),
         quick=("auto", "xla", "pallas"), available=_pallas_here,
         what="the cell list's candidate pass: the Pallas kernel or XLA's "
              "windows (the same pairs; CUDA GPUs only, where the kernel "
              "runs: on a CPU \"auto\" is \"xla\" and Pallas' interpreter "
              "is too slow to sweep)"),
    Knob("delaunay-flips", (_flips(64, 32), _flips(8, 8), _flips(4, 4),
                            _flips(2, 2), _flips(1, 1)),
         # One flip round also ends every rebuild: on the dam break its
         # triangulations then outgrow the list's buffers (overflows).
         quick=("rounds 64, splits 32", "rounds 4, splits 4",
                "rounds 2, splits 2"), dims=(2,),
         what="Delaunay's max_flip_rounds and max_splits (float64, as the "
              "backend needs; capacity multiplier 2): fewer make maintenance give up sooner and "
              "rebuild the triangulation from scratch (Qhull on the host); "
              "the list stays exact, only the time moves "
              "(triangulation_rebuilds counts the rebuilds)"),
    Knob("bvh-precision", (Value("float32", _with_backend("bvh", "float32")),
                           Value("float64", _with_backend("bvh", "float64"))),
         quick=("float32", "float64"), available=_warp,
         what="bvh under float32 or float64 positions (the BVH itself is "
              "float32, padded; the exact test in the positions' dtype)",
         judge="force_rms_rel"),
    Knob("bvh-policy", tuple(Value(p, _with_bvh_policy(p)) for p in
                             ("rebuild", "drift", "fixed", "avg",
                              "gradient")),
         quick=("rebuild", "drift"), available=_warp,
         what="when the kept BVH is rebuilt rather than refit"),
    Knob("spheres-epsilon", tuple(_eps(e) for e in (40, 30, 20, 10, 3)),
         quick=("2^-40", "2^-10"), scenes=("lj",), available=_warp,
         what="the sphere method's eps as a fraction of the data's scale "
              "(default 2^-40)"),
    Knob("list-free", (Value("list", _same), Value("fused", _list_free()),
                       Value("fused-xla", _fused_kernel("xla"),
                             available=_fused_cell("xla")),
                       Value("fused-pallas", _fused_kernel("pallas"),
                             available=_fused_cell("pallas")),
                       Value("fused-pallas-newton", _fused_newton,
                             available=_fused_cell("pallas"))),
         quick=("list", "fused", "fused-xla", "fused-pallas",
                "fused-pallas-newton"),
         scenes=("lj",), available=_has_fused,
         what="neighbour list against the fused list-free LJ energy "
              "(`fused`: its cell search as the backend \"cell\" picks it; "
              "on a CUDA GPU also `jaxrt.backends.Cell(kernel=\"xla\")` and "
              "\"pallas\": its array-program walk and its kernel; "
              "`fused-pallas-newton`: the kernel meeting each pair once, "
              "the partner's force added by an atomic)",
         judge="force_rms_rel"),
    Knob("radii", (Value("one grid", _with_radius_classes(1)),
                   Value("radius classes", _with_radius_classes(None)),
                   Value("bvh", _with_backend("bvh"), available=_warp),
                   Value("brute", _with_backend("brute")),
                   Value("fused", _list_free(), available=_has_fused),
                   Value("fused-bvh", _list_free("bvh"),
                         available=lambda: _warp() and _has_fused())),
         quick=("one grid", "radius classes", "bvh", "fused"),
         scenes=("lj",), own_scene=polydisperse,
         what="per-particle cutoff radii (pair ij within max(r_i, r_j), "
              "the LJ stretched to it) on their own polydisperse scene "
              "(`polydisperse`: a few particles of radius 6 among radius "
              "2.5), its reference that scene's float64 run: the cell list "
              "as one grid of the largest radius (`Cell(radius_classes=1)`)"
              " or one grid per radius class, the BVH, the brute force, "
              "or the list-free fused LJ (its cell search; `fused-bvh`: "
              "ORCS-forces); all exact, so mostly time"),
    Knob("pairs", (Value("list", _same),
                   Value("jaxrt.pairs", _lj_as(LJPairs))),
         quick=("list", "jaxrt.pairs"), scenes=("lj",), dims=(3,),
         what="the LJ forces from `jaxrt.pairs` (pairs with lattice "
              "shifts, searched every step at the cutoff: no skin, no "
              "list kept) against the scene's neighbour list: the same "
              "potential, another search (3D only, as jaxrt.pairs)"),
)
"""Every knob; `knobs` picks those that apply and are available."""


def knobs(kind: str, names: Sequence[str] | None = None,
          dim: int | None = None) -> list[Knob]:
    """The knobs for a scene of ``kind`` (``"lj"`` or ``"sph"``) in ``dim``
    dimensions (any if None) that are available here and have a value to
    run, optionally only ``names``."""
    out = [k for k in KNOBS if kind in k.scenes and k.available()
           and (dim is None or dim in k.dims)
           and k.selected(quick=False, dim=dim)]
    if names:
        unknown = set(names) - {k.name for k in KNOBS}
        if unknown:
            raise ValueError(f"unknown knobs {sorted(unknown)}; known: "
                             f"{[k.name for k in KNOBS]}")
        out = [k for k in out if k.name in names]
    return out



# ---------------------------------------------------------------------------
# Error measures (pure functions of arrays)


def force_rms_rel(force, reference) -> float:
    """``sqrt(mean |F - F_ref|^2) / sqrt(mean |F_ref|^2)`` over particles."""
    f = np.asarray(force, np.float64)
    r = np.asarray(reference, np.float64)
    den = math.sqrt(np.mean(np.sum(r * r, -1)))
    return float(math.sqrt(np.mean(np.sum((f - r) ** 2, -1))) / den)


class Drift(NamedTuple):
    """`energy_drift`'s result: ``slope`` (per particle per ``per``
    steps), ``max_dev`` (``max |E(t) - E(0)| / n``), ``se`` (the slope's
    standard error, from ``blocks`` block means)."""
    slope: float
    max_dev: float
    se: float


def energy_drift(energy, n: int, per: int = 10_000, blocks: int = 10
                 ) -> Drift:
    """The drift of a total-energy series, one value per step: the
    least-squares slope of ``(E(t) - E(0)) / n`` against the step number,
    times ``per`` (drift per particle per ``per`` steps); ``max |E(t) -
    E(0)| / n``; and the slope's standard error: the residual scatter of
    the ``blocks`` block means about their own fitted line (blocks longer
    than the fluctuations' correlation time make the means nearly
    independent), over ``sqrt(sum (t_b - mean t)^2)``, times ``per``."""
    e = (np.asarray(energy, np.float64) - float(energy[0])) / n
    if len(e) < 2:
        return Drift(float("nan"), float(np.abs(e).max(initial=0.0)),
                     float("nan"))
    slope = np.polyfit(np.arange(len(e), dtype=np.float64), e, 1)[0]
    se = float("nan")
    m = len(e) // blocks
    if blocks >= 3 and m >= 1:
        t = np.arange(blocks * m, dtype=np.float64).reshape(blocks, m)
        tb, eb = t.mean(1), e[:blocks * m].reshape(blocks, m).mean(1)
        fit = np.polyfit(tb, eb, 1)
        res = eb - np.polyval(fit, tb)
        se = float(math.sqrt(np.sum(res ** 2) / (blocks - 2))
                   / math.sqrt(np.sum((tb - tb.mean()) ** 2)) * per)
    return Drift(float(slope * per), float(np.abs(e).max()), se)


def _min_image(d, side, periodic):
    side = np.asarray(side, np.float64)
    per = np.asarray(periodic, bool)
    wrap = side * np.round(d / np.where(per, side, 1.0))
    return np.where(per, d - wrap, d)


def _pair_cut(cutoff: float, radii, i, j):
    """The cut of pairs ``(i, j)``: ``cutoff``, or ``max(r_i, r_j)``."""
    if radii is None:
        return cutoff
    return np.maximum(radii[i], radii[j])


def _radii64(radii, n: int):
    if radii is None:
        return None
    r = np.asarray(radii, np.float64)
    if r.shape != (n,):
        raise ValueError(f"radii has shape {r.shape}; the positions have {n} "
                         "particles: pass one radius each.")
    return r


def brute_pairs(position, cutoff: float, side, periodic,
                block: int = 1024, *, radii=None) -> np.ndarray:
    """Sorted codes ``i * n + j`` (i < j) of the pairs closer than
    ``cutoff`` (with ``radii``, float ``(n,)``: closer than ``max(r_i,
    r_j)``, the lists' rule; ``cutoff`` is then unused), float64 brute
    force, minimum image on periodic axes."""
    r = np.asarray(position, np.float64)
    n = len(r)
    radii = _radii64(radii, n)
    codes = []
    for start in range(0, n, block):
        d = _min_image(r[start:start + block, None, :] - r[None], side,
                       periodic)
        rows = np.arange(start, min(start + block, n))
        cut = _pair_cut(cutoff, radii, rows[:, None], np.arange(n)[None])
        i, j = np.nonzero(np.sum(d * d, -1) < cut ** 2)
        i = i + start
        keep = i < j
        codes.append(i[keep].astype(np.int64) * n + j[keep])
    return np.sort(np.concatenate(codes)) if codes else np.zeros(0, np.int64)


def exact_pairs(position, cutoff: float, side, periodic, *, radii=None
                ) -> np.ndarray:
    """`brute_pairs` (``radii`` as there), by scipy's cKDTree in float64
    for large ``n`` (all axes periodic or none); equal to the brute force
    (tested)."""
    r = np.asarray(position, np.float64)
    n = len(r)
    per = np.asarray(periodic, bool)
    if n <= 4096 or (per.any() and not per.all()):
        return brute_pairs(r, cutoff, side, periodic, radii=radii)
    radii = _radii64(radii, n)
    if radii is not None:
        cutoff = float(radii.max())  # the candidates, cut per pair below
    from scipy.spatial import cKDTree
    side = np.asarray(side, np.float64)
    tree = cKDTree(_wrapped(r, side) if per.all() else r,
                   boxsize=side if per.all() else None)
    ij = tree.query_pairs(cutoff, output_type="ndarray").astype(np.int64)
    # query_pairs keeps d <= cutoff; the lists keep d < cutoff.
    d = _min_image(r[ij[:, 0]] - r[ij[:, 1]], side, periodic)
    ij = ij[np.sum(d * d, -1) < _pair_cut(cutoff, radii, ij[:, 0],
                                          ij[:, 1]) ** 2]
    i, j = np.minimum(ij[:, 0], ij[:, 1]), np.maximum(ij[:, 0], ij[:, 1])
    return np.sort(i * n + j)


def pairs_missed(list_codes, reference_codes) -> int:
    """How many pair codes of ``reference_codes`` ``list_codes`` lacks."""
    return int(np.setdiff1d(np.asarray(reference_codes),
                            np.asarray(list_codes)).size)


# A search deciding in the positions' dtype computes each distance from
# rounded inputs (positions plus periodic shifts), rounding each difference
# and product once more: within 16 ulps of that scale, the bound
# tests/test_pairs.py holds jaxrt.pairs' float32 distances to. A pair that
# close to its cut may fall either side, as jax-md's metric decides;
# a deeper miss is a wrong list.
ROUNDING_ULPS = 16.0


def missed_depth_ulps(list_codes, reference_codes, position, cutoff: float,
                      side, periodic, dtype, *, radii=None) -> float:
    """How deep inside its cut the deepest missed pair lies, in ulps (of
    ``dtype``) of the distances' scale: the largest coordinate plus the
    largest periodic side (or the largest cut, if larger); 0.0 when none
    is missed.

    A search deciding in float32, as jax-md's metric decides, may drop a
    pair whose float64 distance is within rounding of the cut: up to
    `ROUNDING_ULPS` that is; a deeper miss is a wrong list. Args: codes as
    `pairs_missed`; ``position`` float ``(n, dim)`` (compared in float64);
    ``radii`` as `brute_pairs`.
    """
    miss = np.setdiff1d(np.asarray(reference_codes), np.asarray(list_codes))
    if miss.size == 0:
        return 0.0
    r = np.asarray(position, np.float64)
    n = len(r)
    i, j = miss // n, miss % n
    d = np.sqrt(np.sum(_min_image(r[i] - r[j], side, periodic) ** 2, -1))
    cut = np.broadcast_to(_pair_cut(cutoff, _radii64(radii, n), i, j),
                          d.shape)
    per = np.asarray(periodic, bool)
    scale = max(float(np.max(cut)), float(np.max(np.abs(r))) + float(
        np.max(np.where(per, np.asarray(side, np.float64), 0.0),
               initial=0.0)))
    return float(np.max(cut - d) / (np.finfo(dtype).eps * scale))


def rdf_grid(r_max: float, dr: float) -> np.ndarray:
    """Bin edges ``0, dr, ..., r_max`` of `rdf`."""
    return np.arange(0.0, r_max + 0.5 * dr, dr)


def rdf(frames, side, edges) -> np.ndarray:
    """g(r) of frames ``(F, N, dim)`` in a periodic box of sides ``side``
    on bin ``edges`` (every axis periodic; ``edges[-1]`` at most half the
    shortest side): pair counts per bin, averaged over frames, over the
    ideal gas's ``N/2 · rho · shell volume``."""
    frames = np.asarray(frames, np.float64)
    if frames.ndim == 2:
        frames = frames[None]
    f, n, dim = frames.shape
    side = np.asarray(side, np.float64)
    counts = np.zeros(len(edges) - 1)
    for r in frames:
        counts += np.histogram(_pair_distances(r, side, edges[-1]),
                               bins=edges)[0]
    rho = n / np.prod(side)
    ball = {1: 2.0, 2: math.pi, 3: 4.0 * math.pi / 3.0}[dim]
    shell = ball * (edges[1:] ** dim - edges[:-1] ** dim)
    return counts / f / (0.5 * n * rho * shell)


def _wrapped(r, side):
    """``r`` in ``[0, side)`` (cKDTree's periodic boxes refuse ``side``)."""
    x = np.mod(r, side)
    return np.where(x >= side, x - side, x)


def _pair_distances(r, side, r_max, kd: bool | None = None):
    """Distances below ``r_max`` of the pairs i < j, minimum image on
    every axis; by cKDTree for large ``n`` (``kd`` forces either way)."""
    n = len(r)
    if kd if kd is not None else n > 4096:
        from scipy.spatial import cKDTree
        ij = cKDTree(_wrapped(r, side), boxsize=side).query_pairs(
            r_max, output_type="ndarray")
        d = _min_image(r[ij[:, 0]] - r[ij[:, 1]], side,
                       np.ones(len(side), bool))
        dist = np.sqrt(np.sum(d * d, -1))
        return dist[dist < r_max]
    out = []
    for start in range(0, n, 1024):
        d = _min_image(r[start:start + 1024, None, :] - r[None], side,
                       np.ones(len(side), bool))
        dist = np.sqrt(np.sum(d * d, -1))
        i, j = np.nonzero(dist < r_max)
        keep = (i + start) < j
        out.append(dist[i[keep], j[keep]])
    return np.concatenate(out)


def rdf_difference(g, g_ref, dr: float) -> tuple[float, float]:
    """``(L2, Linf)``: ``sqrt(sum (g - g_ref)^2 dr)`` and
    ``max |g - g_ref|``."""
    d = np.asarray(g, np.float64) - np.asarray(g_ref, np.float64)
    return float(math.sqrt(np.sum(d * d) * dr)), float(np.abs(d).max())


def position_rms(a, b, side, periodic) -> float:
    """RMS over particles of the (minimum-image) distance between ``a`` and
    ``b``."""
    d = _min_image(np.asarray(a, np.float64) - np.asarray(b, np.float64),
                   side, periodic)
    return float(math.sqrt(np.mean(np.sum(d * d, -1))))


def pareto_front(times, errors) -> list[int]:
    """Indices of the points that no other point beats in both time and
    error (less or equal in both, less in one), by increasing time; NaNs
    are never on the front."""
    t = np.asarray(times, np.float64)
    e = np.asarray(errors, np.float64)
    ok = np.flatnonzero(np.isfinite(t) & np.isfinite(e))
    front = []
    for i in ok:
        beaten = np.any((t[ok] <= t[i]) & (e[ok] <= e[i])
                        & ((t[ok] < t[i]) | (e[ok] < e[i])))
        if not beaten:
            front.append(int(i))
    # Equal points: keep the first.
    seen, out = set(), []
    for i in sorted(front, key=lambda i: (t[i], e[i], i)):
        if (t[i], e[i]) not in seen:
            seen.add((t[i], e[i]))
            out.append(i)
    return out


# ---------------------------------------------------------------------------
# The backend "auto" picks, as the report shows it


def auto_backend_for(scene) -> str:
    """What ``backend="auto"`` resolves to for ``scene`` on this device."""
    import jax
    from jaxrt.lists.neighbors import choose_backend
    from jaxrt.sim import list_radii
    return choose_backend(platform=jax.default_backend(),
                          has_radii=list_radii(scene) is not None,
                          warp=_warp())


# ---------------------------------------------------------------------------
# Scenes, the reference and one measurement


@dataclasses.dataclass(frozen=True)
class Plan:
    """Sizes of a sweep: ``n`` particles (LJ; the dam break's spacing
    ``dx``), ``equilibrate`` steps (float64, before everything), ``steps``
    per run in chunks of ``chunk``, RDF bins of width ``dr`` up to at most
    ``r_max`` over at most ``rdf_frames`` chunk-end frames, evenly
    spaced."""

    n: int = 1000
    dx: float = 0.05
    equilibrate: int = 500
    steps: int = 1000
    chunk: int = 100
    dr: float = 0.05
    r_max: float = 4.0
    rdf_frames: int = 10


QUICK = Plan()
FULL = Plan(n=16_384, dx=0.01, equilibrate=2000, steps=10_000, chunk=500,
            dr=0.02)
"""Full mode's sizes, for a GPU (the H200)."""


SCENES = ("lj-fluid", "lj-fluid-2d", "dam-break")
"""The scenes `run` sweeps (``jaxrt accuracy SCENE``)."""


def lj_fluid_2d(*, n: int = 1000, density: float = 0.7, kT: float = 1.0,
                dt: float = 0.005, backend: str = "cell", seed: int = 0):
    """The LJ fluid in 2D, where the Delaunay backend runs:
    `jaxrt.sim.lj_fluid` with ``dim=2`` at a dense liquid's density (0.7
    at ``kT`` 1). Positions float64 ``(n, 2)``."""
    from jaxrt.sim import lj_fluid
    return lj_fluid(n=n, density=density, kT=kT, dt=dt, backend=backend,
                    seed=seed, dim=2)


def base_scene(name: str, plan: Plan):
    """The scene ``name`` (one of `SCENES`) at the plan's size, float32,
    its backend explicit (``cell``: the base of the backend knob)."""
    from jaxrt import sim
    if name == "lj-fluid":
        scene = sim.lj_fluid(n=plan.n, backend="cell")
    elif name == "lj-fluid-2d":
        scene = lj_fluid_2d(n=plan.n, backend="cell")
    elif name == "dam-break":
        scene = sim.dam_break(dx=plan.dx, backend="cell")
    else:
        raise ValueError(f"accuracy: scene {name!r}: choose one of "
                         f"{', '.join(SCENES)}.")
    return dataclasses.replace(scene, dtype="float32")


def scene_kind(scene) -> str:
    return "lj" if scene.effect("lj") is not None else "sph"


def in_walls(scene, position) -> np.ndarray:
    """``position`` (float64) clipped into ``[0, size]`` on wall axes: a
    particle pressed into a potential wall may sit a little outside it,
    which a scene refuses (`jaxrt.sim.spec`)."""
    r = np.array(position, np.float64)
    for a, b in enumerate(scene.box.boundary):
        if b == "wall":
            r[:, a] = np.clip(r[:, a], 0.0, scene.box.size[a])
    return r


def with_state(scene, position, velocity):
    """``scene`` with its particles at ``position`` / ``velocity``
    (`in_walls`)."""
    p = scene.particles
    return dataclasses.replace(scene, particles=dataclasses.replace(
        p, positions=in_walls(scene, position),
        velocities=np.asarray(velocity, np.float64)))


def equilibrate(scene, steps: int, chunk: int):
    """``(compiled, state, nbrs)`` of the scene in float64 (from its own
    initial state) after ``steps`` steps in chunks of ``chunk``."""
    from jaxrt import sim
    sc = dataclasses.replace(scene, dtype="float64")
    compiled = sim.compile_scene(sc)
    state, nbrs = compiled.init()
    done = 0
    while done < steps:
        k = min(chunk, steps - done)
        state, nbrs = sim.run_chunk(compiled, state, nbrs, steps=k)
        done += k
    return compiled, state, nbrs


def reference_scene(scene):
    """The reference of ``scene``: float64, brute force."""
    return _replace_neighbors(dataclasses.replace(scene, dtype="float64"),
                              backend="brute")


def long_cutoff(scene) -> float | None:
    """``r_ref`` of ``force_rms_rel_full``: 5 sigma, or less where the box
    is shorter (LJ scenes only; None otherwise)."""
    if scene_kind(scene) != "lj":
        return None
    if scene.effect("lj").radii is not None:
        return None  # stretched per pair: no one plain LJ to compare with
    side = min(np.asarray(scene.box.size, float))
    return float(min(5.0, 0.5 * side - scene.neighbors.skin - 0.01))


def reference_forces(scene) -> dict:
    """Float64 brute-force accelerations at the scene's positions: the
    scene's own (``"scene"``) and, for LJ, plain LJ cut at `long_cutoff`
    (``"full"``)."""
    from jaxrt import sim
    out = {"scene": np.asarray(sim.compile_scene(reference_scene(scene))
                               .init()[0].accel)}
    r_ref = long_cutoff(scene)
    if r_ref is not None:
        full = _with_lj("truncated", r_ref)(reference_scene(scene))
        out["full"] = np.asarray(sim.compile_scene(full).init()[0].accel)
    return out


def _periodic_all(scene) -> bool:
    return all(scene.box.periodic)


def rdf_edges(scene, plan: Plan) -> np.ndarray | None:
    if not _periodic_all(scene):
        return None
    r_max = min(plan.r_max, 0.5 * min(scene.box.size))
    return rdf_grid(math.floor(r_max / plan.dr) * plan.dr, plan.dr)


@dataclasses.dataclass
class Measured:
    """One run: the row's numbers and what a reference keeps (frames,
    final positions)."""

    row: dict
    frames: list
    final: np.ndarray | None = None
    rdf: np.ndarray | None = None


def measure(scene, plan: Plan, *, ref_forces: dict, start=None) -> Measured:
    """Run ``scene`` (its particles at the equilibrated state) for
    ``plan.steps`` steps in chunks, timing each chunk and checking its
    list against the brute force after it; the row's measures (module
    docstring) except those against the reference run (`finish_row`).
    ``start``: ``(compiled, state, nbrs)`` to continue instead of
    compiling ``scene`` (the reference continues its equilibration)."""
    import jax
    from jaxrt import sim
    from jaxrt.layouts.codes import pair_codes
    if start is None:
        compiled = sim.compile_scene(scene)
        state, nbrs = compiled.init()
    else:
        compiled, state, nbrs = start
    rebuilds0 = int(state.rebuilds)
    n = scene.particles.n
    own = _own_search(scene)  # a list-free effect's pairs, checked too
    radii = sim.list_radii(scene)  # a list with radii: max(r_i, r_j) each
    triangulated = 0  # Delaunay rebuilds of lists replaced after overflow
    row = {"force_rms_rel": force_rms_rel(state.accel,
                                          ref_forces["scene"])}
    if "full" in ref_forces:
        row["force_rms_rel_full"] = force_rms_rel(state.accel,
                                                  ref_forces["full"])
    side = np.asarray(scene.box.size, float)
    periodic = scene.box.periodic
    frames, energies, times = [], [], []
    missed = checked = overflows = 0
    depth = 0.0
    done = 0
    while done < plan.steps:
        k = min(plan.chunk, plan.steps - done)
        t = time.perf_counter()
        new_state, new_nbrs, trace = compiled.chunk(state, nbrs, steps=k)
        jax.block_until_ready(new_state.position)
        dt = time.perf_counter() - t
        if new_nbrs is not None and new_nbrs.did_buffer_overflow:
            overflows += 1
            triangulated += _triangulation_rebuilds(nbrs) or 0
            nbrs = compiled.neighbor_fn.allocate(state.position)
            new_state, new_nbrs, trace = compiled.chunk(state, nbrs,
                                                        steps=k)
            jax.block_until_ready(new_state.position)
            if new_nbrs.did_buffer_overflow:
                raise RuntimeError("the list overflowed twice in a chunk")
        elif done > 0 and k == plan.chunk:
            times.append(dt / k)
        state, nbrs = new_state, new_nbrs
        done += k
        pos = np.asarray(state.position, np.float64)
        if not np.all(np.isfinite(pos)):
            raise RuntimeError(f"positions became non-finite by step "
                               f"{done}")
        frames.append(pos)
        energies.append(np.asarray(trace.kinetic, np.float64)
                        + np.asarray(trace.potential, np.float64))
        if nbrs is not None or own is not None:
            want = exact_pairs(pos, own[0] if own else scene.cutoff, side,
                               periodic, radii=None if own else radii)
            got = own[1](pos) if own else pair_codes(nbrs, n)
            missed += pairs_missed(got, want)
            depth = max(depth, missed_depth_ulps(
                got, want, pos, own[0] if own else scene.cutoff, side,
                periodic, state.position.dtype,
                radii=None if own else radii))
            checked += len(want)
    if nbrs is not None:
        from jaxrt.errors import check
        check(nbrs)
    if not times:  # a run of one chunk: its time, compilation included
        times = [dt / k]
    row.update(time_per_step_ms=1e3 * float(np.median(times)),
               time_min_ms=1e3 * float(np.min(times)),
               time_max_ms=1e3 * float(np.max(times)), repeats=len(times),
               rebuilds=int(state.rebuilds) - rebuilds0, overflows=overflows,
               steps=done)
    row["time_per_tau_ms"] = row["time_per_step_ms"] / scene.integrator.dt
    if compiled.conservative:
        d = energy_drift(np.concatenate(energies), n)
        row.update(drift_per_particle_1e4=d.slope, drift_se=d.se,
                   max_abs_dE_per_particle=d.max_dev)
    if nbrs is not None or own is not None:
        row.update(pairs_missed=missed, missed_depth_ulps=depth,
                   pairs_checked=checked,
                   k=2.0 * checked / len(frames) / n)
    tri = _triangulation_rebuilds(nbrs)
    if tri is not None:
        row["triangulation_rebuilds"] = triangulated + tri
    return Measured(row, frames, frames[-1])


def _own_search(scene):
    """``(cutoff, codes(position))`` of the scene's list-free effect that
    searches pairs of its own (`LJPairs`), or None: its pairs are checked
    against the brute force as a list's are."""
    for e in scene.effects:
        if hasattr(e, "pair_checker"):
            return e.cutoff, e.pair_checker(scene)
    return None


def _triangulation_rebuilds(nbrs) -> int | None:
    """Rebuilds from scratch of a Delaunay list's triangulation since its
    ``allocate`` (`jaxrt.delaunay.stats`); None for other lists."""
    from jaxrt.backends import delaunay
    if not isinstance(getattr(nbrs, "backend_state", None),
                      delaunay.Triangulation):
        return None
    return int(delaunay.stats(nbrs)["rebuilds"])


def finish_row(m: Measured, ref: Measured, scene, plan: Plan,
               setting=None) -> dict:
    """The measures against the reference run: RDF, final positions (only
    for a ``setting`` at the reference's time step: after the same number
    of steps of another dt the positions are at another time)."""
    row = dict(m.row)
    edges = rdf_edges(scene, plan)
    if edges is not None:
        g = rdf(_every(m.frames, plan.rdf_frames), scene.box.size, edges)
        if ref.rdf is None:
            ref.rdf = rdf(_every(ref.frames, plan.rdf_frames),
                          scene.box.size, edges)
        g_ref = ref.rdf
        row["rdf_l2"], row["rdf_linf"] = rdf_difference(g, g_ref, plan.dr)
    if setting is None or setting.integrator.dt == scene.integrator.dt:
        row["position_rms"] = position_rms(m.final, ref.final,
                                           scene.box.size, scene.box.periodic)
    return row


def _depth(row) -> str:
    """How deep the missed pairs lay, for the summary ('' when unknown)."""
    depth = _num(row, "missed_depth_ulps")
    if not np.isfinite(depth):
        return ""
    why = (": rounding of the distance in the positions' dtype, as "
           "jax-md's metric decides" if depth <= ROUNDING_ULPS else
           ": deeper than rounding, a wrong list")
    return f"; the deepest {_fmt(depth)} ulps inside the cut{why}"


def _every(frames: list, most: int) -> list:
    """At most ``most`` of ``frames``, evenly spaced, the last included."""
    if len(frames) <= most:
        return frames
    pick = np.round(np.linspace(len(frames) - 1, 0, most)).astype(int)
    return [frames[i] for i in sorted(set(pick))]


def rdf_noise(ref: Measured, scene, plan: Plan) -> float | None:
    """L2 difference between the RDFs of the reference run's two halves."""
    edges = rdf_edges(scene, plan)
    if edges is None or len(ref.frames) < 2:
        return None
    frames = _every(ref.frames, plan.rdf_frames)
    h = len(frames) // 2
    return rdf_difference(rdf(frames[:h], scene.box.size, edges),
                          rdf(frames[h:], scene.box.size, edges),
                          plan.dr)[0]


def _describe(scene) -> dict:
    """The setting's own columns (what the row ran with)."""
    nb = scene.neighbors
    backend = nb.backend
    if not isinstance(backend, str):
        policy = getattr(backend, "policy", None)
        classes = getattr(backend, "radius_classes", None)
        backend = backend.name + (f"[{type(policy).__name__.lower()}]"
                                  if policy is not None else "") + (
            f"[radius_classes={classes}]" if classes is not None else "")
    if not scene.pair_effects:  # the search of the list-free effect
        backend = next((e.search for e in scene.effects
                        if hasattr(e, "search")), "none (list-free)")
    out = {"N": scene.particles.n, "dtype": scene.dtype,
           "backend": backend,
           "format": nb.format, "skin": nb.skin,
           "capacity_multiplier": nb.capacity_multiplier,
           "dt": scene.integrator.dt,
           # A list-free effect's own cutoff (no list: scene.cutoff is 0).
           "cutoff": scene.cutoff or max(
               (e.cutoff for e in scene.effects if hasattr(e, "search")),
               default=0.0)}
    lj = next((e for e in scene.effects if e.kind.startswith("lj")), None)
    if lj is not None:
        out["truncation"] = lj.truncation
    return out


def _key(scene, value: Value) -> str:
    """Identical settings (the base, reached by several knobs) run once."""
    return repr((scene.dtype, repr(scene.neighbors), repr(scene.effects),
                 scene.integrator))


# ---------------------------------------------------------------------------
# Outputs

ERRORS = (("force_rms_rel", "force RMS error (rel., vs float64 same "
           "potential)"),
          ("force_rms_rel_full", "force RMS error (rel., vs float64 LJ to "
           "r_ref)"),
          ("drift_per_particle_1e4", "|energy drift| per particle per 1e4 "
           "steps"),
          ("max_abs_dE_per_particle", "max |E(t) - E(t1)| / N"),
          ("pairs_missed", "pairs missed (vs float64 brute force)"),
          ("rdf_l2", "RDF L2 difference"),
          ("position_rms", "final position RMS deviation"))
"""The error columns, with the axis label of each."""

COLUMNS = ("scene", "knob", "value", "status", "failed", "time_per_step_ms",
           "time_min_ms", "time_max_ms", "repeats", "time_per_tau_ms",
           "force_rms_rel", "force_rms_rel_full", "drift_per_particle_1e4",
           "drift_se", "max_abs_dE_per_particle", "pairs_missed",
           "missed_depth_ulps", "pairs_checked", "rdf_l2", "rdf_linf",
           "position_rms", "rebuilds", "triangulation_rebuilds", "overflows",
           "steps", "N", "k", "dtype", "backend", "format", "skin",
           "capacity_multiplier", "dt",
           "cutoff", "truncation", "auto_backend")
"""The CSV's columns, then `PROVENANCE`."""


def write_csv(rows: list[dict], path: pathlib.Path) -> pathlib.Path:
    """All rows (`COLUMNS`, any others, then `PROVENANCE`), rewritten
    whole (via a temporary file) so an interrupted run keeps its rows."""
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    extra = [k for r in rows for k in r
             if k not in COLUMNS and k not in PROVENANCE]
    fields = list(COLUMNS) + list(dict.fromkeys(extra)) + [
        c for c in PROVENANCE if any(c in r for r in rows)]
    tmp = path.with_suffix(".tmp")
    with open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: _cell(v) for k, v in r.items()})
    tmp.replace(path)
    return path


def _cell(v):
    if isinstance(v, float):
        return "" if math.isnan(v) else f"{v:.6g}"
    return v


def _num(row: dict, col: str) -> float:
    v = row.get(col)
    try:
        return float(v)
    except (TypeError, ValueError):
        return float("nan")


def _err(row: dict, col: str) -> float:
    v = _num(row, col)
    return abs(v) if col == "drift_per_particle_1e4" else v


def plot_knob(rows: list[dict], knob: str, path: pathlib.Path
              ) -> pathlib.Path | None:
    """``path``: one panel per error column that varies, each error
    against the time per step (per unit of simulated time for ``dt``),
    every value labelled, the Pareto front
    drawn (the drift with ± one standard error); errors equal for every
    value are named in the title instead."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    mine = [r for r in rows if r["knob"] == knob and r.get("status") == "ok"]
    if not mine:
        return None
    cols, same = [], []
    for c, label in ERRORS:
        v = [_err(r, c) for r in mine]
        if not any(np.isfinite(v)):
            continue
        if len(mine) > 1 and all(x == v[0] for x in v):
            same.append(f"{c} = {_fmt(v[0])}")
        else:
            cols.append((c, label))
    if not cols:
        cols = [("force_rms_rel", dict(ERRORS)["force_rms_rel"])]
    ncol = 2 if len(cols) > 1 else 1
    nrow = math.ceil(len(cols) / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(5.2 * ncol, 3.4 * nrow),
                             squeeze=False)
    # The time step's cost is per unit of simulated time, not per step.
    xcol, xlabel = (("time_per_tau_ms", "time per unit of simulated time "
                     "(ms)") if knob == "dt" else
                    ("time_per_step_ms", "time per step (ms)"))
    t = np.array([_num(r, xcol) for r in mine])
    for ax, (col, label) in zip(axes.ravel(), cols):
        e = np.array([_err(r, col) for r in mine])
        if col == "drift_per_particle_1e4":
            se = np.array([_num(r, "drift_se") for r in mine])
            ax.errorbar(t, e, yerr=np.where(np.isfinite(se), se, 0),
                        fmt="o", color="C0", ms=5, capsize=2, zorder=3)
        else:
            ax.scatter(t, e, color="C0", zorder=3)
        for r, x, y in zip(mine, t, e):
            if np.isfinite(y):
                ax.annotate(str(r["value"]), (x, y), fontsize=7,
                            xytext=(3, 3), textcoords="offset points")
        front = pareto_front(t, e)
        if front:
            ax.step(t[front], e[front], where="post", color="C3", lw=1.2,
                    label="Pareto front", zorder=2)
            ax.scatter(t[front], e[front], facecolors="none",
                       edgecolors="C3", s=80, zorder=4)
            ax.legend(fontsize=7)
        pos = e[np.isfinite(e) & (e > 0)]
        if pos.size and pos.max() / pos.min() > 20:
            if np.all(e[np.isfinite(e)] > 0):
                ax.set_yscale("log")
            else:
                ax.set_yscale("symlog", linthresh=pos.min())
        ax.set_xlabel(xlabel)
        ax.set_ylabel(label, fontsize=8)
        ax.grid(alpha=0.3)
    for ax in axes.ravel()[len(cols):]:
        ax.set_visible(False)
    title = f"{mine[0]['scene']}: knob {knob}"
    if same:
        title += "\nthe same for every value: " + ", ".join(same)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=72)
    plt.close(fig)
    return path


TARGETS = (("drift_per_particle_1e4", (1e-3, 1e-4),
            "an energy drift resolved below {x:g} per particle per 10^4 "
            "steps (|drift| + 2 standard errors)"),
           ("max_abs_dE_per_particle", (1e-3, 1e-4),
            "energy excursions max |E(t) - E(t1)| / N below {x:g}"),
           ("force_rms_rel", (1e-3, 1e-6),
            "a force RMS error below {x:g} (relative, vs float64 of the "
            "same potential)"),
           ("force_rms_rel_full", (1e-2, 1e-3),
            "a force RMS error below {x:g} against LJ cut at r_ref"))
"""Targets of the summary's sentences: (column, thresholds, phrase)."""

NOT_FOR = {"force_rms_rel": ("dt",), "force_rms_rel_full": ("dt",)}
"""Knobs a target does not judge: the force at one configuration does not
depend on the time step (its cost shows in the energy instead)."""


def _fmt(v) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if v == 0:
        return "0"
    return f"{v:.3g}"


def _setting(r: dict) -> str:
    return f"`{r['knob']} = {r['value']}`"


def _bound(r: dict, col: str) -> float:
    """The error a target compares: the drift's |slope| + 2 standard
    errors (a drift resolved below the target), else the error itself."""
    if col == "drift_per_particle_1e4":
        return abs(_num(r, col)) + 2 * _num(r, "drift_se")
    return _err(r, col)


def cheapest(rows: list[dict], col: str, below: float) -> dict | None:
    """The ok row, fastest per unit of simulated time, whose error ``col``
    (`_bound`) is below ``below`` (rows of the knobs `NOT_FOR` excludes
    left out)."""
    ok = [r for r in rows if r.get("status") == "ok"
          and r["knob"] not in NOT_FOR.get(col, ())
          and _bound(r, col) < below
          and np.isfinite(_num(r, "time_per_tau_ms"))]
    return min(ok, key=lambda r: _num(r, "time_per_tau_ms"), default=None)


def _cost(r: dict) -> str:
    return (f"{_fmt(_num(r, 'time_per_step_ms'))} ms per step, "
            f"{_fmt(_num(r, 'time_per_tau_ms'))} ms per unit of time")


def summary_lines(rows: list[dict], meta: dict) -> list[str]:
    """The Markdown summary: what was run, the sentences, the table."""
    table = rows
    rows = [r for r in rows if r["knob"] != "reference"]
    ok = [r for r in rows if r.get("status") == "ok"]
    L = [f"# What accuracy costs in time: {meta['scene']}", ""]
    L.append(f"{meta['scene']}, N = {meta['N']}, {meta['steps']} steps per "
             f"run (chunks of {meta['chunk']}), on {meta.get('device', '?')}"
             f", git {meta.get('git_sha', '?')}, {meta.get('date', '?')}"
             f"{meta.get('load', '')}. "
             f"Base setting: {meta['base']}. Each row changes one knob from "
             "the base. Reference: the same scene in float64 from the same "
             "equilibrated state (its list by `cell`; its forces by a float64 "
             "brute force). \"Cheapest\" ranks by time per unit of simulated "
             "time (time per step / dt), which orders every knob but `dt` "
             "as the time per step does.")
    if meta.get("own_scenes"):
        L.append("")
        L.append("Knobs run elsewhere: " + "; ".join(meta["own_scenes"])
                 + " (its reference row: `reference = float64, <scene>`).")
    if not meta.get("only_own_scenes"):  # else stated with its scene
        L.append("")
        L.append(f"`backend=\"auto\"` chose **{meta['auto']}** for this "
                 "scene on this device (`jaxrt.neighbors.choose_backend`).")
    backends_ok = [r for r in ok if r["knob"] == "backend"]
    if backends_ok:
        fastest = min(backends_ok, key=lambda r: _num(r, "time_per_step_ms"))
        auto_row = next((r for r in backends_ok if r["value"] == meta["auto"]),
                        None)
        L.append(f"The fastest backend measured here was "
                 f"`{fastest['value']}` "
                 f"({_fmt(_num(fastest, 'time_per_step_ms'))} ms per step)"
                 + (f"; auto's `{meta['auto']}` took "
                    f"{_fmt(_num(auto_row, 'time_per_step_ms'))} ms."
                    if auto_row is not None and auto_row is not fastest
                    else "."))
    L.append("")
    L.append("## What to choose")
    L.append("")
    for col, thresholds, phrase in TARGETS:
        if not any(np.isfinite(_bound(r, col)) for r in ok):
            continue
        for x in thresholds:
            best = cheapest(ok, col, x)
            if best is None:
                hint = ""
                if col == "drift_per_particle_1e4":
                    se = min(_num(r, "drift_se") for r in ok)
                    hint = (f" (the smallest standard error of a drift here "
                            f"is {_fmt(se)} per 10^4 steps: runs of "
                            f"{meta['steps']} steps cannot resolve much "
                            "less)")
                L.append(f"- For {phrase.format(x=x)}: no setting measured "
                         f"meets it{hint}.")
            else:
                L.append(f"- For {phrase.format(x=x)}, the cheapest setting "
                         f"is {_setting(best)}: {_cost(best)} "
                         f"({col} = {_fmt(_num(best, col))}).")
    if any(np.isfinite(_num(r, "pairs_missed")) for r in ok):
        lossy = [r for r in ok if _num(r, "pairs_missed") > 0]
        if lossy:
            L.append("- Settings whose list missed pairs: " + ", ".join(
                f"{_setting(r)} ({_fmt(_num(r, 'pairs_missed'))} of "
                f"{_fmt(_num(r, 'pairs_checked'))}{_depth(r)})"
                for r in lossy) + ".")
        else:
            L.append("- No setting's list missed a pair (checked against a "
                     "float64 brute force after every chunk, with radii at "
                     "max(r_i, r_j)): the list knobs (skin, format, "
                     "backend, cell kernel, Delaunay's options, BVH policy, "
                     "ε, jaxrt.pairs, radii) trade time only.")
    by_knob = meta.get("rdf_noise_by_knob") or {}

    def floor(r):
        v = by_knob.get(r["knob"], meta.get("rdf_noise"))
        return math.nan if v is None else v
    floors = [f"{_fmt(meta['rdf_noise'])} (L2)"] if meta.get(
        "rdf_noise") is not None else []
    floors += [f"{_fmt(v)} for `{k}`'s own scene" for k, v in by_knob.items()
               if v is not None]
    if floors and any(np.isfinite(_num(r, "rdf_l2")) for r in ok):
        above = [r for r in ok if _num(r, "rdf_l2") > 2 * floor(r)]
        L.append(f"- The RDFs of the reference run's two halves differ by "
                 f"{', '.join(floors)}: the noise floor. Settings beyond "
                 "twice that: " + (", ".join(
                     f"{_setting(r)} ({_fmt(_num(r, 'rdf_l2'))})"
                     for r in above) if above else "none") + ".")
    bad = [r for r in rows if r.get("status") != "ok"]
    if bad:
        L.append("- Not measured: " + "; ".join(
            f"{_setting(r)} ({r.get('status')}: "
            f"{str(r.get('failed', ''))[:100]})" for r in bad) + ".")
    L.append("")
    L.append("## Per knob")
    L.append("")
    whats = {k.name: k.what for k in KNOBS}
    L.append("What each knob varies: " + "; ".join(
        f"**{k}**: {whats[k]}" for k in dict.fromkeys(r["knob"] for r in rows)
        if whats.get(k)) + ".")
    L.append("")
    judges = {k.name: k.judge for k in KNOBS}
    for knob in dict.fromkeys(r["knob"] for r in rows):
        mine = [r for r in ok if r["knob"] == knob]
        if not mine:
            continue
        judge = judges.get(knob, "force_rms_rel")
        if not any(np.isfinite(_err(r, judge)) for r in mine):
            fast = min(mine, key=lambda r: _num(r, "time_per_tau_ms"))
            L.append(f"- **{knob}**: no error measure here applies to it "
                     f"(no energy in this scene); fastest `{fast['value']}` "
                     f"({_cost(fast)}).")
            continue
        t = [_num(r, "time_per_tau_ms") for r in mine]
        e = [_err(r, judge) for r in mine]
        front = [mine[i] for i in pareto_front(t, e)]
        fast = min(mine, key=lambda r: _num(r, "time_per_tau_ms"))
        best = min(mine, key=lambda r: (_err(r, judge)
                                        if np.isfinite(_err(r, judge))
                                        else math.inf))
        # Values without the measure (a list-free value's pairs) do not
        # make the others differ.
        measured = [_err(r, judge) for r in mine
                    if np.isfinite(_err(r, judge))]
        if all(v == measured[0] for v in measured):
            some = "" if len(measured) == len(mine) else " that has it"
            L.append(f"- **{knob}** ({judge} the same for every value{some}"
                     f", {_fmt(measured[0])}): fastest "
                     f"`{fast['value']}` ({_cost(fast)}).")
            continue
        L.append(f"- **{knob}** (by {judge}): fastest `{fast['value']}` "
                 f"({_cost(fast)}; {_fmt(_err(fast, judge))}); most "
                 f"accurate `{best['value']}` ({_cost(best)}; "
                 f"{_fmt(_err(best, judge))}); Pareto front: " + ", ".join(
                     f"`{r['value']}`" for r in front) + ".")
    L.append("")
    L.append("## All rows")
    L.append("")
    rows = table
    cols = ["time_per_step_ms", "force_rms_rel", "force_rms_rel_full",
            "drift_per_particle_1e4", "drift_se", "max_abs_dE_per_particle",
            "pairs_missed", "rdf_l2", "position_rms", "rebuilds",
            "triangulation_rebuilds"]
    cols = [c for c in cols if any(np.isfinite(_num(r, c)) for r in rows)]
    heads = {"time_per_step_ms": "ms/step", "force_rms_rel": "force err",
             "force_rms_rel_full": "force err vs r_ref",
             "drift_per_particle_1e4": "drift /N/1e4 steps",
             "drift_se": "± (s.e.)", "max_abs_dE_per_particle": "max |ΔE|/N",
             "pairs_missed": "missed", "rdf_l2": "RDF L2",
             "position_rms": "pos. RMS", "rebuilds": "rebuilds",
             "triangulation_rebuilds": "DT rebuilds"}
    L.append("| knob | value | " + " | ".join(heads[c] for c in cols)
             + " | status |")
    L.append("| --- | --- | " + " | ".join("---" for _ in cols) + " | --- |")
    for r in rows:
        vals = [_fmt(_num(r, c)) if c not in ("pairs_missed", "rebuilds",
                                              "triangulation_rebuilds")
                or not np.isfinite(_num(r, c)) else str(int(_num(r, c)))
                for c in cols]
        L.append(f"| {r['knob']} | {r['value']} | " + " | ".join(vals)
                 + f" | {r.get('status')} |")
    L.append("")
    L.append("Definitions: `jaxrt/accuracy.py`'s docstring. Drift: the "
             "least-squares slope of (E(t) − E(t₁))/N over the run, scaled "
             f"to 10⁴ steps (runs of {meta['steps']} steps), ± its standard "
             "error from 10 block means. Times: median over the run's "
             "chunks, compilation excluded.")
    return L


def write_summary(rows: list[dict], meta: dict, path: pathlib.Path
                  ) -> pathlib.Path:
    pathlib.Path(path).write_text("\n".join(summary_lines(rows, meta)) + "\n")
    return path


# ---------------------------------------------------------------------------
# The sweep


def _load() -> float | None:
    try:
        return os.getloadavg()[0]
    except (AttributeError, OSError):
        return None


def run(scene_name: str = "lj-fluid", *, out, quick: bool = False,
        budget: float | None = None, plan: Plan | None = None,
        knob_names: Sequence[str] | None = None,
        log: Callable[[str], None] = print) -> list[dict]:
    """Sweep the knobs on ``scene_name`` and write ``accuracy.csv``, one
    PNG per knob and ``summary.md`` into ``out``; returns the rows.

    ``quick``: `QUICK` sizes and each knob's ``quick`` values (a CPU in a
    few minutes); else `FULL` sizes and every value. ``plan`` overrides the
    sizes. ``budget``: seconds; once spent, no new setting starts and the
    rest are written as ``skipped`` (rows done are kept).
    """
    import jax
    # The float64 reference needs x64; the caller's setting is restored
    # after the run (a library call must not switch a process-wide flag).
    before = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore",
                                    message="Explicitly requested dtype")
            return _run(scene_name, out=out, quick=quick, budget=budget,
                        plan=plan, knob_names=knob_names, log=log)
    finally:
        jax.config.update("jax_enable_x64", before)


def _run(scene_name: str, *, out, quick: bool, budget, plan, knob_names,
         log) -> list[dict]:
    import jax
    t0 = time.perf_counter()
    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    plan = plan or (QUICK if quick else FULL)
    base = base_scene(scene_name, plan)
    kind, dim = scene_kind(base), base.particles.dim
    chosen = knobs(kind, knob_names, dim)
    prov = provenance()
    # Knobs on the sweep's base first, then each own scene (Knob.own_scene)
    # with its own reference; a knob's rows follow its reference row.
    groups: dict = {}
    for knob in chosen:
        groups.setdefault(knob.own_scene, []).append(knob)
    groups = dict(sorted(groups.items(), key=lambda kv: kv[0] is not None))
    log(f"accuracy: {scene_name}, N = {base.particles.n}, {plan.steps} steps"
        f" per run, knobs {[k.name for k in chosen]}, auto -> "
        f"{auto_backend_for(base)}")
    load0 = _load()
    csv_path = out / "accuracy.csv"
    rows: list[dict] = []
    noise: dict = {}
    own: list[str] = []
    first = None
    for hook, members in groups.items():
        scene = members[0].base_for(base, plan)
        auto = auto_backend_for(scene)
        if first is None:
            first = (scene, auto)
        if hook is not None:
            own.append(f"{', '.join(f'`{k.name}`' for k in members)} on "
                       f"its own scene, {scene.description} "
                       f"(`{hook.__name__}`; `backend=\"auto\"` chose "
                       f"**{auto}** for it), against its own float64 run")
        _sweep_group(scene, members, hook, rows=rows, plan=plan, quick=quick,
                     budget=budget, t0=t0,
                     # An own scene's rows (and plot titles) name it.
                     common={"scene": scene.name if hook is not None
                             else scene_name, "auto_backend": auto, **prov},
                     noise=noise, csv_path=csv_path, log=log)
    write_csv(rows, csv_path)
    for knob in chosen:
        plot_knob(rows, knob.name, out / f"{knob.name}.png")
    load1 = _load()
    scene, auto = first if first is not None else (base, auto_backend_for(base))
    meta = {"scene": scene_name, "N": scene.particles.n, "steps": plan.steps,
            "load": (f", CPU load average {load0:.1f} at the start and "
                     f"{load1:.1f} at the end (on {os.cpu_count()} cores: "
                     "other work shares them, so compare times loosely)"
                     if load0 is not None and jax.default_backend() == "cpu"
                     else ""),
            "chunk": plan.chunk, "auto": auto,
            "rdf_noise": noise.get(None), "rdf_noise_by_knob": {
                k.name: noise[k.own_scene] for k in chosen
                if k.own_scene is not None and k.own_scene in noise},
            "own_scenes": own,
            "base": ", ".join(f"{k} {v}" for k, v in _describe(
                dataclasses.replace(scene, dtype="float32")).items()
                if k != "N"), **prov}
    if None not in groups:  # only knobs of their own scenes ran
        meta["base"] = f"{scene.name}'s ({meta['base']}; see below)"
        meta["rdf_noise"] = None
        meta["only_own_scenes"] = True
    write_summary(rows, meta, out / "summary.md")
    log(f"accuracy: {len(rows)} rows in {time.perf_counter() - t0:.0f} s -> "
        f"{out}")
    return rows


def _spent(budget, t0: float) -> bool:
    return budget is not None and time.perf_counter() - t0 > budget


def _sweep_group(base, members, hook, *, rows: list, plan: Plan,
                 quick: bool, budget, t0: float, common: dict, noise: dict,
                 csv_path, log) -> None:
    """Append to ``rows`` (and rewrite ``csv_path`` after each) the
    reference run of ``base`` and the rows of the knobs ``members`` (those
    whose `Knob.base_for` is ``base``); the reference row's value is
    ``float64`` (``float64, <scene name>`` for an own scene). Sets
    ``noise[hook]`` (`rdf_noise`). An own scene whose turn comes after the
    budget is spent runs nothing, not even its reference."""
    dim = base.particles.dim
    if hook is not None and _spent(budget, t0):
        rows += [{**common, "knob": k.name, "value": v.label,
                  "status": "skipped", "failed": f"budget of {budget:g} s "
                  "spent"} for k in members for v in k.selected(quick, dim)]
        write_csv(rows, csv_path)
        return
    start = None
    if plan.equilibrate:  # the reference run continues the equilibration
        start = equilibrate(base, plan.equilibrate, plan.chunk)
        base = with_state(base, start[1].position, start[1].velocity)
        if not np.array_equal(base.particles.positions,
                              np.asarray(start[1].position)):
            start = None  # clipped into the walls: start the reference anew
    ref_forces = reference_forces(base)
    ref_scene = dataclasses.replace(base, dtype="float64")
    ref = measure(ref_scene, plan, ref_forces=ref_forces, start=start)
    noise[hook] = rdf_noise(ref, base, plan)
    label = "float64" if hook is None else f"float64, {base.name}"
    rows.append({**common, "knob": "reference", "value": label,
                 "status": "ok", **_describe(ref_scene),
                 **finish_row(ref, ref, base, plan)})
    write_csv(rows, csv_path)
    log(f"  reference {label} done ({time.perf_counter() - t0:.0f} s)")
    # Settings two knobs reach run once; keys are per base scene (they do
    # not hold the particles).
    done: dict[str, dict] = {_key(ref_scene, Value("", _same)): rows[-1]
                             | {"knob": None, "value": None}}
    for k in ("knob", "value", "status", "scene", "auto_backend",
              *PROVENANCE):
        done[next(iter(done))].pop(k, None)
    for knob in members:
        for value in knob.selected(quick, dim):
            row = {**common, "knob": knob.name, "value": value.label}
            if _spent(budget, t0):
                rows.append({**row, "status": "skipped",
                             "failed": f"budget of {budget:g} s spent"})
                continue
            try:
                sc = value.apply(base)
                row.update(_describe(sc))
                key = _key(sc, value)
                if key not in done:
                    m = measure(sc, plan, ref_forces=ref_forces)
                    done[key] = finish_row(m, ref, base, plan, sc)
                row.update(status="ok", **done[key])
            except Exception as e:  # noqa: BLE001 - recorded in the row
                row.update(status="error",
                           failed=f"{type(e).__name__}: {e}"[:300])
            rows.append(row)
            log(f"  {knob.name} = {value.label}: {row['status']} "
                f"{_fmt(_num(row, 'time_per_step_ms'))} ms/step "
                f"({time.perf_counter() - t0:.0f} s)")
            write_csv(rows, csv_path)
