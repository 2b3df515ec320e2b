"""Put a neighbour list in jax-md's place everywhere jax-md has bound it.

A drop-in for ``jax_md.partition.neighbor_list`` has to replace more than
that one attribute: ``jax_md.energy``'s ``*_neighbor_list`` functions took
``neighbor_list_fn=partition.neighbor_list`` as a default when the module
was imported, and a module may hold the function under another name
(``from jax_md.partition import neighbor_list``). `swapped` finds every
such binding by identity with jax-md's function (module attributes,
positional and keyword-only defaults of functions, of methods in classes and
of the functions that decorators wrap), replaces it, and restores it all on
exit, so no list of names has to follow jax-md's releases.

Also a pytest plugin (``-p upstream.swap``): the run that
`upstream.sdist` starts on jax-md's own test files swaps the list in after
collection, counts each test's calls of it, and writes one JSON record per
test. The environment picks the list:

``JAXRT_UPSTREAM_BASELINE=1``
    jax-md's own list (through the same counting wrapper), to compare with.
``JAXRT_UPSTREAM_BACKEND=<name>``
    ``jaxrt.neighbor_list(..., backend=<name>)``; ``disable_cell_list=True``
    then asks for ``brute``, as that flag means. Default: jaxrt's default
    backend, as a user gets it.
"""
from __future__ import annotations

import contextlib
import functools
import json
import os
import sys
import time
import types
from typing import Callable, Iterable, Iterator

import pytest

REPORT_ENV = "JAXRT_UPSTREAM_REPORT"
ROOTS_ENV = "JAXRT_UPSTREAM_ROOTS"


def _is_jax_md(name: str) -> bool:
    return name == "jax_md" or name.startswith("jax_md.")


def _modules(roots: Iterable[str] = ()) -> list[types.ModuleType]:
    """jax-md's loaded modules, and those loaded from a file under one of
    ``roots`` (jax-md's test files)."""
    roots = tuple(os.path.abspath(r) + os.sep for r in roots)
    found = []
    for name, module in list(sys.modules.items()):
        if not isinstance(module, types.ModuleType):
            continue
        path = getattr(module, "__file__", None) or ""
        if _is_jax_md(name) or (roots and os.path.abspath(path).startswith(roots)):
            found.append(module)
    return found


def _functions(namespace: dict) -> Iterator[types.FunctionType]:
    """Plain functions in a module's or a class's namespace (one level of
    classes, static and class methods, and what decorators wrap)."""
    for value in list(namespace.values()):
        candidates = [value]
        if isinstance(value, type):
            candidates = list(vars(value).values())
        for candidate in candidates:
            if isinstance(candidate, (staticmethod, classmethod)):
                candidate = candidate.__func__
            seen = set()
            while candidate is not None and id(candidate) not in seen:
                seen.add(id(candidate))
                if isinstance(candidate, types.FunctionType):
                    yield candidate
                candidate = getattr(candidate, "__wrapped__", None)


def bindings(original: Callable, roots: Iterable[str] = ()) -> list[str]:
    """Where ``original`` is bound in the modules `swapped` covers, as
    readable names (empty once it is swapped)."""
    where = []
    for module in _modules(roots):
        namespace = vars(module)
        for attr, value in list(namespace.items()):
            if value is original:
                where.append(f"{module.__name__}.{attr}")
        for fn in _functions(namespace):
            if any(d is original for d in fn.__defaults__ or ()):
                where.append(f"{fn.__module__}.{fn.__qualname__} (default)")
            if any(d is original for d in (fn.__kwdefaults__ or {}).values()):
                where.append(f"{fn.__module__}.{fn.__qualname__} "
                             "(keyword-only default)")
    return sorted(set(where))


@contextlib.contextmanager
def swapped(replacement: Callable, original: Callable | None = None,
            roots: Iterable[str] = ()) -> Iterator[list[str]]:
    """Replace ``original`` (jax-md's ``partition.neighbor_list``) by
    ``replacement`` wherever jax-md's modules (and modules under ``roots``)
    bind it; yields the names replaced; restores them on exit."""
    if original is None:
        import jax_md.partition
        original = jax_md.partition.neighbor_list
    undo: list[Callable[[], None]] = []
    replaced: list[str] = []
    done: set[int] = set()
    try:
        for module in _modules(roots):
            namespace = vars(module)
            for attr, value in list(namespace.items()):
                if value is original:
                    setattr(module, attr, replacement)
                    undo.append(functools.partial(setattr, module, attr, original))
                    replaced.append(f"{module.__name__}.{attr}")
            for fn in _functions(namespace):
                if id(fn) in done:
                    continue
                done.add(id(fn))
                name = f"{fn.__module__}.{fn.__qualname__}"
                defaults = fn.__defaults__
                if defaults and any(d is original for d in defaults):
                    fn.__defaults__ = tuple(replacement if d is original else d
                                            for d in defaults)
                    undo.append(functools.partial(setattr, fn, "__defaults__",
                                                  defaults))
                    replaced.append(f"{name} (default)")
                kwdefaults = fn.__kwdefaults__
                if kwdefaults and any(d is original for d in kwdefaults.values()):
                    fn.__kwdefaults__ = {k: replacement if d is original else d
                                         for k, d in kwdefaults.items()}
                    undo.append(functools.partial(setattr, fn, "__kwdefaults__",
                                                  kwdefaults))
                    replaced.append(f"{name} (keyword-only default)")
        yield sorted(set(replaced))
    finally:
        for step in reversed(undo):
            step()


class Counting:
    """A neighbour-list factory that counts its calls (a test that never
    calls it did not test the list that was swapped in)."""

    def __init__(self, fn: Callable, describe: str):
        self.fn = fn
        self.describe = describe
        self.calls = 0
        functools.update_wrapper(self, fn)

    def __call__(self, *args, **kwargs):
        self.calls += 1
        return self.fn(*args, **kwargs)


def replacement_from_environment(original: Callable) -> Counting:
    """The list the environment asks for (module docstring)."""
    if os.environ.get("JAXRT_UPSTREAM_BASELINE", "") not in ("", "0"):
        return Counting(original, "jax_md.partition.neighbor_list (baseline)")
    import jaxrt
    backend = os.environ.get("JAXRT_UPSTREAM_BACKEND", "")
    if not backend:
        return Counting(jaxrt.neighbor_list, "jaxrt.neighbor_list")

    def neighbor_list(*args, disable_cell_list=False, **kwargs):
        chosen = "brute" if disable_cell_list else backend
        return jaxrt.neighbor_list(*args, backend=chosen, **kwargs)
    functools.update_wrapper(neighbor_list, jaxrt.neighbor_list)
    return Counting(neighbor_list, f"jaxrt.neighbor_list(backend={backend!r})")


# The pytest plugin, in the run on jax-md's test files. The report is
# rewritten after each test, so that a run killed on a timeout still
# reports the tests it finished.

_state: dict = {"collected": [], "errors": {}, "records": {}}


def _write_report() -> None:
    path = os.environ.get(REPORT_ENV)
    if not path:
        return
    counting = _state.get("counting")
    data = {"list": counting.describe if counting else None,
            "replaced": _state.get("replaced", []),
            "left": _state.get("left", []),
            "collected": _state["collected"],
            "errors": _state["errors"],
            "records": _state["records"]}
    with open(path + ".tmp", "w") as f:
        json.dump(data, f, indent=1)
    os.replace(path + ".tmp", path)


def pytest_collectreport(report):
    if report.failed:
        _state["errors"][report.nodeid or "collection"] = report.longreprtext


def pytest_collection_finish(session):
    _state["collected"] = [item.nodeid for item in session.items]
    if session.config.option.collectonly:
        _write_report()
        return
    import jax_md.partition
    original = jax_md.partition.neighbor_list
    roots = [p for p in os.environ.get(ROOTS_ENV, "").split(os.pathsep) if p]
    counting = replacement_from_environment(original)
    stack = contextlib.ExitStack()
    replaced = stack.enter_context(swapped(counting, original, roots))
    _state.update(stack=stack, counting=counting, replaced=replaced,
                  left=bindings(original, roots))
    _write_report()


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item):
    if "counting" in _state:
        _state["counting"].calls = 0
        _state["cpu"] = time.process_time()


def pytest_runtest_logreport(report):
    if "counting" not in _state:
        return
    record = _state["records"].setdefault(report.nodeid, {
        "outcome": None, "calls": 0, "duration": 0.0, "cpu": 0.0, "text": ""})
    record["duration"] += report.duration
    if report.when == "call" or (report.when == "setup" and not report.passed):
        record["calls"] = _state["counting"].calls
        if hasattr(report, "wasxfail"):
            record["outcome"] = "xfailed" if report.skipped else "xpassed"
        else:
            record["outcome"] = report.outcome
        if report.skipped and isinstance(report.longrepr, tuple):
            record["text"] = str(report.longrepr[2])  # (path, line, reason)
        elif not report.passed:
            record["text"] = report.longreprtext
    elif report.when == "teardown":
        # CPU seconds of the whole test (all threads): less sensitive than
        # the wall-clock duration to other work on a shared machine.
        record["cpu"] = time.process_time() - _state.get("cpu", 0.0)
        if report.failed:
            record["outcome"] = "failed"
            record["text"] += "\n[teardown]\n" + report.longreprtext
        _write_report()


def pytest_sessionfinish(session, exitstatus):
    _write_report()
    stack = _state.pop("stack", None)
    if stack is not None:
        stack.close()
