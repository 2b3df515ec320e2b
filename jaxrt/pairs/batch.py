"""Flat batches of systems in jraph's layout: ``jaxrt.pairs_batch``.

The atoms of every system are concatenated into one ``(N, 3)`` array and
``n_node`` says how many belong to each system, in order (jraph's
``GraphsTuple``); each system has its own cell and ``pbc``, so molecules,
slabs and bulk share one batch and one compiled program. The edges of all
systems come out concatenated, system after system (sorted by ``i``), with
``n_edge`` per system and global indices: ``senders`` (``i``, the centre)
and ``receivers`` (``j``), ``d = R[receivers] - R[senders] + S @ cell`` of
the edge's system (mace-jax's convention; ASE's ``i``, ``j``, ``S``).

Padding follows jraph's ``pad_with_graphs``: the nodes past ``sum(n_node)``
and the nodes of systems that ``graph_mask`` marks False are padding (no
pairs); padding edges are ``(p, p, 0)`` with ``p`` the first padding node
(``N`` where there is none: an index past the atoms), never an atom of a
real system, and they are counted in ``n_edge`` of the system that holds
``p`` (jraph's padding graph), so ``sum(n_edge)`` is the capacity there.
An overflow (more edges than the capacity) is flagged in ``error`` as by
`jaxrt.pairs`; ``n_edge`` then holds the exact counts each system needs.
"""
from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxrt.layouts.edges import materialized
from jaxrt.pairs import checks
from jaxrt.pairs.bits import ErrorBit, raise_if
from jaxrt.pairs.cells import safe_norm, shift_vectors
from jaxrt.pairs import program
from jaxrt.pairs.program import search
from jaxrt.pairs.search import PairSizes

__all__ = ["BatchPairs", "pairs_batch", "pairs_batch_sizes"]


@functools.partial(jax.tree_util.register_dataclass,
                   data_fields=["i", "j", "shift", "n_edge", "n_node",
                                "count", "overflow", "error"],
                   meta_fields=[])
@dataclasses.dataclass(frozen=True)
class BatchPairs:
    """The edges of a flat batch (a pytree: jit-able).

    Attributes:
      i, j: int32 ``(capacity,)`` global atom indices (``senders``,
        ``receivers``), sorted by ``i``; padding ``(p, p)`` (module
        docstring).
      shift: int32 ``(capacity, 3)`` lattice shifts (zero where padded).
      n_edge: int32 ``(G,)`` edges per system, padding edges in the system
        of the padding node.
      n_node: int32 ``(G,)`` atoms per system, as given.
      count: int32 scalar, the real edges (exact past the capacity).
      overflow: bool scalar; error: int32 `jaxrt.pairs.ErrorBit` bits.
    """

    i: jax.Array
    j: jax.Array
    shift: jax.Array
    n_edge: jax.Array
    n_node: jax.Array
    count: jax.Array
    overflow: jax.Array
    error: jax.Array

    @property
    def senders(self):
        return self.i

    @property
    def receivers(self):
        return self.j

    @property
    def capacity(self) -> int:
        return self.i.shape[-1]

    @property
    def valid(self):
        """bool ``(capacity,)``: which edges are real."""
        return jnp.arange(self.capacity) < self.count

    def edge_graph(self, n_atoms: int):
        """int32 ``(capacity,)``: each edge's system (padding edges: the
        padding node's, or ``G`` past every system)."""
        node_graph = _node_graph(self.n_node, n_atoms)
        return jnp.where(self.i < n_atoms, node_graph[jnp.minimum(
            self.i, n_atoms - 1)], self.n_node.shape[0])

    def shift_vectors(self, cell, n_atoms: int):
        """float ``(capacity, 3)``: ``S @ cell`` of each edge's system
        (``cell`` ``(G, 3, 3)`` or ``(G, 3)`` sides), differentiable in
        ``cell``; zero where padded."""
        h = checks.as_cell_matrix(jnp.asarray(cell))
        return _edge_shifts(self, h, n_atoms)

    def vectors(self, positions, cell=None):
        """float ``(capacity, 3)`` ``R[j] - R[i] + S @ cell`` (``positions``
        ``(N, 3)``, ``cell`` ``(G, 3, 3)`` / ``(G, 3)`` or None), zero where
        padded; differentiable in both."""
        positions = jnp.asarray(positions)
        h = None if cell is None else checks.as_cell_matrix(
            jnp.asarray(checks.plain(cell) if not isinstance(
                cell, jax.Array) else cell, positions.dtype))
        return _batch_vectors(self, positions, h)

    def distances(self, positions, cell=None):
        """float ``(capacity,)``, zero (with a zero gradient) where padded."""
        return safe_norm(self.vectors(positions, cell))

    def graphs_tuple(self, nodes=None, edges=None, globals_=None):
        """A ``jraph.GraphsTuple`` of these edges (jraph must be installed:
        ``pip install jraph``; jaxrt does not depend on it)."""
        try:
            import jraph
        except ImportError:
            raise ImportError("BatchPairs.graphs_tuple needs jraph (pip "
                              "install jraph); the arrays themselves are "
                              "senders, receivers, n_node and n_edge.") \
                from None
        return jraph.GraphsTuple(nodes=nodes, edges=edges, globals=globals_,
                                 senders=self.i, receivers=self.j,
                                 n_node=self.n_node, n_edge=self.n_edge)

    def check(self) -> "BatchPairs":
        """Raise `jaxrt.PairsError` if the list is incomplete (host side)."""
        raise_if(ErrorBit.of(self.error), self.count, self.capacity)
        return self


def _node_graph(n_node, n_atoms: int):
    """int32 ``(N,)``: each node's system, ``G`` past ``sum(n_node)``."""
    ends = jnp.cumsum(n_node.astype(jnp.int32))
    return jnp.searchsorted(ends, jnp.arange(n_atoms, dtype=jnp.int32),
                            side="right").astype(jnp.int32)


@functools.partial(jax.jit, static_argnames="n_atoms")
def _edge_shifts(result: BatchPairs, h, n_atoms: int):
    g = jnp.minimum(result.edge_graph(n_atoms), h.shape[0] - 1)
    s = jnp.where(result.valid[:, None], result.shift, 0)
    return shift_vectors(s.astype(h.dtype), h[g])


@jax.jit
def _batch_vectors(result: BatchPairs, positions, h):
    n = positions.shape[0]
    ii = jnp.minimum(result.i, n - 1)
    jj = jnp.minimum(result.j, n - 1)
    to, start = materialized((positions[jj], positions[ii]))
    d = to - start
    if h is not None:
        d = d + _edge_shifts(result, h, n)
    return jnp.where(result.valid[:, None], d, 0)


# ---------------------------------------------------------------------------
# The front


def _cells(cell, n_graph: int, dtype):
    """``(G, 3, 3)`` cells (traced or numpy in ``dtype``) from None, one
    cell, or one per system (matrices or sides)."""
    if cell is None:
        return np.broadcast_to(np.eye(3, dtype=dtype), (n_graph, 3, 3))
    shape = np.shape(cell)
    if shape not in ((3,), (3, 3), (n_graph, 3), (n_graph, 3, 3)) or (
            shape == (3, 3) and n_graph == 3):
        if shape != (n_graph, 3, 3):
            raise ValueError(
                f"jaxrt.pairs_batch: cell must be None, one cell ((3, 3) or "
                f"(3,) sides) or one per system (({n_graph}, 3, 3) or "
                f"({n_graph}, 3)), got shape {shape}.")
    if checks.is_concrete(cell):
        c = checks.plain(cell).astype(dtype)
        if c.shape in ((3,), (n_graph, 3)) and c.shape != (3, 3):
            c = checks.as_cell_matrix(c)
        return np.broadcast_to(c, (n_graph, 3, 3))
    c = jnp.asarray(cell, dtype)
    if c.shape in ((3,), (n_graph, 3)) and c.shape != (3, 3):
        c = checks.as_cell_matrix(c)
    return jnp.broadcast_to(c, (n_graph, 3, 3))


def _pbc(pbc, has_cell: bool, n_graph: int):
    """bool ``(G, 3)`` (numpy, or traced) and the static union per axis."""
    if pbc is None:
        pbc = has_cell
    if not checks.is_concrete(pbc):
        if np.shape(pbc) not in ((3,), (n_graph, 3)):
            raise ValueError(f"jaxrt.pairs_batch: pbc must be a bool, (3,) "
                             f"or ({n_graph}, 3), got {np.shape(pbc)}.")
        return jnp.broadcast_to(pbc, (n_graph, 3)), (True, True, True)
    p = np.asarray(pbc)
    if p.dtype != bool or p.shape not in ((), (3,), (n_graph, 3)):
        raise ValueError(f"jaxrt.pairs_batch: pbc must be a bool, (3,) or "
                         f"({n_graph}, 3) bools (per system and axis), got "
                         f"{p.dtype} {p.shape}.")
    p = np.broadcast_to(p, (n_graph, 3))
    if p.any() and not has_cell:
        raise ValueError("jaxrt.pairs_batch: periodic axes need cell=.")
    return p, tuple(bool(v) for v in p.any(axis=0))


def _n_node(n_node, n_atoms: int):
    if np.ndim(n_node) != 1:
        raise ValueError(f"jaxrt.pairs_batch: n_node must be int (G,), atoms "
                         f"per system, got shape {np.shape(n_node)}.")
    if checks.is_concrete(n_node):
        counts = np.asarray(n_node)
        if not np.issubdtype(counts.dtype, np.integer) or np.any(
                counts < 0) or counts.sum() > n_atoms:
            raise ValueError(f"jaxrt.pairs_batch: n_node must be ints >= 0 "
                             f"summing to at most N = {n_atoms} (the rows of "
                             f"positions), got {counts.tolist()[:8]}...")
        return counts.astype(np.int32)
    return n_node.astype(jnp.int32)


def _graph_mask(graph_mask, n_graph: int):
    if graph_mask is None:
        return np.ones((n_graph,), bool)
    if np.shape(graph_mask) != (n_graph,):
        raise ValueError(f"jaxrt.pairs_batch: graph_mask must be bool "
                         f"({n_graph},) (False: a padding system, "
                         f"jraph.get_graph_padding_mask), got "
                         f"{np.shape(graph_mask)}.")
    return np.asarray(graph_mask, bool) if checks.is_concrete(graph_mask) \
        else graph_mask


def pairs_batch(positions, n_node, cutoff, *, cell=None, pbc=None,
                graph_mask=None, capacity=None, max_shift=None, species=None,
                half: bool = False, self_interaction: bool = False,
                backend: str = "auto", max_nodes=None) -> BatchPairs:
    """The pairs of every system of a flat batch (module docstring).

    Args:
      positions: float ``(N, 3)``, the systems' atoms concatenated (rows
        past ``sum(n_node)`` are padding).
      n_node: int ``(G,)`` atoms per system.
      cutoff: as `jaxrt.pairs` (a float, or cutoffs by species).
      cell: None (free space), one cell for all, or ``(G, 3, 3)`` / ``(G,
        3)`` one per system (a molecule's may be zero: completed).
      pbc: None (periodic with a cell), a bool, ``(3,)`` or ``(G, 3)``; may
        be traced (then every axis is searched as possibly periodic).
      graph_mask: bool ``(G,)``, False for padding systems (their atoms are
        padding); None: every system is real.
      capacity: static total edges; None (eager only): sized exactly.
      max_shift: static reach, as `jaxrt.pairs` (needed with traced cells).
      species, half, self_interaction, backend: as `jaxrt.pairs`.
      max_nodes: static int: positive, at most this many atoms in any
        system, each system then searched as one dense block (every atom
        against every atom of its system in every image of the reach; past
        32 atoms only the 32-atom tiles near each atom), faster than cells
        for small systems (a system with more atoms sets
        ``ErrorBit.MAX_NODES``); 0: cells. None: eager calls choose (dense
        blocks for small systems), under ``jit`` cells;
        `jaxrt.pairs_batch_sizes` gives it.
    Returns:
      `BatchPairs` (numpy arrays from an eager call, as `jaxrt.pairs`). An
      eager call raises `jaxrt.PairsError` on an incomplete list; under
      ``jit`` ``overflow`` is set.
    """
    positions = checks.positions_array(positions, "jaxrt.pairs_batch")
    if positions.ndim != 2:
        raise ValueError(f"jaxrt.pairs_batch: positions must be (N, 3), the "
                         f"systems concatenated; got {positions.shape}.")
    n = positions.shape[0]
    n_node = _n_node(n_node, n)
    n_graph = n_node.shape[0]
    traced_ok = capacity is not None and max_shift is not None
    radius, cut, species = checks.cutoffs(cutoff, species, n, traced_ok,
                                          "jaxrt.pairs_batch")
    cells = _cells(cell, n_graph, positions.dtype)
    pbc, periodic = _pbc(pbc, cell is not None, n_graph)
    graph_mask = _graph_mask(graph_mask, n_graph)
    capacity = checks.check_capacity(capacity)
    options = dict(half=bool(half), self_interaction=bool(self_interaction),
                   max_nodes=_max_nodes(max_nodes))
    concrete = all(checks.is_concrete(x) for x in (
        positions, n_node, cut, species, cells, pbc, graph_mask))
    if concrete:
        return _eager(np.asarray(positions), n_node, cells, pbc, periodic,
                      graph_mask, radius, cut, species, max_shift, capacity,
                      backend, options)
    if capacity is None:
        raise ValueError("jaxrt.pairs_batch: capacity=None needs concrete "
                         "inputs; under jit pass capacity= (and max_shift= "
                         "with traced cells): jaxrt.pairs_batch_sizes.")
    if max_shift is None:
        if not checks.is_concrete(cells):
            raise ValueError("jaxrt.pairs_batch: the cells are traced: pass "
                             "max_shift= (jaxrt.pairs_batch_sizes).")
        shift = _batch_reach(cells, pbc, graph_mask, radius, periodic)
    else:
        shift = checks.check_max_shift(max_shift, periodic)
    brute, reach, chunk = checks.plan(n, periodic, shift, backend)
    options["max_nodes"] = options["max_nodes"] or 0
    if options["max_nodes"]:
        reach = tuple(shift)  # dense blocks: every image within the reach
    return _call(positions, n_node, cells, pbc, graph_mask, cut, species,
                 periodic=periodic, reach=reach, brute=brute, chunk=chunk,
                 capacity=capacity, **options)


def _call(positions, n_node, cells, pbc, graph_mask, cut, species, *,
          capacity, **static) -> BatchPairs:
    """The program on a batch: atoms' systems and mask from ``n_node`` and
    ``graph_mask``, the padding node, the padding edges' system."""
    n, n_graph = positions.shape[0], n_node.shape[0]
    node_graph = _node_graph(jnp.asarray(n_node), n)
    inside = node_graph < n_graph
    real = inside & jnp.asarray(graph_mask)[jnp.minimum(node_graph,
                                                        n_graph - 1)]
    pad = jnp.where(jnp.all(real), n, jnp.argmin(real)).astype(jnp.int32)
    rows, total, per_system, error = search(
        positions, node_graph, real, cells, pbc, cut, species, pad,
        capacity=capacity, n_graph=n_graph, sort=True,
        own_reach=bool(program.OWN_REACH), **static)
    padding = jnp.maximum(capacity - total, 0)
    pad_graph = jnp.where(pad < n, node_graph[jnp.minimum(pad, n - 1)],
                          n_graph)
    n_edge = per_system + jnp.where(jnp.arange(n_graph) == pad_graph,
                                    padding, 0)
    return BatchPairs(i=rows[:, 0], j=rows[:, 1], shift=rows[:, 2:],
                      n_edge=n_edge.astype(jnp.int32),
                      n_node=jnp.asarray(n_node, jnp.int32), count=total,
                      overflow=error != 0, error=error)


def _max_nodes(max_nodes):
    """The static ``max_nodes`` option checked: an int >= 0, or None."""
    if max_nodes is None:
        return None
    if isinstance(max_nodes, (bool, np.bool_)) or not isinstance(
            max_nodes, (int, np.integer)) or max_nodes < 0:
        raise ValueError(f"jaxrt.pairs_batch: max_nodes={max_nodes!r}: pass "
                         f"an int, the most atoms of one system (0: search "
                         f"by cells), or None.")
    return int(max_nodes)


def _batch_reach(cells, pbc, graph_mask, radius, periodic):
    """The largest reach any real system needs, per axis (concrete)."""
    need = [0, 0, 0]
    for h, p, real in zip(cells, pbc, graph_mask):
        if real and p.any():
            shift = checks.shift_for_cell(checks.concrete_cell(h, tuple(p)),
                                          radius, tuple(p))
            need = [max(a, b) for a, b in zip(need, shift)]
    return tuple(max(v, 1) if p else 0 for v, p in zip(need, periodic))


def _padded(positions, n_node, cells, pbc, graph_mask):
    """The batch padded to size buckets: atoms (masked, in no system) and
    systems (empty, masked)."""
    n, g = positions.shape[0], n_node.shape[0]
    size, systems = checks.bucket(n), checks.bucket(g)
    positions = np.concatenate([positions, np.zeros((size - n, 3),
                                                    positions.dtype)])
    n_node = np.concatenate([n_node, np.zeros((systems - g,), np.int32)])
    cells = np.concatenate([cells, np.broadcast_to(np.eye(
        3, dtype=cells.dtype), (systems - g, 3, 3))])
    pbc = np.concatenate([pbc, np.zeros((systems - g, 3), bool)])
    graph_mask = np.concatenate([graph_mask, np.zeros((systems - g,), bool)])
    return positions, n_node, cells, pbc, graph_mask


def _prepare(positions, n_node, cells, pbc, periodic, graph_mask, radius,
             max_shift, backend, options):
    """Eager: the padded batch, its static options and a capacity guess."""
    ends = np.cumsum(n_node)
    shift = _batch_reach(cells, pbc, graph_mask, radius, periodic) \
        if max_shift is None else checks.check_max_shift(max_shift, periodic)
    counts = np.where(graph_mask, n_node, 0)
    guess = 0
    for k in np.nonzero(counts)[0]:
        r = positions[ends[k] - n_node[k]:ends[k]]
        p = tuple(bool(v) for v in pbc[k])
        h = checks.concrete_cell(cells[k], p)
        full = checks.estimate(np.asarray(r, np.float64), h, p, radius)
        guess += (full + 1) // 2 if options["half"] else full
        if options["self_interaction"]:
            guess += len(r)
    padded = _padded(positions, n_node, np.asarray(cells), np.asarray(pbc),
                     graph_mask)
    brute, reach, chunk = checks.plan(
        padded[0].shape[0], periodic, shift, backend,
        candidates=int(np.sum(counts.astype(np.int64) ** 2)))
    if options["max_nodes"] is None:
        options = dict(options, max_nodes=checks.dense_nodes(
            int(np.max(counts, initial=0)), shift, int(counts.sum()),
            padded[1].shape[0]))
    if options["max_nodes"]:
        reach = tuple(shift)  # dense blocks: every image within the reach
    # The guess at the padded size (shared by batches of one bucket).
    guess = guess * padded[0].shape[0] / max(int(counts.sum()), 1)
    return padded, dict(periodic=periodic, reach=reach, brute=brute,
                        chunk=chunk, **options), checks.bucket(guess)


def _eager(positions, n_node, cells, pbc, periodic, graph_mask, radius, cut,
           species, max_shift, capacity, backend, options) -> BatchPairs:
    """An eager call: the batch padded to size buckets, one program (again
    with the count's bucket when the guess was short), the arrays cut on
    the host."""
    n, g = positions.shape[0], n_node.shape[0]
    (r, nodes, h, p, mask), static, guess = _prepare(
        positions, n_node, cells, pbc, periodic, graph_mask, radius,
        max_shift, backend, options)
    if species is not None:
        species = np.concatenate([species, np.zeros(
            (r.shape[0] - n,), np.int32)])

    def call(cap):
        return jax.device_get(_call(r, nodes, h, p, mask, cut, species,
                                    capacity=cap, **static))

    if capacity is not None:
        out = call(capacity)
        raise_if(int(out.error), out.count, capacity)
        return _on_host(out, capacity, n, g, int(out.error))
    out = call(guess)
    raise_if(int(out.error) & ~int(ErrorBit.CAPACITY))
    count = int(out.count)
    if count > guess:
        out = call(checks.bucket(count))
    n_edge = np.array(out.n_edge)
    if count < out.capacity:  # the padding edges cut off: uncount them
        pad_graph = np.searchsorted(np.cumsum(nodes), out.i[count],
                                    side="right")
        if pad_graph < len(n_edge):
            n_edge[pad_graph] -= out.capacity - count
    return _on_host(dataclasses.replace(out, n_edge=n_edge), count, n, g,
                      int(out.error) & ~int(ErrorBit.CAPACITY))


def _on_host(out: BatchPairs, length: int, n: int, g: int,
             error: int) -> BatchPairs:
    """A host result cut to ``length`` edges and the caller's ``g``
    systems, padding indices past the caller's ``n`` atoms set to ``n``
    (numpy arrays, as an eager `jaxrt.pairs` returns)."""
    error = np.array(error, np.int32)
    return BatchPairs(
        i=np.where(out.i[:length] < n, out.i[:length], n).astype(np.int32),
        j=np.where(out.j[:length] < n, out.j[:length], n).astype(np.int32),
        shift=np.ascontiguousarray(out.shift[:length]),
        n_edge=np.array(out.n_edge[:g]), n_node=np.array(out.n_node[:g]),
        count=np.array(out.count, np.int32), overflow=error != 0,
        error=error)


def pairs_batch_sizes(positions, n_node, cutoff, *, cell=None, pbc=None,
                      graph_mask=None, species=None, half: bool = False,
                      self_interaction: bool = False) -> PairSizes:
    """Eager: static sizes for `pairs_batch` under ``jit`` on this batch:
    the capacity rounded up to its size bucket, and the reach.

    Returns `jaxrt.PairSizes` (``**sizes.kwargs``); take the largest over
    the batches of a data set (`PairSizes.merge`)."""
    positions = checks.positions_array(positions, "jaxrt.pairs_batch_sizes")
    result = pairs_batch(positions, n_node, cutoff, cell=cell, pbc=pbc,
                         graph_mask=graph_mask, species=species, half=half,
                         self_interaction=self_interaction)
    n_graph = np.shape(n_node)[0]
    cells = _cells(cell, n_graph, np.float64)
    p, periodic = _pbc(pbc, cell is not None, n_graph)
    radius = checks.cutoffs(cutoff, species, positions.shape[0], False,
                            "jaxrt.pairs_batch_sizes")[0]
    shift = _batch_reach(cells, p, _graph_mask(graph_mask, n_graph), radius,
                         periodic)
    counts = np.where(_graph_mask(graph_mask, n_graph), np.asarray(n_node),
                      0)
    return PairSizes(capacity=checks.bucket(int(result.count)),
                     max_shift=shift, max_nodes=checks.dense_nodes(
                         int(np.max(counts, initial=0)), shift,
                         int(counts.sum()), n_graph))
