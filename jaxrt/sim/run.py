"""Running a compiled scene chunk by chunk: `run_chunk` and its `RunStats`.

A chunk is ``steps`` steps in one jitted ``lax.scan``; the neighbour list's
overflow flag is read between chunks. A chunk whose list overflowed is
thrown away and redone from its start with a list reallocated there, so an
overflow never reaches the results.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from jaxrt.errors import ErrorCode, check
from jaxrt.sim.compile import Compiled, State


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
              stats: RunStats | None = None):
    """Run ``steps`` steps; returns ``(state, nbrs)``.

    If the list overflowed, reallocate it at the chunk's start and redo the
    chunk; raises `RuntimeError` if it overflows again, and
    `jaxrt.NeighborListError` if a position became non-finite.
    """
    new_state, new_nbrs, trace = compiled.chunk(state, nbrs, steps=steps)
    if new_nbrs is not None and new_nbrs.did_buffer_overflow:
        if stats is not None:
            stats.overflows += 1
        code = int(np.asarray(new_nbrs.error.code))
        if code & ErrorCode.NONFINITE_POSITION:  # reallocating cannot help
            check(new_nbrs)
        nbrs = compiled.neighbor_fn.allocate(state.position)
        new_state, new_nbrs, trace = compiled.chunk(state, nbrs, steps=steps)
        if new_nbrs.did_buffer_overflow:
            raise RuntimeError(
                "the neighbour list overflowed twice in one chunk: lower the "
                "chunk length or raise neighbors.capacity_multiplier.")
    if stats is not None:
        stats.steps += steps
        stats.kinetic.append(np.asarray(trace.kinetic))
        stats.potential.append(np.asarray(trace.potential))
        stats.momentum.append(np.asarray(trace.momentum))
        stats.rebuilds = int(new_state.rebuilds)
    return new_state, new_nbrs
