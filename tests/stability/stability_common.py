"""Helpers shared by the stability suite (the float64 oracle itself is
tests/oracle.py)."""
from __future__ import annotations

import jax
import numpy as np
import pytest
from jax_md import partition

import jaxrt

FORMATS = [partition.Dense, partition.Sparse, partition.OrderedSparse]
WARP = [b for b in ("bvh", "spheres", "squares")
        if b in jaxrt.available_backends()]
# Every 3D backend; radii are supported by brute, cell and bvh only.
BACKENDS_3D = ["brute", "cell"] + WARP
RADII_BACKENDS = ["brute", "cell"] + [b for b in WARP if b == "bvh"]


def jax_md_pairs(metric, box, cutoff, R, fmt=partition.Dense, **kw):
    """jax-md's all-pairs list: the metric decides every pair."""
    from oracle import list_pairs
    nbrs = partition.neighbor_list(metric, box, cutoff, format=fmt,
                                   disable_cell_list=True, **kw).allocate(R)
    return list_pairs(nbrs)


def ulp_neighbours(x, dtype):
    """(x one ulp below, x, one ulp above) in ``dtype``."""
    x = dtype(x)
    return (np.nextafter(x, dtype(-np.inf)), x, np.nextafter(x, dtype(np.inf)))


def grid(fast, xfail=None, **axes):
    """pytest params over the product of ``axes`` (name -> values); a
    combination is in the fast part iff ``fast(**combination)``, else it is
    marked slow (the fast part must stay within ~90 s on a 2-core CPU).
    ``xfail(**combination)``: None, or the reason of a known bug (strict
    xfail: the case must fail while the bug is there)."""
    import itertools
    names = list(axes)
    params = []
    for combo in itertools.product(*axes.values()):
        kw = dict(zip(names, combo))
        marks = () if fast(**kw) else (pytest.mark.slow,)
        reason = xfail(**kw) if xfail is not None else None
        if reason:
            marks += (pytest.mark.xfail(strict=True, reason=reason),)
        params.append(pytest.param(*combo, marks=marks,
                                   id="-".join(_name(v) for v in combo)))
    return ",".join(names), params


def _name(v):
    if isinstance(v, type):
        return v.__name__
    return getattr(v, "name", None) or str(v)
