"""Scenes: only the asked-for effects are compiled; conservation; TOML."""
import dataclasses
import warnings

import jax
import numpy as np
import pytest

import jaxrt
from jaxrt import scene as S

warnings.filterwarnings("ignore", message="Explicitly requested dtype")


def _jaxpr(compiled) -> str:
    state, nbrs = compiled.init()
    return str(jax.make_jaxpr(compiled.step)(state, nbrs))


def _gas(effects, boundary=("periodic",) * 3, n=64, side=6.0, skin=0.2,
         radius=None, integrator=None):
    rng = np.random.default_rng(1)
    pos = (np.stack(np.meshgrid(*[np.arange(4)] * 3, indexing="ij"), -1)
           .reshape(-1, 3) + 0.5) * side / 4 + 0.05 * rng.standard_normal(
               (n, 3))
    return S.Scene(
        particles=S.make_particles(positions=pos, temperature=0.5,
                                   radius=radius),
        box=S.Box((side,) * 3, boundary), effects=tuple(effects),
        integrator=integrator or S.Integrator(dt=0.002),
        neighbors=S.Neighbors(skin=skin, capacity_multiplier=2.0))


LJ = S.LJ(r_cutoff=2.5, r_onset=2.0)


class Counting:
    """A neighbor_list factory that counts how often it is asked for."""

    def __init__(self):
        self.calls = 0

    def __call__(self, *a, **kw):
        self.calls += 1
        return jaxrt.neighbor_list(*a, **kw)


def test_lj_only_has_no_sph():
    text = _jaxpr(S.compile_scene(_gas([LJ])))
    assert "name=lj" in text
    assert "random_bits" not in text  # NVE: no thermostat noise
    assert "sph_density" not in text and "sph_forces" not in text


def test_sph_scene_has_sph_and_conserves_momentum():
    sc = _gas([S.SPHDensity(h=0.6), S.SPHPressure(rho0=0.2, c0=1.0),
               S.SPHViscosity(alpha=0.1)])
    c = S.compile_scene(sc)
    text = _jaxpr(c)
    assert "name=sph_density" in text and "name=sph_forces" in text
    assert "name=lj" not in text
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
    c = S.compile_scene(sc, neighbor_list_fn=count)
    assert count.calls == 1 and sc.cutoff == 2.0  # cubic spline: 2h


def test_equal_radii_no_radius_handling():
    eq = S.compile_scene(_gas([LJ], radius=0.5))
    assert any("equal radii" in line for line in eq.plan)
    rng = np.random.default_rng(0)
    neq = S.compile_scene(_gas([LJ], radius=0.45 + 0.1 * rng.random(64)))
    assert any("per-particle radii" in line for line in neq.plan)


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
    sc = S.dam_break(dx=0.1)
    _, state, stats = _run(sc, 20)
    x = np.asarray(state.position)
    assert sc.particles.masses.sum() == S.dam_break(dx=0.1).particles.masses.sum()
    assert (x > -0.05).all() and (x[:, 0] < 4.05).all()


def test_builtin_sphere_surface_momentum():
    sc = S.sphere_surface(alpha=4, p=2)
    _, state, stats = _run(sc, 20)
    mom = np.concatenate(stats.momentum)
    assert np.abs(mom - mom[0]).max() < 1e-5
    assert stats.rebuilds >= 0


def test_langevin_runs_and_is_random():
    sc = _gas([LJ], integrator=S.Integrator(dt=0.002, kind="langevin",
                                            kT=1.0, gamma=1.0))
    c = S.compile_scene(sc)
    assert "random_bits" in _jaxpr(c)



def test_mixed_boundaries_wrap_periodic_axis_only():
    """``["periodic", "wall", "free"]`` (the module docstring's example)
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
    from jaxrt.cli import _pair_codes  # i * n + j, i < j, any layout
    assert list(_pair_codes(c.init()[1], 6)) == [0 * 6 + 1]
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
    text = sc.to_toml()
    back = S.Scene.from_toml(text)
    assert back.to_toml() == text
    np.testing.assert_array_equal(back.particles.positions,
                                  sc.particles.positions)
    assert back.effects == sc.effects and back.box == sc.box


GOOD = """
[box]
size = [6.0, 6.0]
boundary = "periodic"

[particles]
positions = [[1.0, 1.0], [2.0, 1.5], [3.0, 4.0]]

[[effects]]
kind = "lj"
r_cutoff = 2.5

[integrator]
dt = 0.001
"""


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
        S.Scene.from_toml(text)
    assert field in str(e.value)
    if line is not None:
        assert f"line {line}" in str(e.value)
