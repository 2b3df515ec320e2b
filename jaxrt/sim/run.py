"""Running a compiled scene chunk by chunk: `run_chunk` and its `RunStats`.

A chunk is ``steps`` steps in one jitted ``lax.scan``; the neighbour list's
overflow flag is read between chunks. A chunk whose list overflowed is
thrown away and redone from its start with a list reallocated there, so an
overflow never reaches the results.

A blow-up (a time step too large for the forces, overlapping particles)
is never carried on silently: after each chunk `run_chunk` raises
`BlowUpError` if

* a position, velocity, acceleration or energy became NaN or infinite;
* a particle moved farther in one step than the interaction range
  (``scene.cutoff``; scenes with pair effects): velocity Verlet assumes
  the force changes little over a step, and a particle that jumps a whole
  cutoff skips its interactions altogether (healthy runs move a small
  fraction of the mean spacing per step). Periodic wrapping keeps such
  positions finite, so without this check the run would go on;
* in a conservative scene (`Compiled.conservative`), the total energy
  changed within the chunk by more than ``energy_tolerance`` times
  ``|KE| + |PE|`` at the chunk's start. Velocity Verlet is symplectic: for a
  stable step (``omega dt < 2`` for the fastest mode ``omega``) its energy
  error stays bounded, of relative size ``O((omega dt)**2)``; past that the
  error grows exponentially, by orders of magnitude within a few steps. A
  threshold of order one (0.5 by default) sits between the two regimes.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from jaxrt.errors import Error, ErrorCode, check
from jaxrt.sim.compile import Compiled, State

ENERGY_TOLERANCE = 0.5
"""Default ``energy_tolerance`` of `run_chunk` (module docstring)."""


class BlowUpError(Error, RuntimeError):
    """The simulation blew up (module docstring); the message names the
    step, what went wrong and the time step to lower.

    Attributes:
      step: the step of the chunk (1-based) where it was first seen, or
        None where only the chunk's end state shows it.
    """

    def __init__(self, message: str, step: int | None = None):
        super().__init__(message)
        self.step = step


@dataclasses.dataclass
class RunStats:
    """What `run_chunk` accumulates over a run (mutable: it is filled in).

    steps: steps run; overflows: chunks redone after an overflow; rebuilds:
    list rebuilds since `Compiled.init`; kinetic, potential: one float
    ``(steps,)`` array per chunk; momentum: one float ``(steps, dim)`` per
    chunk.
    """
    steps: int = 0
    overflows: int = 0
    rebuilds: int = 0
    kinetic: list = dataclasses.field(default_factory=list)
    potential: list = dataclasses.field(default_factory=list)
    momentum: list = dataclasses.field(default_factory=list)


def run_chunk(compiled: Compiled, state: State, nbrs, *, steps: int,
              stats: RunStats | None = None,
              energy_tolerance: float | None = ENERGY_TOLERANCE):
    """Run ``steps`` steps; returns ``(state, nbrs)``.

    If the list overflowed, reallocate it at the chunk's start and redo the
    chunk; raises `RuntimeError` if it overflows again, and `BlowUpError`
    if the run blew up (module docstring; ``energy_tolerance=None`` turns
    the energy test off, the others always run). ``stats`` holds the
    chunk's records even when it raises.
    """
    start_energy = None
    if (energy_tolerance is not None and compiled.conservative
            and compiled.energy is not None):
        start_energy = float(compiled.energy(state, nbrs))
        start_kinetic = 0.5 * float(np.sum(
            _mass_column(compiled, state) * np.asarray(state.velocity,
                                                       np.float64) ** 2))
    new_state, new_nbrs, trace = compiled.chunk(state, nbrs, steps=steps)
    if new_nbrs is not None and new_nbrs.did_buffer_overflow:
        if stats is not None:
            stats.overflows += 1
        code = int(np.asarray(new_nbrs.error.code))
        if not code & ErrorCode.NONFINITE_POSITION:  # else: raised below
            nbrs = compiled.neighbor_fn.allocate(state.position)
            new_state, new_nbrs, trace = compiled.chunk(state, nbrs,
                                                        steps=steps)
            if new_nbrs.did_buffer_overflow and not (
                    int(np.asarray(new_nbrs.error.code))
                    & ErrorCode.NONFINITE_POSITION):
                raise RuntimeError(
                    "the neighbour list overflowed twice in one chunk: lower "
                    "the chunk length or raise "
                    "neighbors.capacity_multiplier.")
    if stats is not None:
        stats.steps += steps
        stats.kinetic.append(np.asarray(trace.kinetic))
        stats.potential.append(np.asarray(trace.potential))
        stats.momentum.append(np.asarray(trace.momentum))
        stats.rebuilds = int(new_state.rebuilds)
    _check_blow_up(compiled, new_state, trace, start_energy,
                   None if start_energy is None else start_kinetic,
                   energy_tolerance)
    if new_nbrs is not None and (int(np.asarray(new_nbrs.error.code))
                                 & ErrorCode.NONFINITE_POSITION):
        check(new_nbrs)  # a position was non-finite in the chunk
    return new_state, new_nbrs


def _mass_column(compiled: Compiled, state: State) -> np.ndarray:
    masses = np.asarray(compiled.scene.particles.masses, np.float64)
    return np.broadcast_to(masses.reshape(-1, 1), state.velocity.shape)


def _check_blow_up(compiled: Compiled, after: State, trace,
                   start_energy, start_kinetic, tolerance) -> None:
    """Raise `BlowUpError` where the chunk shows a blow-up (module
    docstring)."""
    dt = compiled.scene.integrator.dt
    advice = (f"The time step dt = {dt:g} is likely too large for these "
              "forces (or particles overlap): lower integrator.dt.")
    ke = np.asarray(trace.kinetic, np.float64)
    pe = np.asarray(trace.potential, np.float64)
    bad = ~(np.isfinite(ke) & np.isfinite(pe))
    if bad.any():
        k = int(np.argmax(bad))
        raise BlowUpError(
            f"the simulation blew up: the energy became non-finite at step "
            f"{k + 1} of this chunk (kinetic {ke[k]:.3g}, potential "
            f"{pe[k]:.3g}). {advice}", step=k + 1)
    for name in ("position", "velocity", "accel"):
        value = np.asarray(getattr(after, name))
        if not np.all(np.isfinite(value)):
            i = int(np.argwhere(~np.isfinite(value))[0][0])
            raise BlowUpError(
                f"the simulation blew up: particle {i}'s {name} became NaN "
                f"or infinite by the end of this chunk. {advice}")
    if start_energy is not None:
        total = ke + pe
        scale = abs(start_kinetic) + abs(start_energy - start_kinetic)
        change = np.abs(total - start_energy)
        limit = tolerance * scale
        if (change > limit).any():
            k = int(np.argmax(change > limit))
            raise BlowUpError(
                f"the simulation blew up: the total energy went from "
                f"{start_energy:.6g} to {total[k]:.6g} by step {k + 1} of this "
                f"chunk, a change of {change[k]:.3g} > {tolerance:g} x "
                f"(|KE| + |PE|) = {limit:.3g} at its start, in a scene that "
                f"conserves energy. {advice}", step=k + 1)
    reach = compiled.scene.cutoff
    if compiled.neighbor_fn is not None and reach > 0:
        v = np.asarray(after.velocity, np.float64)
        jump = dt * float(np.sqrt(np.max(np.sum(v * v, axis=1),
                                         initial=0.0)))
        if jump > reach:
            raise BlowUpError(
                f"the simulation blew up: a particle moves {jump:.3g} per "
                f"step at the end of this chunk, more than the interaction "
                f"range {reach:g}, so it skips its interactions. {advice}")
