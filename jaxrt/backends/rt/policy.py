"""When a kept BVH is rebuilt rather than refit: Meneses et al. (seed 003),
§3.1, and the baselines it compares against.

A refit keeps the tree's topology and recomputes every box from the current
positions: cheap and always exact, but queries slow down as particles wander
from where the tree was built (a particle that leaves the box across a
periodic face is wrapped to the other side, and its ancestors' boxes grow to
span the box). A rebuild costs more and restores the query speed. A policy
decides between them at every search call; it knows nothing of Warp or JAX,
only the times it is told (`PolicyState.record`), so its decisions can be
tested with any clock.

Policies (frozen values, options of `jaxrt.backends.Bvh`):

* `Drift` (``"drift"``, the default): rebuild once a particle has drifted
  more than ``drift_fraction`` of the cutoff from where the last build put
  it (the caller measures the drift, `PolicyState.wants_rebuild`'s
  ``drifted``), refit otherwise. A rule of thumb with no clock: the tree
  never degrades far, and no particle is ever wrapped by a refit.
* `Rebuild` (``"rebuild"``): rebuild on every call.
* `Refit` (``"refit"``): never rebuild after the first build (the tree
  degrades without bound; for measuring that degradation).
* `Fixed` (``"fixed"``): rebuild every ``k`` calls (one rebuild and
  ``k - 1`` refits per period; the paper's fixed-200).
* `Avg` (``"avg"``): rebuild once the mean cost of the calls since the last
  rebuild (refit + query) exceeds the mean cost of the calls that rebuilt
  (rebuild + query): the paper's "avg", formalised.
* `Gradient` (``"gradient"``): the paper's Eq. 8,
  ``k_opt = −1 + sqrt(1 − 2 (t_u − t_r) / Δq)`` refits between rebuilds,
  from exponential averages of the rebuild and refit times t_r, t_u and the
  least-squares growth Δq of the query time per refit since the last
  rebuild. Eq. 8 is implemented as printed; the exact discrete sum of the
  query growth, ``Δq k (k + 1) / 2``, would give
  ``−1 + sqrt(2 (t_r − t_u) / Δq)`` instead.

No rule but the policy rebuilds a tree that exists: a refit is exact
whatever the particles did (`jaxrt.backends.rt.aabb.AabbSearch`). The caller
builds a new tree only where none fits (the first call, another N, dtype or
device), and rebuilds one whose cutoff, periodic axes or radii-or-not
changed; it records why (`REASONS`).
"""
from __future__ import annotations

import dataclasses
import math
from typing import ClassVar, Protocol

ACTIONS = ("build", "rebuild", "refit")
# Why a tree was built or rebuilt: "new" (no tree fitted these particles),
# "setup" (the cutoff, periodic axes or radii-or-not changed), "policy".
REASONS = ("new", "setup", "policy")


class PolicyState(Protocol):
    """The mutable state of one policy for one tree."""

    def wants_rebuild(self, drifted: bool = False) -> bool:
        """Rebuild now rather than refit? ``drifted``: a particle moved more
        than the drift bound since the last build (measured only for a
        policy whose ``needs_drift`` is set)."""

    def record(self, action: str, t_action: float, t_query: float) -> None:
        """One call done: ``action`` (`ACTIONS`) took ``t_action`` and the
        queries on the result ``t_query`` (seconds; NaN where not timed)."""


def choose(state: PolicyState, *, has_tree: bool, drifted: bool = False) -> str:
    """How the BVH follows the particles: ``"build"`` (no tree yet), else
    ``"rebuild"`` or ``"refit"`` as the policy's state decides."""
    if not has_tree:
        return "build"
    return "rebuild" if state.wants_rebuild(drifted) else "refit"


# ---------------------------------------------------------------------------
# The policies, as values; ``start()`` makes the state of one tree.


@dataclasses.dataclass(frozen=True)
class Drift:
    """Rebuild once a particle drifted past the bound (``drift_fraction``
    of the cutoff, an option of the tree) since the last build."""

    name: ClassVar[str] = "drift"
    needs_timing: ClassVar[bool] = False
    needs_drift: ClassVar[bool] = True

    def start(self) -> PolicyState:
        return _DriftState()


@dataclasses.dataclass(frozen=True)
class Rebuild:
    """Rebuild on every call."""

    name: ClassVar[str] = "rebuild"
    needs_timing: ClassVar[bool] = False
    needs_drift: ClassVar[bool] = False

    def start(self) -> PolicyState:
        return _Always()


@dataclasses.dataclass(frozen=True)
class Refit:
    """Never rebuild: build once, refit on every later call."""

    name: ClassVar[str] = "refit"
    needs_timing: ClassVar[bool] = False
    needs_drift: ClassVar[bool] = False

    def start(self) -> PolicyState:
        return _Never()


@dataclasses.dataclass(frozen=True)
class Fixed:
    """Rebuild every ``k`` calls (k >= 1; 1 rebuilds every call)."""

    k: int = 200
    name: ClassVar[str] = "fixed"
    needs_timing: ClassVar[bool] = False
    needs_drift: ClassVar[bool] = False

    def __post_init__(self):
        if not isinstance(self.k, int) or self.k < 1:
            raise ValueError(f"Fixed(k={self.k!r}): k must be an int >= 1.")

    def start(self) -> PolicyState:
        return _FixedState(self.k)


@dataclasses.dataclass(frozen=True)
class Avg:
    """Rebuild when refitting has cost more, on average since the last
    rebuild, than rebuilding did on average."""

    name: ClassVar[str] = "avg"
    needs_timing: ClassVar[bool] = True
    needs_drift: ClassVar[bool] = False

    def start(self) -> PolicyState:
        return _AvgState()


@dataclasses.dataclass(frozen=True)
class Gradient:
    """Seed 003's adaptive policy (Eq. 8).

    Attributes:
      alpha: weight of the newest time in the averages of t_r and t_u.
      window: most refits of the current cycle that the fit of Δq reads.
      k_max: the most refits between rebuilds (while Δq is unknown or not
        positive, refits continue up to this).
    """

    alpha: float = 0.2
    window: int = 64
    k_max: int = 10_000
    name: ClassVar[str] = "gradient"
    needs_timing: ClassVar[bool] = True
    needs_drift: ClassVar[bool] = False

    def __post_init__(self):
        if not 0.0 < self.alpha <= 1.0:
            raise ValueError(f"Gradient(alpha={self.alpha!r}): must be in "
                             "(0, 1].")
        for field in ("window", "k_max"):
            value = getattr(self, field)
            if not isinstance(value, int) or value < 2:
                raise ValueError(f"Gradient({field}={value!r}): must be an "
                                 "int >= 2.")

    def start(self) -> PolicyState:
        return _GradientState(self)


POLICIES = {p.name: p for p in (Drift, Rebuild, Refit, Fixed, Avg, Gradient)}


def resolve(policy) -> "Drift | Rebuild | Refit | Fixed | Avg | Gradient":
    """A policy value from a name (`POLICIES`) or a value."""
    if isinstance(policy, str):
        if policy not in POLICIES:
            raise ValueError(f"policy={policy!r} is not known; choose one of "
                             f"{sorted(POLICIES)} or a value such as "
                             "jaxrt.backends.rt.policy.Fixed(k=50).")
        return POLICIES[policy]()
    if not isinstance(policy, tuple(POLICIES.values())):
        raise TypeError(f"policy must be a name ({sorted(POLICIES)}) or a "
                        "jaxrt.backends.rt.policy value; got "
                        f"{type(policy).__name__}.")
    return policy


# ---------------------------------------------------------------------------
# States.


class _Never:
    def wants_rebuild(self, drifted: bool = False) -> bool:
        return False

    def record(self, action, t_action, t_query) -> None:
        pass


class _Always(_Never):
    def wants_rebuild(self, drifted: bool = False) -> bool:
        return True


class _DriftState(_Never):
    def wants_rebuild(self, drifted: bool = False) -> bool:
        return bool(drifted)


class _FixedState(_Never):
    def __init__(self, k: int):
        self.k = k
        self.refits = 0

    def wants_rebuild(self, drifted: bool = False) -> bool:
        return self.refits >= self.k - 1

    def record(self, action, t_action, t_query) -> None:
        self.refits = self.refits + 1 if action == "refit" else 0


class _AvgState(_Never):
    def __init__(self):
        self.since_rebuild: list[float] = []  # refit + query of this cycle
        self.rebuild_total = 0.0              # rebuild + query, summed
        self.rebuilds = 0

    def wants_rebuild(self, drifted: bool = False) -> bool:
        if not self.since_rebuild or not self.rebuilds:
            return False
        mean_refit = sum(self.since_rebuild) / len(self.since_rebuild)
        return mean_refit > self.rebuild_total / self.rebuilds

    def record(self, action, t_action, t_query) -> None:
        cost = t_action + t_query
        if not math.isfinite(cost):
            return
        if action == "refit":
            self.since_rebuild.append(cost)
        else:
            self.rebuild_total += cost
            self.rebuilds += 1
            self.since_rebuild = []


class _GradientState(_Never):
    """SPECS.md §1's estimator: exponential averages of t_r and t_u, the
    query time q0 right after the last rebuild, and the slope through zero
    of the query's growth over the refits of this cycle; Δq is carried over
    from the previous cycle until two refits have measured it anew."""

    def __init__(self, options: Gradient):
        self.options = options
        self.t_rebuild: float | None = None
        self.t_refit: float | None = None
        self.q0: float | None = None
        self.growth: list[tuple[int, float]] = []
        self.delta_q: float | None = None
        self.refits = 0

    def k_opt(self) -> float:
        """Refits between rebuilds that Eq. 8 asks for now."""
        o = self.options
        dq = self.delta_q
        if (dq is None or not dq > 0 or self.t_rebuild is None
                or self.t_refit is None):
            return float(o.k_max)
        k = -1.0 + math.sqrt(max(0.0, 1.0 + 2.0 * (self.t_rebuild
                                                   - self.t_refit) / dq))
        return min(max(k, 0.0), float(o.k_max))

    def wants_rebuild(self, drifted: bool = False) -> bool:
        return self.refits >= self.k_opt()

    def _average(self, old: float | None, new: float) -> float:
        a = self.options.alpha
        return new if old is None else (1 - a) * old + a * new

    def record(self, action, t_action, t_query) -> None:
        if action == "refit":
            self.refits += 1
            if math.isfinite(t_action):
                self.t_refit = self._average(self.t_refit, t_action)
            if self.q0 is not None and math.isfinite(t_query):
                self.growth.append((self.refits, t_query - self.q0))
                self.growth = self.growth[-self.options.window:]
                if len(self.growth) >= 2:
                    self.delta_q = (sum(j * e for j, e in self.growth)
                                    / sum(j * j for j, _ in self.growth))
            return
        self.refits = 0
        self.growth = []
        if math.isfinite(t_action):
            self.t_rebuild = self._average(self.t_rebuild, t_action)
        self.q0 = t_query if math.isfinite(t_query) else None
