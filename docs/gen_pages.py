"""The site's generated pages, written at build time by mkdocs-gen-files (``mkdocs.yml``).

Nothing here is copied by hand, so no page can drift from what it documents:

* ``reference/<package>.md``: the API reference, one page per package (and top-level
  module) of ``imitrl``. Every name of the package's ``__all__``, then, module by module,
  every name of a public submodule's ``__all__`` that the package does not export,
  rendered from its docstring by mkdocstrings (``::: imitrl.<package>``). The package
  list is read from the source tree (griffe, no import) and ordered by the layers of
  ``[tool.importlinter]`` in ``pyproject.toml``, so a new package gets a page.
* ``benchmarks/<name>.md``: one page per section of ``benchmarks/README.md``, whose
  tables each script rewrites from its ``benchmarks/results/<name>.json``, with the
  section's figures from ``benchmarks/results/``.
* ``commands.md``: every subcommand of ``imitrl --help`` with an example and its whole
  ``--help`` (run now), and every extra of ``pyproject.toml`` with its install line.

``hooks.py`` imports this module for :func:`nav`, the order of the generated pages.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from functools import cache
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: the docs extra brings tomli
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src"
BENCH = ROOT / "benchmarks"


# ----------------------------------------------------------------------------- reference
@cache
def _package():
    """imitrl as griffe reads it (statically), its lazy exports as aliases."""
    import griffe

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from griffe_rest import LazyExports

    return griffe.load(
        "imitrl",
        search_paths=[str(SRC)],
        resolve_aliases=False,
        extensions=griffe.load_extensions(LazyExports),
    )


@cache
def layers() -> list[list[str]]:
    """The import-linter layers, highest first: ``[["__main__"], ["cli"], ["jobs",
    "experiments"], ...]``."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())
    (contract,) = (c for c in config["tool"]["importlinter"]["contracts"] if c["type"] == "layers")
    return [[p.strip() for p in layer.split("|")] for layer in contract["layers"]]


def packages() -> list[str]:
    """Every package and top-level module of imitrl with a page, in layer order."""
    found = {
        name
        for name, member in _package().members.items()
        if not member.is_alias and member.is_module and not name.startswith("_")
    }
    ordered = [name for layer in layers() for name in layer if name in found]
    missing = sorted(found - set(ordered))
    if missing:  # a package outside the contract: the architecture test fails too
        raise SystemExit(f"packages outside [tool.importlinter]'s layers: {missing}")
    return ordered


def _exports(module) -> list[str]:
    return [str(name) for name in (module.exports or [])]


def _follow(path: str) -> str:
    """The canonical path an imitrl alias path leads to (its own where it leaves the
    loaded tree)."""
    seen: set[str] = set()
    while path.startswith("imitrl.") and path not in seen:
        seen.add(path)
        obj = _package()
        for part in path.split(".")[1:]:
            if part not in obj.members:
                return path
            obj = obj.members[part]
        if not obj.is_alias:
            return obj.path
        path = obj.target_path
    return path


def _target(module, name: str) -> str:
    """The canonical path of ``module.name``, an alias followed to what it names."""
    member = module.members[name]
    return _follow(member.target_path) if member.is_alias else member.path


def sections(name: str) -> list[tuple[str, list[str]]]:
    """``(module path, names)`` to render on the page of package ``name``: the package's
    ``__all__``, then each public submodule's exports not already on the page."""
    out, seen = [], set()

    def walk(module) -> None:
        names = _exports(module)
        missing = [n for n in names if n not in module.members]
        if missing:  # a name in __all__ that the source does not define or import
            raise SystemExit(f"{module.path}.__all__ names what it lacks: {missing}")
        new = [n for n in names if _target(module, n) not in seen]
        seen.update(_target(module, n) for n in names)
        if new or module.path == f"imitrl.{name}":
            out.append((module.path, new))
        for sub in module.members.values():
            if not sub.is_alias and sub.is_module and not sub.name.startswith("_"):
                walk(sub)

    walk(_package().members[name])
    return out


def _reference_page(name: str) -> str:
    lines = [f"# `imitrl.{name}`", ""]
    for path, names in sections(name):
        top = path == f"imitrl.{name}"
        if not top:
            lines += [f"## `{path}`", ""]
        members = f"[{', '.join(names)}]" if names else "false"
        lines += [
            f"::: {path}",
            "    options:",
            f"      members: {members}",
            f"      heading_level: {2 if top else 3}",
            "",
        ]
    return "\n".join(lines)


def layers_table(link: str = "{name}.md") -> str:
    """The layer contract as a Markdown table: layer, packages (linked by ``link``) and
    the first paragraph of each package's docstring."""
    lines = ["| layer | package | what it holds |", "|---|---|---|"]
    pkg = _package()
    shown = [[n for n in layer if n in pkg.members and not n.startswith("_")] for layer in layers()]
    for i, layer in enumerate([names for names in shown if names], 1):  # __main__ has no page
        for name in layer:
            doc = pkg.members[name].docstring
            first = doc.value.split("\n\n")[0].replace("\n", " ") if doc else ""
            first = re.sub(r":\w+:`~?([^`]+)`", r"`\1`", first).replace("``", "`")
            lines.append(f"| {i} | [imitrl.{name}]({link.format(name=name)}) | {first} |")
    return "\n".join(lines) + "\n"


def _reference_index() -> str:
    lines = [
        "# API reference",
        "",
        "Every public name of imitrl, from its docstring: each package's `__all__`, then the",
        "names its public modules export beyond it. Packages are listed by layer, highest",
        "first: a package imports only the packages below it (the import-linter contract",
        "in `pyproject.toml`; see [Design notes](../design.md#layers)).",
        "",
    ]
    return "\n".join(lines) + layers_table()


# ---------------------------------------------------------------------------- benchmarks
HEADING = re.compile(r"^## (?P<title>.+)$", re.M)


def benchmark_sections() -> list[tuple[str, str, str]]:
    """``(slug, title, body)`` of every ``##`` section of ``benchmarks/README.md``; the
    slug is the section's first script (``loss_functions``)."""
    text = (BENCH / "README.md").read_text()
    heads = list(HEADING.finditer(text))
    out = []
    for head, nxt in zip(heads, [*heads[1:], None]):
        body = text[head.end() : nxt.start() if nxt else len(text)].strip("\n")
        scripts = re.findall(r"`(\w+)\.py`", head["title"])
        blocks = re.findall(r"<!-- BEGIN (\S+) -->", body)
        slug = (scripts or blocks or [re.sub(r"\W+", "_", head["title"]).strip("_").lower()])[0]
        out.append((slug, head["title"], body))
    return out


def _figures(body: str, names: list[str]) -> tuple[list[str], list[str]]:
    """The figures the section shows, and those under results/ named after one of its
    blocks that it does not show."""
    shown = re.findall(r"\]\((results/[^)]+\.(?:png|svg))\)", body)
    extra = [
        f"results/{p.name}"
        for n in names
        for p in sorted((BENCH / "results").glob(f"{n}.png"))
        if f"results/{p.name}" not in shown
    ]
    return shown, extra


def _benchmark_page(slug: str, title: str, body: str) -> tuple[str, list[str]]:
    blocks = re.findall(r"<!-- BEGIN (\S+) -->", body)
    shown, extra = _figures(body, blocks)
    body = re.sub(r"^(#+) ", lambda m: m.group(1)[1:] + " ", body, flags=re.M)
    lines = [f"# {title}", "", body, ""]
    for fig in extra:
        lines += [f"![{Path(fig).stem}]({fig})", ""]
    scripts = re.findall(r"`(\w+)\.py`", title) or [slug]
    results = [
        f"`benchmarks/results/{b}.json`" for b in blocks if (BENCH / f"results/{b}.json").is_file()
    ]
    lines += [
        "---",
        "",
        "The tables and figures on this page are the blocks that "
        + ", ".join(f"`benchmarks/{s}.py`" for s in scripts)
        + " wrote into `benchmarks/README.md` from "
        + (", ".join(results) if results else "its results")
        + "; the page is generated from that file at every build. Re-run: "
        + ", ".join(f"`imitrl bench {s}`" for s in scripts)
        + " (`--quick` for the smoke run the tests make).",
        "",
    ]
    return "\n".join(lines), shown + extra


def _benchmarks_index(sections: list[tuple[str, str, str]]) -> str:
    text = (BENCH / "README.md").read_text()
    preamble = text[: HEADING.search(text).start()].split("\n", 1)[1].strip()
    lines = ["# Benchmarks", "", preamble, "", "| benchmark | script | tables |", "|---|---|---|"]
    for slug, title, body in sections:
        name = re.sub(r"\s*\(`[^)]*`\)\s*$", "", title)
        scripts = ", ".join(f"`{s}.py`" for s in re.findall(r"`(\w+)\.py`", title))
        blocks = ", ".join(f"`{b}`" for b in re.findall(r"<!-- BEGIN (\S+) -->", body))
        lines.append(f"| [{name}]({slug}.md) | {scripts} | {blocks} |")
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------ commands
EXAMPLES = {
    "bc": "imitrl bc --env CartPole-v1 --demos 2 --out results/bc",
    "dagger": "imitrl dagger --env Pendulum-v1 --expert pendulum --demos 1 --rounds 5 --out results/dagger",
    "gail": "imitrl gail --env Acrobot-v1 --demos 10 --out results/gail",
    "airl": "imitrl airl --env Pendulum-v1 --demos 10 --anneal-lr --out results/airl",
    "eval": "imitrl eval --checkpoint results/dagger --eval-episodes 20",
    "compare": "imitrl compare --a results/bc --b results/dagger --env Pendulum-v1 --sequential --return-range=-2000,0",
    "bench": "imitrl bench loss_functions --quick",
    "frozenlake": "imitrl frozenlake --out results/frozenlake",
}
"""one real command line per subcommand (a new subcommand without one fails the build)"""

EXTRAS = {
    "datasets": "read and write LeRobot and Minari datasets (pyarrow, h5py) and camera videos (PyAV)",
    "hub": "download LeRobot datasets from the Hugging Face Hub (`huggingface_hub`)",
    "distributed": "DAgger's relabel rounds on Ray workers (`--workers N`)",
    "mujoco": "the MuJoCo envs (InvertedPendulum, Reacher, ...) and their LQR experts",
    "metaworld": "Meta-World v3's 50 manipulation tasks and their scripted experts",
    "box2d": "LunarLander and the other Box2D envs",
    "dev": "the tests, ruff, mypy and the layer contract (`.ci/run`)",
    "docs": "this site: `.venv/bin/mkdocs build --strict`",
}
"""what each extra of pyproject.toml brings (a new extra without a line fails the build)"""


def _help(command: str) -> str:
    env = {**os.environ, "COLUMNS": "100", "PYTHONPATH": str(SRC)}
    done = subprocess.run(
        [sys.executable, "-m", "imitrl", command, "--help"],
        capture_output=True, text=True, env=env, cwd=ROOT, timeout=300,
    )  # fmt: skip
    if done.returncode != 0:
        raise SystemExit(f"imitrl {command} --help failed: {done.stderr[-2000:]}")
    return done.stdout


def _commands_page() -> str:
    sys.path.insert(0, str(SRC))
    from imitrl.cli import COMMANDS

    missing = sorted(set(COMMANDS) - set(EXAMPLES))
    if missing:
        raise SystemExit(f"docs/gen_pages.py: no example for imitrl {missing}")
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"][
        "optional-dependencies"
    ]
    undocumented = sorted(set(extras) - set(EXTRAS))
    if undocumented:
        raise SystemExit(f"docs/gen_pages.py: extras without a line: {undocumented}")
    from imitrl.cli import build_parser

    for name, example in EXAMPLES.items():  # every flag of every example exists
        argv = example.split()[1:]
        try:
            build_parser(flags_for=[name]).parse_args(argv)
        except SystemExit as error:
            raise SystemExit(f"docs/gen_pages.py: `{example}` does not parse") from error
    with ThreadPoolExecutor(4) as pool:
        helps = dict(zip(COMMANDS, pool.map(_help, COMMANDS)))
    lines = [
        "# Commands and extras",
        "",
        "`imitrl --help` lists the commands. Each is a function of one frozen config",
        "dataclass whose fields are its flags (`imitrl.jobs`: `run_bc(BCJob(...))`, ...), and",
        "every flag's help is its field's docstring, with its range. Results go to stdout,",
        "progress bars to stderr; bad input is one line and exit status 2. This page is",
        "generated at every build from the parser itself.",
        "",
        "| command | what it does | for example |",
        "|---|---|---|",
    ]
    for name, command in COMMANDS.items():
        summary = command.help.replace("|", "\\|")
        lines.append(f"| [`imitrl {name}`](#imitrl-{name}) | {summary} | `{EXAMPLES[name]}` |")
    lines += [
        "",
        "## Extras",
        "",
        "The base install (`pip install -e .`) runs every command on gymnasium's own envs.",
        "Each extra adds one capability; a command that needs a missing one says which.",
        "Install `torch==2.13.0` first (see [Home](index.md#set-up)).",
        "",
        "| extra | what it adds | install | packages |",
        "|---|---|---|---|",
    ]
    for extra, deps in extras.items():
        pkgs = ", ".join(f"`{d}`" for d in deps)
        lines.append(f'| `{extra}` | {EXTRAS[extra]} | `pip install -e ".[{extra}]"` | {pkgs} |')
    lines += ["", "## Every flag", ""]
    for name, text in helps.items():
        lines += [f"### `imitrl {name}`", "", "```text", text.rstrip(), "```", ""]
    return "\n".join(lines)


# ----------------------------------------------------------------------------------- nav
def nav() -> dict[str, list]:
    """The generated pages in their order, for ``hooks.py`` to place in the nav."""
    return {
        "reference": [{"Overview": "reference/index.md"}]
        + [{f"imitrl.{n}": f"reference/{n}.md"} for n in packages()],
        "benchmarks": [{"Overview": "benchmarks/index.md"}]
        + [
            {re.sub(r"\s*\(`[^)]*`\)\s*$", "", title): f"benchmarks/{slug}.md"}
            for slug, title, _ in benchmark_sections()
        ],
    }


def generate() -> None:
    import mkdocs_gen_files

    with mkdocs_gen_files.open("reference/index.md", "w") as f:
        f.write(_reference_index())
    for name in packages():
        with mkdocs_gen_files.open(f"reference/{name}.md", "w") as f:
            f.write(_reference_page(name))
        mkdocs_gen_files.set_edit_path(f"reference/{name}.md", f"../src/imitrl/{name}")
    found = benchmark_sections()
    with mkdocs_gen_files.open("benchmarks/index.md", "w") as f:
        f.write(_benchmarks_index(found))
    for slug, title, body in found:
        page, figures = _benchmark_page(slug, title, body)
        with mkdocs_gen_files.open(f"benchmarks/{slug}.md", "w") as f:
            f.write(page)
        for fig in figures:
            with mkdocs_gen_files.open(f"benchmarks/{fig}", "wb") as f:
                f.write((BENCH / fig).read_bytes())
    with mkdocs_gen_files.open("commands.md", "w") as f:
        f.write(_commands_page())


if __name__ in ("__main__", "<run_path>"):
    generate()
