"""A griffe extension: imitrl's reST-flavoured docstrings rendered as Markdown.

imitrl's docstrings are Google style (``Args:``, ``Returns:``) written with reST's inline
markup: double-backtick literals (Markdown reads them as code already), Sphinx roles
(``:func:`~imitrl.x.y```, ``:class:`Learner```) and a few simple tables (``=== ===``
borders). This extension rewrites, once the package is loaded:

* every role into a link to the object it names (an ``<autoref ... optional>`` tag that
  mkdocs-autorefs resolves on the rendered site), resolved as Python would resolve the
  name from the docstring's scope (its module's imports included). A name of another
  library (torch, TorchRL, ...) stays code; a name that resolves to nothing is logged as
  a warning, which fails ``mkdocs build --strict``;
* every simple table into a Markdown table.
"""

from __future__ import annotations

import ast
import html
import logging
import re
from pathlib import Path

import griffe

LOG = logging.getLogger("mkdocs.plugins.imitrl_docs")
"""under ``mkdocs.``: a warning here counts in ``--strict``"""

ROLE = re.compile(
    r":(?:py:)?(?P<role>func|class|mod|data|meth|attr|obj|exc|const|ref|term):"
    r"`(?P<body>[^`]+)`"
)
BORDER = re.compile(r"^(?P<indent> *)=+( +=+)+ *$")
EXTERNAL = ("torch", "torchrl", "tensordict", "gymnasium", "numpy", "np", "ray", "pyarrow",
            "h5py", "av", "metaworld", "mujoco", "minari", "lerobot", "huggingface_hub",
            "matplotlib", "tqdm", "argparse", "collections", "contextlib", "dataclasses",
            "os", "pathlib", "typing", "concurrent", "multiprocessing", "json", "io",
            "subprocess", "functools", "itertools", "logging", "math", "re", "sys", "tempfile",
            "threading", "warnings", "gc", "enum", "abc", "errno", "fcntl", "signal", "stat",
            "time", "zlib", "hashlib", "shutil", "socket", "ssl", "http", "urllib", "builtins",
            "inspect", "importlib", "struct", "uuid", "weakref", "copy", "random", "heapq",
            "bisect", "operator", "string", "textwrap", "queue", "select", "asyncio", "ctypes",
            "mmap", "array", "tomllib", "zipfile", "gzip", "email")  # fmt: skip
"""first components of names that belong to another library or to Python"""


def _member(obj: griffe.Object | griffe.Alias, parts: list[str]) -> griffe.Object | None:
    """``obj.parts[0].parts[1]...`` following aliases; None when a part is missing or an
    alias leads out of the loaded packages."""
    for part in parts:
        try:
            if obj.is_alias:
                obj = obj.final_target  # type: ignore[union-attr]
            obj = obj.members[part]
        except (KeyError, griffe.AliasResolutionError, griffe.CyclicAliasError):
            return None
    try:
        return obj.final_target if obj.is_alias else obj  # type: ignore[union-attr,return-value]
    except (griffe.AliasResolutionError, griffe.CyclicAliasError):
        return None


def _external_alias(scope: griffe.Object, first: str) -> bool:
    """``first`` is a name imported into ``scope`` (or a parent) from outside imitrl."""
    while scope is not None:
        member = scope.members.get(first)
        if member is not None:
            return member.is_alias and not member.target_path.startswith("imitrl")
        scope = scope.parent  # type: ignore[assignment]
    return False


def _inherits_from_outside(scope: griffe.Object | None) -> bool:
    """``scope`` is, or is inside, a class with a base class from another library."""
    while scope is not None:
        if scope.is_class and any(
            not str(getattr(b, "canonical_path", b)).startswith("imitrl")
            for b in scope.bases  # type: ignore[attr-defined]
        ):
            return True
        scope = scope.parent
    return False


class Resolver:
    """Names in docstrings to the objects they mean, within one loaded package."""

    def __init__(self, package: griffe.Module) -> None:
        self.package = package
        self.by_name: dict[str, list[griffe.Object]] = {}
        self._index(package)

    def _index(self, obj: griffe.Object) -> None:
        for member in obj.members.values():
            if member.is_alias:
                continue
            self.by_name.setdefault(member.name, []).append(member)
            if member.is_module or member.is_class:
                self._index(member)

    def resolve(self, scope: griffe.Object, name: str) -> griffe.Object | str | None:
        """The object ``name`` means from ``scope``; ``"external"`` for another library's
        name; None when nothing matches."""
        if name.startswith("."):  # relative to the docstring's package, as an import
            dots = len(name) - len(name.lstrip("."))
            base: griffe.Object | None = scope.module
            if not scope.module.is_init_module:
                base = base.parent  # type: ignore[union-attr]
            for _ in range(dots - 1):
                base = base.parent if base is not None else None
            return _member(base, name.lstrip(".").split(".")) if base is not None else None
        parts = name.split(".")
        if parts[0] == self.package.name:
            found = _member(self.package, parts[1:])
            if found is None:  # a path that moved: the one object of that name, if unique
                found = self.unique(name.rsplit(".", 1)[-1])
                if found is not None:
                    LOG.info("%s: %s is now %s", scope.path, name, found.path)
            return found
        if parts[0] in EXTERNAL or _external_alias(scope, parts[0]):
            return "external"
        at: griffe.Object | None = scope
        while at is not None:  # the docstring's scope, then each enclosing one
            if parts[0] in at.members:
                return _member(at, parts)
            at = at.parent
        # a bare name used across modules (``:func:`fit_bc``` in prose): unique in the package
        found = self.unique(name)
        if found is None and _inherits_from_outside(scope):
            return "external"  # a method a class inherits from TorchRL, torch, gymnasium
        return found

    def unique(self, name: str) -> griffe.Object | None:
        """The one object whose path ends with ``name``, if there is exactly one."""
        found = [f for f in self.by_name.get(name.rsplit(".", 1)[-1], [])
                 if f.path.endswith("." + name)]  # fmt: skip
        return found[0] if len(found) == 1 else None


def _link(resolver: Resolver, scope: griffe.Object, role: str, body: str) -> str:
    """One role as Markdown: a link where the name resolves, code where it is not imitrl's."""
    text, _, target = body.partition(" <")
    if target:
        target, shown = target.rstrip(">").strip(), text.strip()
    else:
        target = text.strip()
        shown = target.lstrip("~").split(".")[-1] if target.startswith("~") else target
        target = target.lstrip("~")
    target = re.sub(r"\s+", "", target).removesuffix("()")
    code = f"<code>{html.escape(shown)}</code>"
    if role in ("ref", "term"):
        return code
    found = resolver.resolve(scope, target)
    if found == "external":
        return code
    if found is None:
        LOG.warning(
            "%s: :%s:`%s` names nothing in %s", scope.path, role, body, resolver.package.name
        )
        return code
    return f'<autoref identifier="{found.path}" optional>{code}</autoref>'  # type: ignore[union-attr]


def _cells(line: str, starts: list[int]) -> list[str]:
    """A table row cut at the columns' starts; a cell that runs past its column's border
    pushes the cut to the next space."""
    cuts, at = [], 0
    for start in starts[1:]:
        cut = max(start, at)
        while cut < len(line) and cut > 0 and line[cut - 1] != " ":
            cut += 1
        cuts.append(cut)
        at = cut
    bounds = [0, *cuts, len(line)]
    return [line[a:b].strip() for a, b in zip(bounds, bounds[1:])]


def _join(a: str, b: str) -> str:
    if not a or not b:
        return a or b
    return a + b if a.endswith(("-", "_")) else f"{a} {b}"


def _rows(lines: list[str], indent: int, starts: list[int]) -> list[list[str]]:
    """The rows of a table's lines between two borders: a line whose first cell is empty
    (or that closes a literal its previous line opened) continues the row above."""
    rows: list[list[str]] = []
    for line in lines:
        if not line.strip():
            continue
        cells = _cells(line[indent:], starts)
        if rows and (not cells[0] or rows[-1][0].count("`") % 2 == 1):
            rows[-1] = [_join(a, b) for a, b in zip(rows[-1], cells)]
        else:
            rows.append(cells)
    return rows


def _table(lines: list[str], indent: int) -> list[str]:
    """A reST simple table (its lines, borders included) as a Markdown table."""
    starts = [m.start() for m in re.finditer(r"=+", lines[0][indent:])]
    groups: list[list[str]] = [[]]
    for line in lines[1:-1]:
        if BORDER.match(line):
            groups.append([])
        else:
            groups[-1].append(line)
    if len(groups) == 2:  # a header, then the body
        header = [" ".join(c for c in col if c) for col in zip(*_rows(groups[0], indent, starts))]
        rows = _rows(groups[1], indent, starts)
    else:
        rows = _rows(groups[0], indent, starts)
        header, rows = rows[0], rows[1:]
    cell = lambda c: c.replace("|", "\\|")  # noqa: E731
    out = ["| " + " | ".join(map(cell, header)) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(map(cell, row)) + " |" for row in rows]
    return [" " * indent + line for line in out]


def tables(text: str) -> str:
    """Every simple table of ``text`` as a Markdown table, a blank line either side."""
    lines, out, i = text.split("\n"), [], 0
    while i < len(lines):
        m = BORDER.match(lines[i])
        if not m:
            out.append(lines[i])
            i += 1
            continue
        indent, j, borders = len(m.group("indent")), i + 1, 1
        while j < len(lines):  # three borders with a header, two without
            if BORDER.match(lines[j]):
                borders += 1
                if borders == 3 or not (j + 1 < len(lines) and lines[j + 1].strip()):
                    break
            j += 1
        if out and out[-1].strip():
            out.append("")
        out += _table(lines[i : j + 1], indent)
        out.append("")
        i = j + 1
    return "\n".join(out)


SECTION = re.compile(
    r"^(?P<indent> *)(Args|Arguments|Parameters|Keyword Args|Other Parameters):\s*$"
)
ITEM = re.compile(r"^(?P<names>\*{0,2}\w+(?:\s*,\s*\*{0,2}\w+)*)\s*(?:\([^)]*\))?\s*:(\s|$)")


def parameters(text: str) -> str:
    """Google ``Args:`` sections as griffe reads them: ``a, b: text`` (one description for
    several parameters) becomes one item per name; a line at an item's indentation that
    is not ``name: text`` continues the item above."""
    lines, out, i = text.split("\n"), [], 0
    while i < len(lines):
        out.append(lines[i])
        head = SECTION.match(lines[i])
        i += 1
        if not head:
            continue
        indent = None
        items: list[list[str]] = []
        while i < len(lines):
            line = lines[i]
            depth = len(line) - len(line.lstrip())
            if line.strip() and depth <= len(head["indent"]):
                break
            if not line.strip() and (i + 1 == len(lines) or (
                lines[i + 1].strip() and len(lines[i + 1]) - len(lines[i + 1].lstrip())
                <= len(head["indent"])
            )):  # fmt: skip
                break
            indent = depth if indent is None and line.strip() else indent
            if line.strip() and depth == indent and ITEM.match(line.strip()):
                items.append([line])
            elif line.strip() and depth == indent and items:
                items[-1].append(" " * 4 + line)  # not an item: it continues the one above
            elif items:
                items[-1].append(line)
            else:
                items.append([line])
            i += 1
        for item in items:
            first = item[0].strip()
            match = ITEM.match(first)
            names = [n.strip() for n in match["names"].split(",")] if match else []
            if len(names) < 2:
                out += item
                continue
            rest = first[match.end("names") :]
            for name in names:
                out += [" " * (indent or 0) + name + rest, *item[1:]]
    return "\n".join(out)


def markdown(resolver: Resolver, scope: griffe.Object, text: str) -> str:
    """A docstring's text as Markdown: parameter lists, simple tables, then roles."""
    text = tables(parameters(text))
    return ROLE.sub(lambda m: _link(resolver, scope, m["role"], m["body"]), text)


class ReSTRoles(griffe.Extension):
    """Rewrite every docstring of a loaded package (see the module docstring)."""

    def on_package(self, *, pkg: griffe.Module, loader: griffe.GriffeLoader, **kwargs) -> None:
        resolver = Resolver(pkg)
        seen: set[int] = set()

        def walk(obj: griffe.Object) -> None:
            if id(obj) in seen:
                return
            seen.add(id(obj))
            if obj.docstring is not None:
                obj.docstring.value = markdown(resolver, obj, obj.docstring.value)
            for member in obj.members.values():
                if not member.is_alias:
                    walk(member)

        walk(pkg)


class LazyExports(griffe.Extension):
    """Module-level names griffe's static reading misses, so that the API reference has
    every name of an ``__all__``: the names a package exports lazily (``__getattr__,
    __dir__ = _lazy_exports(__name__, {name: module, ...})``, PEP 562), as the aliases an
    eager ``from module import name`` would make, and the names a tuple assignment binds
    (``A, B = 1, 2``)."""

    def on_package(self, *, pkg: griffe.Module, loader: griffe.GriffeLoader, **kwargs) -> None:
        def walk(module: griffe.Module) -> None:
            for exports in _lazy_maps(module):
                for name, source in exports.items():
                    if name not in module.members:
                        alias = griffe.Alias(name, f"{source}.{name}", parent=module)
                        module.set_member(name, alias)
            for name, node, value in _tuple_assignments(module):
                if name not in module.members:
                    attribute = griffe.Attribute(
                        name, lineno=node.lineno, endlineno=node.end_lineno, value=value
                    )
                    module.set_member(name, attribute)
            for member in list(module.members.values()):
                if not member.is_alias and member.is_module:
                    walk(member)  # type: ignore[arg-type]

        walk(pkg)


def _lazy_maps(module: griffe.Module) -> list[dict[str, str]]:
    """The ``{name: module}`` literals given to ``_lazy_exports`` in ``module``'s source."""
    path = module.filepath
    if not isinstance(path, Path) or path.suffix != ".py":
        return []
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if (
            isinstance(node, ast.Call)
            and getattr(node.func, "id", getattr(node.func, "attr", None)) == "_lazy_exports"
            and len(node.args) == 2
            and isinstance(node.args[1], ast.Dict)
        ):
            found.append(
                {
                    k.value: v.value
                    for k, v in zip(node.args[1].keys, node.args[1].values)
                    if isinstance(k, ast.Constant) and isinstance(v, ast.Constant)
                }
            )
    return found


def _tuple_assignments(module: griffe.Module) -> list[tuple[str, ast.Assign, str]]:
    """``(name, statement, value)`` for each name of a module-level ``A, B = x, y``."""
    path = module.filepath
    if not isinstance(path, Path) or path.suffix != ".py":
        return []
    out = []
    for node in ast.parse(path.read_text()).body:
        if (
            isinstance(node, ast.Assign)
            and len(node.targets) == 1
            and isinstance(node.targets[0], ast.Tuple)
            and isinstance(node.value, ast.Tuple)
            and len(node.targets[0].elts) == len(node.value.elts)
        ):
            for target, value in zip(node.targets[0].elts, node.value.elts):
                if isinstance(target, ast.Name):
                    out.append((target.id, node, ast.unparse(value)))
    return out
