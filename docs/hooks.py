"""MkDocs hooks (``mkdocs.yml``: ``hooks:``): the generated pages in the nav, and the
tutorials' code run where it cannot touch the checkout.

* :func:`on_config` expands the ``Benchmarks`` and ``API reference`` entries of the nav
  into every page ``gen_pages.py`` writes, in its order (a new package or benchmark
  appears without editing ``mkdocs.yml``).
* Every ``imitrl.<package>.x`` named in backticks on a written page (not a generated
  one) must name an object of the package: it becomes a link to its API entry, and a name that
  resolves to nothing is a warning (so ``--strict`` fails on a stale name).
* A page whose code blocks markdown-exec runs (``exec="on"``) is rendered inside a fresh
  temporary folder, its own, so the files the code writes (datasets, buffers) land
  there; torch runs on one thread, as the tests run the same blocks.
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")  # the shell blocks' commands, as the tests run
os.environ.setdefault("MPLBACKEND", "Agg")
# the shell blocks run `imitrl ...`: the one installed beside the Python running mkdocs
os.environ["PATH"] = os.pathsep.join([str(Path(sys.executable).parent), os.environ["PATH"]])

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import gen_pages  # noqa: E402

_state: dict = {}
LOG = logging.getLogger("mkdocs.plugins.imitrl_docs")
NAME = re.compile(r"(?<!`)`(imitrl(?:\.\w+)+)(\(\))?`(?!`)")
FENCE = re.compile(r"^(```|~~~).*?^\1", re.M | re.S)


def _run_sh(code: str, returncode: int | None = None, **kwargs) -> str:
    """markdown-exec's shell runner, but a page shows the command's standard output (its
    report) alone: standard error (progress bars) joins it only when the command fails."""
    from markdown_exec._internal.formatters.base import ExecutionError
    from markdown_exec._internal.rendering import code_block

    done = subprocess.run(["sh", "-c", code], capture_output=True, text=True, check=False)
    if done.returncode != returncode:
        raise ExecutionError(code_block("sh", done.stdout + done.stderr), done.returncode)
    return done.stdout


def on_config(config, **kwargs):
    from markdown_exec._internal.formatters import console, sh

    console._run_sh = sh._run_sh = _run_sh  # markdown-exec 1.12.6 (pinned by the docs extra)
    generated = gen_pages.nav()
    nav = []
    for entry in config.nav or []:
        ((title, target),) = entry.items() if isinstance(entry, dict) else ((None, entry),)
        if target == "benchmarks/index.md":
            entry = {title: ["benchmarks/index.md", *generated["benchmarks"][1:]]}
        elif target == "reference/index.md":
            entry = {title: ["reference/index.md", *generated["reference"][1:]]}
        nav.append(entry)
    config.nav = nav
    return config


def on_pre_build(config, **kwargs):
    _state["root"] = Path(tempfile.mkdtemp(prefix="imitrl-docs-"))
    _state["cwd"] = os.getcwd()


def _resolve(path: str):
    """The object an ``imitrl.x.y`` path names (aliases followed), or None."""
    obj = gen_pages._package()
    for part in path.split(".")[1:]:
        try:
            obj = obj.final_target if obj.is_alias else obj
            obj = obj.members[part]
        except Exception:
            return None
    try:
        return obj.final_target if obj.is_alias else obj
    except Exception:
        return None


def _link_names(markdown: str, page) -> str:
    """``imitrl.x.y`` in backticks -> a link to its API entry (outside code blocks)."""

    top = gen_pages._package().members

    def link(match: re.Match) -> str:
        if match.group(1).split(".")[1] not in top:
            return match.group(0)  # not a Python name: a column (``imitrl.round``), a file
        found = _resolve(match.group(1))
        if found is None:
            LOG.warning("%s: `%s` names nothing in imitrl", page.file.src_uri, match.group(1))
            return match.group(0)
        return (
            f'<autoref identifier="{found.path}" optional><code>{match.group(1)}'
            f"{match.group(2) or ''}</code></autoref>"
        )

    out, at = [], 0
    for fence in FENCE.finditer(markdown):
        out += [NAME.sub(link, markdown[at : fence.start()]), fence.group(0)]
        at = fence.end()
    out.append(NAME.sub(link, markdown[at:]))
    return "".join(out)


SNIPPET = re.compile(r'^--8<-- "([^"]+)"$', re.MULTILINE)


def _expanded(markdown: str, config) -> str:
    """``markdown`` with each whole-file snippet line (``--8<-- "CONTRIBUTING.md"``) replaced
    by the file, as pymdownx.snippets would: so that the names of an included file are
    checked and linked too (they were not: snippets expand after this hook runs)."""
    root = Path(config.config_file_path).parent
    return SNIPPET.sub(lambda m: (root / m.group(1)).read_text(), markdown)


def on_page_markdown(markdown, page, config, files, **kwargs):
    if (Path(config.docs_dir) / page.file.src_uri).is_file():  # written, not generated
        markdown = _link_names(_expanded(markdown, config), page)
    if 'exec="on"' in markdown or "exec='on'" in markdown:
        import torch

        torch.set_num_threads(1)
        folder = _state["root"] / page.file.src_uri.replace("/", "_").removesuffix(".md")
        folder.mkdir(parents=True, exist_ok=True)
        os.chdir(folder)
    return markdown


def on_page_content(html, page, config, files, **kwargs):
    os.chdir(_state["cwd"])
    return html


def on_build_error(error, **kwargs):
    if "cwd" in _state:
        os.chdir(_state["cwd"])


def on_post_build(config, **kwargs):
    os.chdir(_state["cwd"])
    shutil.rmtree(_state.pop("root"), ignore_errors=True)
