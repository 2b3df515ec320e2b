"""Float64 brute-force oracle and list normalisation shared by the tests."""
from __future__ import annotations

import numpy as np
from jax_md import partition


def _square_distances(position, side, periodic):
    """float64 ``(N, N)`` squared minimum-image distances."""
    r = np.asarray(position, np.float64)
    dim = r.shape[1]
    per = np.broadcast_to(np.asarray(periodic, bool), (dim,))
    d = r[:, None, :] - r[None, :, :]
    if per.any():
        L = np.broadcast_to(np.asarray(side, np.float64), (dim,))
        d = np.where(per, d - L * np.round(d / np.where(per, L, 1.0)), d)
    return np.sum(d * d, axis=-1)


def _pairs_of(keep, mask_self):
    if mask_self:
        np.fill_diagonal(keep, False)
    i, j = np.nonzero(keep)
    return set(zip(i.tolist(), j.tolist()))


def brute_pairs(position, cutoff, side=None, periodic=False, mask_self=True):
    """Set of (i, j) with |r_i - r_j| < cutoff, in float64 (min image).

    Args:
      position: ``(N, dim)`` array, any float dtype (cast to float64).
      side: ``(dim,)`` or scalar box side for periodic axes.
      periodic: bool or per-axis bools.
    """
    d2 = _square_distances(position, side, periodic)
    return _pairs_of(d2 < float(cutoff) ** 2, mask_self)


def brute_pairs_radii(position, radii, side=None, periodic=False,
                      mask_self=True):
    """Set of (i, j) with |r_i - r_j| < max(radii_i, radii_j), float64."""
    d2 = _square_distances(position, side, periodic)
    reach = np.asarray(radii, np.float64)
    return _pairs_of(d2 < np.maximum(reach[:, None], reach[None, :]) ** 2,
                     mask_self)


def list_pairs(nbrs) -> set[tuple[int, int]]:
    """Set of (i, j) (i the centre, j its neighbour) in any jax-md layout."""
    idx = np.asarray(nbrs.idx)
    n = np.asarray(nbrs.reference_position).shape[0]
    if nbrs.format is partition.Dense:
        i, k = np.nonzero(idx < n)
        return set(zip(i.tolist(), idx[i, k].tolist()))
    receivers, senders = idx
    keep = receivers < n
    return set(zip(senders[keep].tolist(), receivers[keep].tolist()))


def ordered(pairs):
    """OrderedSparse keeps j < i."""
    return {(i, j) for i, j in pairs if j < i}


def expected_pairs(fmt, pairs):
    return ordered(pairs) if fmt is partition.OrderedSparse else pairs


def assert_layout(nbrs):
    """jax-md's layout invariants: padding N, Dense left-packed, Sparse prefix."""
    idx = np.asarray(nbrs.idx)
    n = np.asarray(nbrs.reference_position).shape[0]
    assert idx.dtype == np.int32
    assert idx.min(initial=0) >= 0 and idx.max(initial=n) <= n
    if nbrs.format is partition.Dense:
        valid = idx < n
        # left-packed: no valid entry after a padding entry
        assert not np.any(~valid[:, :-1] & valid[:, 1:])
        for row in idx:
            row = row[row < n]
            assert len(set(row.tolist())) == len(row), "duplicate neighbour"
    else:
        assert idx.shape[0] == 2
        valid = idx[0] < n
        assert np.array_equal(valid, idx[1] < n)
        assert not np.any(~valid[:-1] & valid[1:]), "valid edges not a prefix"
        edges = list(zip(idx[0][valid].tolist(), idx[1][valid].tolist()))
        assert len(set(edges)) == len(edges), "duplicate edge"


def brute_pairs_general(fractional, box, cutoff, mask_self=True):
    """Set of (i, j) within ``cutoff`` in a triclinic box, float64, with
    jax-md's ``periodic_general`` rule: the fractional difference wrapped
    into [-1/2, 1/2) per axis, then mapped by ``box`` (columns are the
    lattice vectors).

    Args:
      fractional: ``(N, dim)`` fractional coordinates.
      box: ``(dim, dim)`` matrix.
    """
    f = np.asarray(fractional, np.float64)
    b = np.asarray(box, np.float64)
    d = f[:, None, :] - f[None, :, :]
    # jax-md's wrap, not d - round(d): at exactly half a period the two
    # disagree (round halves to even), and in a sheared box the two images
    # of such a pair have different lengths.
    d = np.mod(d + 0.5, 1.0) - 0.5
    cart = np.einsum("ab,ijb->ija", b, d)
    keep = np.sum(cart * cart, axis=-1) < float(cutoff) ** 2
    if mask_self:
        np.fill_diagonal(keep, False)
    i, j = np.nonzero(keep)
    return set(zip(i.tolist(), j.tolist()))


def brute_pairs_shifts(position, cell, pbc, cutoff):
    """Set of (i, j, S0, S1, S2) with |R[j] - R[i] + S @ cell| < cutoff, in
    float64, every image: S_k over ``ceil(cutoff / h_k) + 1`` plus the whole
    cells any atom lies outside the cell (free axes S_k = 0). ``cell`` has
    lattice vectors as rows (ASE's convention); (i, i, 0) is left out.
    """
    r = np.asarray(position, np.float64)
    h = np.asarray(cell, np.float64)
    f = r @ np.linalg.inv(h)
    heights = 1 / np.linalg.norm(np.linalg.inv(h), axis=0)
    spread = np.ceil(np.max(f, axis=0) - np.min(f, axis=0)) if len(r) else 0
    reach = [int(np.ceil(cutoff / heights[k]) + 1 + spread[k]) if pbc[k]
             else 0 for k in range(3)]
    found = set()
    grid = np.meshgrid(*(np.arange(-m, m + 1) for m in reach), indexing="ij")
    shifts = np.stack([g.ravel() for g in grid], axis=1)
    for s in shifts:
        d = r[None, :, :] - r[:, None, :] + s @ h
        keep = np.sqrt(np.sum(d * d, axis=-1)) < cutoff
        if not s.any():
            np.fill_diagonal(keep, False)
        for i, j in zip(*np.nonzero(keep)):
            found.add((int(i), int(j), *map(int, s)))
    return found
