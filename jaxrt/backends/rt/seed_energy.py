"""The pair interaction of seed 001's fused (list-free) mode: Algis & Bramas
(2024), §5 ("the computation step includes ... performing the
interactions") and their code [OptixLJ]: the Lennard-Jones energy is
computed inside the intersection / any-hit program of each method, summed
in the ray's payload and added once per ray into ``energy[i]`` with an
``atomicAdd``.

The kernels that do it sit next to each method's list kernel:
`jaxrt.backends.rt.aabb` (``_energy_kernel``, §4.4), `jaxrt.backends.rt.spheres` and
`jaxrt.backends.rt.squares` (their ray kernels' fused mode, §4.2 and §4.3). This
module holds only what they share: the pair function and its parameters.

The quantity is the one `benchmarks/seed_rt/worker.py` sums from each
method's Dense list, so that a list run and a fused run of the study can be
compared value for value::

    U(r) = 4 eps [(sigma^2 / r2)^6 - (sigma^2 / r2)^3],  r2 = max(|r_ij|^2, r2_min)

for every ordered pair ``i != j`` with ``|r_ij|^2 < C^2`` (the method's own
strict test), and ``E_i = sum_j U(r_ij)``: each unordered pair is in both
``E_i`` and ``E_j`` (as in the seed, where every particle's rays sum over
all its neighbours), so ``sum_i E_i`` is twice the system's energy. The
paper takes ``sigma = eps = 1``; the study takes ``sigma = C/2`` (with C
as small as 1/32, sigma = 1 overflows float32 at r < 1e-3).

``r2_min`` (the study: ``(sigma/10)^2``) keeps pairs closer than that,
coincident particles included, finite: they contribute ``U`` at
``sqrt(r2_min)`` (about ``4e12 eps`` at sigma/10), never inf or NaN. A
non-finite particle casts no ray and is nobody's neighbour in every
method, so it adds nothing.

Pure Warp: nothing here knows of JAX (`jaxrt.backends.rt.ffi` wraps it).
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
import warp as wp

# Layout of the ``params`` array (position precision) of the fused kernels.
SIGMA_SQ, EPSILON, R2_MIN = range(3)
N_PARAMS = 3


@wp.func
def clamped_lj(d2: Any, params: wp.array(dtype=Any)):
    """``U`` at squared distance ``d2``, in ``d2``'s precision (the
    parameters are cast to it): the worker's JAX arithmetic, operation for
    operation (``max``, one division, ``s*s*s``, ``s6*s6 - s6``)."""
    r2 = wp.max(d2, type(d2)(params[R2_MIN]))
    s = type(d2)(params[SIGMA_SQ]) / r2
    s6 = s * s * s
    return type(d2)(4.0) * type(d2)(params[EPSILON]) * (s6 * s6 - s6)


def lj_params(*, sigma: float, epsilon: float = 1.0, r_min: float | None = None,
              dtype=np.float32) -> np.ndarray:
    """The ``params`` array of the fused kernels, ``(N_PARAMS,)`` in
    ``dtype`` (the positions' float32 or float64).

    Args:
      sigma: LJ sigma (> 0, finite).
      epsilon: LJ epsilon (finite).
      r_min: distance below which pairs are clamped (>= 0); default
        ``sigma / 10``, the study's.
    Raises:
      ValueError: naming the bad argument.
    """
    if not (isinstance(sigma, (int, float, np.floating)) and math.isfinite(sigma)
            and sigma > 0):
        raise ValueError(f"sigma must be a finite number > 0; got {sigma!r}.")
    if not (isinstance(epsilon, (int, float, np.floating)) and math.isfinite(epsilon)):
        raise ValueError(f"epsilon must be a finite number; got {epsilon!r}.")
    r_min = 0.1 * float(sigma) if r_min is None else r_min
    if not (isinstance(r_min, (int, float, np.floating)) and math.isfinite(r_min)
            and r_min >= 0):
        raise ValueError(f"r_min must be a finite number >= 0 (pairs closer are "
                         f"clamped to it); got {r_min!r}.")
    if r_min == 0:
        # Coincident particles would give inf - inf = NaN.
        raise ValueError("r_min = 0 lets coincident particles give NaN energies; "
                         "pass r_min > 0 (default sigma / 10).")
    out = np.empty(N_PARAMS, dtype=dtype)
    # As the worker's JAX code: Python-float products, rounded once.
    out[SIGMA_SQ] = float(sigma) * float(sigma)
    out[EPSILON] = float(epsilon)
    out[R2_MIN] = float(r_min) ** 2
    return out
