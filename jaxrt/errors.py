"""Error bits carried by every neighbour list, and the host-side check.

jax-md's `PartitionError` holds a uint8 bitmask that survives ``jit`` and
``lax.scan``; jaxrt uses jax-md's four bits unchanged and adds four (the last shared
by two causes).
A non-finite position, a metric that disagrees with the box, a box too
small for the cutoff, bad radii or a failed triangulation also set the
overflow bit, so that the usual loop
(``if nbrs.did_buffer_overflow: nbrs = neighbor_fn.allocate(R)``) reaches
``allocate``, which raises a clear error instead of carrying on with a list
that silently lacks the bad particle's pairs.
"""
from __future__ import annotations

import enum
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # jax-md takes long to import; the CLI imports this early
    from jax_md.partition import NeighborList


class ErrorCode(enum.IntFlag):
    NEIGHBOR_LIST_OVERFLOW = 1 << 0
    CELL_LIST_OVERFLOW = 1 << 1
    CELL_SIZE_TOO_SMALL = 1 << 2
    MALFORMED_BOX = 1 << 3
    NONFINITE_POSITION = 1 << 4
    METRIC_MISMATCH = 1 << 5
    BOX_TOO_SMALL = 1 << 6
    # The eighth and last bit of jax-md's uint8 code: a search that could
    # not build a right list from what update was given. Two names, one
    # bit; allocate (which the overflow bit sends the loop to) names the
    # cause.
    SEARCH_FAILED = 1 << 7
    BAD_RADII = 1 << 7
    DELAUNAY_FAILED = 1 << 7


_MESSAGES = {
    ErrorCode.NONFINITE_POSITION:
        "a position was NaN or infinite at the last update; the list lacks "
        "that particle's pairs. Find where the simulation blew up (time step, "
        "overlapping particles) before reallocating.",
    ErrorCode.METRIC_MISMATCH:
        "displacement_or_metric disagreed with the box and periodicity the "
        "list was allocated for (checked on the particles at the extremes "
        "of each axis at the last rebuild): a periodic displacement given "
        "box=None, a box that does not match it, or a box that became "
        "sheared. Reallocate; allocate names the pair and the fix.",
    ErrorCode.BOX_TOO_SMALL:
        "the box passed to update shrank so that r_cutoff + dr_threshold is "
        "no longer below half its height on a periodic axis, which the "
        "list's backend needs (the ray-traced ones and delaunay; "
        "backend='cell' and 'brute' list such boxes), or the box has no "
        "height or is not finite. Use a larger box, a smaller cutoff, or "
        "backend='cell'.",
    ErrorCode.SEARCH_FAILED:
        "the search could not build a right list at the last update: the "
        "radii passed to update had a NaN, infinite or negative entry, or "
        "one above r_cutoff (pass radii in [0, r_cutoff]), or "
        "backend='delaunay' could not rebuild its triangulation (coincident "
        "or degenerate positions). Reallocate: allocate names the cause.",
    ErrorCode.NEIGHBOR_LIST_OVERFLOW:
        "the neighbour buffer overflowed: reallocate with "
        "neighbor_fn.allocate(position) (a larger capacity_multiplier "
        "reallocates less often).",
    ErrorCode.CELL_LIST_OVERFLOW:
        "an internal search buffer overflowed: reallocate with "
        "neighbor_fn.allocate(position).",
    ErrorCode.CELL_SIZE_TOO_SMALL:
        "the box grew past what the list was built for: reallocate.",
    ErrorCode.MALFORMED_BOX:
        "the box is not upper triangular.",
}


# The causes that also set the overflow bit (module docstring): with one of
# them set, "the buffer overflowed" would send the reader the wrong way.
_SETS_OVERFLOW = (ErrorCode.NONFINITE_POSITION | ErrorCode.METRIC_MISMATCH
                  | ErrorCode.BOX_TOO_SMALL | ErrorCode.SEARCH_FAILED)


class NeighborListError(RuntimeError):
    """Raised by `check` for a list whose error bits are set."""


class ListTooLargeError(ValueError):
    """Raised by ``allocate`` for a list (or the candidate buffers that
    build it) past what the backend can index or the device can hold,
    before anything that large is built. The message names the sizes and
    the ways out; energies need no list
    (`jaxrt.energy.lennard_jones_fused`), so a caller may catch this and
    switch to it."""


def check(neighbors: "NeighborList") -> None:
    """Raise `NeighborListError` if ``neighbors`` carries any error bit.

    Host-side (it reads the error code), so call it outside ``jit``: after a
    ``lax.scan`` of steps, or every few hundred steps. Works on a batch of
    lists (any bit set in any system). The message names each cause once:
    the overflow bit that a cause sets with its own is not reported apart.
    """
    code = int(np.bitwise_or.reduce(np.asarray(neighbors.error.code).ravel()))
    if code & _SETS_OVERFLOW:
        code &= ~int(ErrorCode.NEIGHBOR_LIST_OVERFLOW)
    problems = [msg for bit, msg in _MESSAGES.items() if code & bit]
    if problems:
        raise NeighborListError("neighbour list error: " + " ".join(problems))
