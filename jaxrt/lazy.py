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
from typing import Callable


def exports(package: str, names: dict[str, str]
            ) -> tuple[Callable[[str], object], Callable[[], list[str]]]:
    """``__getattr__`` and ``__dir__`` for the package named ``package``.

    Args:
      package: the package's ``__name__``.
      names: public name -> ``"module"`` or ``"module:attribute"``.
    """

    def __getattr__(name: str):
        try:
            target = names[name]
        except KeyError:
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
