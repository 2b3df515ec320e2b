"""Spatial orderings of particles, for the memory locality of list gathers.

A Dense list's forces read ``R[idx]``: ``N x capacity`` gathers whose
addresses are the neighbours' indices. Particles numbered in random order
(a snapshot from another code, particles inserted over time, a lattice
shuffled for a test) send those gathers all over the position array; once
it no longer fits the cache, every gather is a miss. Numbering particles
along a space-filling curve makes neighbours near in space near in memory,
which is what LAMMPS' ``atom_modify sort`` and HOOMD's sorter do every few
hundred steps.

`spatial_order` gives the permutation (jit-compatible, static shapes);
`reorder` applies it to a state's per-particle arrays; `inverse_order`
maps results back to the caller's numbering. A Verlet list stays right
across a reorder: ``nbrs.update(R[perm])`` sees particles "moved" from
their reference positions and rebuilds whenever one did by more than half
the skin, and if none did, the old list is still a valid list for the new
positions (every index's position is within half the skin of the one it
was built from).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

Array = jax.Array

CURVES = ("morton", "hilbert", "cells")

# Bits per axis of a curve key, so that a key fits int32 (3 x 10, 2 x 15).
_BITS = {2: 15, 3: 10}


def _fractional(position: Array, box) -> Array:
    """Positions mapped into ``[0, 1)^dim``: wrapped in a periodic box,
    or scaled to the particles' bounding box when ``box`` is None."""
    if box is None:
        lo = jnp.min(position, axis=0)
        hi = jnp.max(position, axis=0)
        # The top particle maps just below 1, not onto the next bin.
        span = (hi - lo) * (1 + 1e-6) + jnp.finfo(position.dtype).tiny
        return (position - lo) / span
    box = jnp.asarray(box, position.dtype)
    if box.ndim == 2:
        u = jnp.linalg.solve(box, position.T).T
    else:
        u = position / box
    return u - jnp.floor(u)


def _morton_key(bins: Array, bits: int) -> Array:
    """int32 key interleaving the bits of ``bins`` (``(N, dim)``,
    each in ``[0, 2**bits)``), axis 0 most significant."""
    dim = bins.shape[1]
    key = jnp.zeros(bins.shape[0], jnp.int32)
    for b in range(bits - 1, -1, -1):
        for a in range(dim):
            key = (key << 1) | ((bins[:, a] >> b) & 1)
    return key


def _hilbert_key(bins: Array, bits: int) -> Array:
    """int32 Hilbert index of ``bins`` (``(N, dim)`` in ``[0, 2**bits)``):
    the axes turned into the index's transposed bits as in Skilling's
    "Programming the Hilbert curve" (2004), then interleaved like a Morton
    key."""
    dim = bins.shape[1]
    x = [bins[:, a] for a in range(dim)]
    q = 1 << (bits - 1)
    while q > 1:  # coarse to fine: each level's reflections and swaps
        p = q - 1
        for a in range(dim):
            hit = (x[a] & q) != 0
            # Bit q of axis a set: flip the low bits of axis 0; else swap
            # the low bits of axes 0 and a.
            flip0 = jnp.where(hit, x[0] ^ p, x[0])
            t = (x[0] ^ x[a]) & p
            x0 = jnp.where(hit, flip0, x[0] ^ t)
            xa = jnp.where(hit, x[a], x[a] ^ t)
            x[0] = x0
            if a:
                x[a] = xa
        q >>= 1
    for a in range(1, dim):  # Gray encode
        x[a] = x[a] ^ x[a - 1]
    t = jnp.zeros_like(x[0])
    q = 1 << (bits - 1)
    while q > 1:
        t = jnp.where((x[dim - 1] & q) != 0, t ^ (q - 1), t)
        q >>= 1
    x = [v ^ t for v in x]
    return _morton_key(jnp.stack(x, axis=1), bits)


def _check(position, box, cell_size, curve) -> tuple[int, int]:
    if curve not in CURVES:
        raise ValueError(f"curve={curve!r}: pass one of {CURVES}.")
    shape = getattr(position, "shape", None)
    if shape is None or len(shape) != 2 or shape[1] not in _BITS:
        raise ValueError(f"position of shape {shape}: pass float positions "
                         "of shape (N, 2) or (N, 3).")
    if not jnp.issubdtype(jnp.asarray(position).dtype, jnp.floating):
        raise ValueError("position: pass float positions (float32 or "
                         "float64), not integers.")
    dim = shape[1]
    if box is not None:
        bshape = np.shape(box)
        if bshape not in ((), (dim,), (dim, dim)):
            raise ValueError(f"box of shape {bshape}: pass a scalar, "
                             f"({dim},) sides or a ({dim}, {dim}) matrix "
                             "with the lattice vectors as columns, or "
                             "None for free space.")
    if curve == "cells":
        if cell_size is None:
            raise ValueError("curve='cells' needs cell_size= (e.g. the "
                             "cutoff, or half of it, as LAMMPS' binsize).")
        if box is None or np.shape(box) == (dim, dim):
            raise ValueError("curve='cells' bins an orthorhombic periodic "
                             "box: pass box= as a scalar or sides, or use "
                             "curve='morton' / 'hilbert'.")
    elif cell_size is not None:
        raise ValueError(f"cell_size= is for curve='cells'; curve={curve!r} "
                         "bins at 2**bits per axis: drop cell_size.")
    return dim, _BITS[dim]


def _bin_counts(box, cell_size: float, dim: int) -> np.ndarray:
    """Bins per axis of ``curve="cells"``: a static size, so ``box`` must
    be concrete."""
    try:
        sides = np.broadcast_to(np.asarray(box, np.float64), (dim,))
    except jax.errors.TracerArrayConversionError:
        raise ValueError("curve='cells' with a traced box: pass box= as a "
                         "Python or numpy value (it sets the number of "
                         "bins, a static size).") from None
    if not cell_size > 0:
        raise ValueError(f"cell_size={cell_size!r}: pass a positive bin side.")
    counts = np.maximum(np.floor(sides / cell_size), 1).astype(np.int64)
    if np.prod(counts, dtype=np.float64) >= 2 ** 31:
        raise ValueError(f"{counts.tolist()} bins overflow int32: pass a "
                         "larger cell_size.")
    return counts.astype(np.int32)


def spatial_order(position: Array, box=None, *, curve: str = "hilbert",
                  cell_size: float | None = None) -> Array:
    """A permutation that numbers particles along a space-filling curve.

    Args:
      position: float ``(N, 2)`` or ``(N, 3)``.
      box: a periodic box as scalar, ``(dim,)`` sides or ``(dim, dim)``
        lattice vectors as columns (positions are wrapped into it), or None
        for free space (the particles' bounding box is binned).
      curve: ``"hilbert"`` (neighbours in space nearest in index),
        ``"morton"`` (Z-order, cheaper keys), or ``"cells"``: bins of
        ``cell_size`` numbered x-major, particles within a bin in their
        current order (LAMMPS' binned sort).
      cell_size: the bin side for ``curve="cells"`` (in ``position``'s
        units); the curves bin each axis into ``2**10`` (3D) or ``2**15``
        (2D) slots.
    Returns:
      int32 ``(N,)`` ``perm``: particle ``perm[k]`` goes to slot ``k``
      (``R_new = R[perm]``; `reorder`). Ties keep the current order, so a
      second call on ordered particles returns the identity.
    """
    dim, bits = _check(position, box, cell_size, curve)
    position = jnp.asarray(position)
    u = _fractional(position, box)
    if curve == "cells":
        counts = _bin_counts(box, cell_size, dim)
        bins = jnp.minimum((u * counts).astype(jnp.int32), counts - 1)
        key = jnp.zeros(position.shape[0], jnp.int32)
        for a in range(dim):
            key = key * int(counts[a]) + bins[:, a]
    else:
        slots = 1 << bits
        bins = jnp.clip((u * slots).astype(jnp.int32), 0, slots - 1)
        key = (_hilbert_key if curve == "hilbert" else _morton_key)(bins, bits)
    return jnp.argsort(key, stable=True).astype(jnp.int32)


def inverse_order(perm: Array) -> Array:
    """The inverse permutation: int32 ``(N,)`` ``inv`` with
    ``inv[perm[k]] == k``, so ``X_new[inv]`` is ``X`` in the old numbering."""
    perm = jnp.asarray(perm)
    n = perm.shape[0]
    return jnp.zeros(n, jnp.int32).at[perm].set(jnp.arange(n, dtype=jnp.int32))


def reorder(perm: Array, tree):
    """``tree`` (a state, a tuple of arrays, ...) with every array leaf whose
    leading axis has ``len(perm)`` entries taken in the order ``perm``.

    Args:
      perm: int ``(N,)`` from `spatial_order`.
      tree: any pytree, e.g. jax-md's ``NVEState`` (position, momentum,
        force, mass) or ``(R, V, species)``. Scalars and arrays of another
        leading size pass unchanged.
    Returns:
      the same structure, per-particle leaves as ``leaf[perm]``.

    Per-pair ``(N, N)`` arrays need both axes permuted (``m[perm][:,
    perm]``); this gathers only the first, so pass such arrays yourself.
    Parameters that an energy factory captured at its construction (e.g.
    jax-md's ``species=``) are not in ``tree``: pass them at call time or
    build the factory again.
    """
    perm = jnp.asarray(perm)
    if perm.ndim != 1 or not jnp.issubdtype(perm.dtype, jnp.integer):
        raise ValueError(f"perm of shape {perm.shape} and dtype {perm.dtype}"
                         ": pass the int (N,) permutation of spatial_order.")
    n = perm.shape[0]

    def take(leaf):
        if hasattr(leaf, "shape") and leaf.ndim >= 1 and leaf.shape[0] == n:
            return jnp.asarray(leaf)[perm]
        return leaf

    return jax.tree.map(take, tree)
