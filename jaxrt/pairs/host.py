"""The pairs of one small system on the host, in numpy, for eager calls of
`jaxrt.pairs`: every candidate ``(i, j, S)`` decided at once, as the
program (`jaxrt.pairs.program`) decides it, with no program to dispatch
(which is most of the time of a system of a few atoms)."""
from __future__ import annotations

import functools
import itertools

import numpy as np

from jaxrt.pairs.bits import ErrorBit


def lex_positive(s):
    """bool ``(...)``: ``s`` (int ``(..., 3)``, numpy or JAX)
    lexicographically > 0."""
    return (s[..., 0] > 0) | ((s[..., 0] == 0) & (
        (s[..., 1] > 0) | ((s[..., 1] == 0) & (s[..., 2] > 0))))


@functools.lru_cache(maxsize=64)
def _host_stencil(reach):
    """int32 ``(M, 3)`` every offset within ``reach``, bool ``(M,)`` the
    lexicographically positive ones, and the zero offset's index (cached:
    an eager call builds them once)."""
    every = np.array(list(itertools.product(
        *(range(-k, k + 1) for k in reach))), np.int32)
    every.flags.writeable = False
    lex = lex_positive(every)
    return every, lex, int(np.argmin(np.abs(every).sum(axis=1)))


_HOST_VECTORS: dict = {}


def _host_vectors(h, reach):
    """``S @ h`` of every offset of the stencil (the program's sum of three
    products, in ``h``'s dtype), kept by the cell's bytes: the frames of
    one structure share their cell."""
    key = (h.dtype.str, h.tobytes(), reach)
    found = _HOST_VECTORS.get(key)
    if found is None:
        sf = _host_stencil(reach)[0].astype(h.dtype)
        found = (sf[:, 0:1] * h[0] + sf[:, 1:2] * h[1]) + sf[:, 2:3] * h[2]
        found.flags.writeable = False
        if len(_HOST_VECTORS) >= 256:
            _HOST_VECTORS.clear()
        _HOST_VECTORS[key] = found
    return found


def search_small_host(positions, mask, h, hinv, cutoff, species, *,
                      periodic: tuple[bool, ...], reach: tuple[int, ...],
                      half: bool, self_interaction: bool):
    """The pairs of one small system in numpy, for eager calls on host
    arrays: every candidate ``(i, j, S)`` at once (no grid, no loop, no
    program to dispatch, which is most of the time of a system of a few
    atoms), decided as `search` decides (``d`` computed as there, in the
    positions' dtype; ``d(j, i, -S)`` is ``-d(i, j, S)`` bit for bit), in
    ``i``-major order (sorted by ``i``).

    Args:
      positions: numpy float ``(N, 3)``; mask: bool ``(N,)``; h, hinv:
        numpy ``(3, 3)`` the completed cell and its inverse, in the
        positions' dtype; cutoff: float, or numpy ``(S, S)``; species: int
        ``(N,)`` or None.
      periodic, reach: static; the cell needs no shift past ``reach``
        (checked on the host); half, self_interaction: as `search`.
    Returns:
      int32 ``(count, 5)`` rows ``(i, j, S)`` (exactly the pairs) and the
      int error bits.
    """
    dtype = positions.dtype
    n = positions.shape[0]
    reach = tuple(reach)
    everyone = bool(mask.all()) and bool(np.isfinite(positions).all())
    if everyone:
        error, real, r = 0, mask, positions
    else:
        finite = np.isfinite(positions).all(axis=1)
        error = int(ErrorBit.NONFINITE_POSITION) if np.any(
            mask & ~finite) else 0
        real = mask & finite
        r = np.where(real[:, None], positions, 0).astype(dtype)
    every, lex_every, zero = _host_stencil(reach)
    # (Few numpy calls: each costs more than its arithmetic here.)
    w = np.floor(r @ hinv) if any(periodic) else None
    if w is not None and not all(periodic):
        w[:, ~np.array(periodic)] = 0
    moved = w is not None and bool(w.any())
    if not moved:
        # Atoms inside the cell: S is the offset, its vector cached.
        vectors = _host_vectors(np.asarray(h, dtype), reach)
        d = (r[None, :, None, :] - r[:, None, None, :]) + vectors
    else:
        w = w.astype(np.int32)
        s = every + (w[:, None, None, :] - w[None, :, None, :])
        sf = s.astype(dtype)
        d = (r[None, :, None, :] - r[:, None, None, :]) + (
            (sf[..., 0:1] * h[0] + sf[..., 1:2] * h[1]) + sf[..., 2:3] * h[2])
    d2 = d * d
    dist = np.sqrt((d2[..., 0] + d2[..., 1]) + d2[..., 2])
    if species is None:
        keep = dist < np.asarray(cutoff, dtype)
    else:
        keep = dist < np.asarray(cutoff, dtype)[species[:, None, None],
                                                species[None, :, None]]
    if not everyone:
        keep &= real[:, None, None] & real[None, :, None]
    atoms = np.arange(n)
    if half:
        lex = lex_positive(s) if moved else lex_every
        zeros = np.zeros(len(every), bool)
        zeros[zero] = True
        same = atoms[:, None, None] == atoms[None, :, None]
        keep &= (atoms[:, None, None] < atoms[None, :, None]) | (
            same & (lex | zeros))
    if not self_interaction:  # (i, i, 0) otherwise kept where 0 < rc
        keep[atoms, atoms, zero] = False
    i, j, m = np.nonzero(keep)
    rows = np.empty((len(i), 5), np.int32)
    rows[:, 0], rows[:, 1] = i, j
    rows[:, 2:] = s[i, j, m] if moved else every[m]
    return rows, error
