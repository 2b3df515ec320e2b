"""`jaxrt.sim.domains`: the slab decomposition against the single-device run.

The multi-device cases need JAX's CPU backend split into 4 fake devices,
which must be asked for before JAX starts; the suite's processes have
started it, so those cases run in subprocesses with
``XLA_FLAGS=--xla_force_host_platform_device_count=4``:
`tests/domains_cases.py` for the library cases, ``python -m jaxrt run``
for the command line.
"""
import os
import pathlib
import subprocess
import sys

import numpy as np
import pytest

from jaxrt.sim.domains import Decomposition, DomainError, decompose

HERE = pathlib.Path(__file__).resolve().parent
REPO = HERE.parents[1]


def _env(devices: int = 4) -> dict:
    flags = os.environ.get("XLA_FLAGS", "")
    flags = " ".join(f for f in flags.split()
                     if "xla_force_host_platform_device_count" not in f)
    return dict(os.environ, PYTHONPATH=str(REPO), XLA_FLAGS=(
        flags + f" --xla_force_host_platform_device_count={devices}").strip())


def _run(args, timeout=900):
    p = subprocess.run([sys.executable, *args], cwd=REPO, env=_env(),
                       capture_output=True, text=True, timeout=timeout)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    return p.stdout


def _energy(d):
    from jaxrt.energy import lennard_jones_pair_neighbor_list
    return lennard_jones_pair_neighbor_list(d, r_onset=2.0, r_cutoff=2.5,
                                            per_particle=True)


def _library_cases(*cases):
    out = _run([str(HERE.parent / "domains_cases.py"), *cases])
    for case in cases:
        assert f"CASE {case} ok" in out, out


def test_library_cases():
    """Energies, forces and jax.grad equal the single device's (float64);
    the README's jitted user step; overflow flagged; a NaN position named as such."""
    _library_cases("forces", "overflow", "nonfinite")


@pytest.mark.slow
def test_library_cases_migration_emptied_domains_and_redone_chunks():
    """Migration across every face; emptied domains; a chunk redone after
    an overflow."""
    _library_cases("migration", "empty_domain", "redo")


def test_halo_wider_than_a_domain_is_refused():
    with pytest.raises(DomainError, match=r"halo wider than a domain: "
                       r"cutoff \+ skin = 2.8.*devices <= 3"):
        decompose(box_size=(8.55,) * 3, periodic=True, cutoff=2.5, skin=0.3,
                  energy=_energy, decomposition=Decomposition(devices=4))


def test_too_few_devices_is_refused():
    import jax
    n = len(jax.devices())
    with pytest.raises(DomainError, match=rf"needs {n + 1} JAX devices, "
                       rf"found {n}.*xla_force_host_platform_device_count"):
        decompose(box_size=(100.0,) * 3, periodic=True, cutoff=2.5,
                  skin=0.3, energy=_energy,
                  decomposition=Decomposition(devices=n + 1))


def test_bad_decomposition_is_refused():
    with pytest.raises(DomainError, match="devices must be an int >= 1"):
        Decomposition(devices=0)
    with pytest.raises(DomainError, match="capacity must be an int"):
        Decomposition(devices=2, capacity=-3)


def test_scene_it_cannot_decompose_is_refused():
    from jaxrt import sim
    from jaxrt.sim import domains
    with pytest.raises(DomainError, match="decomposed runs take "
                       "Lennard-Jones and SPH scenes.*'boids'"):
        domains.from_scene(sim.builtin("boids"), 2)


def test_cli_devices_with_a_check_is_refused(capsys):
    from jaxrt.tools import cli
    rc = cli.main(["run", "boids", "--steps", "2", "--devices", "2"])
    assert rc == 2
    assert "--devices runs without" in capsys.readouterr().err


def _cli(out: pathlib.Path, *extra):
    _run(["-m", "jaxrt", "run", "lj-fluid", "--steps", "50", "--dtype",
          "float64", "--n", "1200", "--out", str(out), "--save-pairs",
          *extra])
    snap = np.load(out / "snapshots.npz")
    return snap["positions"][-1], snap["box"], np.load(out / "pairs.npy")


@pytest.mark.slow
def test_cli_devices_follows_single_device(tmp_path):
    """``jaxrt run lj-fluid --steps 50 --dtype float64 --devices 4``
    against the same without ``--devices``: positions within 1e-8, the
    same pairs within the cutoff at the end."""
    r4, box, p4 = _cli(tmp_path / "d4", "--devices", "4")
    r1, _, p1 = _cli(tmp_path / "d1")
    d = r4 - r1
    d -= box * np.round(d / box)
    assert np.abs(d).max() < 1e-8
    assert len(p1) > 1000 and np.array_equal(p1, p4)


@pytest.mark.slow
def test_cli_dam_break_devices_follows_single_device(tmp_path):
    """SPH with walls: the column's front crosses the first face (x = 1)
    into the empty slabs; positions within 1e-8 of the single device's,
    the same pairs."""
    runs = {}
    for name, extra in (("d4", ("--devices", "4")), ("d1", ())):
        out = tmp_path / name
        _run(["-m", "jaxrt", "run", "dam-break", "--steps", "600",
              "--dtype", "float64", "--out", str(out), "--save-pairs",
              *extra])
        runs[name] = (np.load(out / "snapshots.npz")["positions"][-1],
                      np.load(out / "pairs.npy"))
    (r4, p4), (r1, p1) = runs["d4"], runs["d1"]
    assert r1[:, 0].max() > 1.05  # particles migrated to slab 1
    assert np.abs(r4 - r1).max() < 1e-8
    assert np.array_equal(p1, p4)


@pytest.mark.slow
def test_cli_devices_bvh_backend(tmp_path):
    """The Warp BVH backend (an XLA FFI call) inside shard_map: 2 devices
    against one, 20 steps."""
    pytest.importorskip("warp")
    got = {}
    for name, extra in (("d2", ("--devices", "2")), ("d1", ())):
        out = tmp_path / name
        _run(["-m", "jaxrt", "run", "lj-fluid", "--steps", "20", "--n",
              "1200", "--backend", "bvh", "--dtype", "float64", "--out",
              str(out), "--save-pairs", *extra])
        snap = np.load(out / "snapshots.npz")
        got[name] = (snap["positions"][-1], snap["box"],
                     np.load(out / "pairs.npy"))
    (r2, box, p2), (r1, _, p1) = got["d2"], got["d1"]
    d = r2 - r1
    d -= box * np.round(d / box)
    assert np.abs(d).max() < 1e-8
    assert np.array_equal(p1, p2)
