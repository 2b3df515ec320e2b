"""The jaxrt command, driven through main()."""
import numpy as np
import pytest

from jaxrt.tools import cli, outputs


def test_demo_small(tmp_path, capsys):
    assert cli.main(["demo", "--steps", "10", "--n", "256",
                     "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "lists equal to jax-md's" in out and "speed-up" in out
    for name in ("energies.png", "final.png", "snapshots.npz",
                 "trajectory.xyz"):
        assert (tmp_path / name).stat().st_size > 0


def test_scenes_lists_builtins(capsys):
    assert cli.main(["scenes"]) == 0
    out = capsys.readouterr().out
    for name in ("lj-fluid", "dam-break", "sphere-surface"):
        assert name in out


def test_run_toml(tmp_path, capsys):
    from scenes import GOOD
    p = tmp_path / "s.toml"
    p.write_text(GOOD.replace("[integrator]", "[neighbors]\nskin = 0.2\n\n"
                              "[integrator]"))
    assert cli.main(["run", str(p), "--steps", "10", "--out",
                     str(tmp_path / "o")]) == 0
    assert (tmp_path / "o" / "energies.png").exists()
    xyz = (tmp_path / "o" / "trajectory.xyz").read_text().splitlines()
    assert xyz[0] == "3" and "Lattice=" in xyz[1]


MIXED = """
[box]
size = [8.0, 8.0, 8.0]
boundary = ["periodic", "wall", "free"]

[particles]
positions = [[0.5, 4.0, 4.0], [7.45, 4.0, 4.0], [4.0, 2.0, 1.0]]
velocities = [[-0.3, 0.2, -0.1], [0.1, 0.0, 0.3], [0.05, -0.05, 0.01]]
species = [0, 1, 2]

[[effects]]
kind = "lj"
r_cutoff = 2.5

[integrator]
dt = 0.01
"""


@pytest.mark.parametrize("text", [MIXED, "2d"], ids=["mixed-3d", "2d"])
def test_trajectory_reads_in_ase(tmp_path, capsys, text):
    """trajectory.xyz used to name species X0, X1 (ASE: KeyError 'X0'),
    write the box with 6 digits and no velocities. Every frame must read
    back in ASE as what the run had: symbols by the stated map, positions
    and velocities bit for bit (float32 written with 9 digits), cell, pbc.
    """
    import ase.io as ase_io  # a test dependency (pyproject: test extra)
    from scenes import GOOD
    from jaxrt import sim as S
    text = GOOD if text == "2d" else text
    p = tmp_path / "s.toml"
    p.write_text(text)
    assert cli.main(["run", str(p), "--steps", "6", "--chunk", "2",
                     "--out", str(tmp_path / "o")]) == 0
    frames = ase_io.read(tmp_path / "o" / "trajectory.xyz", index=":")
    snap = np.load(tmp_path / "o" / "snapshots.npz")
    assert len(frames) == 4 and list(snap["steps"]) == [0, 2, 4, 6]
    sc = S.load(p)
    dim, n = sc.particles.dim, sc.particles.n
    species = (np.zeros(n, int) if sc.particles.species is None
               else sc.particles.species)
    names = ["Ar", "Ne", "Kr"]
    for k, atoms in enumerate(frames):
        assert atoms.get_chemical_symbols() == [names[s] for s in species]
        assert atoms.info["step"] == 2 * k
        assert atoms.info["species_map"].startswith("0:Ar")
        pos, vel = atoms.positions, atoms.arrays["velocities"]
        np.testing.assert_array_equal(pos[:, :dim].astype(np.float32),
                                      snap["positions"][k])
        np.testing.assert_array_equal(vel[:, :dim].astype(np.float32),
                                      snap["velocities"][k])
        assert not pos[:, dim:].any() and not vel[:, dim:].any()
        cell = np.zeros((3, 3))
        cell[:dim, :dim] = np.diag(sc.box.size)
        np.testing.assert_array_equal(atoms.cell.array, cell)
        assert list(atoms.pbc) == [b == "periodic" for b in
                                   sc.box.boundary] + [False] * (3 - dim)
    # Frame 0 is the scene's input exactly; the last is the final state.
    np.testing.assert_array_equal(
        snap["positions"][0], sc.particles.positions.astype(np.float32))
    np.testing.assert_array_equal(
        snap["velocities"][0], sc.particles.velocities.astype(np.float32))
    np.testing.assert_array_equal(snap["velocities"][-1], snap["velocity"])
    assert np.any(snap["positions"][-1] != snap["positions"][0])  # it moved


def test_bad_scene_exit_code(tmp_path, capsys):
    p = tmp_path / "bad.toml"
    p.write_text("[box]\nsize = 1\n")
    assert cli.main(["run", str(p), "--steps", "2"]) == 2
    assert "particles" in capsys.readouterr().err
    assert cli.main(["run", "no-such-scene"]) == 2


def test_polydisperse_run_checks_its_list_with_radii(tmp_path, capsys):
    """The built-in radii scene's list holds pairs up to max(r_i, r_j) + skin
    (6.3 for its 1 % of large particles, 2.8 for the rest): the brute-force
    check must cut each pair there. With the scene's single cutoff (6.0) it
    would count every small pair out to 6.3 and report a mismatch."""
    assert cli.main(["run", "lj-polydisperse", "--steps", "20", "--chunk",
                     "10", "--check-brute", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "lists equal to brute force      yes" in out


# ---------------------------------------------------------------------------
# Before JAX: help and scene checks answer at once.

HEAVY = ("jax", "jax_md", "warp")


def _python(*args: str):
    """Run ``python args`` on the jaxrt these tests import."""
    import os
    import pathlib
    import subprocess
    import sys

    import jaxrt
    root = pathlib.Path(jaxrt.__file__).resolve().parents[1]
    env = dict(os.environ, PYTHONPATH=str(root))
    return subprocess.run([sys.executable, *args], env=env,
                          capture_output=True, text=True, timeout=300)


def _imported(stderr: str) -> set[str]:
    """Top-level packages in ``python -X importtime``'s report."""
    names = set()
    for line in stderr.splitlines():
        if line.startswith("import time:") and "|" in line:
            names.add(line.rsplit("|", 1)[1].strip().split(".")[0])
    return names


@pytest.mark.parametrize("argv", [["--help"], ["run", "--help"],
                                  ["demo", "--help"], ["scenes"]])
def test_help_and_scene_list_need_no_jax(argv):
    p = _python("-X", "importtime", "-m", "jaxrt", *argv)
    assert p.returncode == 0, p.stderr[-2000:]
    imported = _imported(p.stderr)  # every module the command imported
    assert "jaxrt" in imported and not imported & set(HEAVY), imported
    if argv[0] == "run":  # the built-in scenes and a scene file's layout
        for text in ("lj-fluid", "dam-break", "[[effects]]", "[integrator]",
                     "jaxrt scenes", "pydoc jaxrt.sim.toml",
                     "default: jaxrt-out", "1000 for a TOML file"):
            assert text in p.stdout
    if argv[0] == "scenes":
        assert "lj-polydisperse" in p.stdout


@pytest.mark.parametrize("typo, line, message", [
    (("r_cutoff = 2.5", "r_cutof = 2.5"), 13, "effects[0].r_cutof"),
    (("dt = 0.005", "dtt = 0.005"), 16, "integrator.dtt"),
    (("[box]", "[bx]"), 3, "unknown key 'bx'"),
    (("kind = \"lj\"", "kind = \"lj2\""), 12, "unknown effect 'lj2'"),
    (("size = [10.0", "size = [10.0,,"), 4, "not valid TOML"),
], ids=["effect-key", "integrator-key", "table", "effect-kind", "syntax"])
def test_scene_file_typo_is_rejected_before_jax(tmp_path, typo, line,
                                                message):
    """A typo in a scene file is named with its line without JAX, jax-md
    or Warp imported (they took the command a minute to load first)."""
    path = tmp_path / "typo.toml"
    assert typo[0] in cli.EXAMPLE_SCENE
    path.write_text(cli.EXAMPLE_SCENE.replace(typo[0], typo[1], 1))
    p = _python("-c", "import sys; from jaxrt.tools.cli import main; "
                "code = main(['run', sys.argv[1]]); "
                f"print(code, [m for m in {HEAVY!r} if m in sys.modules])",
                str(path))
    assert p.stdout.split() == ["2", "[]"], p.stdout + p.stderr[-2000:]
    assert "jaxrt: bad scene: " in p.stderr and message in p.stderr
    assert f"line {line}" in p.stderr


def test_bad_arguments_are_rejected_before_jax(tmp_path):
    for argv, message in ((["run", "lj-fluid", "--steps", "0"], "--steps"),
                          (["run", "no-such-scene"], "jaxrt run --help"),
                          (["run", "dam-break", "--n", "10"], "--n"),
                          (["demo", "--chunk", "-1"], "--chunk")):
        p = _python("-c", "import sys; from jaxrt.tools.cli import main; "
                    "code = main(sys.argv[1:]); "
                    f"print(code, [m for m in {HEAVY!r} if m in sys.modules])",
                    *argv)
        assert p.stdout.split() == ["2", "[]"], p.stdout + p.stderr[-2000:]
        assert message in p.stderr


def test_example_scene_of_the_help_runs(tmp_path):
    from jaxrt import sim
    scene = sim.from_toml(cli.EXAMPLE_SCENE)
    assert scene.particles.n == 2 and scene.effects[0].kind == "lj"
    path = tmp_path / "two.toml"
    path.write_text(cli.EXAMPLE_SCENE)
    assert cli.main(["run", str(path), "--steps", "4", "--out",
                     str(tmp_path / "o")]) == 0


def test_lazy_package_keeps_every_public_name():
    import jaxrt
    import jaxrt.pairs  # the submodule: must not replace the function
    import jaxrt.sim.builtin
    from jaxrt import sim
    assert set(jaxrt.__all__) <= set(dir(jaxrt))
    assert set(sim.__all__) <= set(dir(sim))
    for name in jaxrt.__all__:
        assert getattr(jaxrt, name) is not None
    for name in sim.__all__:
        assert getattr(sim, name) is not None
    assert callable(jaxrt.pairs) and jaxrt.pairs.__module__ == "jaxrt.pairs.search"
    assert callable(sim.builtin) and sim.builtin.__module__.endswith("builtin")
    assert jaxrt.neighbor_list.__module__ == "jaxrt.lists.neighbors"
    assert jaxrt.ase_neighbor_list.__module__ == "jaxrt.pairs.ase"
    assert "cell" in jaxrt.available_backends()
    assert jaxrt.energy.lennard_jones_fused is not None  # a submodule
    with pytest.raises(AttributeError, match="no_such_name"):
        jaxrt.no_such_name


# ---------------------------------------------------------------------------
# Plots: labelled, with units.


@pytest.mark.parametrize("name, length, energy, speed", [
    ("lj-fluid", "σ", "ε", "σ/τ"), ("dam-break", "m", "J/m", "m/s"),
    ("boids", "scene units", "scene units", "scene units")])
def test_plots_have_labelled_axes_with_units(name, length, energy, speed):
    from jaxrt import sim
    kw = {"dx": 0.2} if name == "dam-break" else {"n": 256}
    scene = sim.builtin(name, **kw)
    n, dim = scene.particles.n, scene.particles.dim
    rng = np.random.default_rng(0)
    ke, u = rng.uniform(1, 2, 10), -rng.uniform(1, 2, 10)
    fig = outputs.energy_figure(scene, ke, u)
    ax = fig.axes[0]
    assert ax.get_xlabel().startswith("time t (") and energy in ax.get_ylabel()
    assert scene.name in ax.get_title()
    assert [t.get_text() for t in ax.get_legend().get_texts()] == [
        "kinetic", "potential", "total"]
    fig = outputs.final_figure(scene, scene.particles.positions,
                           rng.normal(size=(n, dim)), 40)
    ax, bar = fig.axes
    assert ax.get_xlabel() == f"x ({length})"
    assert ax.get_ylabel() == f"y ({length})"
    assert bar.get_ylabel() == f"speed |v| ({speed})"
    assert "step 40" in ax.get_title() and scene.name in ax.get_title()
    assert ax.get_xlim() == (0.0, scene.box.size[0])
