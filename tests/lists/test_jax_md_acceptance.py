"""jax-md's own tests, from its published sdist, run on `jaxrt.neighbor_list`.

jaxrt is a drop-in for ``jax_md.partition.neighbor_list``, so a user can
check it the plain way: swap it in everywhere jax-md binds that function
and run jax-md's tests. `upstream.sdist` takes the tests of the installed
jax-md version from its sdist (pip; cached), `upstream.swap` does the
swap in a pytest run of those files, and each upstream test that builds a
neighbour list is an item here, named by its jax-md id
(``tests/upstream/README.md``: the selection rule, and how to run it).

Which ids run by default is `DEFAULT`; the others are marked slow.
``JAXRT_UPSTREAM_BASELINE=1`` runs the same items on jax-md's own list.
Without network access to PyPI (no cached sdist) they are skipped.
"""
from __future__ import annotations

import gc
import io
import json
import os
import pathlib
import tarfile
import tempfile
import types
import uuid

import pytest

from upstream import sdist, swap

BASELINE = os.environ.get("JAXRT_UPSTREAM_BASELINE", "") not in ("", "0")

# Upstream ids (without ``tests/``) that fail on jaxrt now, each with the
# reason, so that the default run stays green until the fix lands. They
# are strict expected failures: once one passes it fails as XPASS, and its
# line here must go. Not applied to the baseline run.
KNOWN_FAILING: dict[str, str] = {}

# The default run's ids (without ``tests/``), chosen for their cost on two
# CPU cores and to cover each layout, the custom mask, mask_self=False,
# overflow, a time-dependent box and an energy's bound default; every other
# selected id is marked slow. An id here that jax-md no longer has is an
# error.
DEFAULT: set[str] = {
    # a periodic box less than twice the cutoff across; every layout, 2D
    # and 3D, is in tests/lists/test_small_box.py and the slow selection
    "energy_test.py::EnergyTest::test_lennard_jones_small_neighbor_list_energy_dim=2_dtype=float32_format=NeighborListFormat.Dense",
}


def _plan():
    """(params, reason unavailable)."""
    try:
        upstream = sdist.prepare()
        collected = sdist.collect(upstream)
    except sdist.Unavailable as e:
        return [], str(e)
    ids = sdist.selected(upstream, collected["ids"])
    shorts = {i.removeprefix("tests/") for i in ids}
    params = []
    for name, listed in (("DEFAULT", DEFAULT), ("KNOWN_FAILING", KNOWN_FAILING)):
        if set(listed) - shorts:
            params.append(pytest.param(upstream, "error:" + (
                f"{name} names ids that jax-md {upstream.version} does not "
                f"select: {sorted(set(listed) - shorts)}"), id=f"stale {name}"))
    for test_id in ids:
        short = test_id.removeprefix("tests/")
        marks = [] if short in DEFAULT else [pytest.mark.slow]
        if short in KNOWN_FAILING and not BASELINE:
            marks.append(pytest.mark.xfail(reason=KNOWN_FAILING[short],
                                           strict=True))
        params.append(pytest.param(upstream, test_id, marks=marks, id=short))
    for where, text in collected["errors"].items():
        params.append(pytest.param(
            upstream, f"error:jax-md's {where} could not be collected: {text}",
            id=f"collecting {where}"))
    return params, None


PARAMS, UNAVAILABLE = _plan()
if UNAVAILABLE:
    PARAMS = [pytest.param(None, None, id="unavailable", marks=pytest.mark.skip(
        reason=f"jax-md's tests are not available: {UNAVAILABLE}"))]


class _Batches:
    """One upstream run per file for this test run, shared by the xdist
    workers through files in a folder of the run (``testrunuid``): the
    first worker to need a file's results runs them (and, while another
    holds a file it needs, the files nobody has started)."""

    def __init__(self, folder: pathlib.Path, ids_by_file: dict, upstream):
        self.folder = folder
        self.ids_by_file = ids_by_file
        self.upstream = upstream
        folder.mkdir(parents=True, exist_ok=True)

    def _result(self, path: str) -> pathlib.Path:
        return self.folder / (path.replace("/", "_") + ".json")

    def _try(self, path: str, blocking: bool) -> bool:
        lock = self.folder / (path.replace("/", "_") + ".lock")
        with sdist.locked(lock, blocking=blocking) as got:
            if not got:
                return False
            if not self._result(path).exists():
                data = sdist.run(self.upstream, self.ids_by_file[path],
                                 baseline=BASELINE)
                tmp = self._result(path).with_suffix(".tmp")
                tmp.write_text(json.dumps(data))
                tmp.replace(self._result(path))
            return True

    def get(self, path: str) -> dict:
        if not self._result(path).exists() and not self._try(path, False):
            for other in self.ids_by_file:
                if other != path and not self._result(other).exists():
                    self._try(other, False)
            self._try(path, True)
        return json.loads(self._result(path).read_text())


_LOCAL_RUN = uuid.uuid4().hex


@pytest.fixture(scope="session")
def batches(request):
    config = request.config
    run = getattr(config, "workerinput", {}).get("testrunuid", _LOCAL_RUN)
    # The run's compilation-cache folder when tests/conftest.py made one
    # (it removes it at the end), else the temporary folder.
    base = (os.environ.get("JAX_COMPILATION_CACHE_DIR")
            if os.environ.get("JAXRT_TEST_CACHE_OWNER")
            else tempfile.gettempdir())
    ids_by_file: dict[str, list[str]] = {}
    upstream = None
    for item in request.session.items:
        spec = getattr(item, "callspec", None)
        if (getattr(item, "originalname", "") == "test_jax_md_upstream"
                and spec and spec.params.get("test_id")
                and not spec.params["test_id"].startswith("error:")):
            upstream = spec.params["upstream"]
            test_id = spec.params["test_id"]
            ids_by_file.setdefault(test_id.split("::")[0], []).append(test_id)
    mode = "baseline" if BASELINE else "jaxrt"
    folder = pathlib.Path(base) / f"jaxrt-upstream-{run}-{mode}"
    return _Batches(folder, ids_by_file, upstream)


@pytest.mark.parametrize("upstream,test_id", PARAMS)
def test_jax_md_upstream(upstream, test_id, batches):
    """The upstream test passes with the list swapped in, and it called
    that list (else the selection picked a test that builds none)."""
    if test_id.startswith("error:"):
        pytest.fail(test_id.removeprefix("error:"))
    data = batches.get(test_id.split("::")[0])
    assert data.get("list"), ("the upstream run did not start:\n"
                              + data.get("output", ""))
    assert not data["left"], (
        f"jax-md's list is still bound after the swap: {data['left']}")
    record = data["records"].get(test_id)
    if record is None or record["outcome"] is None:
        pytest.fail(f"{test_id} was not reported by the upstream run "
                    f"(killed or crashed?):\n{data.get('output', '')}")
    outcome, text = record["outcome"], record["text"]
    if outcome == "skipped":
        pytest.skip(f"skipped upstream: {text.strip()[-300:]}")
    if outcome == "xfailed":
        pytest.xfail(f"expected to fail upstream: {text.strip()[-300:]}")
    assert outcome in ("passed", "xpassed"), (
        f"{test_id} {outcome} on {data['list']}:\n{text[-3000:]}")
    assert record["calls"] > 0, (
        f"{test_id} passed without calling {data['list']}: it builds no "
        "list through jax-md's binding (the selection rule is wrong)")


# Our own checks of the machinery (no sdist needed).

def _energy_functions_binding(fn):
    """jax-md's functions whose positional or keyword-only defaults hold
    ``fn``, found through the garbage collector's referrers (independent
    of `swap`'s walk of modules)."""
    found = set()
    for referrer in gc.get_referrers(fn):
        if isinstance(referrer, (tuple, dict)):
            for owner in gc.get_referrers(referrer):
                if (isinstance(owner, types.FunctionType)
                        and owner.__module__.startswith("jax_md")
                        and (owner.__defaults__ is referrer
                             or owner.__kwdefaults__ is referrer)):
                    found.add(f"{owner.__module__}.{owner.__qualname__}")
    return found


def test_swap_replaces_every_binding_and_restores_it():
    import jax_md.energy
    import jax_md.partition
    original = jax_md.partition.neighbor_list
    before = _energy_functions_binding(original)
    assert "jax_md.energy.lennard_jones_neighbor_list" in before
    assert "jax_md.energy.graph_network_neighbor_list" in before  # kw-only

    def replacement(*args, **kwargs):
        return original(*args, **kwargs)

    with swap.swapped(replacement) as replaced:
        assert jax_md.partition.neighbor_list is replacement
        assert _energy_functions_binding(original) == set()
        assert _energy_functions_binding(replacement) == before
        assert swap.bindings(original) == []
        assert "jax_md.partition.neighbor_list" in replaced
        assert len(replaced) == len(before) + 1
    assert jax_md.partition.neighbor_list is original
    assert _energy_functions_binding(original) == before
    assert _energy_functions_binding(replacement) == set()


def test_swap_covers_aliases_and_wrapped_defaults_in_given_modules(tmp_path):
    import functools
    import importlib.util
    import jax_md.partition
    original = jax_md.partition.neighbor_list
    (tmp_path / "alias_test.py").write_text(
        "import functools\n"
        "from jax_md.partition import neighbor_list as nl\n"
        "def build(fn=nl):\n    return fn\n"
        "def _make():\n"
        "    def inner(*, fn=nl):\n        return fn\n"
        "    return functools.wraps(inner)(lambda **k: inner(**k))\n"
        "wrapped = _make()\n"
        "class Case:\n"
        "    @staticmethod\n"
        "    def make(fn=nl):\n        return fn\n")
    spec = importlib.util.spec_from_file_location("alias_test",
                                                  tmp_path / "alias_test.py")
    module = importlib.util.module_from_spec(spec)
    import sys
    sys.modules["alias_test"] = module
    try:
        spec.loader.exec_module(module)
        sentinel = functools.partial(original)
        with swap.swapped(sentinel, original, roots=[str(tmp_path)]):
            assert module.nl is sentinel
            assert module.build() is sentinel
            assert module.wrapped() is sentinel
            assert module.Case.make() is sentinel
        assert module.nl is original and module.build() is original
        assert module.Case.make() is original and module.wrapped() is original
    finally:
        del sys.modules["alias_test"]


def test_selection_rule():
    source = '''
from ase.neighborlist import neighbor_list as ase_neighbor_list
from jax_md import energy, partition

def helper(x):
    return partition.neighbor_list(x)

class T:
    def _build(self):
        return energy.lennard_jones_neighbor_list(1)
    def test_direct(self):
        partition.neighbor_list(1)
    def test_through_helper(self):
        helper(1)
    def test_through_method(self):
        self._build()
    def test_energy_without_list(self):
        energy.lennard_jones(1)
    def test_ase_list(self):
        ase_neighbor_list("ij", 1, 2)
    def test_other_multi_image(self):
        partition.neighbor_list_mask(1)

def test_function():
    helper(2)
'''
    assert sdist.builds_a_list(source) == {
        "T.test_direct", "T.test_through_helper", "T.test_through_method",
        "test_function"}
    methods = {"T.test_a", "T.test_a_b", "test_c"}
    assert sdist.method_of("tests/x.py::T::test_a_b_dim=2", methods) == "T.test_a_b"
    assert sdist.method_of("tests/x.py::T::test_a_dim=2", methods) == "T.test_a"
    assert sdist.method_of("tests/x.py::test_c[1]", methods) == "test_c"
    assert sdist.method_of("tests/x.py::U::test_a", methods) is None


def test_extraction_takes_only_the_tests_folder(tmp_path):
    archive = tmp_path / "jax_md-0.0.0.tar.gz"
    with tarfile.open(archive, "w:gz") as tar:
        for name, text in [("jax_md-0.0.0/tests/a_test.py", b"x = 1\n"),
                           ("jax_md-0.0.0/tests/data/d.txt", b"d"),
                           ("jax_md-0.0.0/jax_md/partition.py", b"")]:
            info = tarfile.TarInfo(name)
            info.size = len(text)
            tar.addfile(info, io.BytesIO(text))
        link = tarfile.TarInfo("jax_md-0.0.0/tests/link")
        link.type, link.linkname = tarfile.SYMTYPE, "/etc/passwd"
        tar.addfile(link)
    sdist.extract_tests(archive, tmp_path / "out")
    files = sorted(p.relative_to(tmp_path / "out").as_posix()
                   for p in (tmp_path / "out").rglob("*") if p.is_file())
    assert files == ["tests/a_test.py", "tests/data/d.txt"]
    assert not (tmp_path / "out" / "tests" / "link").exists()

    bad = tmp_path / "bad.tar.gz"
    with tarfile.open(bad, "w:gz") as tar:
        info = tarfile.TarInfo("jax_md-0.0.0/tests/../../escape.py")
        tar.addfile(info, io.BytesIO(b""))
    with pytest.raises(sdist.Unavailable, match="unsafe path"):
        sdist.extract_tests(bad, tmp_path / "out2")


def test_no_registry_is_a_clear_skip_reason(tmp_path, monkeypatch):
    monkeypatch.setenv("PIP_NO_INDEX", "1")
    monkeypatch.setenv("PIP_FIND_LINKS", str(tmp_path))
    with pytest.raises(sdist.Unavailable, match="could not download jax-md"):
        sdist.fetch_sdist("0.2.29", tmp_path / "sdists")
