"""`BySize`: one backend for small lists, another for the rest.

N is a static shape in both ``measure`` and ``search``, so the pick is made
again, the same way, wherever a list is measured or searched: a list is
always searched by the backend that measured it, and its capacity holds
that backend's buffer names.
"""
from __future__ import annotations

import dataclasses
from typing import ClassVar

from jaxrt.backends.contract import (Backend, Capabilities, capabilities,
                                    is_stateful)

_CAPABILITIES = frozenset(f.name for f in dataclasses.fields(Capabilities)
                          if f.name != "binds")


@dataclasses.dataclass(frozen=True)
class BySize:
    """``small`` for lists of at most ``max_small`` particles, ``large``
    for larger ones, as a `jaxrt.backends.Backend` (``"auto"``'s on a CPU:
    all pairs for small N, whose program is smaller to compile than the
    cell list's).

    Its capabilities are ``large``'s: ``small`` must serve every list that
    ``large`` serves, exactly (``"brute"`` does for ``"cell"``: any metric,
    any box, radii). Neither may be stateful or bind state of its own.
    """

    small: Backend
    large: Backend
    max_small: int

    name: ClassVar[str] = "auto"

    def __post_init__(self):
        for part in (self.small, self.large):
            if is_stateful(part) or capabilities(part).binds:
                raise ValueError(f"BySize cannot hold backend {part.name!r}"
                                 ": it keeps state of its own.")

    def __getattr__(self, name):
        # Only the capabilities delegate (`jaxrt.backends.capabilities`
        # reads them by name); dataclass fields never reach here.
        if name in _CAPABILITIES:
            return getattr(capabilities(self.large), name)
        raise AttributeError(name)

    def for_size(self, n: int) -> Backend:
        """The backend that measures and searches lists of ``n``
        particles."""
        return self.small if n <= self.max_small else self.large

    def pick(self, position) -> Backend:
        """`for_size` of float ``(N, dim)`` ``position`` (N static)."""
        return self.for_size(position.shape[0])

    def measure(self, position, geometry, query, metric_sq):
        return self.pick(position).measure(position, geometry, query,
                                           metric_sq)

    def search(self, position, geometry, query, capacity, metric_sq):
        return self.pick(position).search(position, geometry, query, capacity,
                                          metric_sq)
