"""The architecture's rules, read from the source: layers point down, no import circle,
private attributes of other libraries in ``compat.py`` only, no file or function past
its size.

* The layer contract is ``[tool.importlinter]`` in ``pyproject.toml`` (one line per layer,
  highest first); import-linter checks it here and in CI.
* No two modules of ``src/imitrl`` import each other, directly or around a circle, at any
  level (function-level imports included): the strongly connected components of grimp's
  import graph are single modules.
* A private attribute (``x._name``, ``getattr(x, "_name")``, ``from lib import _name``)
  that imitrl does not define itself is reached in :mod:`imitrl.compat` only, where each
  use is listed with its reason and tested against the public path.
"""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import grimp
import pytest

import imitrl

SRC = Path(imitrl.__file__).resolve().parent
COMPAT = SRC / "compat.py"


def test_the_layer_contract_holds():
    root = SRC.parent.parent
    if not (root / "pyproject.toml").exists():  # an installed copy: the contract is the repo's
        return
    lint = Path(sys.executable).parent / "lint-imports"
    done = subprocess.run([str(lint)], cwd=root, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-2000:]
    assert "1 kept, 0 broken" in done.stdout


def _components(graph: grimp.ImportGraph) -> list[list[str]]:
    """Tarjan's strongly connected components of the module import graph (iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    out: list[list[str]] = []
    for start in sorted(graph.modules):
        if start in index:
            continue
        work = [(start, iter(sorted(graph.find_modules_directly_imported_by(start))))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append(
                        (child, iter(sorted(graph.find_modules_directly_imported_by(child))))
                    )
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                out.append(sorted(component))
    return out


def test_no_import_circle():
    graph = grimp.build_graph("imitrl", cache_dir=None)
    circles = [c for c in _components(graph) if len(c) > 1]
    assert circles == []


def test_the_circle_finder_finds_a_circle():
    graph = grimp.ImportGraph()
    for name in ("p", "p.a", "p.b", "p.c"):
        graph.add_module(name)
    graph.add_import(importer="p.a", imported="p.b")
    graph.add_import(importer="p.b", imported="p.a")
    graph.add_import(importer="p.c", imported="p.a")
    assert [c for c in _components(graph) if len(c) > 1] == [["p.a", "p.b"]]


def _defined_names(trees: dict[Path, ast.Module]) -> set[str]:
    """Every name imitrl defines: functions, classes, assigned attributes and names,
    arguments, and attributes set by name (``object.__setattr__(self, "_x", ...)``,
    ``register_buffer("_x", ...)``)."""
    own: set[str] = set()
    for tree in trees.values():
        for n in ast.walk(tree):
            if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                own.add(n.name)
            elif isinstance(n, ast.Attribute) and isinstance(n.ctx, ast.Store):
                own.add(n.attr)
            elif isinstance(n, ast.Name) and isinstance(n.ctx, ast.Store):
                own.add(n.id)
            elif isinstance(n, ast.arg):
                own.add(n.arg)
            elif isinstance(n, ast.Call) and len(n.args) >= 2:
                name = n.args[1] if _called(n) == "__setattr__" else n.args[0]
                if _called(n) in ("__setattr__", "setattr", "register_buffer", "register_module",
                                  "register_parameter") and isinstance(name, ast.Constant):  # fmt: skip
                    own.add(str(name.value))
    return own


def _called(call: ast.Call) -> str:
    f = call.func
    return f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def private_uses(trees: dict[Path, ast.Module]) -> list[str]:
    """``file:line name`` of every private attribute of another library used outside
    ``compat.py``."""
    own = _defined_names(trees)
    hits = []
    for path, tree in trees.items():
        if path == COMPAT:
            continue
        for n in ast.walk(tree):
            names: list[str] = []
            if isinstance(n, ast.Attribute):
                names = [n.attr]
            elif isinstance(n, ast.ImportFrom) and n.module and not n.module.startswith("imitrl"):
                names = [a.name for a in n.names] + n.module.split(".")
            elif isinstance(n, ast.Import):
                names = [
                    p for a in n.names if not a.name.startswith("imitrl") for p in a.name.split(".")
                ]
            elif (isinstance(n, ast.Call) and _called(n) in ("getattr", "hasattr", "setattr")
                  and len(n.args) > 1 and isinstance(n.args[1], ast.Constant)):  # fmt: skip
                names = [str(n.args[1].value)]
            hits += [f"{path.relative_to(SRC)}:{n.lineno} {x}" for x in names
                     if _private(x) and x not in own]  # fmt: skip
    return sorted(hits)


def _trees() -> dict[Path, ast.Module]:
    return {p: ast.parse(p.read_text(), str(p)) for p in sorted(SRC.rglob("*.py"))}


def test_private_attributes_of_other_libraries_only_in_compat():
    assert private_uses(_trees()) == []


def test_the_private_attribute_finder_finds_each_form(tmp_path):
    fake = SRC / "fake_module.py"  # a path inside the package, parsed, never written
    code = (
        "import torch\nfrom torch.nn.modules import _functions\nfrom torchrl import _utils\n"
        "def f(m):\n    m._forward_hooks\n    getattr(m, '_kwargs')\n    m.__dict__\n"
        "    m._mine = 1\n    return m._mine\n"
    )
    hits = private_uses({fake: ast.parse(code)})
    assert hits == [
        "fake_module.py:2 _functions",
        "fake_module.py:3 _utils",
        "fake_module.py:5 _forward_hooks",
        "fake_module.py:6 _kwargs",
    ]


def test_contributing_layout_table_is_the_tree():
    """CONTRIBUTING.md's layout table names every module of ``src/imitrl``, file for
    file, with its docstring's first line (``python tests/_layout.py`` refreshes it)."""
    from tests import _layout

    assert _layout.current() == _layout.table(), "stale layout table: run python tests/_layout.py"


def test_the_layout_table_sees_a_new_module(tmp_path, monkeypatch):
    from tests import _layout

    package = tmp_path / "imitrl"
    (package / "sub").mkdir(parents=True)
    (package / "__init__.py").write_text('"""top."""\n')
    (package / "sub" / "__init__.py").write_text('"""sub."""\n')
    monkeypatch.setattr(_layout, "PACKAGE", package)
    before = _layout.table()
    (package / "sub" / "new.py").write_text('"""A new module | with a pipe."""\n')
    after = _layout.table()
    assert after != before and "| `sub/new.py` | A new module \\| with a pipe. |" in after
    (package / "sub" / "bare.py").write_text("x = 1\n")
    with pytest.raises(ValueError, match="no module docstring"):
        _layout.table()


TESTS = Path(__file__).resolve().parent
TOP_LEVEL = {
    "test_architecture.py", "test_child.py", "test_readme_blocks.py", "test_readme_examples.py",
}  # fmt: skip
"""tests of the whole tree, of the README and of the tests' own child processes, beside the
mirror"""


def mirror_misses(tests: Path, src: Path, benchmarks: Path) -> list[str]:
    """Test files that do not mirror a module: ``tests/<package>/test_<module>[_<aspect>].py``
    for a module (or the package itself) of ``src/imitrl/<package>``, and
    ``tests/benchmarks/test_<script>[_<aspect>].py`` for a script of ``benchmarks/``."""
    misses = []
    for path in sorted(tests.rglob("test_*.py")):
        rel = path.relative_to(tests)
        if len(rel.parts) == 1 and rel.name in TOP_LEVEL:
            continue
        folder = benchmarks if rel.parts[0] == "benchmarks" else src.joinpath(*rel.parts[:-1])
        if rel.parts[0] == "benchmarks" and len(rel.parts) != 2:
            folder = benchmarks / "missing"
        names = {p.stem.lstrip("_") for p in folder.glob("*.py")} if folder.is_dir() else set()
        names.add(folder.name)
        stem = path.stem.removeprefix("test_")
        if not folder.is_dir() or not any(stem == n or stem.startswith(n + "_") for n in names):
            misses.append(rel.as_posix())
    return misses


def test_tests_mirror_the_source_tree():
    """Every test file sits in the folder of the package it tests, named after a module."""
    assert mirror_misses(TESTS, SRC, TESTS.parent / "benchmarks") == []


def test_the_mirror_check_finds_a_misplaced_test(tmp_path):
    src, tests, bench = tmp_path / "src", tmp_path / "tests", tmp_path / "bench"
    for d in (src / "data", tests / "data", tests / "benchmarks", bench):
        d.mkdir(parents=True)
    (src / "data" / "buffer.py").write_text("")
    (bench / "seam.py").write_text("")
    for name in ("data/test_buffer.py", "data/test_buffer_disk.py", "data/test_data.py",
                 "benchmarks/test_seam.py"):  # fmt: skip
        (tests / name).write_text("")
    assert mirror_misses(tests, src, bench) == []
    for name in ("data/test_bufferx.py", "test_newcomer.py", "envs/test_make.py"):
        (tests / name).parent.mkdir(exist_ok=True)
        (tests / name).write_text("")
    assert mirror_misses(tests, src, bench) == [
        "data/test_bufferx.py", "envs/test_make.py", "test_newcomer.py",
    ]  # fmt: skip


MACHINE_PATH = re.compile(r"/work/\w+|/home/\w+|/Users/\w+|/root(?:/)|[A-Z]:\\\\Users")
"""an absolute path of one machine: a work folder, a home, a venv"""


def machine_paths(root: Path, files: list[str]) -> list[str]:
    """``file:line`` of every committed text file line naming :data:`MACHINE_PATH`."""
    hits = []
    for name in files:
        try:
            text = (root / name).read_text()
        except (UnicodeDecodeError, FileNotFoundError, IsADirectoryError):
            continue  # binary files, and files deleted but not yet committed
        for number, line in enumerate(text.splitlines(), 1):
            if MACHINE_PATH.search(line):
                hits.append(f"{name}:{number}")
    return hits


def test_no_committed_file_names_a_machines_path():
    """Issue 44: committed text named a venv and a source folder by absolute path."""
    root = SRC.parents[1]
    listed = subprocess.run(
        ["git", "ls-files"], cwd=root, capture_output=True, text=True, check=False
    )
    if listed.returncode != 0:
        pytest.skip("not a git checkout")
    files = listed.stdout.splitlines()  # this file too: its examples are built, not written
    assert machine_paths(root, files) == []


def test_the_machine_path_finder_finds_one(tmp_path):
    venv = "/".join(["", "work", "some_venv", "bin", "python"])  # a machine's path, built
    (tmp_path / "a.md").write_text(f"ran with {venv}\nfine: --out /tmp/x\n")
    (tmp_path / "b.json").write_text('{"python": "imitrl_venv/bin/python"}\n')
    (tmp_path / "c.bin").write_bytes(b"\xff\xfe" + "/".join(["", "home", "x"]).encode())
    assert machine_paths(tmp_path, ["a.md", "b.json", "c.bin"]) == ["a.md:1"]


MAX_FILE_LINES = 550
"""most lines of a Python file (the style guide's "no file past ~500 lines")"""
MAX_FUNCTION_LINES = 80
"""most lines of a function's code, its docstring not counted ("no function past ~80")"""


def oversized(root: Path, folders: tuple[str, ...]) -> list[str]:
    """``path (lines)`` of every Python file under ``folders`` past :data:`MAX_FILE_LINES`,
    and ``path:function (lines)`` of every function past :data:`MAX_FUNCTION_LINES`."""
    found = []
    for path in sorted(p for f in folders for p in (root / f).rglob("*.py")):
        text = path.read_text()
        rel = path.relative_to(root).as_posix()
        if text.count("\n") > MAX_FILE_LINES:
            found.append(f"{rel} ({text.count(chr(10))} lines)")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                body = node.body
                if len(body) > 1 and ast.get_docstring(node, clean=False) is not None:
                    body = body[1:]  # the docstring is prose, not code
                lines = node.end_lineno - body[0].lineno + 1  # type: ignore[operator]
                if lines > MAX_FUNCTION_LINES:
                    found.append(f"{rel}:{node.name} ({lines} lines)")
    return found


def test_no_file_or_function_past_its_size():
    """The style guide's sizes, for the source, the benchmarks and the tests."""
    assert oversized(SRC.parents[1], ("src", "benchmarks", "tests")) == []


def test_the_size_check_finds_a_long_file_and_a_long_function(tmp_path):
    (tmp_path / "src").mkdir()
    doc = '    """' + "prose\n" * 200 + '    """\n'
    short = "def fine():\n" + doc + "    x = 1\n" * MAX_FUNCTION_LINES
    long = "def long():\n" + "    x = 1\n" * (MAX_FUNCTION_LINES + 1)
    (tmp_path / "src" / "a.py").write_text(short + long)
    (tmp_path / "src" / "b.py").write_text("x = 1\n" * (MAX_FILE_LINES + 1))
    assert oversized(tmp_path, ("src",)) == [  # fine() is long with its docstring alone
        f"src/a.py:long ({MAX_FUNCTION_LINES + 1} lines)",
        f"src/b.py ({MAX_FILE_LINES + 1} lines)",
    ]
