"""The accuracy sweep itself: `run` (what ``jaxrt accuracy`` calls)."""
from __future__ import annotations

import dataclasses
import os
import pathlib
import time
import warnings
from typing import Callable, Sequence

import numpy as np

from jaxrt.tools.accuracy.knobs import Value, knobs, unchanged
from jaxrt.tools.accuracy.report import (fmt_value, num, plot_knob,
                                         write_csv, write_summary)
from jaxrt.tools.accuracy.scenes import (FULL, QUICK, Plan, auto_backend_for,
                                         base_scene, describe, equilibrate,
                                         finish_row, measure, rdf_noise,
                                         reference_forces, row_key,
                                         scene_kind, with_state)
from jaxrt.tools.provenance import PROVENANCE, provenance


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
            "base": ", ".join(f"{k} {v}" for k, v in describe(
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
                 "status": "ok", **describe(ref_scene),
                 **finish_row(ref, ref, base, plan)})
    write_csv(rows, csv_path)
    log(f"  reference {label} done ({time.perf_counter() - t0:.0f} s)")
    # Settings two knobs reach run once; keys are per base scene (they do
    # not hold the particles).
    done: dict[str, dict] = {row_key(ref_scene, Value("", unchanged)): rows[-1]
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
                row.update(describe(sc))
                key = row_key(sc, value)
                if key not in done:
                    m = measure(sc, plan, ref_forces=ref_forces)
                    done[key] = finish_row(m, ref, base, plan, sc)
                row.update(status="ok", **done[key])
            except Exception as e:  # noqa: BLE001 - recorded in the row
                row.update(status="error",
                           failed=f"{type(e).__name__}: {e}"[:300])
            rows.append(row)
            log(f"  {knob.name} = {value.label}: {row['status']} "
                f"{fmt_value(num(row, 'time_per_step_ms'))} ms/step "
                f"({time.perf_counter() - t0:.0f} s)")
            write_csv(rows, csv_path)
