"""The accuracy sweep's error measures, each a pure function of arrays
(tested by hand), and `pareto_front`."""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np


# ---------------------------------------------------------------------------
# Error measures (pure functions of arrays)


def force_rms_rel(force, reference) -> float:
    """``sqrt(mean |F - F_ref|^2) / sqrt(mean |F_ref|^2)`` over particles."""
    f = np.asarray(force, np.float64)
    r = np.asarray(reference, np.float64)
    den = math.sqrt(np.mean(np.sum(r * r, -1)))
    return float(math.sqrt(np.mean(np.sum((f - r) ** 2, -1))) / den)


class Drift(NamedTuple):
    """`energy_drift`'s result: ``slope`` (per particle per ``per``
    steps), ``max_dev`` (``max |E(t) - E(0)| / n``), ``se`` (the slope's
    standard error, from ``blocks`` block means)."""
    slope: float
    max_dev: float
    se: float


def energy_drift(energy, n: int, per: int = 10_000, blocks: int = 10
                 ) -> Drift:
    """The drift of a total-energy series, one value per step: the
    least-squares slope of ``(E(t) - E(0)) / n`` against the step number,
    times ``per`` (drift per particle per ``per`` steps); ``max |E(t) -
    E(0)| / n``; and the slope's standard error: the residual scatter of
    the ``blocks`` block means about their own fitted line (blocks longer
    than the fluctuations' correlation time make the means nearly
    independent), over ``sqrt(sum (t_b - mean t)^2)``, times ``per``."""
    e = (np.asarray(energy, np.float64) - float(energy[0])) / n
    if len(e) < 2:
        return Drift(float("nan"), float(np.abs(e).max(initial=0.0)),
                     float("nan"))
    slope = np.polyfit(np.arange(len(e), dtype=np.float64), e, 1)[0]
    se = float("nan")
    m = len(e) // blocks
    if blocks >= 3 and m >= 1:
        t = np.arange(blocks * m, dtype=np.float64).reshape(blocks, m)
        tb, eb = t.mean(1), e[:blocks * m].reshape(blocks, m).mean(1)
        fit = np.polyfit(tb, eb, 1)
        res = eb - np.polyval(fit, tb)
        se = float(math.sqrt(np.sum(res ** 2) / (blocks - 2))
                   / math.sqrt(np.sum((tb - tb.mean()) ** 2)) * per)
    return Drift(float(slope * per), float(np.abs(e).max()), se)


def _min_image(d, side, periodic):
    side = np.asarray(side, np.float64)
    per = np.asarray(periodic, bool)
    wrap = side * np.round(d / np.where(per, side, 1.0))
    return np.where(per, d - wrap, d)


def _pair_cut(cutoff: float, radii, i, j):
    """The cut of pairs ``(i, j)``: ``cutoff``, or ``max(r_i, r_j)``."""
    if radii is None:
        return cutoff
    return np.maximum(radii[i], radii[j])


def _radii64(radii, n: int):
    if radii is None:
        return None
    r = np.asarray(radii, np.float64)
    if r.shape != (n,):
        raise ValueError(f"radii has shape {r.shape}; the positions have {n} "
                         "particles: pass one radius each.")
    return r


def brute_pairs(position, cutoff: float, side, periodic,
                block: int = 1024, *, radii=None) -> np.ndarray:
    """Sorted codes ``i * n + j`` (i < j) of the pairs closer than
    ``cutoff`` (with ``radii``, float ``(n,)``: closer than ``max(r_i,
    r_j)``, the lists' rule; ``cutoff`` is then unused), float64 brute
    force, minimum image on periodic axes."""
    r = np.asarray(position, np.float64)
    n = len(r)
    radii = _radii64(radii, n)
    codes = []
    for start in range(0, n, block):
        d = _min_image(r[start:start + block, None, :] - r[None], side,
                       periodic)
        rows = np.arange(start, min(start + block, n))
        cut = _pair_cut(cutoff, radii, rows[:, None], np.arange(n)[None])
        i, j = np.nonzero(np.sum(d * d, -1) < cut ** 2)
        i = i + start
        keep = i < j
        codes.append(i[keep].astype(np.int64) * n + j[keep])
    return np.sort(np.concatenate(codes)) if codes else np.zeros(0, np.int64)


def exact_pairs(position, cutoff: float, side, periodic, *, radii=None
                ) -> np.ndarray:
    """`brute_pairs` (``radii`` as there), by scipy's cKDTree in float64
    for large ``n`` (all axes periodic or none); equal to the brute force
    (tested)."""
    r = np.asarray(position, np.float64)
    n = len(r)
    per = np.asarray(periodic, bool)
    if n <= 4096 or (per.any() and not per.all()):
        return brute_pairs(r, cutoff, side, periodic, radii=radii)
    radii = _radii64(radii, n)
    if radii is not None:
        cutoff = float(radii.max())  # the candidates, cut per pair below
    from scipy.spatial import cKDTree
    side = np.asarray(side, np.float64)
    tree = cKDTree(_wrapped(r, side) if per.all() else r,
                   boxsize=side if per.all() else None)
    ij = tree.query_pairs(cutoff, output_type="ndarray").astype(np.int64)
    # query_pairs keeps d <= cutoff; the lists keep d < cutoff.
    d = _min_image(r[ij[:, 0]] - r[ij[:, 1]], side, periodic)
    ij = ij[np.sum(d * d, -1) < _pair_cut(cutoff, radii, ij[:, 0],
                                          ij[:, 1]) ** 2]
    i, j = np.minimum(ij[:, 0], ij[:, 1]), np.maximum(ij[:, 0], ij[:, 1])
    return np.sort(i * n + j)


def pairs_missed(list_codes, reference_codes) -> int:
    """How many pair codes of ``reference_codes`` ``list_codes`` lacks."""
    return int(np.setdiff1d(np.asarray(reference_codes),
                            np.asarray(list_codes)).size)


# A search deciding in the positions' dtype computes each distance from
# rounded inputs (positions plus periodic shifts), rounding each difference
# and product once more: within 16 ulps of that scale, the bound
# tests/pairs/test_pairs.py holds jaxrt.pairs' float32 distances to. A pair that
# close to its cut may fall either side, as jax-md's metric decides;
# a deeper miss is a wrong list.
ROUNDING_ULPS = 16.0


def missed_depth_ulps(list_codes, reference_codes, position, cutoff: float,
                      side, periodic, dtype, *, radii=None) -> float:
    """How deep inside its cut the deepest missed pair lies, in ulps (of
    ``dtype``) of the distances' scale: the largest coordinate plus the
    largest periodic side (or the largest cut, if larger); 0.0 when none
    is missed.

    A search deciding in float32, as jax-md's metric decides, may drop a
    pair whose float64 distance is within rounding of the cut: up to
    `ROUNDING_ULPS` that is; a deeper miss is a wrong list. Args: codes as
    `pairs_missed`; ``position`` float ``(n, dim)`` (compared in float64);
    ``radii`` as `brute_pairs`.
    """
    miss = np.setdiff1d(np.asarray(reference_codes), np.asarray(list_codes))
    if miss.size == 0:
        return 0.0
    r = np.asarray(position, np.float64)
    n = len(r)
    i, j = miss // n, miss % n
    d = np.sqrt(np.sum(_min_image(r[i] - r[j], side, periodic) ** 2, -1))
    cut = np.broadcast_to(_pair_cut(cutoff, _radii64(radii, n), i, j),
                          d.shape)
    per = np.asarray(periodic, bool)
    scale = max(float(np.max(cut)), float(np.max(np.abs(r))) + float(
        np.max(np.where(per, np.asarray(side, np.float64), 0.0),
               initial=0.0)))
    return float(np.max(cut - d) / (np.finfo(dtype).eps * scale))


def rdf_grid(r_max: float, dr: float) -> np.ndarray:
    """Bin edges ``0, dr, ..., r_max`` of `rdf`."""
    return np.arange(0.0, r_max + 0.5 * dr, dr)


def rdf(frames, side, edges) -> np.ndarray:
    """g(r) of frames ``(F, N, dim)`` in a periodic box of sides ``side``
    on bin ``edges`` (every axis periodic; ``edges[-1]`` at most half the
    shortest side): pair counts per bin, averaged over frames, over the
    ideal gas's ``N/2 · rho · shell volume``."""
    frames = np.asarray(frames, np.float64)
    if frames.ndim == 2:
        frames = frames[None]
    f, n, dim = frames.shape
    side = np.asarray(side, np.float64)
    counts = np.zeros(len(edges) - 1)
    for r in frames:
        counts += np.histogram(pair_distances(r, side, edges[-1]),
                               bins=edges)[0]
    rho = n / np.prod(side)
    ball = {1: 2.0, 2: math.pi, 3: 4.0 * math.pi / 3.0}[dim]
    shell = ball * (edges[1:] ** dim - edges[:-1] ** dim)
    return counts / f / (0.5 * n * rho * shell)


def _wrapped(r, side):
    """``r`` in ``[0, side)`` (cKDTree's periodic boxes refuse ``side``)."""
    x = np.mod(r, side)
    return np.where(x >= side, x - side, x)


def pair_distances(r, side, r_max, kd: bool | None = None):
    """Distances below ``r_max`` of the pairs i < j, minimum image on
    every axis; by cKDTree for large ``n`` (``kd`` forces either way)."""
    n = len(r)
    if kd if kd is not None else n > 4096:
        from scipy.spatial import cKDTree
        ij = cKDTree(_wrapped(r, side), boxsize=side).query_pairs(
            r_max, output_type="ndarray")
        d = _min_image(r[ij[:, 0]] - r[ij[:, 1]], side,
                       np.ones(len(side), bool))
        dist = np.sqrt(np.sum(d * d, -1))
        return dist[dist < r_max]
    out = []
    for start in range(0, n, 1024):
        d = _min_image(r[start:start + 1024, None, :] - r[None], side,
                       np.ones(len(side), bool))
        dist = np.sqrt(np.sum(d * d, -1))
        i, j = np.nonzero(dist < r_max)
        keep = (i + start) < j
        out.append(dist[i[keep], j[keep]])
    return np.concatenate(out)


def rdf_difference(g, g_ref, dr: float) -> tuple[float, float]:
    """``(L2, Linf)``: ``sqrt(sum (g - g_ref)^2 dr)`` and
    ``max |g - g_ref|``."""
    d = np.asarray(g, np.float64) - np.asarray(g_ref, np.float64)
    return float(math.sqrt(np.sum(d * d) * dr)), float(np.abs(d).max())


def position_rms(a, b, side, periodic) -> float:
    """RMS over particles of the (minimum-image) distance between ``a`` and
    ``b``."""
    d = _min_image(np.asarray(a, np.float64) - np.asarray(b, np.float64),
                   side, periodic)
    return float(math.sqrt(np.mean(np.sum(d * d, -1))))


def pareto_front(times, errors) -> list[int]:
    """Indices of the points that no other point beats in both time and
    error (less or equal in both, less in one), by increasing time; NaNs
    are never on the front."""
    t = np.asarray(times, np.float64)
    e = np.asarray(errors, np.float64)
    ok = np.flatnonzero(np.isfinite(t) & np.isfinite(e))
    front = []
    for i in ok:
        beaten = np.any((t[ok] <= t[i]) & (e[ok] <= e[i])
                        & ((t[ok] < t[i]) | (e[ok] < e[i])))
        if not beaten:
            front.append(int(i))
    # Equal points: keep the first.
    seen, out = set(), []
    for i in sorted(front, key=lambda i: (t[i], e[i], i)):
        if (t[i], e[i]) not in seen:
            seen.add((t[i], e[i]))
            out.append(i)
    return out
