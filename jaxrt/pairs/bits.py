"""The error bits of `jaxrt.pairs` and `jaxrt.pairs_batch`, their messages,
and the exception an incomplete list raises."""
from __future__ import annotations

import enum

import numpy as np

from jaxrt.errors import Bits, Error, raise_for


class PairsError(Error, RuntimeError):
    """Raised by `Pairs.check` (and by an eager `pairs`) for an incomplete
    list."""


@enum.unique
class ErrorBit(Bits):
    """Bits of `Pairs.error`."""
    CAPACITY = 1
    MAX_SHIFT = 2
    NONFINITE_POSITION = 4
    SINGULAR_CELL = 8
    MAX_NODES = 16


MESSAGES = {
    ErrorBit.CAPACITY: "more pairs than capacity (count is the exact number "
                       "needed): pass a larger capacity=",
    ErrorBit.MAX_SHIFT: "the cell needs larger lattice shifts than max_shift "
                        "(a cell shorter than cutoff / max_shift across a "
                        "periodic axis): pass a larger max_shift= (e.g. "
                        "from jaxrt.pairs_sizes)",
    ErrorBit.NONFINITE_POSITION: "a real atom's position is NaN or infinite: "
                                 "its pairs are missing",
    ErrorBit.SINGULAR_CELL: "the cell is singular or not finite, or has a "
                            "zero row on a periodic axis",
    ErrorBit.MAX_NODES: "a system has more atoms than max_nodes (its pairs "
                        "are missing): pass a larger max_nodes= (at least "
                        "the largest n_node)",
}


def raise_if(code: int, count=None, capacity=None) -> None:
    """Raise `PairsError` naming each bit set in ``code`` (and, given them,
    the count that overflowed the capacity)."""
    messages = dict(MESSAGES)
    if count is not None and code & ErrorBit.CAPACITY:
        messages[ErrorBit.CAPACITY] += (
            f" (count {int(np.max(np.asarray(count)))}, "
            f"capacity {capacity})")
    raise_for(code, messages, PairsError,
              "jaxrt.pairs: the list is incomplete: ")
