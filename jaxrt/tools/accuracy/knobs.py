"""The accuracy sweep's knobs, as data: `Knob` (a name, its `Value`\\s, the
scenes and dimensions it applies to, whether it is available here),
`KNOBS` and `knobs`, and the effects a knob puts in place of a scene's LJ
(`LJFused`, `LJPairs`)."""
from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np

from jaxrt.sim.effects import LJFields

if TYPE_CHECKING:
    from jaxrt.tools.accuracy.scenes import Plan


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


def replace_neighbors(scene, **kw):
    return dataclasses.replace(scene, neighbors=dataclasses.replace(
        scene.neighbors, **kw))


def _with_dtype(dtype: str):
    return lambda s: dataclasses.replace(s, dtype=dtype)


_BY_OBJECT = ("bvh", "spheres", "squares")
"""Backends a knob passes as objects: then "bvh" is Bvh(policy="drift")'s
run, found again under its options (a setting two knobs reach runs once,
`row_key`)."""


def _with_backend(backend, dtype: str | None = None):
    def apply(s):
        b = backend
        if b in _BY_OBJECT:
            from jaxrt.backends import resolve
            b = resolve(b)
        s = replace_neighbors(s, backend=b)
        return dataclasses.replace(s, dtype=dtype) if dtype else s
    return apply


def with_lj(truncation: str, cutoff: float):
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
    return lambda s: replace_neighbors(s, skin=s.neighbors.skin * factor)


def _with_dt(factor: float):
    """Time step as a multiple of the scene's own."""
    return lambda s: dataclasses.replace(s, integrator=dataclasses.replace(
        s.integrator, dt=s.integrator.dt * factor))


def _with_bvh_policy(policy: str):
    def apply(s):
        from jaxrt.backends import Bvh
        return replace_neighbors(s, backend=Bvh(policy=policy))
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
        s = replace_neighbors(s, backend=Delaunay(
            max_flip_rounds=max_flip_rounds, max_splits=max_splits),
            capacity_multiplier=DELAUNAY_CAPACITY)
        return dataclasses.replace(s, dtype="float64")
    return apply


def _with_cell_kernel(kernel: str):
    def apply(s):
        from jaxrt.backends import Cell
        return replace_neighbors(s, backend=Cell(kernel=kernel))
    return apply


def warp_here() -> bool:
    import jaxrt
    return "bvh" in jaxrt.available_backends()


def _has_fused() -> bool:
    import jaxrt.energy
    return hasattr(jaxrt.energy, "lennard_jones_fused")


def pallas_here() -> bool:
    """Whether the cell list's Pallas kernel can run here: a CUDA GPU and a
    JAX with Pallas' Triton backend (`jaxrt.backends.cell.kernel`). Pallas'
    interpreter runs anywhere but is far too slow for a sweep."""
    import jax
    from jaxrt.backends.cell import kernel as _cell_kernel
    return (jax.default_backend() in ("gpu", "cuda")
            and _cell_kernel.plgpu is not None)


def fused_takes(backend) -> bool:
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
        return pallas_here() and fused_takes(Cell(kernel=kernel))
    return available


def lj_as(cls, **options):
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
    return lj_as(LJFused, backend=backend)


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


def unchanged(s):
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
        return replace_neighbors(s, backend=Cell(radius_classes=classes))
    return apply


def _eps(e: int) -> Value:
    def apply(s):
        from jaxrt.backends import Spheres
        return replace_neighbors(s, backend=Spheres(epsilon_relative=2.0 ** -e))
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
        Value(f"{t} {c:g}", with_lj(t, c))
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
    Knob("format", tuple(Value(f, lambda s, f=f: replace_neighbors(
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
         quick=("auto", "xla", "pallas"), available=pallas_here,
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
         quick=("float32", "float64"), available=warp_here,
         what="bvh under float32 or float64 positions (the BVH itself is "
              "float32, padded; the exact test in the positions' dtype)",
         judge="force_rms_rel"),
    Knob("bvh-policy", tuple(Value(p, _with_bvh_policy(p)) for p in
                             ("rebuild", "drift", "fixed", "avg",
                              "gradient")),
         quick=("rebuild", "drift"), available=warp_here,
         what="when the kept BVH is rebuilt rather than refit"),
    Knob("spheres-epsilon", tuple(_eps(e) for e in (40, 30, 20, 10, 3)),
         quick=("2^-40", "2^-10"), scenes=("lj",), available=warp_here,
         what="the sphere method's eps as a fraction of the data's scale "
              "(default 2^-40)"),
    Knob("list-free", (Value("list", unchanged), Value("fused", _list_free()),
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
                   Value("bvh", _with_backend("bvh"), available=warp_here),
                   Value("brute", _with_backend("brute")),
                   Value("fused", _list_free(), available=_has_fused),
                   Value("fused-bvh", _list_free("bvh"),
                         available=lambda: warp_here() and _has_fused())),
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
    Knob("pairs", (Value("list", unchanged),
                   Value("jaxrt.pairs", lj_as(LJPairs))),
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
