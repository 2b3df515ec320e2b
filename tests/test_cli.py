"""The jaxrt command, driven through main()."""
import pytest

from jaxrt import cli


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
    from test_scene import GOOD
    p = tmp_path / "s.toml"
    p.write_text(GOOD.replace("[integrator]", "[neighbors]\nskin = 0.2\n\n"
                              "[integrator]"))
    assert cli.main(["run", str(p), "--steps", "10", "--out",
                     str(tmp_path / "o")]) == 0
    assert (tmp_path / "o" / "energies.png").exists()
    xyz = (tmp_path / "o" / "trajectory.xyz").read_text().splitlines()
    assert xyz[0] == "3" and "Lattice=" in xyz[1]


def test_bad_scene_exit_code(tmp_path, capsys):
    p = tmp_path / "bad.toml"
    p.write_text("[box]\nsize = 1\n")
    assert cli.main(["run", str(p), "--steps", "2"]) == 2
    assert "particles" in capsys.readouterr().err
    assert cli.main(["run", "no-such-scene"]) == 2
