"""The dense blocks of `jaxrt.pairs.program` (``max_nodes > 0``, its
docstring): each small system of a flat batch searched as one block, every
atom against every atom of its system in every image of the reach, read by
32-atom tiles past 32 atoms; no cells."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxrt.pairs.bits import ErrorBit
from jaxrt.pairs.cells import frame, offsets, shift_vectors
from jaxrt.pairs.checks import DENSE_WORD as _WORD
from jaxrt.pairs.host import lex_positive
from jaxrt.pairs.prefix import exclusive_prefix, prefix_sum, row_ranks
from jaxrt.pairs.rows import self_mask
from jaxrt.pairs.words import pack, popcount, row_words, select_bit


# Dense blocks of more than one word are read by 32-atom tiles (`dense_rows`):
# the (atom, tile, image) words decided this many at a time in a loop, ...
TILE_CHUNK = 2 ** 13
# ... a tile dropped only where the cutoff, grown by this much (relatively)
# and by this many of the dtype's epsilons per unit of fractional
# coordinate, does not reach its box: only where the exact test would drop
# every atom of it (the wrapped fractional coordinates' rounding is far
# smaller).
TILE_MARGIN = 2.0 ** -10
TILE_EPS = 2.0 ** 8


def _dense_setup(positions, graph, mask, cells, pbc, cut, species, radius,
                 *, reach, max_nodes, n_graph, completed, self_interaction):
    """What every dense block reads: each system's atoms as ``(G, M)``
    slots (the frame's arrays gathered), the stencil, the error bits."""
    n = positions.shape[0]
    g, m = n_graph, max_nodes
    fr = frame(positions, graph, mask, cells, pbc, n_graph=n_graph,
                completed=completed)
    stencil = offsets(reach, full=True)
    # Each system's atoms are contiguous (a flat batch): slot = a - first.
    sizes = jnp.zeros((g,), jnp.int32).at[fr.unclipped].add(1, mode="drop")
    first = exclusive_prefix(sizes)
    slot = jnp.arange(n, dtype=jnp.int32) - first[fr.graph]
    error = fr.error | jnp.where(jnp.any(fr.real & (slot >= m)),
                                 int(ErrorBit.MAX_NODES), 0)
    short = jnp.any(pbc & (radius / fr.h_height > np.array(reach)),
                    axis=-1) & (fr.count > 0) & ~fr.bad_cell
    error = error | jnp.where(jnp.any(short), int(ErrorBit.MAX_SHIFT), 0)
    slots = jnp.arange(m, dtype=jnp.int32)
    idx = first[:, None] + slots
    present = slots < sizes[:, None]
    at = jnp.where(present, idx, 0)
    real = present & fr.real[at]                                  # (G, M)
    o = jnp.asarray(stencil)
    if self_interaction:
        selfs = self_mask(fr.real, cut, species)[at] & real
    else:
        selfs = jnp.zeros((g, m), bool)
    return dict(
        n=n, fr=fr, error=error, first=first, idx=idx, real=real,
        p=positions[at], w=fr.w[at].astype(jnp.int32), fw=fr.fw[at],
        sp=None if species is None else species[at], o=o,
        own=int(np.argmin(np.abs(stencil).sum(axis=1))),
        # On a free axis only the zero offset (its wrap is 0).
        allowed=jnp.all(pbc[:, None, :] | (o == 0)[None], axis=-1),  # (G, K)
        selfs=selfs)


def _dense_full(st, cut, species, *, m, half):
    """Every atom against every atom of its system in every image: uint32
    ``(G, M, K W)`` words, word ``k W + t`` holding slots ``32 t ..`` in
    image ``k``."""
    g = st["real"].shape[0]
    dtype = st["p"].dtype
    p, w, o, real = st["p"], st["w"], st["o"], st["real"]
    k_offsets = o.shape[0]
    slots = jnp.arange(m, dtype=jnp.int32)
    s = (o[None, None, :, None, :] + w[:, :, None, None, :]
         - w[:, None, None, :, :])                          # (G, M, K, M, 3)
    diff = p[:, None, :, :] - p[:, :, None, :]              # (G, Mi, Mj, 3)
    d = diff[:, :, None] + shift_vectors(
        s.astype(dtype), st["fr"].h[:, None, None, None])
    dist = jnp.sqrt(d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1]
                    + d[..., 2] * d[..., 2])
    if species is None:
        limit = cut
    else:
        sp = st["sp"]
        limit = cut.at[sp[:, :, None], sp[:, None, :]].get(
            mode="fill", fill_value=0)[:, :, None, :]
    same = (slots[:, None] == slots[None, :])[None, :, None, :]
    not_self = ~(same & (jnp.arange(k_offsets) == st["own"])[
        None, None, :, None])
    keep = ((dist < limit) & real[:, :, None, None] & real[:, None, None, :]
            & st["allowed"][:, None, :, None] & not_self)
    if half:
        before = (slots[:, None] < slots[None, :])[None, :, None, :]
        keep = keep & (before | (same & lex_positive(s)))
    words = -(-m // _WORD)
    keep = jnp.pad(keep, ((0, 0), (0, 0), (0, 0), (0, words * _WORD - m)))
    return pack(keep).reshape(g, m, k_offsets * words)


def _morton(u, bits: int = 3):
    """int32 Morton codes of ``u`` in ``[0, 1]`` ``(..., 3)``, ``bits``
    per axis."""
    q = jnp.clip(jnp.floor(u * (1 << bits)), 0, (1 << bits) - 1).astype(
        jnp.int32)
    code = jnp.zeros(u.shape[:-1], jnp.int32)
    for b in range(bits - 1, -1, -1):
        for a in range(3):
            code = code * 2 + ((q[..., a] >> b) & 1)
    return code


def _dense_tiles(st, radius, *, m, budget, self_interaction):
    """The words each atom reads (`dense_rows`), listed flat, atom by
    atom: int32 ``(budget,)`` entries ``a C' + c`` (slot ``a = g M + i``;
    ``c = 0`` its self pair where ``self_interaction``, then ``lead + k T +
    t``: tile ``t`` in image ``k``; ``G M C'`` past the last), int32 the
    entries needed (the list is whole only if at most ``budget``), and the
    sort, int32 ``(G, 32 T)`` sorted slot -> slot (``M`` past the atoms).

    An atom reads tile ``t`` in image ``o`` unless, on some axis ``k``, the
    tile's box of wrapped fractional coordinates is farther from it than
    the cutoff: ``|d| >= |f_j - f_i + o|_k h_k`` (``h_k`` the height), so
    no atom of the tile is within the cutoff in that image
    (`TILE_MARGIN`)."""
    g = st["real"].shape[0]
    dtype = st["p"].dtype
    real, fw, o = st["real"], st["fw"], st["o"]
    tiles = -(-m // _WORD)
    big = jnp.asarray(jnp.finfo(dtype).max, dtype)
    lo = jnp.min(jnp.where(real[..., None], fw, big), axis=1)     # (G, 3)
    hi = jnp.max(jnp.where(real[..., None], fw, -big), axis=1)
    span = jnp.maximum(hi - lo, 0)
    u = (fw - lo[:, None]) / jnp.where(span > 0, span, 1)[:, None]
    key = jnp.where(real, _morton(u), 1 << 30)
    order = jnp.argsort(key, axis=1, stable=True).astype(jnp.int32)
    pad = tiles * _WORD - m
    # The last tile's missing slots are slot m: past every atom (padded
    # below wherever a tile reads it, so never real).
    order = jnp.pad(order, ((0, 0), (0, pad)), constant_values=m)
    real_s = jnp.pad(jnp.take_along_axis(real, order[:, :m], axis=1),
                     ((0, 0), (0, pad)))
    fw_s = jnp.take_along_axis(fw, jnp.minimum(order, m - 1)[..., None],
                               axis=1)
    real_t = real_s.reshape(g, tiles, _WORD)
    fw_t = fw_s.reshape(g, tiles, _WORD, 3)
    t_lo = jnp.min(jnp.where(real_t[..., None], fw_t, big), axis=2)
    t_hi = jnp.max(jnp.where(real_t[..., None], fw_t, -big), axis=2)
    filled = jnp.any(real_t, axis=2)                               # (G, T)
    # |d| >= |f_j - f_i + o|_k h_k on each axis k: the gap between the
    # atom and the tile's box, in heights.
    of = o.astype(dtype)
    gap = jnp.maximum(jnp.maximum(
        t_lo[:, None, None, :, :] + of[None, None, :, None, :]
        - fw[:, :, None, None, :],
        fw[:, :, None, None, :] - of[None, None, :, None, :]
        - t_hi[:, None, None, :, :]), 0)                    # (G, M, K, T, 3)
    scale = 1 + jnp.max(jnp.abs(fw), axis=(1, 2))                  # (G,)
    reach = (radius / st["fr"].h_height) * (1 + TILE_MARGIN) + (
        TILE_EPS * jnp.finfo(dtype).eps * scale)[:, None]          # (G, 3)
    near = jnp.all(gap < reach[:, None, None, None, :], axis=-1)
    near = (near & filled[:, None, None, :] & real[:, :, None, None]
            & st["allowed"][:, None, :, None]).reshape(g, m, -1)
    if self_interaction:
        near = jnp.concatenate([st["selfs"][..., None], near], axis=-1)
    # Each entry's place: the words listed before its atom's, then its
    # rank among the atom's (float32 block products: a few thousand words
    # per atom at most).
    near = near.reshape(g * m, -1)
    ranks = row_ranks(near)
    count = ranks[:, -1]
    at = exclusive_prefix(count)[:, None] + ranks - 1
    needed = jnp.sum(count, dtype=jnp.int32)
    entries = jnp.full((budget,), near.size, jnp.int32).at[
        jnp.where(near, at, budget).reshape(-1)].set(
            jnp.arange(near.size, dtype=jnp.int32), mode="drop")
    return entries, needed, order


def _dense_tile_rows(st, cut, species, entries, needed, order, *, m, half,
                     self_interaction, capacity):
    """The rows of the entries of `_dense_tiles` (all of them: ``needed``
    at most their number): the words decided exactly (as `_dense_full`),
    ``TILE_CHUNK`` entries at a time in a loop (the work follows the words
    there are), then placed and read as `_dense_decode` reads its words.
    Returns int32 ``(capacity, 5)`` rows, the count and the count per
    system."""
    g = st["real"].shape[0]
    dtype = st["p"].dtype
    p, w, o, real = st["p"], st["w"], st["o"], st["real"]
    k_offsets = o.shape[0]
    tiles = order.shape[1] // _WORD
    lead = int(self_interaction)
    width = lead + k_offsets * tiles
    pad = tiles * _WORD - m
    p_flat, w_flat = p.reshape(-1, 3), w.reshape(-1, 3)
    sp_flat = None if species is None else st["sp"].reshape(-1)

    def tiled(x):
        """``(G T, ..., 32)`` of ``(G, M, ...)``: the tiles' slots last
        (each coordinate one ``(E, 32)`` array below: no ``(E, 32, 3)``
        array is ever made)."""
        x = jnp.pad(x, ((0, 0), (0, pad)) + ((0, 0),) * (x.ndim - 2))
        x = jnp.take_along_axis(x, order.reshape(
            (g, -1) + (1,) * (x.ndim - 2)), axis=1)
        x = x.reshape((g * tiles, _WORD) + x.shape[2:])
        return jnp.moveaxis(x, 1, -1)

    slot_tab = order.reshape(g * tiles, _WORD)
    real_tab, p_tab, w_tab = tiled(real), tiled(p), tiled(w)
    sp_tab = None if species is None else tiled(st["sp"])

    def split(e):
        valid = e < g * m * width
        atom = jnp.where(valid, e // width, 0)                    # g M + i
        combo = e - atom * width - lead
        is_self = valid & (combo < 0)
        word = valid & (combo >= 0)
        combo = jnp.maximum(combo, 0)
        k = jnp.where(word, combo // tiles, 0)
        t = jnp.where(word, combo - k * tiles, 0)
        gi = atom // m
        return valid, atom, is_self, word, k, t, gi

    def decide(e):
        _, atom, is_self, word, k, t, gi = split(e)
        si = atom - gi * m
        tile = gi * tiles + t
        slot_t = slot_tab[tile]                                  # (E, 32)
        real_t = real_tab[tile] & word[:, None]
        pj = p_tab[tile]                                         # (E, 3, 32)
        wj = w_tab[tile]
        si_w = o[k] + w_flat[atom]                               # (E, 3)
        s = [si_w[:, c, None] - wj[:, c] for c in range(3)]
        sf = [x.astype(dtype) for x in s]
        h = st["fr"].h[gi]                                       # (E, 3, 3)
        pi = p_flat[atom]
        dist2 = None
        for c in range(3):
            # As `shift_vectors` and `_dense_full`: the same operations in
            # the same order, so the same decisions.
            dc = (pj[:, c] - pi[:, c, None]) + (
                sf[0] * h[:, 0, c, None] + sf[1] * h[:, 1, c, None]
                + sf[2] * h[:, 2, c, None])
            dist2 = dc * dc if dist2 is None else dist2 + dc * dc
        dist = jnp.sqrt(dist2)
        if species is None:
            limit = cut
        else:
            limit = cut.at[sp_flat[atom][:, None], sp_tab[tile]].get(
                mode="fill", fill_value=0)
        same = slot_t == si[:, None]
        not_self = ~(same & (k == st["own"])[:, None])
        keep = (dist < limit) & real_t & not_self
        if half:
            positive = (s[0] > 0) | ((s[0] == 0) & (
                (s[1] > 0) | ((s[1] == 0) & (s[2] > 0))))
            keep = keep & ((si[:, None] < slot_t) | (same & positive))
        bits = pack(keep)[:, 0]
        count = jnp.where(is_self, 1, popcount(bits))
        # Where the rows of the word find their partner: its tile's first
        # sorted slot (flat over the systems), or -1 for the self pair.
        base = jnp.where(is_self, -1, tile * _WORD)
        kk = jnp.where(is_self, st["own"], k)
        return jnp.stack([jax.lax.bitcast_convert_type(bits, jnp.int32),
                          count, atom, gi, base, kk], axis=1)

    budget = entries.shape[0]
    chunk = min(TILE_CHUNK, budget)
    steps = -(-budget // chunk)
    entries = jnp.pad(entries, (0, steps * chunk - budget),
                      constant_values=g * m * width)

    # Each word's bits, count and where its rows go, written by the loop
    # (written out once: the rows below read them many times over).
    def step(c, words):
        at = c * chunk
        return jax.lax.dynamic_update_slice(words, decide(
            jax.lax.dynamic_slice(entries, (at,), (chunk,))), (at, at * 0))

    words = jax.lax.fori_loop(
        0, (jnp.minimum(needed, budget) + chunk - 1) // chunk, step,
        jnp.zeros((steps * chunk, 6), jnp.int32))
    return _word_rows(st, words, order, m=m, capacity=capacity)


def _word_rows(st, words, order, *, m, capacity):
    """The rows of `_dense_tile_rows`' decided words (int32 ``(W, 6)``:
    bits, count, atom, system, partner tile's first slot or -1 for the
    self pair, stencil offset), read as `_dense_decode` reads its words.
    Returns int32 ``(capacity, 5)`` rows, the count and the count per
    system."""
    g = st["real"].shape[0]
    counts = words[:, 1]
    ends = prefix_sum(counts, jnp.float64)
    wid, rank, stored = row_words(counts, ends, capacity)
    row = words[wid]                                           # (R, 6)
    bits = jax.lax.bitcast_convert_type(row[:, 0], jnp.uint32)
    row_atom, row_g, base, kk = row[:, 2], row[:, 3], row[:, 4], row[:, 5]
    b = select_bit(bits, rank)
    sj = jnp.where(base < 0, row_atom - row_g * m, order.reshape(-1)[
        jnp.maximum(base, 0) + b])
    rows = _block_rows(st, row_atom, row_g, sj, kk, stored, m=m)
    per_system = jax.ops.segment_sum(counts, words[:, 3], g)
    return rows, ends[-1], per_system


def _block_rows(st, row_atom, gi, sj, k, stored, *, m):
    """int32 ``(R, 5)`` rows ``(i, j, S)`` of atom slots ``row_atom``
    (``g M + slot``) of systems ``gi`` against slots ``sj`` in stencil
    image ``k`` (int32 ``(R,)`` each), ``S = o + w[i] - w[j]``; rows not
    ``stored`` padded with ``(N, N, 0)``. The slot is clipped for the
    wrap's gather only: an unstored row may point past its block."""
    n, w_flat = st["n"], st["w"].reshape(-1, 3)
    shift = (st["o"][k] + w_flat[row_atom]
             - w_flat[gi * m + jnp.minimum(sj, m - 1)])
    i = st["idx"].reshape(-1)[row_atom]
    j = st["first"][gi] + sj
    rows = jnp.concatenate([jnp.stack([i, j], axis=1), shift], axis=1)
    return jnp.where(stored[:, None], rows,
                     jnp.array([n, n, 0, 0, 0], jnp.int32))


def _dense_decode(st, packed, *, m, capacity):
    """The rows of `_dense_full`'s words ``packed`` (uint32 ``(G, M, K
    W)``), each atom's self pair (where ``st["selfs"]``) first: int32
    ``(capacity, 5)``, the count and the count per system."""
    g = st["real"].shape[0]
    tiles = -(-m // _WORD)
    width_words = packed.shape[-1]
    per_word = popcount(packed).reshape(g * m, width_words)
    # Each atom's row of counts: its self pair, then its words; row r of
    # the list is in the word whose running count first passes r.
    counts = jnp.concatenate([st["selfs"].reshape(-1, 1).astype(jnp.int32),
                              per_word], axis=1)
    width = counts.shape[1]
    ends = prefix_sum(counts.reshape(-1), jnp.float64)
    degree = jnp.sum(counts, axis=1, dtype=jnp.int32)
    wid, rank, stored = row_words(counts.reshape(-1), ends, capacity)
    row_atom = wid // width                               # g M + i slot
    col = wid - row_atom * width
    is_self = col == 0
    word = jnp.maximum(col - 1, 0)
    bits = packed.reshape(-1)[row_atom * width_words + word]
    k = word // tiles
    b = select_bit(bits, rank)
    gi = row_atom // m
    si = row_atom - gi * m
    sj = jnp.where(is_self, si, (word - k * tiles) * _WORD + b)
    k = jnp.where(is_self, st["own"], k)
    rows = _block_rows(st, row_atom, gi, sj, k, stored, m=m)
    per_system = jnp.sum(degree.reshape(g, m), axis=1, dtype=jnp.int32)
    return rows, ends[-1], per_system


def dense_rows(positions, graph, mask, cells, pbc, cut, species, radius, *,
                reach, max_nodes, n_graph, completed, half,
                self_interaction, capacity):
    """The sorted rows of a batch of small systems, each system one dense
    block: atom ``i`` against every atom ``j`` of its system in every
    image ``o`` of the stencil, ``S = o + w[i] - w[j]`` (the wraps as in
    step 2), decided as in step 5 (no cells, no runs, no per-candidate
    gathers); each atom's self pair first, then its rows in the order of
    its words (``o``, then the word's slots).

    One word per system (``max_nodes <= 32``): every ``(G, M, K, M)``
    candidate is decided. More: each system's atoms are sorted along a
    Morton curve of their wrapped fractional coordinates and cut into
    tiles of 32 (one word each), and each atom decides only the ``(tile,
    image)`` words whose box may come within the cutoff (`_dense_tiles`,
    conservative), listed flat for the batch, in a loop that reads only
    the words listed: the work grows with the words near the atoms, not
    with ``M² K``. The list has room for ``K`` words per atom slot on
    average (a tile a little smaller than the cutoff's sphere has about
    half of that); a batch needing more (tiles as wide as the cell, short
    cells) is decided whole, as with one word.

    The decisions are packed into 32-bit words; the running count over
    each atom's self pair and words places the words, and each of the
    ``capacity`` rows finds its word (the last word starting at or before
    it: marks and a running maximum) and its bit (the word's set bit of
    its rank, by population counts): nothing runs over the candidates but
    the decision, nothing is scattered per candidate.

    Returns int32 ``(capacity, 5)`` rows padded with ``(N, N, 0)``, the
    count, the count per system and the error bits (a system with more
    than ``max_nodes`` atoms sets ``MAX_NODES``).
    """
    m = max_nodes
    st = _dense_setup(positions, graph, mask, cells, pbc, cut, species,
                      radius, reach=reach, max_nodes=m, n_graph=n_graph,
                      completed=completed, self_interaction=self_interaction)
    k_offsets = st["o"].shape[0]
    words = -(-m // _WORD)

    def full():
        packed = _dense_full(st, cut, species, m=m, half=half)
        return _dense_decode(st, packed, m=m, capacity=capacity)

    if words < 2:
        rows, total, per_system = full()
        return rows, total, per_system, st["error"]
    # Room for one word per image per atom, in all (every word where
    # fewer would do): past that, every candidate.
    budget = st["real"].size * (k_offsets + int(self_interaction))
    entries, needed, order = _dense_tiles(
        st, radius, m=m, budget=budget, self_interaction=self_interaction)

    def pruned():
        return _dense_tile_rows(
            st, cut, species, entries, needed, order, m=m, half=half,
            self_interaction=self_interaction, capacity=capacity)

    rows, total, per_system = jax.lax.cond(needed > budget, full, pruned)
    return rows, total, per_system, st["error"]
