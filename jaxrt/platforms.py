"""The platforms of this process, for code that chooses one per platform.

`jax.lax.platform_dependent` picks a branch where a program is lowered,
but traces every branch first: on a machine with no CUDA backend the
CUDA kernels' traces (Pallas) were a tenth of a second or more per traced
search, for a branch that can never run there.
"""
from __future__ import annotations

import functools
from typing import Callable

import jax
import jax.numpy


def under_trace() -> bool:
    """Is a trace under way (inside a caller's ``jit``, ``scan``...)? A
    jitted call there is nested, and JAX refuses compile options on a
    nested ``jit``: programs compiled with options are for eager calls
    only. A fresh array is a tracer exactly under a trace."""
    return isinstance(jax.numpy.zeros(()), jax.core.Tracer)


@functools.cache
def cuda_present() -> bool:
    """Whether JAX has a CUDA backend in this process (read once: the
    backends are fixed when JAX starts)."""
    try:
        return len(jax.devices("cuda")) > 0
    except RuntimeError:  # no such backend
        return False


def cuda_or_default(cuda: Callable, default: Callable):
    """``jax.lax.platform_dependent(cuda=cuda, default=default)``, or
    ``default()`` alone where the process has no CUDA backend, so that a
    CUDA-only branch is not traced there. A program lowered for CUDA on a
    machine without one (an export) then holds the default branch, which
    gives the same results."""
    if not cuda_present():
        return default()
    return jax.lax.platform_dependent(cuda=cuda, default=default)
