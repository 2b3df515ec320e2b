"""The jaxrt command, driven through main()."""
import numpy as np
import pytest

from jaxrt.tools import cli


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
