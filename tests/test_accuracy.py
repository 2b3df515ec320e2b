"""jaxrt.accuracy: the error measures against hand-computed cases, the knob
table, the auto rule, and one tiny end-to-end sweep writing CSV, PNG and
Markdown."""
from __future__ import annotations

import csv
import dataclasses
import math

import jax
import numpy as np
import pytest

from jaxrt import accuracy


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
    from jaxrt.cli import _pair_codes
    displacement, _ = space.periodic(4.0)
    fn = jaxrt.neighbor_list(displacement, 4.0, 1.1, backend="brute",
                             format=jaxrt.OrderedSparse)
    nbrs = fn.allocate(jnp.asarray(r, jnp.float32))
    assert accuracy.pairs_missed(_pair_codes(nbrs, 64), full) == 64 * 12 // 2


def test_exact_pairs_by_kdtree_equal_the_brute_force():
    rng = np.random.default_rng(0)
    r = rng.random((4200, 3)) * 12.0
    side = np.full(3, 12.0)
    a = accuracy.exact_pairs(r, 1.0, side, (True,) * 3)  # the cKDTree path
    b = accuracy.brute_pairs(r, 1.0, side, (True,) * 3)
    assert len(a) > 5_000 and np.array_equal(a, b)
    # The RDF's pair distances, both ways.
    kd = np.sort(accuracy._pair_distances(r, side, 1.5, kd=True))
    brute = np.sort(accuracy._pair_distances(r, side, 1.5, kd=False))
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
            for v in knob.selected(quick=False, dim=dim):
                try:
                    v.apply(base)
                except Exception as e:  # only box-too-small refusals
                    assert "half the periodic box" in str(e), (knob.name, e)
    names = {k.name for k in accuracy.knobs("lj")}
    assert {"dtype", "truncation", "skin", "dt", "format", "backend",
            "pairs", "delaunay-flips"} <= names
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
    pallas = accuracy._pallas_here()
    assert ("cell-kernel" in in3) == pallas
    free = next(k for k in accuracy.KNOBS if k.name == "list-free")
    labels = {v.label for v in free.selected(quick=True, dim=3)}
    assert {"list", "fused"} <= labels
    if not pallas:  # a CPU: no Cell kernel values, and no crash probing
        assert not labels & {"fused-xla", "fused-pallas"}
    from jaxrt.backends import Cell
    assert isinstance(accuracy._fused_takes(Cell(kernel="xla")), bool)


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
    assert accuracy._key(sc, None) == accuracy._key(same, None)
    few = _knob_value("delaunay-flips", "rounds 1, splits 1").apply(base)
    assert few.neighbors.backend.max_flip_rounds == 1
    _, _, nbrs = _tiny_step(few)
    assert accuracy._triangulation_rebuilds(nbrs) >= 0
    assert accuracy._describe(few)["backend"] == "delaunay"


def test_pairs_value_runs_lj_on_jaxrt_pairs_with_the_lists_forces(x64):
    from jaxrt import sim
    n = 216
    base = dataclasses.replace(accuracy.base_scene("lj-fluid",
                                                   accuracy.Plan(n=n)),
                               dtype="float64")
    sc = _knob_value("pairs", "jaxrt.pairs").apply(base)
    assert not sc.pair_effects and sc.effects[0].kind == "lj_pairs"
    assert accuracy._describe(sc)["backend"] == "jaxrt.pairs (no list)"
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
    cutoff, codes = accuracy._own_search(sc)
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
    assert accuracy._describe(fused)["backend"] == "fused cell (no list)"
    for k in ("xla", "pallas"):
        sc = _knob_value("list-free", f"fused-{k}").apply(base)
        assert sc.effects[0].backend == Cell(kernel=k)
        assert accuracy._describe(sc)["backend"] == f"fused cell[{k}] (no list)"
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
    from jaxrt.neighbors import _auto_backend, choose_backend
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
    from jaxrt import cli
    assert cli.main(["accuracy", "--quick", "--knobs", "dtype,nope",
                     "--out", str(tmp_path)]) == 2
    assert "unknown knobs ['nope']" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.main(["accuracy", "no-such-scene"])
