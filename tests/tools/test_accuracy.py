"""jaxrt.tools.accuracy: the error measures against hand-computed cases, the knob
table, the auto rule, and one tiny end-to-end sweep writing CSV, PNG and
Markdown."""
from __future__ import annotations

import csv
import dataclasses
import math

import jax
import numpy as np
import pytest

from jaxrt.tools import accuracy


def simple_cubic(m: int, a: float = 1.0) -> np.ndarray:
    g = (np.arange(m) + 0.5) * a
    return np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)


# ---------------------------------------------------------------------------
# Error measures


def test_rdf_of_a_simple_cubic_lattice_counts_its_shells():
    m, a = 6, 1.0
    side = np.full(3, m * a)
    edges = accuracy.rdf_grid(2.9, 0.05)
    g = accuracy.rdf(simple_cubic(m, a), side, edges)
    rho = m ** 3 / side.prod()
    shell = 4 / 3 * math.pi * (edges[1:] ** 3 - edges[:-1] ** 3)
    per_particle = g * rho * shell  # neighbours per particle in each bin
    mid = 0.5 * (edges[1:] + edges[:-1])

    def within(lo, hi):
        return per_particle[(mid > lo) & (mid < hi)].sum()
    # Shells of the simple cubic lattice: 6 at a, 12 at a√2, 8 at a√3,
    # 6 at 2a, 24 at a√5; nothing in between.
    assert within(0.9, 1.1) == pytest.approx(6)
    assert within(1.35, 1.48) == pytest.approx(12)
    assert within(1.68, 1.78) == pytest.approx(8)
    assert within(1.95, 2.05) == pytest.approx(6)
    assert within(2.2, 2.27) == pytest.approx(24)
    assert within(0.0, 0.95) == 0 and within(1.1, 1.35) == 0
    # Up to 2.9: d² = 1, 2, 3, 4, 5, 6, 8 (7 is no sum of three squares).
    assert per_particle.sum() == pytest.approx(6 + 12 + 8 + 6 + 24 + 24 + 12)


def test_rdf_difference_l2_and_linf_by_hand():
    l2, linf = accuracy.rdf_difference([1.0, 2.0], [1.0, 0.0], 0.25)
    assert l2 == pytest.approx(1.0) and linf == pytest.approx(2.0)


def test_pairs_missed_on_a_deliberately_short_cutoff():
    r = simple_cubic(4)
    side, periodic = np.full(3, 4.0), (True,) * 3
    full = accuracy.brute_pairs(r, 1.5, side, periodic)
    short = accuracy.brute_pairs(r, 1.1, side, periodic)
    # 64 particles: 6 nearest (d = 1) and 12 next (d = √2) neighbours each.
    assert len(full) == 64 * 18 // 2 and len(short) == 64 * 6 // 2
    assert accuracy.pairs_missed(short, full) == 64 * 12 // 2
    assert accuracy.pairs_missed(full, short) == 0
    # A real list with the short cutoff, read like the sweep reads one.
    import jax.numpy as jnp
    from jax_md import space
    import jaxrt
    from jaxrt.layouts.codes import pair_codes
    displacement, _ = space.periodic(4.0)
    fn = jaxrt.neighbor_list(displacement, 4.0, 1.1, backend="brute",
                             format=jaxrt.OrderedSparse)
    nbrs = fn.allocate(jnp.asarray(r, jnp.float32))
    assert accuracy.pairs_missed(pair_codes(nbrs, 64), full) == 64 * 12 // 2


def test_missed_depth_tells_rounding_from_a_wrong_list():
    # The deliberately short cutoff misses the d = sqrt(2) shell, 0.086
    # inside a cut of 1.5: far deeper than float32 rounding at this scale.
    r = simple_cubic(4)
    side, periodic = np.full(3, 4.0), (True,) * 3
    full = accuracy.brute_pairs(r, 1.5, side, periodic)
    short = accuracy.brute_pairs(r, 1.1, side, periodic)
    ulp = np.finfo(np.float32).eps * (np.max(np.abs(r)) + 4.0)  # |x| + side
    depth = accuracy.missed_depth_ulps(short, full, r, 1.5, side, periodic,
                                       np.float32)
    assert depth == pytest.approx((1.5 - np.sqrt(2.0)) / ulp)
    assert depth > accuracy.ROUNDING_ULPS
    assert accuracy.missed_depth_ulps(full, full, r, 1.5, side, periodic,
                                      np.float32) == 0.0
    # A pair 3 ulps inside the cut, missed: rounding; in float64 ulps the
    # same miss is ~5e8 ulps deep, a wrong list.
    eps32 = float(np.finfo(np.float32).eps)
    pair = np.array([[0.0, 0.0, 0.0], [1.5 - 3 * 1.5 * eps32, 0.0, 0.0]])
    free = (False,) * 3
    assert accuracy.missed_depth_ulps([], [1], pair, 1.5, side, free,
                                      np.float32) == pytest.approx(3.0)
    assert accuracy.missed_depth_ulps([], [1], pair, 1.5, side, free,
                                      np.float64) > 1e8
    row = {"pairs_missed": 1, "pairs_checked": 10, "missed_depth_ulps": 3.0}
    assert "rounding" in accuracy.depth_note(row)
    assert "wrong list" in accuracy.depth_note({**row, "missed_depth_ulps": 40})
    assert accuracy.depth_note({"pairs_missed": 1}) == ""


def test_exact_pairs_by_kdtree_equal_the_brute_force():
    rng = np.random.default_rng(0)
    r = rng.random((4200, 3)) * 12.0
    side = np.full(3, 12.0)
    a = accuracy.exact_pairs(r, 1.0, side, (True,) * 3)  # the cKDTree path
    b = accuracy.brute_pairs(r, 1.0, side, (True,) * 3)
    assert len(a) > 5_000 and np.array_equal(a, b)
    # The RDF's pair distances, both ways.
    kd = np.sort(accuracy.pair_distances(r, side, 1.5, kd=True))
    brute = np.sort(accuracy.pair_distances(r, side, 1.5, kd=False))
    np.testing.assert_allclose(kd, brute, rtol=0, atol=1e-12)


def test_energy_drift_of_a_synthetic_series():
    n, s = 10, 3e-5  # drift per particle per step
    t = np.arange(500)
    e = 2.0 + n * s * t
    slope, dev, se = accuracy.energy_drift(e, n)
    assert slope == pytest.approx(s * 1e4) and dev == pytest.approx(s * 499)
    assert se == pytest.approx(0, abs=1e-12)  # a straight line: no scatter
    # A bounded oscillation (a whole number of periods per block) has no
    # drift; its excursion is 2 x the amplitude (it starts at the top).
    d = accuracy.energy_drift(2.0 + 0.1 * n * np.cos(2 * np.pi * t / 50), n)
    assert abs(d.slope) < 0.05 and d.max_dev == pytest.approx(0.2, rel=0.01)
    assert d.se < 1e-9
    # Noise: the slope is within a few standard errors of the truth.
    rng = np.random.default_rng(1)
    d = accuracy.energy_drift(e + n * rng.normal(0, 1e-3, len(t)), n)
    assert abs(d.slope - s * 1e4) < 4 * d.se and 0 < d.se < 1.0


def test_force_rms_rel_by_hand():
    ref = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 5.0]])
    f = ref + np.array([[0.0, 0.0, 0.5], [0.5, 0.0, 0.0]])
    assert accuracy.force_rms_rel(f, ref) == pytest.approx(0.1)


def test_position_rms_uses_the_minimum_image():
    a = np.array([[0.1, 0.0, 0.0]])
    b = np.array([[9.9, 0.0, 0.0]])
    assert accuracy.position_rms(a, b, np.full(3, 10.0), (True,) * 3) == \
        pytest.approx(0.2)
    assert accuracy.position_rms(a, b, np.full(3, 10.0), (False,) * 3) == \
        pytest.approx(9.8)


def test_pareto_front_of_given_points():
    t = [1.0, 2.0, 3.0, 4.0, 2.5, np.nan, 2.0]
    e = [5.0, 3.0, 4.0, 1.0, 3.0, 0.0, 3.0]
    # (2.5, 3) and (3, 4) are beaten by (2, 3); NaN never counts; the equal
    # point (2, 3) appears once.
    assert accuracy.pareto_front(t, e) == [0, 1, 3]
    assert accuracy.pareto_front([1.0], [float("nan")]) == []


# ---------------------------------------------------------------------------
# Knobs and the auto rule


def test_every_knob_value_applies_to_its_scenes():
    import jaxrt.energy
    for name in accuracy.SCENES:
        base = accuracy.base_scene(name, accuracy.QUICK)
        kind, dim = accuracy.scene_kind(base), base.particles.dim
        for knob in accuracy.knobs(kind, dim=dim):
            assert knob.quick and set(knob.quick) <= {v.label
                                                       for v in knob.values}
            own = knob.base_for(base, accuracy.QUICK)  # the radii knob's
            for v in knob.selected(quick=False, dim=dim):
                try:
                    v.apply(own)
                except Exception as e:  # only box-too-small refusals
                    assert "half the periodic box" in str(e), (knob.name, e)
    names = {k.name for k in accuracy.knobs("lj")}
    assert {"dtype", "truncation", "skin", "dt", "format", "backend",
            "pairs", "delaunay-flips", "radii"} <= names
    assert "radii" not in {k.name for k in accuracy.knobs("sph")}
    assert ("list-free" in names) == hasattr(jaxrt.energy,
                                            "lennard_jones_fused")
    assert "truncation" not in {k.name for k in accuracy.knobs("sph")}
    with pytest.raises(ValueError, match="unknown knobs"):
        accuracy.knobs("lj", ["nope"])


def test_knobs_by_dimension_and_availability():
    # Delaunay is 2D only, jaxrt.pairs 3D only; the cell kernel knob and
    # the fused Cell values only where the Pallas kernel runs.
    in3 = {k.name for k in accuracy.knobs("lj", dim=3)}
    in2 = {k.name for k in accuracy.knobs("lj", dim=2)}
    sph = {k.name for k in accuracy.knobs("sph", dim=2)}
    assert "pairs" in in3 and "pairs" not in in2
    assert "delaunay-flips" in in2 and "delaunay-flips" in sph
    assert "delaunay-flips" not in in3
    backend = next(k for k in accuracy.KNOBS if k.name == "backend")
    assert "delaunay" in {v.label for v in backend.selected(True, 2)}
    assert "delaunay" not in {v.label for v in backend.selected(True, 3)}
    pallas = accuracy.pallas_here()
    assert ("cell-kernel" in in3) == pallas
    free = next(k for k in accuracy.KNOBS if k.name == "list-free")
    labels = {v.label for v in free.selected(quick=True, dim=3)}
    assert {"list", "fused"} <= labels
    if not pallas:  # a CPU: no Cell kernel values, and no crash probing
        assert not labels & {"fused-xla", "fused-pallas",
                              "fused-pallas-newton"}
    from jaxrt.backends import Cell
    assert isinstance(accuracy.fused_takes(Cell(kernel="xla")), bool)


def _tiny_step(scene, steps: int = 2):
    """Compile ``scene`` and run ``steps`` steps: finite positions."""
    from jaxrt import sim
    compiled = sim.compile_scene(scene)
    state, nbrs = compiled.init()
    state, nbrs, _ = compiled.chunk(state, nbrs, steps=steps)
    assert np.all(np.isfinite(np.asarray(state.position)))
    return compiled, state, nbrs


def _knob_value(knob: str, label: str):
    k = next(k for k in accuracy.KNOBS if k.name == knob)
    return next(v for v in k.values if v.label == label)


@pytest.fixture
def x64():
    before = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)
    yield
    jax.config.update("jax_enable_x64", before)


def test_the_2d_lj_fluid_scene():
    s = accuracy.lj_fluid_2d(n=100, density=0.7)
    assert s.particles.positions.shape == (100, 2)
    assert s.box.size[0] == pytest.approx(math.sqrt(100 / 0.7))
    assert len({tuple(np.round(p, 9)) for p in s.particles.positions}) == 100
    base = accuracy.base_scene("lj-fluid-2d", accuracy.Plan(n=64))
    assert base.dtype == "float32" and base.particles.n == 64
    assert accuracy.scene_kind(base) == "lj"


def test_delaunay_values_run_in_float64_and_count_rebuilds(x64):
    base = accuracy.base_scene("lj-fluid-2d", accuracy.Plan(n=64))
    sc = _knob_value("backend", "delaunay").apply(base)
    assert sc.dtype == "float64" and sc.neighbors.backend.name == "delaunay"
    assert sc.neighbors.capacity_multiplier == accuracy.DELAUNAY_CAPACITY
    # The default options, reached by both knobs, are one setting.
    same = _knob_value("delaunay-flips", "rounds 64, splits 32").apply(base)
    assert accuracy.row_key(sc, None) == accuracy.row_key(same, None)
    few = _knob_value("delaunay-flips", "rounds 1, splits 1").apply(base)
    assert few.neighbors.backend.max_flip_rounds == 1
    _, _, nbrs = _tiny_step(few)
    assert accuracy.triangulation_rebuilds_of(nbrs) >= 0
    assert accuracy.describe(few)["backend"] == "delaunay"


def test_pairs_value_runs_lj_on_jaxrt_pairs_with_the_lists_forces(x64):
    from jaxrt import sim
    n = 216
    base = dataclasses.replace(accuracy.base_scene("lj-fluid",
                                                   accuracy.Plan(n=n)),
                               dtype="float64")
    sc = _knob_value("pairs", "jaxrt.pairs").apply(base)
    assert not sc.pair_effects and sc.effects[0].kind == "lj_pairs"
    assert accuracy.describe(sc)["backend"] == "jaxrt.pairs (no list)"
    # Lattice start: jiggle it, so that forces are not ~0.
    rng = np.random.default_rng(0)
    pos = base.particles.positions + rng.normal(0, 0.05, (n, 3))
    base, sc = (accuracy.with_state(s, np.mod(pos, s.box.size[0]),
                                    s.particles.velocities)
                for s in (base, sc))
    a_list = sim.compile_scene(base).init()[0].accel
    compiled, _, _ = _tiny_step(sc, steps=1)
    a_pairs = compiled.init()[0].accel
    np.testing.assert_allclose(a_pairs, a_list, rtol=1e-9, atol=1e-9)
    # The effect's own pairs are checked as a list's are.
    cutoff, codes = accuracy.own_search(sc)
    want = accuracy.brute_pairs(pos, cutoff, sc.box.size, sc.box.periodic)
    got = codes(np.mod(pos, sc.box.size[0]))
    assert accuracy.pairs_missed(got, want) == 0 and len(got) == len(want)
    # An overflowed search poisons the forces instead of dropping pairs.
    tight = dataclasses.replace(sc.effects[0], capacity_margin=0.5)
    bad = dataclasses.replace(sc, effects=(tight,))
    assert not np.all(np.isfinite(sim.compile_scene(bad).init()[0].accel))


def test_list_free_fused_values_apply(x64):
    import jaxrt.energy
    if not hasattr(jaxrt.energy, "lennard_jones_fused"):
        pytest.skip("no fused energy")
    from jaxrt.backends import Cell
    base = accuracy.base_scene("lj-fluid", accuracy.Plan(n=216))
    fused = _knob_value("list-free", "fused").apply(base)
    assert fused.effects[0].backend == "cell"
    assert accuracy.describe(fused)["backend"] == "fused cell (no list)"
    for k in ("xla", "pallas"):
        sc = _knob_value("list-free", f"fused-{k}").apply(base)
        assert sc.effects[0].backend == Cell(kernel=k)
        assert accuracy.describe(sc)["backend"] == f"fused cell[{k}] (no list)"
    newton = _knob_value("list-free", "fused-pallas-newton").apply(base)
    assert newton.effects[0].backend.newton
    assert (accuracy.describe(newton)["backend"]
            == "fused cell[auto+newton] (no list)")
    _tiny_step(fused, steps=1)


def test_cell_kernel_values_set_the_kernel():
    from jaxrt.backends import Cell
    base = accuracy.base_scene("lj-fluid-2d", accuracy.Plan(n=64))
    for k in ("auto", "xla", "pallas"):
        assert _knob_value("cell-kernel", k).apply(base).neighbors.backend \
            == Cell(kernel=k)
    # No step: on a CPU "xla" is the program of every cell run here, and
    # "pallas" runs on CUDA only (the knob's `available`).


def test_truncation_knob_sets_cutoff_onset_and_truncation():
    base = accuracy.base_scene("lj-fluid", accuracy.QUICK)
    knob = next(k for k in accuracy.KNOBS if k.name == "truncation")
    v = next(v for v in knob.values if v.label == "shifted 3")
    lj = v.apply(base).effect("lj")
    assert (lj.truncation, lj.r_cutoff) == ("shifted", 3.0)
    assert lj.r_onset == pytest.approx(2.4)


def test_auto_rule():
    from jaxrt.lists.neighbors import _auto_backend, choose_backend
    assert choose_backend(platform="cpu") == "cell"
    assert choose_backend(platform="cpu", has_radii=True) == "bvh"
    assert choose_backend(platform="cpu", has_radii=True, warp=False) == \
        "cell"
    for gpu in ("gpu", "cuda", "rocm", "tpu"):
        assert choose_backend(platform=gpu) == "cell"
        assert choose_backend(platform=gpu, has_radii=True) == "cell"
    import jax
    if jax.default_backend() == "cpu":
        assert _auto_backend() == "cell"
    base = accuracy.base_scene("lj-fluid", accuracy.QUICK)
    assert accuracy.auto_backend_for(base) == choose_backend(
        platform=jax.default_backend())


# ---------------------------------------------------------------------------
# Per-particle cutoff radii: the polydisperse scene and the radii knob


def _smooth_lj_radii_oracle(r, side, radii, r_onset=2.0, r_cutoff=2.5):
    """Float64 brute force, NumPy only: every pair i < j (minimum image)
    cut at c = max(r_i, r_j), jax-md's smooth LJ with sigma, r_onset and
    r_cutoff all stretched by c / r_cutoff (epsilon 1)."""
    r = np.asarray(r, np.float64)
    i, j = np.triu_indices(len(r), 1)
    d = r[i] - r[j]
    d -= side * np.round(d / side)
    dr = np.sqrt(np.sum(d * d, -1))
    c = np.maximum(radii[i], radii[j])
    s = c / r_cutoff
    sig, ro, rc = s, r_onset * s, c
    lj = 4 * ((sig / dr) ** 12 - (sig / dr) ** 6)
    sw = np.where(dr < ro, 1.0, np.where(
        dr < rc, (rc ** 2 - dr ** 2) ** 2 * (rc ** 2 + 2 * dr ** 2
                                             - 3 * ro ** 2)
        / (rc ** 2 - ro ** 2) ** 3, 0.0))
    return float(np.sum(lj * sw))


def _small_polydisperse(n=128, **kw):
    from jaxrt import sim
    kw.setdefault("radii", (2.0, 4.5))  # reaches 2.3, 4.8: two classes
    kw.setdefault("fractions", (0.95, 0.05))
    kw.setdefault("density", 0.12)  # side 10.2 > 2 (4.5 + skin 0.3)
    return sim.lj_polydisperse(n=n, backend="cell", **kw)


def test_polydisperse_scene_places_no_pair_inside_its_core():
    s = _small_polydisperse(n=300, seed=3)
    lj = s.effect("lj")
    radii = np.asarray(lj.radii)
    assert s.particles.positions.shape == (300, 3)
    assert sorted(set(lj.radii)) == [2.0, 4.5]
    assert int(np.sum(radii == 4.5)) == 15 and s.cutoff == 4.5
    r = s.particles.positions
    i, j = np.triu_indices(300, 1)
    d = r[i] - r[j]
    d -= s.box.size[0] * np.round(d / s.box.size[0])
    sigma_ij = np.maximum(radii[i], radii[j]) / 2.5
    assert np.min(np.sqrt(np.sum(d * d, -1)) / sigma_ij) >= 2 ** (1 / 6) - 1e-9
    flat = _small_polydisperse(n=200, dim=2)
    assert flat.particles.dim == 2 and flat.box.size == (flat.box.size[0],) * 2
    # A scene's radii survive TOML both ways.
    from jaxrt import sim
    back = sim.from_toml(sim.to_toml(s))
    assert back.effect("lj") == lj and isinstance(back.effect("lj").radii,
                                                  tuple)


def test_polydisperse_list_energy_equals_fused_and_brute_force(x64):
    """The scene's LJ on its radii list, the fused LJ (list-free, brute
    and cell searches) and a NumPy float64 brute force give one energy;
    the forces agree, and with central differences of the oracle."""
    import jax.numpy as jnp
    import jaxrt.energy
    from jaxrt import sim
    s = _small_polydisperse()
    side = s.box.size[0]
    rng = np.random.default_rng(0)
    pos = np.mod(s.particles.positions + rng.normal(0, 0.05, (128, 3)), side)
    # The brute-force list (with radii): the radius classes' allocate takes
    # seconds to compile on a CPU, and the knob's test below runs them.
    s = accuracy.with_state(dataclasses.replace(
        s, dtype="float64", neighbors=sim.Neighbors(backend="brute")), pos,
        np.zeros((128, 3)))
    radii = np.asarray(s.effect("lj").radii)
    compiled = sim.compile_scene(s)
    assert any("per-particle radii" in line for line in compiled.plan)
    state, nbrs = compiled.init()
    e_list = float(compiled.energy(state, nbrs))  # velocities are 0
    f_list = np.asarray(state.accel)  # masses are 1
    e_ref = _smooth_lj_radii_oracle(pos, side, radii)
    assert abs(e_ref) > 1.0  # the sum has something in it
    assert e_list == pytest.approx(e_ref, rel=1e-10)
    fused = jaxrt.energy.lennard_jones_fused(
        compiled.displacement, side, sigma=1.0, r_onset=2.0, r_cutoff=2.5,
        radii=radii, backend="brute")
    R = jnp.asarray(pos)
    assert float(fused(R)) == pytest.approx(e_ref, rel=1e-10)
    np.testing.assert_allclose(-np.asarray(jax.grad(fused)(R)), f_list,
                               rtol=1e-9, atol=1e-10)
    # The accuracy sweep's fused effect (its cell search), in the scene, is
    # the same LJ.
    sc = _knob_value("radii", "fused").apply(s)
    assert not sc.pair_effects and sc.effects[0].radii == tuple(radii)
    np.testing.assert_allclose(sim.compile_scene(sc).init()[0].accel, f_list,
                               rtol=1e-9, atol=1e-10)
    # Central differences of the oracle, on the particles of the large radius.
    h = 1e-6
    for k in np.flatnonzero(radii == radii.max())[:2]:
        for a in range(3):
            up, dn = pos.copy(), pos.copy()
            up[k, a] += h
            dn[k, a] -= h
            fd = -(_smooth_lj_radii_oracle(up, side, radii)
                   - _smooth_lj_radii_oracle(dn, side, radii)) / (2 * h)
            assert f_list[k, a] == pytest.approx(fd, rel=1e-5, abs=1e-6)


def test_brute_pairs_with_radii_by_hand():
    # On a line, free space: 0 at x = 0 (radius 1), 1 at 1.5 (radius 2),
    # 2 at 4.0 (radius 0.5): d01 = 1.5 < max(1, 2), d12 = 2.5 >= 2,
    # d02 = 4 >= 2.
    r = np.array([[0.0, 0, 0], [1.5, 0, 0], [4.0, 0, 0]])
    radii = np.array([1.0, 2.0, 0.5])
    got = accuracy.brute_pairs(r, 99.0, np.ones(3), (False,) * 3,
                               radii=radii)
    assert got.tolist() == [0 * 3 + 1]
    radii[2] = 2.6  # now d12 = 2.5 < 2.6 and d02 = 4 >= 2.6
    got = accuracy.brute_pairs(r, 99.0, np.ones(3), (False,) * 3,
                               radii=radii)
    assert got.tolist() == [0 * 3 + 1, 1 * 3 + 2]
    with pytest.raises(ValueError, match="radii has shape"):
        accuracy.brute_pairs(r, 1.0, np.ones(3), (False,) * 3,
                             radii=radii[:2])
    # Large n: the cKDTree path cuts each pair at max(r_i, r_j) as well.
    rng = np.random.default_rng(1)
    big = rng.random((4200, 3)) * 12.0
    rad = rng.choice([0.4, 1.0], 4200)
    a = accuracy.exact_pairs(big, 0.0, np.full(3, 12.0), (True,) * 3,
                             radii=rad)
    b = accuracy.brute_pairs(big, 0.0, np.full(3, 12.0), (True,) * 3,
                             radii=rad)
    plain = accuracy.brute_pairs(big, 1.0, np.full(3, 12.0), (True,) * 3)
    assert np.array_equal(a, b) and 1000 < len(a) < len(plain)


def test_bad_radii_raise_clear_errors():
    from jaxrt import sim
    from jaxrt.sim import SceneError
    s = _small_polydisperse()
    lj = s.effect("lj")

    def with_lj(**kw):
        return dataclasses.replace(s, effects=(dataclasses.replace(lj, **kw),))
    with pytest.raises(SceneError, match=r"effects\[0\]\.radii: needs one "
                       r"radius per particle \(128\); got 127"):
        with_lj(radii=lj.radii[:-1])
    bad = list(lj.radii)
    bad[5] = -1.0
    with pytest.raises(SceneError, match=r"radii\[5\] = -1.0; radii must be "
                       "finite and >= 0"):
        with_lj(radii=bad)
    bad[5] = float("nan")
    with pytest.raises(SceneError, match=r"radii\[5\] = nan"):
        with_lj(radii=bad)
    with pytest.raises(SceneError, match="all radii are 0"):
        with_lj(radii=np.zeros(128))
    with pytest.raises(SceneError, match=r"lj\.radii: must be a flat"):
        with_lj(radii=np.ones((128, 1)))
    with pytest.raises(SceneError, match="half the periodic box"):
        with_lj(radii=np.full(128, s.box.size[0] / 2))
    with pytest.raises(SceneError, match="scalar sigma and epsilon"):
        dataclasses.replace(s, effects=(dataclasses.replace(
            lj, epsilon=[[1.0, 1.0], [1.0, 1.0]]),), particles=dataclasses
            .replace(s.particles, species=np.zeros(128, int)))
    with pytest.raises(SceneError, match="give one of the two"):
        dataclasses.replace(s, particles=dataclasses.replace(
            s.particles, radius=np.linspace(0.5, 0.6, 128)))
    with pytest.raises(SceneError, match="'perse' needs one cutoff"):
        dataclasses.replace(s, integrator=sim.Integrator(dt=0.005,
                                                         kind="perse"),
                            neighbors=sim.Neighbors(backend="bvh"))
    # A backend without radii is refused where the list is built.
    spheres = dataclasses.replace(s, neighbors=sim.Neighbors(
        backend="brute" if not accuracy.warp_here() else "spheres"))
    if accuracy.warp_here():
        with pytest.raises(SceneError, match="neighbors.backend: 'spheres' "
                           "has no per-particle radii"):
            sim.compile_scene(spheres)
    # jaxrt.pairs searches one cutoff: the pairs knob refuses radii.
    with pytest.raises(SceneError, match=r"effects\[0\]\.radii: jaxrt.pairs "
                       "searches one cutoff"):
        accuracy.lj_as(accuracy.LJPairs)(s)


def test_radii_knob_one_grid_misses_no_pair(x64):
    """The cell list as one grid of the largest radius on the polydisperse
    scene finds every pair within max(r_i, r_j) (float64 brute force after
    every chunk) and gives the reference's forces; the check counts the
    pairs of that rule, fewer than a plain cut at the largest radius (the
    sweep runs the other values: the slow test below)."""
    n = 216
    base = accuracy.base_scene("lj-fluid", accuracy.Plan(n=n))
    knob = next(k for k in accuracy.KNOBS if k.name == "radii")
    s = knob.base_for(base, accuracy.Plan(n=n))
    assert s.name == "lj-polydisperse" and s.dtype == "float32"
    assert s.particles.n == n and s.effect("lj").radii is not None
    rng = np.random.default_rng(2)
    side = s.box.size[0]
    s = accuracy.with_state(s, np.mod(s.particles.positions + rng.normal(
        0, 0.05, (n, 3)), side), s.particles.velocities)
    ref = accuracy.reference_forces(s)
    assert set(ref) == {"scene"}  # no plain LJ to compare stretched pairs to
    plan = accuracy.Plan(n=n, equilibrate=0, steps=20, chunk=10)
    sc = _knob_value("radii", "one grid").apply(s)
    assert accuracy.describe(sc)["backend"] == "cell[radius_classes=1]"
    m = accuracy.measure(sc, plan, ref_forces=ref)
    assert m.row["pairs_missed"] == 0 and m.row["pairs_checked"] > 0
    assert m.row["force_rms_rel"] < 1e-5  # float32 against float64
    plain = sum(len(accuracy.brute_pairs(f, s.cutoff, s.box.size,
                                         s.box.periodic)) for f in m.frames)
    assert m.row["pairs_checked"] < plain


@pytest.mark.slow
def test_radii_sweep_rows_have_their_own_reference(tmp_path):
    plan = accuracy.Plan(n=216, equilibrate=20, steps=40, chunk=20)
    rows = accuracy.run("lj-fluid", out=tmp_path, quick=True, plan=plan,
                        knob_names=["radii"], log=lambda s: None)
    assert rows[0]["knob"] == "reference"
    assert rows[0]["value"] == "float64, lj-polydisperse"
    mine = [r for r in rows if r["knob"] == "radii"]
    knob = next(k for k in accuracy.KNOBS if k.name == "radii")
    assert [r["value"] for r in mine] == [v.label for v in
                                          knob.selected(True, 3)]
    for r in mine:
        assert r["status"] == "ok", r
        assert r["cutoff"] == 6.0  # the largest radius, list or not
        assert r["force_rms_rel"] < 1e-4
        assert math.isfinite(r["drift_per_particle_1e4"])
        if not r["backend"].startswith("fused"):
            assert r["pairs_missed"] == 0 and r["pairs_checked"] > 0
    md = (tmp_path / "summary.md").read_text()
    assert "`radii` on its own scene" in md
    assert (tmp_path / "radii.png").stat().st_size > 1000


# ---------------------------------------------------------------------------
# End to end


def test_tiny_sweep_writes_csv_png_and_summary(tmp_path):
    # Equilibrated a little: on the initial lattice every force is ~0.
    plan = accuracy.Plan(n=216, equilibrate=50, steps=100, chunk=50)
    x64 = jax.config.jax_enable_x64
    rows = accuracy.run("lj-fluid", out=tmp_path, quick=True, plan=plan,
                        knob_names=["dtype"], log=lambda s: None)
    # The float64 reference switched x64 on for the run only.
    assert jax.config.jax_enable_x64 == x64
    with open(tmp_path / "accuracy.csv", newline="") as f:
        read = list(csv.DictReader(f))
    assert len(read) == len(rows) == 3
    for col in accuracy.COLUMNS + ("device", "git_sha", "date"):
        assert col in read[0], col
    by = {(r["knob"], r["value"]): r for r in read}
    ref, f32, f64 = (by[("reference", "float64")], by[("dtype", "float32")],
                     by[("dtype", "float64")])
    assert {r["status"] for r in read} == {"ok"}
    # float64 is the reference's own setting: the same run, no error.
    assert float(f64["force_rms_rel"]) < 1e-12
    assert float(f64["position_rms"]) == 0 and float(f64["rdf_l2"]) == 0
    assert 1e-9 < float(f32["force_rms_rel"]) < 1e-4
    assert f32["dtype"] == "float32" and ref["dtype"] == "float64"
    for r in read:
        assert float(r["time_per_step_ms"]) > 0
        assert int(r["pairs_missed"]) == 0 and int(r["pairs_checked"]) > 0
        assert math.isfinite(float(r["drift_per_particle_1e4"]))
        assert float(r["drift_se"]) > 0 and float(r["time_per_tau_ms"]) > 0
        assert r["auto_backend"] == accuracy.auto_backend_for(
            accuracy.base_scene("lj-fluid", plan))
    assert (tmp_path / "dtype.png").stat().st_size > 1000
    md = (tmp_path / "summary.md").read_text()
    assert "the cheapest setting is" in md
    assert f"chose **{ref['auto_backend']}**" in md
    assert "| dtype | float32 |" in md


@pytest.mark.slow
def test_budget_spent_skips_the_rest_and_keeps_the_rows(tmp_path):
    plan = accuracy.Plan(n=216, equilibrate=0, steps=100, chunk=50)
    rows = accuracy.run("lj-fluid", out=tmp_path, quick=True, plan=plan,
                        knob_names=["dtype", "format"], budget=0.0,
                        log=lambda s: None)
    assert rows[0]["knob"] == "reference" and rows[0]["status"] == "ok"
    assert {r["status"] for r in rows[1:]} == {"skipped"}
    assert (tmp_path / "summary.md").exists()


@pytest.mark.slow
def test_dam_break_sweep_has_no_drift_and_no_rdf(tmp_path):
    plan = accuracy.Plan(dx=0.1, equilibrate=20, steps=100, chunk=50)
    rows = accuracy.run("dam-break", out=tmp_path, quick=True, plan=plan,
                        knob_names=["dtype"], log=lambda s: None)
    ok = [r for r in rows if r["status"] == "ok"]
    assert len(ok) == 3
    for r in ok:
        assert "drift_per_particle_1e4" not in r and "rdf_l2" not in r
        assert r["pairs_missed"] == 0
    assert dataclasses.is_dataclass(accuracy.QUICK)


def test_cli_accuracy_refuses_an_unknown_knob(tmp_path, capsys):
    from jaxrt.tools import cli
    assert cli.main(["accuracy", "--quick", "--knobs", "dtype,nope",
                     "--out", str(tmp_path)]) == 2
    assert "unknown knobs ['nope']" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.main(["accuracy", "no-such-scene"])
