"""Simulations of scenes: what to simulate, compiled to only what it needs.

Modules, each depending only on those above it:

  spec      the `Scene` and its parts (frozen dataclasses), the `Effect`
            protocol, `SceneError`; checks on construction; imports only
            `jaxrt.errors` from jaxrt
  effects   the effects (LJ, SPH density / pressure / viscosity, gravity,
            walls), one class each, and their `Registry` (``EFFECTS``)
  validate  the check that needs the installation (the neighbour backend)
  toml      reading (`from_toml`, `load`) and writing (`to_toml`) TOML
  compile   `compile_scene`: a scene to jitted steps (`State`, `Trace`,
            `Compiled`)
  run       `run_chunk`: chunks of steps, redone on list overflow
  builtin   the built-in scenes (`BUILTIN`, `builtin`), from the seeds'
            distributions (`distributions`)
  domains   a scene cut into slabs over devices (`decompose`; imported
            on its own: ``from jaxrt.sim import domains``)

A run::

    scene = jaxrt.sim.load("scene.toml")  # or jaxrt.sim.builtin("lj-fluid")
    compiled = jaxrt.sim.compile_scene(scene)
    state, nbrs = compiled.init()
    stats = jaxrt.sim.RunStats()
    state, nbrs = jaxrt.sim.run_chunk(compiled, state, nbrs, steps=100,
                                      stats=stats)
"""
from jaxrt import lazy as _lazy

# The modules above, by the names each exports; each is imported when one
# of its names is first read, so that the spec, the TOML reader and the
# list of built-in scenes load without JAX (`jaxrt.lazy`).
_MODULES = {
    "spec": ("BOUNDARIES", "Box", "Context", "Effect", "Integrator",
             "Neighbors", "Particles", "Scene", "SceneError", "Term",
             "check_reach", "make_particles"),
    "effects": ("EFFECTS", "LJ", "Boids", "Gravity", "Registry",
                "SPHDensity", "SPHPressure", "SPHViscosity", "Walls",
                "register", "registered", "unregister"),
    "validate": ("check_backend",),
    "toml": ("from_toml", "load", "to_toml"),
    "compile": ("FORMATS", "Compiled", "State", "Trace", "compile_scene",
                "list_radii"),
    "run": ("BlowUpError", "RunStats", "run_chunk"),
    "builtin": ("BUILTIN", "boids", "builtin", "dam_break", "lj_fluid",
                "lj_polydisperse", "sphere_surface"),
}

__all__ = [name for names in _MODULES.values() for name in names]

__getattr__, __dir__ = _lazy.exports(
    __name__, {name: f"{__name__}.{module}:{name}"
               for module, names in _MODULES.items() for name in names})
_lazy.keep_functions(__name__, ("builtin",))
