"""The backend contract (`jaxrt.backends.contract`): every capability has
its default in one place, `capabilities`, which reads a backend duck-typed;
the built-in backends declare theirs; nothing else reads them."""
import ast
import dataclasses
import pathlib

import pytest

import jaxrt
from jaxrt.backends import Capabilities, capabilities

ROOT = pathlib.Path(__file__).resolve().parents[2]


@dataclasses.dataclass(frozen=True)
class Bare:
    """Only what every backend needs (a value, not a subclass)."""
    name = "bare"

    def measure(self, *args):
        return {"row": 0, "edges": 0}

    def search(self, *args):
        raise NotImplementedError


def test_a_backend_that_declares_nothing_has_every_default():
    assert capabilities(Bare()) == Capabilities()
    assert jaxrt.backends.bind(Bare()) == Bare()


def test_declared_capabilities_are_read():
    @dataclasses.dataclass(frozen=True)
    class Radii(Bare):
        supports_radii = True
        fixed_sizes = ["classes"]

        def bind(self):
            return Bare()

    c = capabilities(Radii())
    assert c.supports_radii and c.fixed_sizes == ("classes",) and c.binds
    assert jaxrt.backends.bind(Radii()) == Bare()
    assert dataclasses.replace(c, supports_radii=False, fixed_sizes=(),
                               binds=False) == Capabilities()


def test_the_built_in_backends_declare_theirs():
    cell = capabilities(jaxrt.backends.Cell())
    assert cell.supports_radii and cell.decides_by_metric
    assert capabilities(jaxrt.backends.Brute()).exact_for_any_metric
    assert capabilities(jaxrt.backends.Delaunay()).stateful


def test_the_ray_traced_backends_bind_a_tree_owner():
    pytest.importorskip("warp")
    bvh = jaxrt.backends.Bvh()
    assert capabilities(bvh).binds and capabilities(bvh).supports_radii
    bound = capabilities(jaxrt.backends.bind(bvh))
    assert bound.build_at_exact_capacity and bound.sparse_without_rows


def test_only_the_contract_reads_capabilities():
    names = {f.name for f in dataclasses.fields(Capabilities)} | {"bind"}
    found = []
    for path in (ROOT / "jaxrt").rglob("*.py"):
        if path.name == "contract.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if (isinstance(node, ast.Call) and getattr(node.func, "id", "")
                    in ("getattr", "hasattr") and len(node.args) >= 2
                    and isinstance(node.args[1], ast.Constant)
                    and node.args[1].value in names):
                found.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert not found
