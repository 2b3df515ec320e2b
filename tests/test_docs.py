"""The generated documentation: the API reference builds with no broken
reference, and docs/benchmarks.md (with the README's headline table) is
what benchmarks/make_docs.py writes from the committed CSVs."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _run(*args, **kwargs):
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        [str(ROOT)] + [p for p in [env.get("PYTHONPATH")] if p])
    return subprocess.run([sys.executable, *args], cwd=ROOT, env=env,
                          capture_output=True, text=True, **kwargs)


def test_benchmark_page_and_readme_table_are_up_to_date():
    done = _run("benchmarks/make_docs.py", "--check")
    assert done.returncode == 0, (
        "docs/benchmarks.md or the README's benchmark table is stale: run "
        "python3 benchmarks/make_docs.py and commit the result\n"
        + done.stderr)


def test_readme_fits_its_size_limit():
    assert (ROOT / "README.md").stat().st_size <= 10_240


def test_api_reference_builds_with_no_broken_reference(tmp_path):
    pytest.importorskip("pdoc", reason="pip install -e '.[docs]'")
    done = _run("docs/build.py", "-o", str(tmp_path), timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    assert (tmp_path / "jaxrt.html").exists()
    assert (tmp_path / "jaxrt" / "lists" / "neighbors.html").exists()
