"""Value checks for the energy functions, shared by `jaxrt.energy.lj` and
`jaxrt.energy.sph`.

A value can only be checked when it is known now: outside ``jit``, and not a
tracer. Inside ``jit`` the energies poison their results with NaN instead
(see each module's docstring).
"""
from __future__ import annotations

import jax
import numpy as np


def concrete(x) -> np.ndarray | None:
    """``x`` as a NumPy array when its value is known now; None if traced
    (or not a number or array)."""
    if isinstance(x, jax.core.Tracer):
        return None
    if isinstance(x, (int, float, np.ndarray, np.generic, jax.Array)):
        return np.asarray(x)
    return None


def check_positive(name: str, value, fix: str) -> None:
    """Raise ``ValueError("{name} must be finite and > 0; got {value}. {fix}")``
    when ``value`` is known and empty, non-finite or ``<= 0`` anywhere."""
    v = concrete(value)
    if v is not None and (v.size == 0 or not np.all(np.isfinite(v))
                          or np.any(v <= 0)):
        raise ValueError(f"{name} must be finite and > 0; got {value}. {fix}")
