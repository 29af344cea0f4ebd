"""CONTRIBUTING.md's layout table, file for file, made from the tree.

Each module of ``src/imitrl`` is one row: its path and the first line of its docstring
(what it holds). ``tests/test_architecture.py`` checks that the table between the
``<!-- BEGIN layout -->`` markers is this one; after adding, moving or removing a module,
or changing a module's first docstring line, refresh it with::

    python tests/_layout.py
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "src" / "imitrl"
CONTRIBUTING = ROOT / "CONTRIBUTING.md"
BEGIN, END = "<!-- BEGIN layout -->", "<!-- END layout -->"


def modules() -> list[Path]:
    """Every module of the package, a folder's ``__init__.py`` before its other files."""
    files = sorted(
        PACKAGE.rglob("*.py"), key=lambda p: (p.parent.parts, p.name != "__init__.py", p.name)
    )
    return [p for p in files if "__pycache__" not in p.parts]


def summary(path: Path) -> str:
    """The first line of ``path``'s module docstring (a module without one is refused)."""
    doc = ast.get_docstring(ast.parse(path.read_text()))
    if not doc:
        raise ValueError(f"{path.relative_to(PACKAGE)} has no module docstring: say what it holds")
    return doc.strip().splitlines()[0].replace("|", "\\|")


def table() -> str:
    """The markdown table: one row per module, paths relative to ``src/imitrl``."""
    rows = ["| module | what it holds |", "|---|---|"]
    for path in modules():
        rows.append(f"| `{path.relative_to(PACKAGE).as_posix()}` | {summary(path)} |")
    return "\n".join(rows)


def current() -> str:
    """The table now in CONTRIBUTING.md, between its markers."""
    text = CONTRIBUTING.read_text()
    match = re.search(re.escape(BEGIN) + r"(.*?)" + re.escape(END), text, re.S)
    if match is None:
        raise ValueError(f"CONTRIBUTING.md has no {BEGIN} ... {END} block")
    return match.group(1).strip("\n")


def refresh() -> None:
    """Write :func:`table` between the markers of CONTRIBUTING.md."""
    text = CONTRIBUTING.read_text()
    start, end = text.index(BEGIN), text.index(END) + len(END)
    CONTRIBUTING.write_text(text[:start] + f"{BEGIN}\n{table()}\n{END}" + text[end:])


if __name__ == "__main__":
    refresh()
