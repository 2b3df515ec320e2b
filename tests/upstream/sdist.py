"""jax-md's own tests, from its published sdist, run on a swapped-in list.

`prepare` downloads the sdist of the installed jax-md version with pip
(``pip download --no-deps --no-binary :all: jax-md==<version>``), keeps it
and its extracted ``tests/`` folder in a cache (``$JAXRT_UPSTREAM_CACHE``,
else ``~/.cache/jaxrt-upstream``), and raises `Unavailable` when pip cannot
get it (an offline machine). `collect` lists the test ids of `FILES`;
`selected` keeps those that build a neighbour list (`builds_a_list`);
`run` runs ids in a subprocess (pytest, with `upstream.swap` as a plugin)
and returns one record per id.
"""
from __future__ import annotations

import ast
import contextlib
import dataclasses
import fcntl
import importlib.metadata
import json
import os
import pathlib
import shutil
import subprocess
import sys
import tarfile
import tempfile

FILES = ("partition_test.py", "simulate_test.py", "custom_partition_test.py",
         "energy_test.py", "nequip_test.py", "custom_smap_test.py")

HERE = pathlib.Path(__file__).resolve().parent
TESTS = HERE.parent          # our tests/ (holds the `upstream` package)


class Unavailable(Exception):
    """jax-md's sdist could not be had (the reason is the message)."""


@dataclasses.dataclass(frozen=True)
class Upstream:
    version: str
    root: pathlib.Path       # holds pytest.ini and tests/

    @property
    def tests(self) -> pathlib.Path:
        return self.root / "tests"


def cache_root() -> pathlib.Path:
    env = os.environ.get("JAXRT_UPSTREAM_CACHE")
    if env:
        return pathlib.Path(env).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or pathlib.Path.home() / ".cache"
    return pathlib.Path(base) / "jaxrt-upstream"


@contextlib.contextmanager
def locked(path: pathlib.Path, blocking: bool = True):
    """An exclusive lock on ``path`` (between test workers and runs);
    yields False, holding nothing, where not ``blocking`` and taken."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | (0 if blocking else fcntl.LOCK_NB))
        except BlockingIOError:
            yield False
            return
        try:
            yield True
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def _sdist(version: str, folder: pathlib.Path) -> pathlib.Path | None:
    for pattern in (f"jax_md-{version}.tar.gz", f"jax-md-{version}.tar.gz"):
        hits = sorted(folder.glob(pattern))
        if hits:
            return hits[0]
    return None


def fetch_sdist(version: str, folder: pathlib.Path) -> pathlib.Path:
    """The sdist of jax-md ``version`` in ``folder``, downloaded by pip if
    it is not there yet."""
    found = _sdist(version, folder)
    if found:
        return found
    folder.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=folder) as tmp:
        cmd = [sys.executable, "-m", "pip", "download", "--no-deps",
               "--no-binary", ":all:", "--disable-pip-version-check",
               "--timeout", "30", "--retries", "2",
               f"jax-md=={version}", "-d", tmp]
        try:
            done = subprocess.run(cmd, capture_output=True, text=True,
                                  stdin=subprocess.DEVNULL,
                                  timeout=600)
        except (OSError, subprocess.TimeoutExpired) as e:
            raise Unavailable(f"`{' '.join(cmd[2:])}` did not finish: {e}")
        got = _sdist(version, pathlib.Path(tmp))
        if done.returncode or got is None:
            lines = (done.stderr or done.stdout).strip().splitlines()
            raise Unavailable(
                f"pip could not download jax-md=={version}'s sdist "
                f"(offline?): {lines[-1] if lines else done.returncode}")
        return pathlib.Path(shutil.move(str(got), folder / got.name))


def extract_tests(sdist: pathlib.Path, dest: pathlib.Path) -> None:
    """Copy the sdist's ``<top>/tests/`` tree (data included) to
    ``dest/tests``: regular files and folders only, none outside it."""
    with tarfile.open(sdist) as tar:
        for member in tar.getmembers():
            parts = pathlib.PurePosixPath(member.name).parts
            if len(parts) < 3 or parts[1] != "tests":
                continue
            if member.name.startswith("/") or ".." in parts:
                raise Unavailable(f"{sdist.name}: unsafe path {member.name!r}")
            target = dest.joinpath("tests", *parts[2:])
            if member.isdir():
                target.mkdir(parents=True, exist_ok=True)
            elif member.isfile():
                target.parent.mkdir(parents=True, exist_ok=True)
                with tar.extractfile(member) as src, open(target, "wb") as out:
                    shutil.copyfileobj(src, out)


def prepare() -> Upstream:
    """The installed jax-md version's tests, fetched and extracted once."""
    try:
        version = importlib.metadata.version("jax-md")
    except importlib.metadata.PackageNotFoundError:
        raise Unavailable("jax-md is not installed")
    root = cache_root()
    where = root / f"jax_md-{version}"
    done = where / ".complete"
    if done.exists():
        return Upstream(version, where)
    with locked(root / ".lock"):
        if not done.exists():
            sdist = fetch_sdist(version, root / "sdists")
            shutil.rmtree(where, ignore_errors=True)
            extract_tests(sdist, where)
            if not (where / "tests").is_dir():
                raise Unavailable(f"{sdist.name} has no tests/ folder")
            # Our own pytest settings there, so that no configuration
            # from the folders above applies.
            (where / "pytest.ini").write_text(
                "[pytest]\naddopts = -p no:cacheprovider\n")
            done.write_text(str(sdist) + "\n")
    return Upstream(version, where)


# Selection.

def _is_list_builder(node: ast.Attribute) -> bool:
    """``partition.neighbor_list`` or ``energy.<name>_neighbor_list``."""
    if not isinstance(node.value, ast.Name):
        return False
    base, attr = node.value.id, node.attr
    return ((base == "partition" and attr == "neighbor_list")
            or (base == "energy" and attr.endswith("_neighbor_list")))


def builds_a_list(source: str) -> set[str]:
    """The test methods (``Class.method``, or ``function``) of a test
    module that build a neighbour list through jax-md: their code, or a
    function or method of the same module that they call (by name, or as
    ``self.name``), refers to ``partition.neighbor_list`` or to an
    ``energy.*_neighbor_list`` function (jax-md's energies that build their
    list with ``partition.neighbor_list``)."""
    tree = ast.parse(source)
    direct: dict[str, bool] = {}
    calls: dict[str, set[str]] = {}

    def scan(key: str, fn: ast.AST) -> None:
        direct[key] = False
        calls[key] = set()
        for node in ast.walk(fn):
            if isinstance(node, ast.Attribute):
                if _is_list_builder(node):
                    direct[key] = True
                elif isinstance(node.value, ast.Name) and node.value.id in (
                        "self", "cls"):
                    calls[key].add(node.attr)
            elif isinstance(node, ast.Name):
                calls[key].add(node.id)

    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            scan(node.name, node)
        elif isinstance(node, ast.ClassDef):
            for sub in node.body:
                if isinstance(sub, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    scan(f"{node.name}.{sub.name}", sub)

    def builds(key: str, seen: frozenset) -> bool:
        if direct[key]:
            return True
        cls = key.split(".")[0] + "." if "." in key else ""
        for name in calls[key]:
            for callee in (cls + name, name):
                if callee in direct and callee not in seen and builds(
                        callee, seen | {callee}):
                    return True
        return False

    return {key for key in direct
            if key.rsplit(".", 1)[-1].startswith("test")
            and builds(key, frozenset({key}))}


def method_of(test_id: str, methods: set[str]) -> str | None:
    """The test method an id comes from (``file::Class::name`` ->
    ``Class.method``): parameterised ids are the method's name plus a
    suffix, so the longest method name that prefixes it."""
    parts = test_id.split("::")
    cls = ".".join(parts[1:-1])
    name = parts[-1].split("[")[0]
    keys = [m for m in methods
            if m.rsplit(".", 1)[0] == cls or ("." not in m and not cls)]
    hits = [m for m in keys if name.startswith(m.rsplit(".", 1)[-1])]
    return max(hits, key=len) if hits else None


def selected(upstream: Upstream, ids: list[str]) -> list[str]:
    """The ids (``tests/<file>::...``) whose method `builds_a_list`."""
    keep = []
    methods: dict[str, set[str]] = {}
    for test_id in ids:
        path = test_id.split("::")[0]
        if path not in methods:
            source = (upstream.root / path).read_text()
            methods[path] = builds_a_list(source)
        if method_of(test_id, methods[path]) in methods[path]:
            keep.append(test_id)
    return keep


# Running.

def _environment(report: pathlib.Path, upstream: Upstream,
                 baseline: bool) -> dict:
    import jaxrt
    env = dict(os.environ)
    repo = pathlib.Path(jaxrt.__file__).resolve().parent.parent
    paths = [str(TESTS), str(repo)] + [
        p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]
    env["PYTHONPATH"] = os.pathsep.join(paths)
    env["JAXRT_UPSTREAM_REPORT"] = str(report)
    env["JAXRT_UPSTREAM_ROOTS"] = str(upstream.tests)
    env["JAXRT_UPSTREAM_BASELINE"] = "1" if baseline else ""
    env.pop("PYTEST_XDIST_WORKER", None)
    env.pop("PYTEST_CURRENT_TEST", None)
    return env


def pytest_run(upstream: Upstream, args: list[str], baseline: bool,
               timeout: float) -> tuple[dict, str]:
    """``python -m pytest -p upstream.swap <args>`` in the extracted folder;
    (the plugin's report, the run's output tail)."""
    with tempfile.TemporaryDirectory(prefix="jaxrt-upstream-") as tmp:
        report = pathlib.Path(tmp) / "report.json"
        cmd = [sys.executable, "-m", "pytest", "-p", "upstream.swap", "-q",
               "-p", "no:randomly", *args]
        try:
            done = subprocess.run(
                cmd, cwd=upstream.root, capture_output=True, text=True,
                stdin=subprocess.DEVNULL,
                timeout=timeout, env=_environment(report, upstream, baseline))
            output = done.stdout + done.stderr
        except subprocess.TimeoutExpired as e:
            output = ((e.stdout or b"").decode(errors="replace")
                      if isinstance(e.stdout, bytes) else (e.stdout or ""))
            output += f"\n[killed after {timeout:.0f} s]"
        data = {}
        if report.exists():
            data = json.loads(report.read_text())
        return data, output[-6000:]


def collect(upstream: Upstream) -> dict:
    """``{"ids": [...], "errors": {file: text}, "without_lists": [file]}``
    for `FILES` (those with no test that `builds_a_list` are listed, not
    collected), kept in the cache once a collection has no errors."""
    cached = upstream.root / "collected.json"
    if cached.exists():
        return json.loads(cached.read_text())
    with locked(upstream.root / ".collect.lock"):
        if cached.exists():
            return json.loads(cached.read_text())
        present = [f for f in FILES if (upstream.tests / f).exists()]
        # Files with no test that builds a list are not imported at all.
        files = [f"tests/{f}" for f in present
                 if builds_a_list((upstream.tests / f).read_text())]
        data, output = pytest_run(upstream, ["--collect-only", *files],
                                  baseline=True, timeout=900)
        result = {"ids": data.get("collected", []),
                  "errors": data.get("errors", {}),
                  "without_lists": [f"tests/{f}" for f in present
                                    if f"tests/{f}" not in files]}
        for f in FILES:
            if f not in present:
                result["errors"][f"tests/{f}"] = "not in this jax-md's sdist"
        if not data:
            result["errors"]["collection"] = output
        if not result["errors"]:
            cached.write_text(json.dumps(result, indent=1))
        return result


def run(upstream: Upstream, ids: list[str], baseline: bool = False,
        timeout: float = 3600) -> dict:
    """Run ``ids``; ``{"list": ..., "replaced": [...], "left": [...],
    "records": {id: {"outcome", "calls", "duration", "text"}},
    "output": tail}``."""
    data, output = pytest_run(upstream, list(ids), baseline, timeout)
    data.setdefault("records", {})
    data["output"] = output
    return data
