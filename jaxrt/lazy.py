"""Names of a package that load on first use (PEP 562), so that importing
the package imports nothing else: ``import jaxrt`` loads neither JAX, nor
jax-md, nor Warp, nor `jaxrt.sim` until a name that needs them is read.

A package states its names once, each as ``"module"`` (the module itself) or
``"module:attribute"``::

    __getattr__, __dir__ = lazy.exports(__name__, {
        "Cell": "jaxrt.backends.cell.search:Cell",
        "rt": "jaxrt.backends.rt",
    })

and keeps ``__all__`` equal to that mapping's keys (tests/test_architecture.py
checks it). The first read of a name imports its module and stores the value
in the package, so later reads cost a dict lookup.
"""
from __future__ import annotations

import importlib
import sys
import types
from typing import Callable


def exports(package: str, names: dict[str, str]
            ) -> tuple[Callable[[str], object], Callable[[], list[str]]]:
    """``__getattr__`` and ``__dir__`` for the package named ``package``.

    Args:
      package: the package's ``__name__``.
      names: public name -> ``"module"`` or ``"module:attribute"``.
    """

    def __getattr__(name: str):
        target = names.get(name)
        if target is None:  # a submodule, as after eager imports
            try:
                return importlib.import_module(f"{package}.{name}")
            except ModuleNotFoundError as e:
                if e.name != f"{package}.{name}":
                    raise  # a dependency of the submodule is missing
                raise AttributeError(f"module {package!r} has no attribute "
                                     f"{name!r}") from None
        module, _, attribute = target.partition(":")
        value = importlib.import_module(module)
        if attribute:
            value = getattr(value, attribute)
        setattr(sys.modules[package], name, value)
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(names))

    return __getattr__, __dir__


def keep_functions(package: str, names: tuple[str, ...]) -> None:
    """Keep each of ``names`` in package ``package`` the function it is
    exported as, although a submodule of the package has the same name
    (``jaxrt.pairs``, ``jaxrt.sim.builtin``): the import system binds a
    submodule on its package when it is first loaded, which must not
    replace the function, whatever was imported first."""

    class Package(types.ModuleType):
        def __setattr__(self, name, value):
            if name in names and isinstance(value, types.ModuleType):
                return
            super().__setattr__(name, value)

    sys.modules[package].__class__ = Package


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
