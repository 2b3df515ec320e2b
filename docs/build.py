"""Build the API reference from jaxrt's docstrings (pdoc) and check it.

    python3 docs/build.py              # writes docs/api/ (not committed)
    python3 docs/build.py -o DIR       # somewhere else

Every public module of jaxrt (no part of its name starting with ``_``) gets
a page. The build fails (exit 1) on a broken reference: pdoc turns a
backticked name that it can resolve into a link and leaves any other as
plain code, so every page is scanned for code spans that name a
``jaxrt.…`` object and are not links; each must at least import (an object
of a private module is fine), else it is reported with its page.

Needs ``pdoc`` (``pip install -e ".[docs]"``).
"""
from __future__ import annotations

import argparse
import html
import importlib
import pkgutil
import re
import sys
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_OUT = ROOT / "docs" / "api"

# An inline code span that is only a dotted jaxrt name (maybe called), and
# the same inside a link, which is what pdoc makes of references it resolved.
CODE_REF = re.compile(r"<code>(jaxrt(?:\.\w+)+)(?:\(\))?</code>")
LINKED = re.compile(r"<a [^>]*>\s*<code>jaxrt(?:\.\w+)+(?:\(\))?</code>\s*</a>")


def public_modules() -> list[str]:
    """jaxrt and every submodule with no private part, sorted."""
    import jaxrt
    names = ["jaxrt"]
    for info in pkgutil.walk_packages(jaxrt.__path__, "jaxrt."):
        if not any(part.startswith("_") for part in info.name.split(".")):
            names.append(info.name)
    return sorted(names)


def resolves(dotted: str) -> bool:
    """Whether ``jaxrt.a.b.c`` names an object: the longest importable
    module prefix, then attributes."""
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        try:
            for name in parts[cut:]:
                obj = getattr(obj, name)
        except AttributeError:
            return False
        return True
    return False


def broken_references(out: Path) -> list[tuple[str, str]]:
    """(page, reference) for each unlinked jaxrt reference that resolves
    to nothing."""
    found: dict[tuple[str, str], None] = {}
    for page in sorted(out.rglob("*.html")):
        text = LINKED.sub("", page.read_text(encoding="utf-8"))
        for match in CODE_REF.finditer(text):
            name = html.unescape(match.group(1))
            if not resolves(name):
                found[(page.relative_to(out).as_posix(), name)] = None
    return list(found)


def build(out: Path) -> int:
    import pdoc
    import pdoc.render

    pdoc.render.configure(docformat="google", show_source=False,
                          search=True)
    modules = public_modules()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        pdoc.pdoc(*modules, output_directory=out)
    # Not about the docstrings: annotations pdoc cannot evaluate, and
    # submodules named both here and in their package's __all__.
    noted = [w for w in caught if not any(
        text in str(w.message) for text in (
            "Error parsing type annotation", "has already been added"))]
    for w in noted:
        print(f"docs/build.py: pdoc warned: {w.message}", file=sys.stderr)
    broken = broken_references(out)
    for page, name in broken:
        print(f"docs/build.py: {page}: `{name}` names no object",
              file=sys.stderr)
    print(f"{len(modules)} modules documented in {out}"
          + (f"; {len(broken)} broken references" if broken else ""))
    return 1 if broken else 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("-o", "--out", type=Path, default=DEFAULT_OUT,
                        help="output folder (default docs/api/)")
    args = parser.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    return build(args.out)


if __name__ == "__main__":
    sys.exit(main())
