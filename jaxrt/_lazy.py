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
    """A package module whose functions keep their names over submodules
    of the same name (``jaxrt.pairs`` the function, ``jaxrt/pairs.py`` the
    module): importing the submodule later binds it on the package, which
    with eager imports happened before the function was bound over it."""

    def __setattr__(self, name: str, value) -> None:
        if (isinstance(value, types.ModuleType)
                and name in self.__dict__.get("_lazy_shadowed", ())):
            return
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
      a function of that module (kept over the submodule).
    renamed: public name -> its name in its module, where they differ.
    """
    renamed = renamed or {}
    package = sys.modules[name]
    namespace = package.__dict__

    def __getattr__(attr: str):
        where = exports.get(attr)
        if where is not None:
            module = importlib.import_module(where)
            itself = where == f"{name}.{attr}" and attr not in shadowed
            value = module if itself else getattr(module,
                                                  renamed.get(attr, attr))
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
    namespace["_lazy_shadowed"] = frozenset(shadowed)
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
