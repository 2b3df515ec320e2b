"""Scenes: only the asked-for effects are compiled; conservation; TOML;
an effect defined outside the package, in one class."""
import dataclasses
import math
import warnings
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrt
from jaxrt import sim as S
from scenes import GOOD

warnings.filterwarnings("ignore", message="Explicitly requested dtype")


def _jaxpr(compiled) -> str:
    state, nbrs = compiled.init()
    return str(jax.make_jaxpr(compiled.step)(state, nbrs))


def _gas(effects, boundary=("periodic",) * 3, n=64, side=6.0, skin=0.2,
         radius=None):
    rng = np.random.default_rng(1)
    pos = (np.stack(np.meshgrid(*[np.arange(4)] * 3, indexing="ij"), -1)
           .reshape(-1, 3) + 0.5) * side / 4 + 0.05 * rng.standard_normal(
               (n, 3))
    return S.Scene(
        particles=S.make_particles(positions=pos, temperature=0.5,
                                   radius=radius),
        box=S.Box((side,) * 3, boundary), effects=tuple(effects),
        integrator=S.Integrator(dt=0.002),
        neighbors=S.Neighbors(skin=skin, capacity_multiplier=2.0))


LJ = S.LJ(r_cutoff=2.5, r_onset=2.0)


class Counting:
    """A neighbor_list factory that counts how often it is asked for and
    records the cutoffs it is asked for."""

    def __init__(self):
        self.calls = 0
        self.cutoffs = []

    def __call__(self, *a, **kw):
        self.calls += 1
        self.cutoffs.append(a[2])  # (displacement, box, r_cutoff, skin)
        return jaxrt.neighbor_list(*a, **kw)


def test_lj_only_has_no_sph():
    text = _jaxpr(S.compile_scene(_gas([LJ])))
    assert "name=lj" in text
    assert "random_bits" not in text  # NVE: no thermostat noise
    assert "sph_density" not in text and "sph_pressure" not in text


def test_sph_scene_has_sph_and_conserves_momentum():
    sc = _gas([S.SPHDensity(h=0.6), S.SPHPressure(rho0=0.2, c0=1.0),
               S.SPHViscosity(alpha=0.1)])
    c = S.compile_scene(sc)
    text = _jaxpr(c)
    assert "name=sph_density" in text and "name=sph_pressure" in text
    assert "name=sph_viscosity" in text and "name=lj" not in text
    # Periodic, no walls or gravity: momentum is conserved.
    _, state, stats = _run(sc, 10)
    mom = np.concatenate(stats.momentum)
    assert np.abs(mom - mom[0]).max() < 1e-4
    assert state.rho.shape == (64,)


def test_gravity_only_does_no_neighbour_search():
    count = Counting()
    sc = _gas([S.Gravity(g=(0.0, 0.0, -1.0))])
    c = S.compile_scene(sc, neighbor_list_fn=count)
    assert count.calls == 0 and c.neighbor_fn is None
    text = _jaxpr(c)
    # The cell list sorts; a neighbour search would show up as a sort.
    assert " sort[" not in text and "sort " not in text.replace("sorted", "")
    # Positive control: an LJ scene does search.
    count = Counting()
    c = S.compile_scene(_gas([LJ, S.Gravity(g=(0.0, 0.0, -1.0))]),
                        neighbor_list_fn=count)
    assert count.calls == 1
    assert "sort" in _jaxpr(c)


def test_wall_box_does_no_periodic_image_work():
    walls = ("wall",) * 3
    sc = _gas([LJ, S.Walls(stiffness=100.0)], boundary=walls, side=8.0)
    text = _jaxpr(S.compile_scene(sc))
    assert "round" not in text and " rem " not in text
    # Positive control: the periodic box wraps (round in the minimum image).
    assert "round" in _jaxpr(S.compile_scene(_gas([LJ])))


def test_one_list_at_largest_cutoff():
    count = Counting()
    sc = _gas([S.LJ(r_cutoff=1.5), S.SPHDensity(h=1.0)], side=8.0)
    S.compile_scene(sc, neighbor_list_fn=count)
    assert count.calls == 1 and count.cutoffs == [2.0]  # cubic spline: 2h


def _init_accel(sc) -> np.ndarray:
    return np.asarray(S.compile_scene(sc).init()[0].accel)


def test_equal_radii_no_radius_handling():
    """Equal radii r act as the scalar sigma = 2r; radii that differ as
    sigma_ij = r_i + r_j, here checked against the same sigmas given as a
    species matrix (one species per particle)."""
    eq = S.compile_scene(_gas([LJ], radius=0.55))
    assert any("equal radii" in line for line in eq.plan)
    np.testing.assert_array_equal(
        np.asarray(eq.init()[0].accel),
        _init_accel(_gas([S.LJ(r_cutoff=2.5, r_onset=2.0, sigma=1.1)])))
    rng = np.random.default_rng(0)
    r = 0.45 + 0.1 * rng.random(64)
    neq = S.compile_scene(_gas([LJ], radius=r))
    assert any("per-particle radii" in line for line in neq.plan)
    base = _gas([LJ])
    matrix = dataclasses.replace(
        base, particles=dataclasses.replace(base.particles,
                                            species=np.arange(64)),
        effects=(S.LJ(r_cutoff=2.5, r_onset=2.0,
                      sigma=(r[:, None] + r[None, :]).tolist()),))
    a = np.asarray(neq.init()[0].accel)
    assert np.abs(a).max() > 1  # the gas is dense enough to feel LJ
    np.testing.assert_allclose(a, _init_accel(matrix), rtol=1e-4, atol=1e-4)


def _run(sc, steps):
    c = S.compile_scene(sc)
    state, nbrs = c.init()
    stats = S.RunStats()
    state, nbrs = S.run_chunk(c, state, nbrs, steps=steps, stats=stats)
    assert np.isfinite(np.asarray(state.position)).all()
    return c, state, stats


def test_builtin_lj_conserves_energy():
    sc = S.lj_fluid(n=256, dt=0.002)
    _, _, stats = _run(sc, 20)
    e = np.concatenate(stats.kinetic) + np.concatenate(stats.potential)
    assert abs(e[-1] - e[0]) / sc.particles.n < 2e-3


def test_builtin_dam_break_mass_and_walls():
    """The 1 x 2 m column of water (1000 kg/m^2 in 2D) at dx = 0.1 is 10 x 20
    particles of 10 kg: 2000 kg, and the summation density inside the
    column (beyond the kernel support 2h = 0.26 from its edges) is rho0."""
    sc = S.dam_break(dx=0.1)
    assert sc.particles.n == 200
    np.testing.assert_allclose(sc.particles.masses, 10.0)
    assert sc.particles.masses.sum() == pytest.approx(1000.0 * 1.0 * 2.0)
    c = S.compile_scene(sc)
    state, nbrs = c.init()
    x0 = sc.particles.positions
    inner = ((x0 > 0.26) & (x0 < np.array([1.0, 2.0]) - 0.26)).all(1)
    assert inner.sum() == 56
    np.testing.assert_allclose(np.asarray(state.rho)[inner], 1000.0,
                               rtol=1e-3)
    state, nbrs = S.run_chunk(c, state, nbrs, steps=20)
    x = np.asarray(state.position)
    assert (x > -0.05).all() and (x[:, 0] < 4.05).all()


def test_builtin_sphere_surface_momentum():
    sc = S.sphere_surface(alpha=4, p=2)
    _, state, stats = _run(sc, 20)
    mom = np.concatenate(stats.momentum)
    assert np.abs(mom - mom[0]).max() < 1e-5


@pytest.mark.parametrize("skin, rebuilds", [(0.25, 3), (0.0, 50)])
def test_rebuild_count(skin, rebuilds):
    """One particle moves at speed 1 (dt = 0.01), the other rests 10 away
    (no force). The list is rebuilt when a particle moved more than skin/2
    since the last build: with skin 0.25 at steps 13, 26 and 39 of 50
    (0.13 > 0.125, 0.12 is not); with skin 0 at every step. Two chunks of
    25: the count carries across chunks."""
    sc = S.Scene(
        particles=S.make_particles(positions=[[5.0, 10, 10], [15.0, 10, 10]],
                                   velocities=[[1.0, 0, 0], [0, 0, 0]]),
        box=S.Box((20.0,) * 3, ("free",) * 3), effects=(LJ,),
        integrator=S.Integrator(dt=0.01), neighbors=S.Neighbors(skin=skin))
    c = S.compile_scene(sc)
    state, nbrs = c.init()
    stats = S.RunStats()
    for _ in range(2):
        state, nbrs = S.run_chunk(c, state, nbrs, steps=25, stats=stats)
    # float32: 50 additions of 0.01 to 5.0
    np.testing.assert_allclose(np.asarray(state.position)[0, 0], 5.5,
                               atol=1e-4)
    assert stats.rebuilds == rebuilds and stats.overflows == 0


def test_langevin_reaches_kT():
    """Langevin on an ideal gas (no forces, so each velocity component is
    exactly an Ornstein-Uhlenbeck process, c = exp(-gamma dt) per step),
    started at a tenth of kT, masses from 0.5 to 2.

    With d = N dim components and T = sum m v^2 / d:
    * after n steps, E[T] = c^2n T_0 + (1 - c^2n) kT and
      Var[T] = (4 c^2n (1 - c^2n) kT T_0 + 2 (1 - c^2n)^2 kT^2) / d
      (checked at c^2n = 1/e: this is the friction's rate);
    * over M steps of the second half (transient e^-2 gamma t < 1e-40),
      each m v^2 / kT is chi-square with 1 degree of freedom and
      autocorrelation c^2k, so the mean has standard deviation
      kT sqrt(2 (1 + c^2) / ((1 - c^2) d M)).
    Both are sums of d = 1536 independent terms (near normal): 4 standard
    deviations.
    """
    n, dim, kT, gamma, dt, steps = 512, 3, 1.0, 5.0, 0.01, 2000
    rng = np.random.default_rng(3)
    sc = S.Scene(
        particles=S.make_particles(positions=rng.random((n, dim)) * 10,
                                   masses=0.5 + 1.5 * rng.random(n),
                                   temperature=0.1 * kT, seed=4),
        box=S.Box((10.0,) * dim, ("free",) * dim), effects=(),
        integrator=S.Integrator(dt=dt, kind="langevin", kT=kT, gamma=gamma,
                                seed=5))
    c, _, stats = _run(sc, steps)
    # The positive control of test_lj_only_has_no_sph's "no random_bits".
    assert "random_bits" in _jaxpr(c)
    d = n * dim
    temp = 2 * np.concatenate(stats.kinetic).astype(np.float64) / d
    p = sc.particles
    t0 = float(np.sum(p.masses[:, None] * p.velocities ** 2)) / d
    assert abs(t0 - 0.1 * kT) < 0.02  # far from kT at the start
    c2 = math.exp(-2 * gamma * dt)
    k = round(1 / (2 * gamma * dt))  # c^2k = 1/e
    e = c2 ** k
    mean_k = e * t0 + (1 - e) * kT
    sd_k = math.sqrt((4 * e * (1 - e) * kT * t0 + 2 * (1 - e) ** 2 * kT ** 2)
                     / d)
    assert abs(temp[k - 1] - mean_k) < 4 * sd_k  # temp[i]: after step i + 1
    late = temp[steps // 2:]
    sd = kT * math.sqrt(2 * (1 + c2) / ((1 - c2) * d * late.size))
    assert abs(late.mean() - kT) < 4 * sd, (late.mean(), sd)


def test_mixed_boundaries_wrap_periodic_axis_only():
    """``["periodic", "wall", "free"]`` (the example of `jaxrt.sim.toml`)
    used to fail at init: the free axis made the scene pass no box at all,
    and the list needs the periodic side. A pair straddles each face; only
    the periodic one may interact (the others are 7.6 and 7.8 apart, 0.4
    and 0.2 if wrongly wrapped)."""
    L = 8.0
    pos = np.array([[0.5, 4.0, 4.0], [7.45, 4.0, 4.0],    # periodic x: 1.05
                    [4.0, 0.2, 4.0], [4.0, 7.8, 4.0],      # wall y
                    [4.0, 4.0, 0.1], [4.0, 4.0, 7.9]])     # free z
    sc = S.Scene(particles=S.make_particles(positions=pos),
                 box=S.Box((L,) * 3, ("periodic", "wall", "free")),
                 effects=(LJ,), integrator=S.Integrator(dt=0.001),
                 neighbors=S.Neighbors(skin=0.3))
    c, state, stats = _run(sc, 5)
    from jaxrt.layouts.codes import pair_codes  # i * n + j, i < j
    assert list(pair_codes(c.init()[1], 6)) == [0 * 6 + 1]
    # Same as every pair within reach under the scene's own displacement.
    d = np.asarray(jax.vmap(jax.vmap(c.displacement, (None, 0)), (0, None))(
        state.position, state.position))
    i, j = np.nonzero(np.triu(np.linalg.norm(d, axis=-1) < 2.8, 1))
    assert list(i * 6 + j) == [1]
    # The straddling pair repels across the face: 0 pushed to +x, 1 to -x;
    # the others feel nothing.
    a = np.asarray(state.accel)
    assert a[0, 0] > 1 and a[1, 0] < -1
    assert np.all(a[2:] == 0)
    u = np.concatenate(stats.potential)
    np.testing.assert_allclose(u[0], 4 * (1.05**-12 - 1.05**-6), rtol=0.02)


# --- TOML ------------------------------------------------------------------

def test_toml_round_trip():
    sc = _gas([LJ, S.Gravity(g=(0.0, 0.0, -1.0))])
    text = S.to_toml(sc)
    back = S.from_toml(text)
    assert S.to_toml(back) == text
    np.testing.assert_array_equal(back.particles.positions,
                                  sc.particles.positions)
    assert back.effects == sc.effects and back.box == sc.box


def test_good_toml_loads(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text(GOOD)
    sc = S.load(p)
    assert sc.particles.n == 3 and sc.box.periodic == (True, True)


@pytest.mark.parametrize("edit, field, line", [
    (('kind = "lj"', 'kind = "magnetism"'), "effects[0].kind", 10),
    (("r_cutoff = 2.5", "sigma = 1.0"), "effects[0].r_cutoff", None),
    (("dt = 0.001", "dt = -0.001"), "integrator.dt", 14),
    (("[1.0, 1.0], [2.0", "[1.0, 1.0], [9.0"), "particles.positions", 7),
    (("r_cutoff = 2.5", "r_cutoff = 3.5"), "effects[0].r_cutoff", 11),
    (("dt = 0.001", "dt = 0.001\ncolour = 1"), "integrator.colour", 15),
])
def test_bad_toml_names_field(edit, field, line):
    text = GOOD.replace(*edit)
    if field == "particles.positions":  # only outside a *walled* box
        text = text.replace('"periodic"', '"wall"')
    with pytest.raises(S.SceneError) as e:
        S.from_toml(text)
    assert field in str(e.value)
    if line is not None:
        assert f"line {line}" in str(e.value)


# --- An effect from outside the package: one class, one registration ------

@dataclasses.dataclass(frozen=True)
class Tether:
    """A spring from every particle to the origin: U = k/2 sum |R_i|^2."""
    k: float
    kind: ClassVar[str] = "tether"
    pairwise: ClassVar[bool] = False
    cutoff: ClassVar[float] = 0.0

    def validate(self, scene, where):
        if not self.k > 0:
            raise S.SceneError.at(f"{where}.k", "must be > 0.")

    def term(self, ctx):
        def tether(R, nbrs):
            return 0.5 * self.k * jnp.sum(R * R)
        return S.Term(energy=tether)


TETHERED = """
[box]
size = [10.0, 10.0]
boundary = "free"

[particles]
positions = [[1.0, 0.0], [0.0, -0.5], [0.3, 0.4]]
velocities = [[0.0, 0.5], [0.2, 0.0], [0.0, 0.0]]
masses = [1.0, 2.0, 4.0]

[[effects]]
kind = "tether"
k = 4.0

[integrator]
dt = 0.001
"""


def test_new_effect_from_toml_is_harmonic():
    """Three independent harmonic oscillators, omega = sqrt(k / m) = 2,
    sqrt 2, 1: x(t) = x0 cos wt + v0/w sin wt. Velocity Verlet's phase
    error is w t (w dt)^2 / 24 < 1e-6 here, so float32 rounding sets the
    tolerance."""
    effects = S.EFFECTS.extended(Tether)  # the package's registry untouched
    sc = S.from_toml(TETHERED, effects=effects)
    assert sc.effects == (Tether(k=4.0),)
    c, state, stats = _run(sc, 1000)
    assert c.neighbor_fn is None and c.conservative
    p = sc.particles
    w = np.sqrt(4.0 / p.masses)[:, None]
    t = 1000 * 0.001
    x = p.positions * np.cos(w * t) + p.velocities / w * np.sin(w * t)
    v = -p.positions * w * np.sin(w * t) + p.velocities * np.cos(w * t)
    np.testing.assert_allclose(np.asarray(state.position), x, atol=1e-5)
    np.testing.assert_allclose(np.asarray(state.velocity), v, atol=1e-5)
    u = np.concatenate(stats.potential)
    assert u[-1] == pytest.approx(0.5 * 4.0 * np.sum(x * x), rel=1e-5)
    # It writes and reads back like any effect.
    assert S.from_toml(S.to_toml(sc), effects=effects).effects == sc.effects


def test_registering_is_explicit_and_scoped():
    with pytest.raises(S.SceneError, match="unknown effect 'tether'"):
        S.from_toml(TETHERED)
    with S.registered(Tether):
        assert S.from_toml(TETHERED).effects == (Tether(k=4.0),)
        with pytest.raises(ValueError, match="already registered"):
            S.register(Tether)
        with pytest.raises(S.SceneError, match=r"effects\[0\]\.k.*line 13"):
            S.from_toml(TETHERED.replace("k = 4.0", "k = -4.0"))
    assert "tether" not in S.EFFECTS
    with pytest.raises(ValueError, match="already registered"):
        S.register(S.LJ)  # the package's own are there once
