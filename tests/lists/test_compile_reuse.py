"""An eager ``update`` compiles its program once: later eager calls with
lists of the same structure and shapes reuse it (they recompiled the whole
search at every call, many times jax-md's eager update)."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import monitoring
from jax_md import space

import jaxrt

_COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"
_compiles: list[str] = []
_listening = []


def _count_compiles():
    if not _listening:
        monitoring.register_event_duration_secs_listener(
            lambda event, _secs, **_: _compiles.append(event)
            if event == _COMPILE_EVENT else None)
        _listening.append(True)
    _compiles.clear()
    return _compiles


def _system(n=48, side=6.0, seed=0):
    r = np.random.default_rng(seed).uniform(0, side, (n, 2))
    return jnp.asarray(r, jnp.float32), side


def _brute_force(position, side, cutoff):
    """float64 minimum-image pairs ``{(i, j)}``, i != j."""
    r = np.asarray(position, np.float64)
    d = r[:, None] - r[None]
    d -= side * np.round(d / side)
    near = (d ** 2).sum(-1) < cutoff ** 2
    np.fill_diagonal(near, False)
    return {(int(i), int(j)) for i, j in zip(*np.nonzero(near))}


def _pairs(nbrs):
    idx = np.asarray(nbrs.idx)
    n = idx.shape[0]
    return {(i, int(j)) for i in range(n) for j in idx[i] if j < n}


@pytest.mark.parametrize("backend", ["auto", "brute"])
def test_second_eager_update_compiles_nothing(backend):
    position, side = _system()
    displacement, _ = space.periodic(side)
    fns = jaxrt.neighbor_list(displacement, side, 1.0, 0.4, backend=backend)
    nbrs = fns.allocate(position)
    shift = jnp.asarray([0.05, -0.03], jnp.float32)
    moved = [jax.block_until_ready(position + k * shift) for k in (1, 2, 3)]
    first = nbrs.update(moved[0])
    compiles = _count_compiles()
    second = nbrs.update(moved[1])
    again = first.update(moved[2])
    assert len(compiles) == 0, compiles
    # The reused program is still the search: exact lists, no error.
    for moved, got in ((moved[1], second), (moved[2], again)):
        assert not bool(got.did_buffer_overflow)
        assert _pairs(got) == _brute_force(np.mod(moved, side), side, 1.4)


def test_eager_update_still_flags_overflow():
    position, side = _system()
    displacement, _ = space.periodic(side)
    fns = jaxrt.neighbor_list(displacement, side, 1.0, 0.0, backend="brute")
    nbrs = fns.allocate(position)
    nbrs.update(position)
    dense = jax.block_until_ready(position * 0.5)  # rows past the capacity
    compiles = _count_compiles()
    out = nbrs.update(dense)
    assert len(compiles) == 0, compiles
    assert bool(out.did_buffer_overflow)
    assert not bool(nbrs.update(position).did_buffer_overflow)


def test_second_factory_reuses_the_cell_lists_programs():
    """A second `neighbor_list` with the same displacement and arguments
    compiles no new sort or search program at ``allocate`` (the squared
    metric wrapping the displacement is equal across factories)."""
    from jaxrt.backends.cell import search
    position, side = _system(seed=1)
    displacement, _ = space.periodic(side)
    first = jaxrt.neighbor_list(displacement, side, 1.0, 0.4, backend="cell")
    expected = first.allocate(position)
    programs = (search._sorted_system, search._visit, search._run_sizes_fast,
                search._run_sizes_quick, search._visit_quick)
    before = [p._cache_size() for p in programs]
    second = jaxrt.neighbor_list(displacement, side, 1.0, 0.4, backend="cell")
    got = second.allocate(position)
    assert [p._cache_size() for p in programs] == before
    np.testing.assert_array_equal(np.sort(np.asarray(got.idx), axis=1),
                                  np.sort(np.asarray(expected.idx), axis=1))
    assert _pairs(got) == _brute_force(position, side, 1.4)


@pytest.mark.parametrize("backend,fmt", [("auto", "Dense"), ("cell", "Sparse"),
                                         ("brute", "OrderedSparse")])
def test_first_eager_update_after_allocate_compiles_nothing(backend, fmt):
    """``allocate`` builds through the program the first eager ``update``
    runs (the same capacity, forced to rebuild): a newcomer's first update,
    rebuild or not, compiles nothing more, and is exact."""
    from jax_md import partition
    position, side = _system(seed=2)
    displacement, _ = space.periodic(side)
    layout = getattr(partition.NeighborListFormat, fmt)
    fns = jaxrt.neighbor_list(displacement, side, 1.0, 0.4, backend=backend,
                              format=layout)
    nbrs = fns.allocate(position)
    near = jax.block_until_ready(position + 0.01)  # no rebuild
    far = jax.block_until_ready(position + jnp.asarray([0.5, -0.3]))  # rebuild
    compiles = _count_compiles()
    kept = nbrs.update(near)
    rebuilt = nbrs.update(far)
    assert len(compiles) == 0, compiles
    np.testing.assert_array_equal(np.asarray(kept.idx), np.asarray(nbrs.idx))
    assert not bool(rebuilt.did_buffer_overflow)
    assert not bool(nbrs.did_buffer_overflow)
    expected = _brute_force(np.mod(far, side), side, 1.4)
    if fmt == "Dense":
        assert _pairs(rebuilt) == expected
        assert _pairs(nbrs) == _brute_force(position, side, 1.4)
    else:
        i, j = np.asarray(rebuilt.idx)
        n = position.shape[0]
        got = {(int(a), int(b)) for a, b in zip(i, j) if a < n}
        if fmt == "OrderedSparse":
            expected = {(a, b) for a, b in expected if a > b} | {
                (b, a) for a, b in expected if a > b}
            got = got | {(b, a) for a, b in got}
            expected = expected | {(b, a) for a, b in expected}
        assert got == expected


def test_auto_searches_small_lists_with_all_pairs_on_a_cpu():
    """``"auto"`` on a CPU: lists of at most 256 particles by ``brute``
    (whose program compiles in a fraction of the cell list's time), larger
    ones by ``cell``, picked per allocate by N, both exact."""
    if jax.default_backend() != "cpu":
        pytest.skip("the small-N rule is the CPU's")
    from jaxrt import backends
    side = 7.0
    displacement, _ = space.periodic(side)
    fns = jaxrt.neighbor_list(displacement, side, 1.0, 0.4)
    searcher = fns.allocate.__self__.searcher
    assert isinstance(searcher, backends.BySize)
    assert searcher.for_size(256).name == "brute"
    assert searcher.for_size(257).name == "cell"
    for n, internal in ((256, {"row"}), (257, {"fixed_grid", "row", "shell",
                                               "shell_rows", "window"})):
        position, _ = _system(n=n, side=side, seed=n)
        nbrs = fns.allocate(position)
        assert set(dict(nbrs.cell_list_capacity.internal)) == internal
        assert not bool(nbrs.did_buffer_overflow)
        assert _pairs(nbrs) == _brute_force(position, side, 1.4)
        moved = jax.block_until_ready(position + 0.3)
        got = nbrs.update(moved)
        assert _pairs(got) == _brute_force(np.mod(moved, side), side, 1.4)


@pytest.mark.parametrize("cloud", [False, True])
def test_a_fixed_box_grid_skips_coarsening_only_where_it_never_coarsens(
        cloud):
    """A periodic list with a fixed box compiles its grid without the
    coarsening loop (``fixed_grid``) where the box proves that the grid
    never coarsens; a small cloud in a huge box does coarsen (and compacts
    an empty slab), and keeps the loop. Both lists exact, before and after
    a rebuild."""
    side = 60.0 if cloud else 7.0
    displacement, _ = space.periodic(side)
    fns = jaxrt.neighbor_list(displacement, side, 1.0, 0.4, backend="cell")
    position, _ = _system(n=300, side=4.0 if cloud else side, seed=5)
    nbrs = fns.allocate(position)
    assert dict(nbrs.cell_list_capacity.internal)["fixed_grid"] == int(
        not cloud)
    assert _pairs(nbrs) == _brute_force(position, side, 1.4)
    moved = jax.block_until_ready(position - 0.7)  # across the box's faces
    got = nbrs.update(moved)
    assert not bool(got.did_buffer_overflow)
    assert _pairs(got) == _brute_force(np.mod(moved, side), side, 1.4)


@pytest.mark.parametrize("backend,fmt", [("auto", "Dense"), ("cell", "Dense"),
                                         ("cell", "Sparse"),
                                         ("brute", "OrderedSparse")])
def test_second_equal_factory_compiles_nothing(backend, fmt):
    """A second `neighbor_list` with the same displacement and arguments
    (a user's second system, a test's second case) meets the first one's
    programs: its ``allocate`` and its updates compile nothing, and its
    lists are exact and its own (their ``update`` is its factory's)."""
    from jax_md import partition
    position, side = _system(n=300, side=7.0, seed=3)
    displacement, _ = space.periodic(side)
    layout = getattr(partition.NeighborListFormat, fmt)

    def factory():
        return jaxrt.neighbor_list(displacement, side, 1.0, 0.4,
                                   backend=backend, format=layout)

    first = factory()
    first.allocate(position).update(position + 0.5).idx.block_until_ready()
    far = jax.block_until_ready(position + jnp.asarray([0.5, -0.3]))
    second = factory()
    compiles = _count_compiles()
    nbrs = second.allocate(position)
    rebuilt = nbrs.update(far)
    kept = rebuilt.update(far + 0.01)
    jax.block_until_ready((nbrs.idx, rebuilt.idx, kept.idx))
    assert len(compiles) == 0, compiles
    assert nbrs.update_fn == second.update
    assert rebuilt.update_fn == second.update
    for got, at in ((nbrs, position), (rebuilt, far), (kept, far)):
        assert not bool(got.did_buffer_overflow)
        expected = _brute_force(np.mod(at, side), side, 1.4)
        if fmt == "Dense":
            assert _pairs(got) == expected
            continue
        i, j = np.asarray(got.idx)
        pairs = {(int(a), int(b)) for a, b in zip(i, j) if a < 300}
        if fmt == "OrderedSparse":
            assert all(a > b for a, b in pairs) or all(a < b for a, b in pairs)
            pairs |= {(b, a) for a, b in pairs}
        assert pairs == expected


@pytest.mark.parametrize("change", ["cutoff", "skin", "mask_self", "box",
                                    "mask_function"])
def test_factories_that_differ_keep_their_own_programs(change):
    """Factories share programs only where nothing they trace differs: each
    list below is exact for its own arguments although an earlier factory
    of almost the same arguments compiled first."""
    position, side = _system(n=300, side=7.0, seed=4)
    displacement, _ = space.periodic(side)
    base = dict(r_cutoff=1.0, dr_threshold=0.4, mask_self=True)
    jaxrt.neighbor_list(displacement, side, **base).allocate(
        position).update(position + 0.5).idx.block_until_ready()
    cutoff, box, mask = 1.4, side, None
    other = dict(base)
    if change == "cutoff":
        other["r_cutoff"], cutoff = 0.7, 1.1
    elif change == "skin":
        other["dr_threshold"], cutoff = 0.1, 1.1
    elif change == "mask_self":
        other["mask_self"] = False
    elif change == "box":
        box = side + 1.0
        displacement, _ = space.periodic(box)
    else:
        def mask(idx):  # drop odd neighbours
            return jnp.where(idx % 2 == 1, idx.shape[0], idx)
        other["custom_mask_function"] = mask
    fns = jaxrt.neighbor_list(displacement, box, **other)
    far = jax.block_until_ready(position + jnp.asarray([0.5, -0.3]))
    nbrs = fns.allocate(position)
    for got, at in ((nbrs, position), (nbrs.update(far), far)):
        assert not bool(got.did_buffer_overflow)
        expected = _brute_force(np.mod(at, box), box, cutoff)
        if change == "mask_self":
            expected |= {(i, i) for i in range(300)}
        if mask is not None:
            expected = {(i, j) for i, j in expected if j % 2 == 0}
        assert _pairs(got) == expected


def _case(name):
    """(position float32 (N, dim), displacement, box, r_cutoff)."""
    from scenes import fluid, lattice
    if name == "lattice":  # every nearest pair exactly at the cutoff
        r = lattice(7, 1.0)
        return jnp.asarray(r), space.periodic(7.0)[0], 7.0, 0.8
    if name == "small_box":  # a cutoff of more than half the box
        r, side = fluid(n_side=4)
        return jnp.asarray(r, jnp.float32), space.periodic(side)[0], side, 2.2
    if name == "free":
        r, _ = fluid(n_side=7)
        return jnp.asarray(r, jnp.float32), space.free()[0], None, 1.0
    if name == "2d":
        r, side = fluid(n_side=20, dim=2)
        return jnp.asarray(r, jnp.float32), space.periodic(side)[0], side, 1.2
    r, side = fluid(n_side=8)
    return jnp.asarray(r, jnp.float32), space.periodic(side)[0], side, 1.0


@pytest.mark.parametrize("name,fmt,mask_self", [
    ("fluid", "Dense", True), ("fluid", "OrderedSparse", True),
    ("fluid", "Sparse", False), ("lattice", "Dense", True),
    ("small_box", "Dense", True), ("free", "Sparse", True),
    ("2d", "Dense", False)])
def test_small_lists_count_over_all_pairs_as_the_windows_do(
        monkeypatch, name, fmt, mask_self):
    """``allocate`` on a CPU counts a small cell list's rows over all pairs
    (its program compiles several times faster than the windows' count):
    the same capacity, the windows' own, shell buffers at least the
    windows' (an upper bound), and the same exact list, never flagged."""
    if jax.default_backend() != "cpu":
        pytest.skip("the all-pairs count is the CPU's")
    import warnings
    from jax_md import partition
    from jaxrt.backends.cell import search
    position, displacement, box, cutoff = _case(name)
    layout = getattr(partition.NeighborListFormat, fmt)

    def allocate(limit):
        monkeypatch.setattr(search, "_ALL_PAIRS_COUNT_MAX_N", limit)
        fns = jaxrt.neighbor_list(displacement, box, cutoff, 0.2,
                                  backend="cell", format=layout,
                                  mask_self=mask_self)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the small box's warning
            nbrs = fns.allocate(position)
        return nbrs, dict(nbrs.cell_list_capacity.internal)

    before = search._visit_quick._cache_size()
    nbrs, sizes = allocate(10 ** 9)
    assert search._visit_quick._cache_size() == before  # no windows' count
    windows, by_windows = allocate(0)
    assert nbrs.idx.shape == windows.idx.shape
    assert sizes["window"] == by_windows["window"]
    assert sizes["shell"] >= by_windows["shell"]
    assert sizes["shell_rows"] >= by_windows["shell_rows"]
    for got in (nbrs, windows):
        assert not bool(got.did_buffer_overflow)
    if fmt == "Dense":
        assert _sorted_rows(nbrs) == _sorted_rows(windows)
    else:
        assert _edges(nbrs) == _edges(windows)
    far = jax.block_until_ready(position + 0.35)
    assert not bool(nbrs.update(far).did_buffer_overflow)


def _sorted_rows(nbrs):
    n = nbrs.idx.shape[0]
    return [sorted(int(j) for j in row if j < n)
            for row in np.asarray(nbrs.idx)]


def _edges(nbrs):
    i, j = np.asarray(nbrs.idx)
    n = nbrs.reference_position.shape[0]
    return sorted((int(a), int(b)) for a, b in zip(i, j) if a < n)


def test_eager_update_past_the_quick_size_on_a_cpu(monkeypatch):
    """Past `_QUICK_EAGER_MAX_N` a CPU's eager ``update`` (and ``allocate``,
    which builds through it) runs the program compiled with
    `CPU_COMPILE_OPTIONS`: it is taken, compiled once for both, and its
    lists are exact before and after a rebuild."""
    from jaxrt.lists import neighbors
    if jax.default_backend() != "cpu":
        pytest.skip("the CPU's program")
    monkeypatch.setattr(neighbors, "_QUICK_EAGER_MAX_N", 8)
    position, side = _system(n=60, seed=5)
    # A displacement of its own: this factory's programs are new.
    displacement, _ = space.periodic(side)
    fns = jaxrt.neighbor_list(displacement, side, 1.0, 0.4)
    lists = fns.allocate.__self__
    before = lists.eager_update_cpu._cache_size()
    nbrs = fns.allocate(position)
    assert lists.eager_update_cpu._cache_size() == before + 1
    far = jax.block_until_ready(position + jnp.asarray([0.5, -0.3]))
    compiles = _count_compiles()
    rebuilt = nbrs.update(far)
    assert len(compiles) == 0, compiles
    assert not bool(nbrs.did_buffer_overflow)
    assert not bool(rebuilt.did_buffer_overflow)
    assert _pairs(nbrs) == _brute_force(position, side, 1.4)
    assert _pairs(rebuilt) == _brute_force(np.mod(far, side), side, 1.4)


def test_cpu_compile_options_are_accepted_by_this_xla():
    """`CPU_COMPILE_OPTIONS` (and the quick ones, which include them) are
    given only where XLA knows them: an unknown option fails every CPU
    ``allocate`` at compile time."""
    from jaxrt.lists import metric
    cpu = jax.devices("cpu")[0]
    x = jax.device_put(np.float32(1.0), cpu)
    for options in (metric.CPU_COMPILE_OPTIONS, metric.QUICK_COMPILE_OPTIONS):
        assert float(jax.jit(lambda v: v * 2, compiler_options=options)(x)) == 2.0
    assert set(metric.CPU_COMPILE_OPTIONS) <= set(metric.QUICK_COMPILE_OPTIONS)


@pytest.mark.parametrize("quick_max_n", [4096, 8])
def test_concrete_arrays_inside_a_callers_jit(monkeypatch, quick_max_n):
    """``update`` and the list-free checks called inside a caller's ``jit``
    on arrays captured from outside (concrete, no tracer among them): the
    CPU's compile options are refused on a nested ``jit``, so the plain
    program runs there, and the list equals the eager one."""
    from jaxrt.lists import neighbors
    monkeypatch.setattr(neighbors, "_QUICK_EAGER_MAX_N", quick_max_n)
    position, side = _system(n=40, seed=7)
    displacement, _ = space.periodic(side)
    fns = jaxrt.neighbor_list(displacement, side, 1.0, 0.4)
    nbrs = fns.allocate(position)
    far = jax.block_until_ready(position + jnp.asarray([0.5, -0.3]))

    @jax.jit
    def captured(_):
        return nbrs.update(far).idx

    idx = np.asarray(captured(0))
    eager = nbrs.update(far)
    np.testing.assert_array_equal(idx, np.asarray(eager.idx))
    assert _pairs(eager) == _brute_force(np.mod(far, side), side, 1.4)
