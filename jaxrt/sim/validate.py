"""Checks of a scene that need more than the spec: that the neighbour
backend it names is available in this installation.

A `Scene` checks itself when it is built (`jaxrt.sim.spec`), and each effect
checks its own parameters (`Effect.validate`, `jaxrt.sim.effects`). The
backends are registered in `jaxrt.backends`, which the spec may not import,
so the TOML reader and the compiler call `check_backend` instead.
"""
from __future__ import annotations

from jaxrt.sim.spec import Scene, SceneError


def check_backend(scene: Scene) -> None:
    """Raise `SceneError` at ``neighbors.backend`` if the scene has a pair
    effect and names a backend that is not available here."""
    backend = scene.neighbors.backend
    if not scene.pair_effects or not isinstance(backend, str) \
            or backend == "auto":
        return  # a backend object (jaxrt.backends.Bvh(...)) is its own check
    from jaxrt import available_backends  # jaxrt imports jaxrt.sim
    if backend not in available_backends():
        raise SceneError.at("neighbors.backend", f"{backend!r} not in "
                            f"{available_backends()}.")
