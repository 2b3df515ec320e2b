"""Package attributes imported on first use (PEP 562).

jaxrt's packages re-export names from submodules that import JAX, jax-md
and Warp, which take many seconds to load; the ``jaxrt`` command must
parse its arguments and read a scene file before paying for them. A
package calls `lazy_package` once, after its light imports; each public
name is then imported from its submodule when it is first read, and any
submodule is an attribute as well (``jaxrt.energy`` after ``import
jaxrt``), as with eager imports.

This module imports nothing from jaxrt.
"""
from __future__ import annotations

import importlib
import sys
import types


class _Package(types.ModuleType):
    """A package module told of each submodule the import system binds on
    it (after the submodule has run): `lazy_package`'s ``_lazy_bound``
    then binds the names that submodule exports as well."""

    def __setattr__(self, name: str, value) -> None:
        bound = self.__dict__.get("_lazy_bound")
        if bound is not None and isinstance(value, types.ModuleType):
            bound(name, value)
        else:
            super().__setattr__(name, value)


def lazy_package(name: str, exports: dict[str, str],
                 shadowed: tuple[str, ...] = (),
                 renamed: dict[str, str] | None = None) -> None:
    """Make package ``name`` (a key of ``sys.modules``) import its public
    names on first use.

    exports: public name -> the module that defines it (the name itself
      is read from that module), or the name of a submodule mapped to
      itself.
    shadowed: public names that are also submodules, the public name being
      a function of that module (``jaxrt.pairs``): the function is kept
      over the submodule, as eager imports bound it last.
    renamed: public name -> its name in its module, where they differ.
    """
    renamed = renamed or {}
    package = sys.modules[name]
    namespace = package.__dict__
    by_module: dict[str, list[str]] = {}
    for public, where in exports.items():
        by_module.setdefault(where, []).append(public)

    def value_of(public: str, module):
        if module.__name__ == f"{name}.{public}" and public not in shadowed:
            return module
        return getattr(module, renamed.get(public, public))

    def bound(child: str, module) -> None:
        # Names are bound as soon as their module is loaded, so that what
        # reads the package's __dict__ (pdoc, for one) finds them there.
        if child not in shadowed:
            namespace[child] = module
        for public in by_module.get(module.__name__, ()):
            namespace[public] = value_of(public, module)

    def __getattr__(attr: str):
        where = exports.get(attr)
        if where is not None:
            value = value_of(attr, importlib.import_module(where))
        else:
            try:
                value = importlib.import_module(f"{name}.{attr}")
            except ModuleNotFoundError as e:
                if e.name != f"{name}.{attr}":
                    raise  # a dependency of the submodule is missing
                raise AttributeError(f"module {name!r} has no attribute "
                                     f"{attr!r}") from None
        namespace[attr] = value
        return value

    def __dir__():
        return sorted(set(namespace) | set(exports))

    namespace["__getattr__"] = __getattr__
    namespace["__dir__"] = __dir__
    namespace["_lazy_bound"] = bound
    package.__class__ = _Package


class lazy_module:
    """A module imported when one of its attributes is first read:
    ``jnp = lazy_module("jax.numpy")`` at the top of a module that must
    load without JAX, where only its functions use ``jnp``."""

    def __init__(self, name: str):
        self._name = name

    def __getattr__(self, attr: str):
        return getattr(importlib.import_module(self._name), attr)

    def __repr__(self) -> str:
        return f"<lazy module {self._name!r}>"
