"""jaxrt's one error system: the base class `Error` of every exception
jaxrt raises, the error bitmasks that survive ``jit`` (`Bits`: the lists'
`ErrorCode`, `jaxrt.pairs.ErrorBit`, `jaxrt.sim.domains.Overflow`), and the
host-side checks that read them (`raise_for`: the same for lists, pairs and
domain states).

jax-md's `PartitionError` holds a uint8 bitmask that survives ``jit`` and
``lax.scan``; jaxrt uses jax-md's four bits unchanged and adds four, each
with one meaning. The uint8 has no bit left, so the last,
`ErrorCode.SEARCH_FAILED`, has one meaning with a cause per backend (bad
radii, a triangulation that could not be rebuilt), which `check` names from
the list.
A non-finite position, a metric that disagrees with the box, a box too
small for the cutoff, bad radii or a failed triangulation also set the
overflow bit, so that the usual loop
(``if nbrs.did_buffer_overflow: nbrs = neighbor_fn.allocate(R)``) reaches
``allocate``, which raises a clear error instead of carrying on with a list
that silently lacks the bad particle's pairs.
"""
from __future__ import annotations

import enum
from typing import TYPE_CHECKING, Mapping

import numpy as np

if TYPE_CHECKING:  # jax-md takes long to import; the CLI imports this early
    from jax_md.partition import NeighborList


class Error(Exception):
    """Base of every exception jaxrt raises on purpose (``except
    jaxrt.Error``). Each also keeps its builtin base (`ValueError`,
    `RuntimeError`, `TypeError`), so ``except ValueError`` still works."""


class Bits(enum.IntFlag):
    """Base of jaxrt's error bitmasks: a subclass's members are its bits,
    one name and one meaning each (subclasses are `enum.unique`), and a
    table of messages (``{bit: text}``) goes with it to `raise_for`."""

    @classmethod
    def of(cls, code) -> "Bits":
        """The bits set in ``code`` (int or integer array: a batch ORed
        together); host-side."""
        return cls(int(np.bitwise_or.reduce(
            np.asarray(code).astype(np.int64).ravel(), initial=0)))


def raise_for(code: int, messages: Mapping[int, str], error: type,
              prefix: str, sep: str = "; ") -> None:
    """Raise ``error(prefix + the messages of the bits set in code)`` if
    any bit of ``messages`` is set; host-side. Lists (`check`), pairs
    (`jaxrt.pairs.Pairs.check`) and domain states (`jaxrt.sim.domains.
    Domains.check`) all raise this way.

    Args:
      code: int, the bits (`Bits.of` for arrays and batches).
      messages: bit -> text, in the order the texts are joined.
      error: the `Error` subclass to raise.
      prefix: the message's start.
      sep: between the texts.
    """
    problems = [text for bit, text in messages.items() if code & int(bit)]
    if problems:
        raise error(prefix + sep.join(problems))


@enum.unique
class ErrorCode(Bits):
    NEIGHBOR_LIST_OVERFLOW = 1 << 0
    CELL_LIST_OVERFLOW = 1 << 1
    CELL_SIZE_TOO_SMALL = 1 << 2
    MALFORMED_BOX = 1 << 3
    NONFINITE_POSITION = 1 << 4
    METRIC_MISMATCH = 1 << 5
    BOX_TOO_SMALL = 1 << 6
    # The eighth and last bit of jax-md's uint8 code: the search could not
    # build a right list from what update was given. Its cause depends on
    # the backend (bad radii; a triangulation that could not be rebuilt):
    # `check` names it from the list, and allocate (which the overflow bit
    # sends the loop to) names it too.
    SEARCH_FAILED = 1 << 7


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
        "the search could not build a right list at the last update: {}. "
        "Reallocate: allocate names the cause.",
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


# `ErrorCode.SEARCH_FAILED`'s causes, by what the list holds.
_SEARCH_FAILED_CAUSES = {
    "radii": "the radii passed to update had a NaN, infinite or negative "
             "entry, or one above r_cutoff (pass radii in [0, r_cutoff])",
    "state": "the backend that keeps state in the list (backend='delaunay': "
             "its triangulation) could not rebuild it (coincident or "
             "degenerate positions)",
}


def _search_failed_cause(neighbors) -> str:
    """`ErrorCode.SEARCH_FAILED`'s cause for ``neighbors``: its radii (the
    list was allocated with radii), or its backend's state (the list
    carries one), or either."""
    causes = []
    if getattr(neighbors.cell_list_capacity, "radii", False):
        causes.append(_SEARCH_FAILED_CAUSES["radii"])
    if getattr(neighbors, "backend_state", None) is not None:
        causes.append(_SEARCH_FAILED_CAUSES["state"])
    return "; or ".join(causes or _SEARCH_FAILED_CAUSES.values())


class NeighborListError(Error, RuntimeError):
    """Raised by `check` for a list whose error bits are set."""


class ListTooLargeError(Error, ValueError):
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
    The other results with error bits
    are checked the same way, by their own ``check()``, which this calls:
    `jaxrt.pairs.Pairs` (`jaxrt.PairsError`) and a domain decomposition's
    state (`jaxrt.sim.domains.DomainState`, `DomainError`).
    """
    if not hasattr(getattr(neighbors, "error", None), "code"):
        if callable(getattr(neighbors, "check", None)):
            neighbors.check()
            return
        raise TypeError(f"check: {type(neighbors).__name__} carries no "
                        "jaxrt error bits (a neighbour list, Pairs or a "
                        "domain state does).")
    code = ErrorCode.of(neighbors.error.code)
    if code & _SETS_OVERFLOW:  # the overflow bit a cause sets with its own
        code &= ~ErrorCode.NEIGHBOR_LIST_OVERFLOW
    messages = dict(_MESSAGES)
    if code & ErrorCode.SEARCH_FAILED:
        messages[ErrorCode.SEARCH_FAILED] = messages[
            ErrorCode.SEARCH_FAILED].format(_search_failed_cause(neighbors))
    raise_for(code, messages, NeighborListError, "neighbour list error: ",
              sep=" ")
