"""The accuracy sweep's scenes (`Plan`, `base_scene`), the float64
reference (`equilibrate`, `reference_forces`) and one measurement
(`measure`, `finish_row`)."""
from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from jaxrt.tools.accuracy.knobs import (Value, replace_neighbors, warp_here,
                                        with_lj)
from jaxrt.tools.accuracy.measures import (energy_drift, exact_pairs,
                                           force_rms_rel, missed_depth_ulps,
                                           pairs_missed, position_rms, rdf,
                                           rdf_difference, rdf_grid)


# ---------------------------------------------------------------------------
# The backend "auto" picks, as the report shows it


def auto_backend_for(scene) -> str:
    """What ``backend="auto"`` resolves to for ``scene`` on this device."""
    import jax
    from jaxrt.lists.neighbors import choose_backend
    from jaxrt.sim import list_radii
    return choose_backend(platform=jax.default_backend(),
                          has_radii=list_radii(scene) is not None,
                          warp=warp_here())


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
    return replace_neighbors(dataclasses.replace(scene, dtype="float64"),
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
        full = with_lj("truncated", r_ref)(reference_scene(scene))
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
    own = own_search(scene)  # a list-free effect's pairs, checked too
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
            triangulated += triangulation_rebuilds_of(nbrs) or 0
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
    tri = triangulation_rebuilds_of(nbrs)
    if tri is not None:
        row["triangulation_rebuilds"] = triangulated + tri
    return Measured(row, frames, frames[-1])


def own_search(scene):
    """``(cutoff, codes(position))`` of the scene's list-free effect that
    searches pairs of its own (`LJPairs`), or None: its pairs are checked
    against the brute force as a list's are."""
    for e in scene.effects:
        if hasattr(e, "pair_checker"):
            return e.cutoff, e.pair_checker(scene)
    return None


def triangulation_rebuilds_of(nbrs) -> int | None:
    """Rebuilds from scratch of a Delaunay list's triangulation since its
    ``allocate`` (`jaxrt.backends.delaunay.stats`); None for other lists."""
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


def describe(scene) -> dict:
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


def row_key(scene, value: Value) -> str:
    """Identical settings (the base, reached by several knobs) run once."""
    return repr((scene.dtype, repr(scene.neighbors), repr(scene.effects),
                 scene.integrator))
