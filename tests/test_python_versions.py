"""jaxrt claims the Python versions it works on (``requires-python``).

Python 3.10 is not one of them: there pip resolves JAX 0.6.2 (JAX's last
release for 3.10), whose Pallas has no ``jax.experimental.pallas.triton.load``,
which the default ``cell`` backend calls. ``import jaxrt`` works on it, and
so do the ``brute`` and ``bvh`` lists, but ``jaxrt.neighbor_list`` with its
default backend raises ``AttributeError``. So ``requires-python`` is
``>=3.11``, and pip must refuse jaxrt on 3.10 with a message that says so.

The interpreters are pyenv's (``$PYENV_ROOT``, else ``~/.pyenv``; CI's image
has 3.10 and 3.11, and its ``python3`` is 3.11); a test without its
interpreter is skipped, saying which.
"""
from __future__ import annotations

import os
import pathlib
import re
import shutil
import subprocess
import sys
import tomllib

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
FLOOR = (3, 11)


def _python(version: tuple[int, int]) -> str | None:
    """An interpreter of ``version``: the running one, else pyenv's."""
    if sys.version_info[:2] == version:
        return sys.executable
    pyenv = pathlib.Path(os.environ.get("PYENV_ROOT",
                                        pathlib.Path.home() / ".pyenv"))
    found = sorted(pyenv.glob("versions/%d.%d.*/bin/python3" % version))
    return str(found[-1]) if found else None


def test_requires_python_is_the_floor_tested_here():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["requires-python"] == ">=%d.%d" % FLOOR
    assert sys.version_info[:2] >= FLOOR
    # tomllib (3.11) needs no backport.
    assert not any(d.split(";")[0].strip().startswith("tomli")
                   for d in project["dependencies"])


def test_pip_refuses_jaxrt_on_python_3_10(tmp_path):
    python = _python((3, 10))
    if python is None:
        pytest.skip("no Python 3.10 interpreter (pyenv) on this machine")
    # The project's metadata only (the package's files are not needed to
    # read it), so the checkout is left as it is.
    project = tmp_path / "jaxrt-metadata"
    (project / "jaxrt").mkdir(parents=True)
    (project / "jaxrt" / "__init__.py").write_text("")
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, project / name)
    done = subprocess.run(
        [python, "-m", "pip", "install", "--dry-run", "--no-deps",
         "--ignore-installed", "--disable-pip-version-check", str(project)],
        capture_output=True, text=True, timeout=300,
        stdin=subprocess.DEVNULL)
    output = done.stdout + done.stderr
    if done.returncode and "requires a different Python" not in output and (
            "setuptools" in output and ("No matching distribution" in output
                                        or "Could not find a version" in output)):
        pytest.skip("pip could not get the build backend (offline?): "
                    + output.strip().splitlines()[-1])
    assert done.returncode != 0, output
    assert re.search(r"jaxrt' requires a different Python: 3\.10\.\d+ not in "
                     r"'>=3\.11'", output), output


def test_oldest_python_claimed_builds_the_default_list():
    """On the floor's interpreter (pyenv's), where this run is on a newer
    one: CI's ``python3`` is 3.11, the floor, and the whole suite checks
    it there."""
    if sys.version_info[:2] == FLOOR:
        pytest.skip("this run is on Python %d.%d, the oldest claimed: the "
                    "suite itself is the check" % FLOOR)
    python = _python(FLOOR)
    if python is None:
        pytest.skip("no Python %d.%d interpreter on this machine" % FLOOR)
    code = (
        "import sys, numpy as np, jax, jaxrt\n"
        "from jax_md import partition, space\n"
        "disp, _ = space.periodic(6.0)\n"
        "R = jax.random.uniform(jax.random.PRNGKey(0), (64, 3)) * 6.0\n"
        "def pairs(fn):\n"
        "    idx = np.asarray(fn.allocate(R).idx)\n"
        "    return {(i, j) for i in range(64) for j in idx[i] if j < 64}\n"
        "ours = pairs(jaxrt.neighbor_list(disp, 6.0, 1.5))\n"
        "theirs = pairs(partition.neighbor_list(disp, 6.0, 1.5))\n"
        "assert ours == theirs and ours, (len(ours), len(theirs))\n"
        "print(sys.version_info[:2], jax.__version__, len(ours))\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(ROOT)] + [p for p in os.environ.get("PYTHONPATH", "").split(
            os.pathsep) if p]))
    done = subprocess.run([python, "-c", code], capture_output=True,
                          text=True, timeout=600, cwd=ROOT, env=env,
                          stdin=subprocess.DEVNULL)
    if done.returncode and python != sys.executable and (
            "ModuleNotFoundError" in done.stderr):
        pytest.skip(f"{python} lacks jaxrt's dependencies: "
                    + done.stderr.strip().splitlines()[-1])
    assert done.returncode == 0, done.stderr[-3000:]
    assert "(%d, %d)" % FLOOR in done.stdout
