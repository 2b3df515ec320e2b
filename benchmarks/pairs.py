"""Pairs with lattice shifts (i, j, S): jaxrt.pairs against ASE, matscipy,
vesin (CPU) and nvalchemiops (GPU), one call each, time per call.

Scene: a diamond silicon supercell (a = 5.43 Å, 8 atoms per cubic cell
repeated r×r×r, rattled by 0.05 Å), periodic, cutoff 5 Å (about 29
neighbours per atom, full lists), N from 10³ to 10⁶ (the nearest 8 r³).
Each row runs in its own worker process (`_harness`); times are the median
of the timed calls, warm-up (compilation) excluded, over three rotating
inputs (the scene and two copies jittered by 10⁻³ Å). ``pairs`` is the
number of pairs the method returned on the first input (every method must
agree with ASE's count where ASE ran: ``same_count``).

Methods:
  jaxrt          jax.jit(jaxrt.pairs) with static sizes from
                 jaxrt.pairs_sizes (what a training loop runs)
  jaxrt[xla]     jaxrt on a GPU with the cells' stencil walked by XLA
                 instead of the Warp walk (the previous GPU search)
  jaxrt[graph]   jaxrt on a GPU with the Warp walk's call replayed as a
                 CUDA graph
  jaxrt[eager]   jaxrt.pairs(..., capacity=None): sizing included
  ase            ase.neighborlist.neighbor_list("ijS", ...)
  matscipy       matscipy.neighbours.neighbour_list("ijS", ...)
  vesin          vesin.NeighborList(cutoff, full_list=True).compute(...)
  nvalchemiops   nvalchemiops' torch neighbor_list on CUDA (COO list with
                 shifts), if installed (nvalchemi-toolkit-ops and torch)
  nvalchemiops[jax]  its JAX binding's neighbor_list (eager dispatcher)
  nvalchemiops[jax-jit]  jax.jit of its JAX cell_list (batch_cell_list for
                 batches) with static max_neighbors and max_total_cells
                 from its estimate helpers, computed once outside the
                 timed call; neighbour matrix out (runs on Warp's CPU
                 device too). Under jit its "auto" strategy is the
                 atom-centric kernel (the pair-centric launch needs static
                 sizes)
  nvalchemiops[jax-jit-pc]  the same with strategy="pair_centric" and its
                 static launch sizes (pair_centric_n_outer; for batches also
                 pair_centric_total_cells and pair_centric_r_max) from the
                 same estimates: CUDA only

Batches (``system`` = GxM): G periodic fcc-like systems of M atoms each
(M/4 conventional cells, lattice constant 3.5..4.1 Å per system, each axis
strained by up to 3 %, rattled by 0.05 Å), cutoff 5 Å, as one flat batch:
jaxrt.pairs_batch under jit (static sizes from jaxrt.pairs_batch_sizes:
small systems are searched as dense blocks), jaxrt[cells] the same with
max_nodes=0 (the cell search),
nvalchemiops[jax-jit] batch_cell_list (batch_idx and batch_ptr), vesin
looping over the systems.

Every nvalchemiops row is checked against jaxrt's eager pairs on the first
input (``same_pairs``): the sorted (i, j, shift) sets must be equal, except
pairs whose float64 length is within a rounding tolerance of the cutoff
(``boundary`` counts those); anything else makes the row ``error`` with
the reason instead of a time. A row whose library is not installed is
``skipped`` with the reason. With nvalchemi-toolkit-ops 0.5.0 and Warp
1.19 the batch atom-centric path (what ``auto`` runs under jit) fails: one
of its kernels is registered with its arrays as static jit arguments (the
row says so); the pair-centric batch path does not use that kernel.

    python benchmarks/pairs.py                    # CPU: 1e3..1e5, all CPU methods
    python benchmarks/pairs.py --sizes 1000000 --methods jaxrt vesin matscipy
    python benchmarks/pairs.py --gpu              # CUDA: jaxrt, nvalchemiops (torch, jax), 1e3..1e6
    python benchmarks/pairs.py --quick            # smoke: N = 1000, 8x32, 2 repeats
    python benchmarks/pairs.py --gpu --sizes --batches 256x32 64x128  # batches only
    python benchmarks/pairs.py --gpu --batches    # single systems only
"""
from __future__ import annotations

from math import prod

if __package__:  # run as -m, or imported: the package's modules
    from benchmarks import _harness
else:  # run as a file: its folder is sys.path[0]
    import _harness

CUTOFF = 5.0
LATTICE = 5.43
CPU_METHODS = ["jaxrt", "jaxrt[eager]", "ase", "matscipy", "vesin"]
NVAL_JIT = "nvalchemiops[jax-jit]"
NVAL_PC = "nvalchemiops[jax-jit-pc]"
# jaxrt with the GPU's cell stencil walked by XLA instead of the Warp walk
# (`jaxrt.pairs.program.WARP_WALK_ON_CUDA` off).
XLA_WALK = "jaxrt[xla]"
# jaxrt with the Warp walk's call replayed as a CUDA graph
# (`jaxrt.pairs.warp_search.GRAPH = "warp"`).
GRAPH_WALK = "jaxrt[graph]"
GPU_METHODS = ["jaxrt", XLA_WALK, GRAPH_WALK, "jaxrt[eager]", "nvalchemiops",
               "nvalchemiops[jax]", NVAL_JIT, NVAL_PC]
CELLS = "jaxrt[cells]"
BATCH_METHODS = ["jaxrt", XLA_WALK, GRAPH_WALK, CELLS, "vesin", NVAL_JIT,
                 NVAL_PC]
CPU_BATCH_METHODS = ["jaxrt", CELLS, "vesin"]
GPU_BATCH_METHODS = ["jaxrt", XLA_WALK, NVAL_JIT, NVAL_PC]
BATCHES = ["256x32", "64x128"]


def scene(n: int, seed: int = 0):
    """float64 positions (M, 3), cell (3, 3) (rows), M = 8 r³ nearest n."""
    import numpy as np
    r = max(1, round((n / 8) ** (1 / 3)))
    base = np.array([[0, 0, 0], [0, 2, 2], [2, 0, 2], [2, 2, 0],
                     [1, 1, 1], [1, 3, 3], [3, 1, 3], [3, 3, 1]]) / 4
    grid = np.stack(np.meshgrid(*[np.arange(r)] * 3, indexing="ij"),
                    -1).reshape(-1, 1, 3)
    frac = ((grid + base[None]) / r).reshape(-1, 3)
    cell = np.eye(3) * LATTICE * r
    rng = np.random.default_rng(seed)
    return frac @ cell + rng.normal(0, 0.05, frac.shape), cell


def fcc_reps(m: int) -> tuple[int, int, int]:
    """Repeats (a, b, c) of the 4-atom fcc cell making m atoms, as cubic as
    possible."""
    if m % 4 or m <= 0:
        raise ValueError(f"batch atoms per system must be a positive "
                         f"multiple of 4 (fcc cells), got {m}")
    k = m // 4
    best = None
    for a in range(1, k + 1):
        for b in range(1, k // a + 1):
            if k % (a * b) == 0:
                r = tuple(sorted((a, b, k // (a * b)), reverse=True))
                if best is None or r[0] - r[2] < best[0] - best[2]:
                    best = r
    return best


def parse_batch(name: str) -> tuple[int, int]:
    """'GxM' -> (G systems, M atoms each)."""
    try:
        g, m = (int(v) for v in name.lower().split("x"))
    except ValueError:
        raise ValueError(f"--batches: expected GxM (systems x atoms), got "
                         f"{name!r}") from None
    fcc_reps(m)
    return g, m


def batch_scene(g: int, m: int, seed: int = 0):
    """float64 positions (g m, 3) concatenated, n_node (g,) int32, cells
    (g, 3, 3) (rows): g periodic fcc-like systems of m atoms."""
    import numpy as np
    reps = np.array(fcc_reps(m))
    base = np.array([[0, 0, 0], [0, .5, .5], [.5, 0, .5], [.5, .5, 0]])
    grid = np.stack(np.meshgrid(*[np.arange(r) for r in reps],
                                indexing="ij"), -1).reshape(-1, 1, 3)
    frac = ((grid + base[None]) / reps).reshape(-1, 3)
    rng = np.random.default_rng(seed)
    pos, cells = [], []
    for _ in range(g):
        a = rng.uniform(3.5, 4.1)
        cell = np.diag(a * reps * rng.uniform(0.97, 1.03, 3))
        pos.append(frac @ cell + rng.normal(0, 0.05, frac.shape))
        cells.append(cell)
    return (np.concatenate(pos), np.full(g, m, np.int32), np.stack(cells))


def _inputs(n: int):
    import numpy as np
    pos, cell = scene(n)
    jitter = np.random.default_rng(1)
    return [pos] + [pos + jitter.normal(0, 1e-3, pos.shape)
                    for _ in range(2)], cell


def _jaxrt(eager: bool, inputs, cell, dtype):
    import jax
    import jax.numpy as jnp
    import numpy as np
    import jaxrt
    xs = [jnp.asarray(x, dtype) for x in inputs]
    c = jnp.asarray(cell, dtype)
    if eager:
        def call(x):
            return jaxrt.pairs(x, CUTOFF, cell=c)
    else:
        sizes = jaxrt.pairs_sizes(jnp.stack(xs), CUTOFF, cell=np.asarray(cell))
        jitted = jax.jit(lambda x, c: jaxrt.pairs(x, CUTOFF, cell=c,
                                                  **sizes.kwargs))

        def call(x):
            return jitted(x, c)

    def count(out):
        out.check()
        return int(out.count)
    return call, xs, None, count


def _ase(inputs, cell):
    from ase import Atoms
    from ase.neighborlist import neighbor_list
    atoms = [Atoms(positions=x, cell=cell, pbc=True) for x in inputs]
    return (lambda a: neighbor_list("ijS", a, CUTOFF)), atoms, \
        (lambda out: out), (lambda out: len(out[0]))


def _matscipy(inputs, cell):
    from ase import Atoms
    from matscipy.neighbours import neighbour_list
    atoms = [Atoms(positions=x, cell=cell, pbc=True) for x in inputs]
    return (lambda a: neighbour_list("ijS", a, CUTOFF)), atoms, \
        (lambda out: out), (lambda out: len(out[0]))


def _vesin(inputs, cell):
    from vesin import NeighborList
    nl = NeighborList(cutoff=CUTOFF, full_list=True)
    return (lambda x: nl.compute(points=x, box=cell, periodic=True,
                                 quantities="ijS")), inputs, \
        (lambda out: out), (lambda out: len(out[0]))


def _probe(call, x, cell, pbc):
    """Call nvalchemiops with one cell and pbc ((3, 3), (3,)) or, where that
    release wants them per system, ((1, 3, 3), (1, 3)); returns the pair
    that worked."""
    try:
        call(x, cell, pbc)
        return cell, pbc
    except (TypeError, ValueError, RuntimeError, IndexError):
        cell, pbc = cell.reshape(1, 3, 3), pbc.reshape(1, 3)
        call(x, cell, pbc)
        return cell, pbc


def _count_pairs(out):
    """nvalchemiops' COO list (return_neighbor_list=True): (2, P) first."""
    first = out[0] if isinstance(out, (tuple, list)) else out
    return int(first.shape[-1])


def _nvalchemiops(inputs, cell, dtype):
    import torch
    try:  # the module moved between releases
        from nvalchemiops.torch.neighbors import neighbor_list
    except ImportError:
        from nvalchemiops.neighborlist import neighbor_list
    torch_dtype = getattr(torch, dtype)
    xs = [torch.as_tensor(x, dtype=torch_dtype, device="cuda")
          for x in inputs]

    def nl(x, c, p):
        return neighbor_list(x, CUTOFF, cell=c, pbc=p,
                             return_neighbor_list=True)

    c, p = _probe(nl, xs[0], torch.as_tensor(cell, dtype=torch_dtype,
                                             device="cuda"),
                  torch.ones(3, dtype=torch.bool, device="cuda"))

    def sync(out):
        torch.cuda.synchronize()
        return out
    return (lambda x: nl(x, c, p)), xs, sync, _count_pairs


def _nvalchemiops_jax(inputs, cell, dtype):
    """nvalchemiops' JAX binding (its eager dispatcher: the documented entry
    point; not a jit boundary)."""
    import jax.numpy as jnp
    from nvalchemiops.jax.neighbors import neighbor_list
    xs = [jnp.asarray(x, dtype) for x in inputs]

    def nl(x, c, p):
        return neighbor_list(x, CUTOFF, cell=c, pbc=p,
                             return_neighbor_list=True)

    c, p = _probe(nl, xs[0], jnp.asarray(cell, dtype), jnp.ones(3, bool))
    return (lambda x: nl(x, c, p)), xs, None, _count_pairs


def _pack(i, j, shift, n_atoms: int):
    """One int64 key per (i, j, shift) row (i, j < 2**20, |shift| < 64)."""
    import numpy as np
    i, j, shift = (np.asarray(v, np.int64) for v in (i, j, shift))
    if n_atoms >= 1 << 20 or (shift.size and np.abs(shift).max() >= 64):
        raise ValueError("pairs too large to pack for the comparison")
    s = shift + 64
    return (((i << 20 | j) << 7 | s[:, 0]) << 7 | s[:, 1]) << 7 | s[:, 2]


def _unpack(keys):
    import numpy as np
    keys = np.asarray(keys, np.int64)
    s = np.stack([(keys >> 14) & 127, (keys >> 7) & 127, keys & 127], 1) - 64
    return keys >> 41, (keys >> 21) & ((1 << 20) - 1), s


def compare_pairs(got, ref, positions, cells, system_of, cutoff: float,
                  tol: float) -> dict:
    """Compare two pair lists ``(i, j, shift)`` (int arrays (P,), (P,),
    (P, 3)) as sets. ``positions`` float64 (N, 3); ``cells`` (G, 3, 3) rows,
    ``system_of`` (N,) each atom's system. Pairs in one list only are
    excused when their float64 length is within ``tol`` of ``cutoff``
    (rounding at the boundary). Returns {"same_pairs", "boundary",
    "reason"} (reason None when they agree)."""
    import numpy as np
    n = len(positions)
    a = _pack(*got, n)
    b = _pack(*ref, n)
    dup = len(a) - len(np.unique(a))
    if dup:
        return {"same_pairs": False, "boundary": 0,
                "reason": f"{dup} duplicate pairs in the list checked"}
    only = np.concatenate([np.setdiff1d(a, b), np.setdiff1d(b, a)])
    if not len(only):
        return {"same_pairs": True, "boundary": 0, "reason": None}
    i, j, s = _unpack(only)
    h = np.asarray(cells)[np.asarray(system_of)[i]]
    d = positions[j] - positions[i] + np.einsum("pk,pkl->pl", s, h)
    r = np.linalg.norm(d, axis=1)
    off = np.abs(r - cutoff) > tol
    if off.any():
        k = int(np.argmax(off))
        return {"same_pairs": False, "boundary": int((~off).sum()),
                "reason": (f"{int(off.sum())} pairs differ from jaxrt's "
                           f"(counts {len(a)} vs {len(b)}), e.g. i={i[k]} "
                           f"j={j[k]} shift={s[k].tolist()} r={r[k]:.6f}")}
    return {"same_pairs": True, "boundary": int(len(only)), "reason": None}


def pair_tolerance(dtype: str, positions, cells) -> float:
    """Length rounding at the cutoff: a few ulps of the largest coordinate
    or cell entry, in the row's dtype."""
    import numpy as np
    scale = max(np.abs(positions).max(), np.abs(cells).max(), CUTOFF)
    return 64 * float(np.finfo(dtype).eps) * scale


def matrix_pairs(out):
    """(i, j, shift) from nvalchemiops' neighbour matrix output
    (neighbor_matrix (N, K), num_neighbors (N,), shifts (N, K, 3))."""
    import numpy as np
    nm, nn, sh = (np.asarray(v) for v in out[:3])
    if nn.max(initial=0) > nm.shape[1]:
        raise RuntimeError(f"nvalchemiops: max_neighbors {nm.shape[1]} too "
                           f"small ({int(nn.max())} neighbours)")
    i = np.repeat(np.arange(len(nn)), nn)
    k = np.arange(len(i)) - np.repeat(np.cumsum(nn) - nn, nn)
    return i, nm[i, k], sh[i, k]


def _count_matrix(out):
    return int(out[1].sum())


def _nval_jit(inputs, cell, dtype, pair_centric: bool):
    """nvalchemiops' JAX cell_list under jit, one system; sizes once from
    its estimators."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    from nvalchemiops.jax.neighbors import (cell_list,
                                            compute_batch_pair_centric_n_outer,
                                            estimate_cell_list_sizes,
                                            estimate_max_neighbors)
    xs = [jnp.asarray(x, dtype) for x in inputs]
    c = jnp.asarray(cell, dtype)[None]
    p = jnp.ones((1, 3), bool)
    total_cells, _, radius = estimate_cell_list_sizes(xs[0], c, CUTOFF, p)
    options = dict(max_neighbors=int(estimate_max_neighbors(CUTOFF)),
                   max_total_cells=int(total_cells))
    if pair_centric:
        r = tuple(int(v) for v in np.asarray(radius).reshape(-1)[:3])
        options.update(strategy="pair_centric",
                       pair_centric_n_outer=int(
                           compute_batch_pair_centric_n_outer(r, False)))
    f = jax.jit(lambda x, c, p: cell_list(x, CUTOFF, cell=c, pbc=p,
                                          **options))
    return (lambda x: f(x, c, p)), xs, None, _count_matrix


def _jaxrt_batch(inputs, n_node, cells, dtype, by_cells: bool = False):
    import jax
    import jax.numpy as jnp
    import jaxrt
    xs = [jnp.asarray(x, dtype) for x in inputs]
    c = jnp.asarray(cells, dtype)
    sizes = jaxrt.pairs_batch_sizes(xs[0], n_node, CUTOFF, cell=c)
    kwargs = dict(sizes.kwargs, max_nodes=0) if by_cells else sizes.kwargs
    f = jax.jit(lambda x, n, c: jaxrt.pairs_batch(x, n, CUTOFF, cell=c,
                                                  **kwargs))
    nn = jnp.asarray(n_node)

    def count(out):
        out.check()
        return int(out.count)
    return (lambda x: f(x, nn, c)), xs, None, count


def _vesin_batch(inputs, n_node, cells):
    import numpy as np
    from vesin import NeighborList
    nl = NeighborList(cutoff=CUTOFF, full_list=True)
    ends = np.cumsum(n_node)
    split = [[x[e - m:e] for e, m in zip(ends, n_node)] for x in inputs]

    def call(parts):
        return [nl.compute(points=x, box=h, periodic=True, quantities="ijS")
                for x, h in zip(parts, cells)]
    return call, split, (lambda out: out), \
        (lambda out: sum(len(o[0]) for o in out))


def _nval_jit_batch(inputs, n_node, cells, dtype, pair_centric: bool):
    """nvalchemiops' JAX batch_cell_list under jit; sizes once from its
    estimators."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    from nvalchemiops.jax.neighbors import (batch_cell_list,
                                            compute_batch_pair_centric_n_outer,
                                            estimate_batch_cell_list_sizes,
                                            estimate_max_neighbors)
    xs = [jnp.asarray(x, dtype) for x in inputs]
    c = jnp.asarray(cells, dtype)
    p = jnp.ones((len(n_node), 3), bool)
    idx = jnp.asarray(np.repeat(np.arange(len(n_node)), n_node), jnp.int32)
    ptr = jnp.asarray(np.concatenate([[0], np.cumsum(n_node)]), jnp.int32)
    total_cells, per_dim, radius = estimate_batch_cell_list_sizes(
        xs[0], batch_ptr=ptr, batch_idx=idx, cell=c, cutoff=CUTOFF, pbc=p)
    options = dict(max_neighbors=int(estimate_max_neighbors(CUTOFF)),
                   max_total_cells=int(total_cells))
    if pair_centric:
        r = tuple(int(v) for v in np.asarray(radius).max(axis=0))
        options.update(
            strategy="pair_centric",
            pair_centric_total_cells=int(np.prod(np.asarray(per_dim),
                                                 axis=1).sum()),
            pair_centric_n_outer=int(compute_batch_pair_centric_n_outer(
                r, False)),
            pair_centric_r_max=r)
    f = jax.jit(lambda x, c, p, idx, ptr: batch_cell_list(
        x, CUTOFF, cell=c, pbc=p, batch_idx=idx, batch_ptr=ptr, **options))

    def call(x):
        try:
            return f(x, c, p, idx, ptr)
        except ValueError as exc:
            if "Non-hashable static arguments" not in str(exc):
                raise
            raise RuntimeError(
                f"nvalchemiops' batch atom-centric gather kernel cannot be "
                f"called with warp {_version('warp-lang')}: its arrays, "
                f"annotated wp.array[...], are taken for static arguments "
                f"(nvalchemiops pins warp-lang>=1.16 only)") from None
    return call, xs, None, _count_matrix


def _check_nval(first, inputs, cells, n_node, dtype) -> dict:
    """Compare an nvalchemiops neighbour-matrix or COO output with jaxrt's
    eager pairs on the same (first) input, in the row's dtype."""
    import numpy as np
    import jaxrt
    x = np.asarray(inputs[0], dtype)
    if n_node is None:
        ref = jaxrt.pairs(x, CUTOFF, cell=np.asarray(cells[0], dtype))
        system_of = np.zeros(len(x), np.int64)
    else:
        ref = jaxrt.pairs_batch(x, n_node, CUTOFF,
                                cell=np.asarray(cells, dtype))
        system_of = np.repeat(np.arange(len(n_node)), n_node)
    k = int(ref.count)
    ref = (np.asarray(ref.i)[:k], np.asarray(ref.j)[:k],
           np.asarray(ref.shift)[:k])
    if isinstance(first, (tuple, list)) and np.ndim(first[0]) == 2 \
            and np.shape(first[0])[0] == 2 and np.ndim(first[1]) == 1 \
            and np.shape(first[1])[0] == len(x) + 1:  # COO, neighbor_ptr
        got = (np.asarray(first[0][0]), np.asarray(first[0][1]),
               np.asarray(first[2]))
    else:
        got = matrix_pairs(first)
    return compare_pairs(got, ref, np.asarray(inputs[0], np.float64), cells,
                         system_of, CUTOFF,
                         pair_tolerance(dtype, inputs[0], cells))


def _version(dist: str) -> str:
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version(dist)
    except PackageNotFoundError:
        return "?"


def _nval_missing(method: str) -> str | None:
    """Why ``method`` cannot run here (None when it can)."""
    mods = ["nvalchemiops", "warp"]
    if method == "nvalchemiops":
        mods.append("torch")
    for mod in mods:
        try:
            __import__(mod)
        except Exception as exc:  # noqa: BLE001 - any import failure skips
            return f"{mod} not importable: {type(exc).__name__}: {exc}"
    if method == "nvalchemiops":
        import torch
        if not torch.cuda.is_available():
            return "torch has no CUDA device"
    if method == NVAL_PC:
        import jax
        if jax.default_backend() != "gpu":
            return "strategy='pair_centric' is CUDA-only"
    return None


def run_row(job: dict) -> dict:
    """One (method, system) row, in a worker."""
    method, dtype = job["method"], job["dtype"]
    batch = job.get("system", "diamond") != "diamond"
    if method.startswith("nvalchemiops"):
        why = _nval_missing(method)
        if why:
            return {"status": "skipped", "failed": why}
    if method.startswith(("jaxrt", "nvalchemiops[jax")) \
            and dtype == "float64":
        import jax
        jax.config.update("jax_enable_x64", True)
    if method == XLA_WALK:
        import importlib
        importlib.import_module("jaxrt.pairs.program").WARP_WALK_ON_CUDA = \
            False
    if method == GRAPH_WALK:
        import importlib
        importlib.import_module("jaxrt.pairs.warp_search").GRAPH = "warp"
    if batch:
        g, m = parse_batch(job["system"])
        pos, n_node, cells = batch_scene(g, m)
        jitter = __import__("numpy").random.default_rng(1)
        inputs = [pos] + [pos + jitter.normal(0, 1e-3, pos.shape)
                          for _ in range(2)]
        if method in ("jaxrt", XLA_WALK, GRAPH_WALK, CELLS):
            call, xs, sync, count = _jaxrt_batch(inputs, n_node, cells, dtype,
                                                 method == CELLS)
        elif method == "vesin":
            call, xs, sync, count = _vesin_batch(inputs, n_node, cells)
        elif method in (NVAL_JIT, NVAL_PC):
            call, xs, sync, count = _nval_jit_batch(inputs, n_node, cells,
                                                    dtype, method == NVAL_PC)
        else:
            raise ValueError(f"no batch row for method {method!r}")
    else:
        n_node = None
        inputs, cell = _inputs(job["N"])
        cells = cell[None]
        if method.startswith("jaxrt"):
            call, xs, sync, count = _jaxrt(method == "jaxrt[eager]", inputs,
                                           cell, dtype)
        elif method == "nvalchemiops":
            call, xs, sync, count = _nvalchemiops(inputs, cell, dtype)
        elif method == "nvalchemiops[jax]":
            call, xs, sync, count = _nvalchemiops_jax(inputs, cell, dtype)
        elif method in (NVAL_JIT, NVAL_PC):
            call, xs, sync, count = _nval_jit(inputs, cell, dtype,
                                              method == NVAL_PC)
        else:
            call, xs, sync, count = {"ase": _ase, "matscipy": _matscipy,
                                     "vesin": _vesin}[method](inputs, cell)
    timing = _harness.time_calls(call, xs, repeats=job["repeats"],
                                 warmup=job["warmup"], sync=sync,
                                 target_s=job["target_s"],
                                 max_repeats=job["max_repeats"])
    pairs = count(timing.first)
    n = len(inputs[0])
    row = {"N": n, "k": round(pairs / n, 1), "pairs": pairs,
           "time_ms": timing.median_ms, **timing.columns()}
    if method.startswith("nvalchemiops"):
        row["nvalchemiops"] = _version("nvalchemi-toolkit-ops")
    if method.startswith("nvalchemiops") and job.get("check", True):
        first = timing.first
        if method == "nvalchemiops":  # torch tensors
            first = tuple(v.cpu().numpy() for v in first[:3])
        verdict = _check_nval(first, inputs, cells, n_node, dtype)
        row.update(same_pairs=verdict["same_pairs"],
                   boundary=verdict["boundary"])
        if verdict["reason"]:
            row.update(status="error", failed=verdict["reason"],
                       time_ms=None)
    return row


def add_ratios(rows: list[dict]) -> None:
    """Time relative to the fastest and count agreement with ASE, per
    system and N."""
    for r in rows:
        r.setdefault("system", "diamond")
    for r in rows:
        same_n = [x for x in rows if x["N"] == r["N"]
                  and x["system"] == r["system"] and x["status"] == "ok"]
        ase = next((x for x in same_n if x["method"] == "ase"), None)
        if r["status"] != "ok":
            continue
        r["vs_fastest"] = r["time_ms"] / min(x["time_ms"] for x in same_n)
        if ase is not None:
            r["same_count"] = r["pairs"] == ase["pairs"]


COLUMNS = ["method", "system", "N", "k", "pairs", "time_ms", "min_ms",
           "max_ms", "repeats", "vs_fastest", "same_count", "same_pairs",
           "boundary"]


def main(argv=None) -> None:
    parser = _harness.make_parser(__doc__)
    parser.add_argument("--sizes", type=int, nargs="*",
                        default=[1_000, 10_000, 100_000])
    parser.add_argument("--batches", nargs="*", default=None,
                        help="flat batches GxM (G systems of M fcc atoms, "
                        f"M a multiple of 4); default {' '.join(BATCHES)}; "
                        "none: single systems only")
    parser.add_argument("--methods", nargs="+", default=None,
                        choices=CPU_METHODS + [m for m in GPU_METHODS
                                               if m not in CPU_METHODS]
                        + [CELLS])
    parser.add_argument("--dtype", default="float64",
                        choices=["float32", "float64"],
                        help="jaxrt's and nvalchemiops' dtype (ASE, matscipy "
                        "and vesin are float64)")
    parser.add_argument("--gpu", action="store_true",
                        help="CUDA rows: jaxrt, jaxrt[eager], nvalchemiops "
                        "(torch, jax, jax-jit) at 1e3..1e6, float32; batches "
                        "jaxrt and nvalchemiops[jax-jit]")
    parser.add_argument("--ase-max", type=int, default=200_000,
                        help="skip ASE above this N (minutes per call)")
    parser.add_argument("--target-s", type=float, default=3.0,
                        help="timed seconds per row (repeats raised to it)")
    parser.add_argument("--no-check", action="store_true",
                        help="skip comparing nvalchemiops' pairs with "
                        "jaxrt's")
    parser.add_argument("--quick", action="store_true")
    _harness.add_common_args(parser, name="pairs.csv", repeats=3, warmup=1,
                             timeout=1200)
    args = parser.parse_args(argv)
    batch_methods = CPU_BATCH_METHODS
    if args.gpu:
        args.methods = args.methods or GPU_METHODS
        batch_methods = GPU_BATCH_METHODS
        if args.sizes == parser.get_default("sizes"):
            args.sizes = [1_000, 10_000, 100_000, 1_000_000]
        if args.dtype == parser.get_default("dtype"):
            args.dtype = "float32"
    methods = args.methods or CPU_METHODS
    if args.methods:
        batch_methods = [m for m in args.methods if m in BATCH_METHODS]
    batches = BATCHES if args.batches is None else args.batches
    if args.quick:
        args.sizes, args.repeats, args.target_s = [1000], 2, 0.2
        if args.batches is None:
            batches = ["8x32"]
    for b in batches:
        parse_batch(b)  # a bad name fails here, not in every worker
    common = {"dtype": args.dtype, "repeats": args.repeats,
              "warmup": args.warmup, "target_s": args.target_s,
              "max_repeats": 50, "check": not args.no_check}
    jobs = [{"method": m, "system": "diamond", "N": n, **common}
            for n in args.sizes for m in methods
            if not (m == "ase" and n > args.ase_max)]
    jobs += [{"method": m, "system": b, "N": prod(parse_batch(b)), **common}
             for b in batches for m in batch_methods]
    _harness.run_jobs("pairs:run_row", jobs, columns=COLUMNS,
                      finish=add_ratios, **_harness.run_options(args))


if __name__ == "__main__":
    main()
