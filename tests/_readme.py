"""Run the named code blocks of the README and of the documentation site as tests:
extract, exec, compare what they print.

A block is named by ``<!-- BEGIN name -->`` ... ``<!-- END name -->`` in ``README.md``
or in a page under ``docs/`` (a tutorial), exactly once across them. :func:`run` runs a
block twice in one folder, as a user who runs it again would: first in a fresh
interpreter, whose whole standard output (C libraries' included) must be exactly the
block's documented output, the ``# ...`` comment lines after each ``print``; then in
this process, returning its namespace for further checks.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"


def pages() -> list[Path]:
    """The README and every written page of the documentation site."""
    return [README, *sorted(DOCS.rglob("*.md"))]


def page_of(name: str) -> Path:
    """The one page that holds the block ``name``."""
    found = [p for p in pages() if f"<!-- BEGIN {name} -->" in p.read_text()]
    assert len(found) == 1, f"the {name} block is in {len(found)} pages: {found}"
    return found[0]


def block(name: str) -> str:
    """The python code between ``<!-- BEGIN name -->`` and ``<!-- END name -->`` (its
    fence may carry markdown-exec's options: ``python exec="on" ...``)."""
    text = page_of(name).read_text()
    found = re.search(rf"<!-- BEGIN {name} -->(.*?)<!-- END {name} -->", text, flags=re.S)
    assert found is not None, f"no page holds the {name} block"
    code = re.search(r"```python[^\n]*\n(.*?)```", found.group(1), flags=re.S)
    assert code is not None, f"the {name} block has no python code"
    return code.group(1)


def documented_output(code: str) -> list[str]:
    """The lines the block says it prints: the ``# ...`` comment lines right after a line
    that calls ``print``."""
    out, after_print = [], False
    for line in code.splitlines():
        text = line.strip()
        if after_print and text.startswith("# "):
            out.append(text[2:])
            continue
        after_print = "print(" in text
    return out


_TOLERANCE = re.compile(r"-?[0-9.]+ \(±([0-9.]+)")
"""``71.2 (±0.3 on another CPU kind ...)``: a number documented with the spread it may
show across machines (a CNN fit's float sums follow the CPU's vector width)"""


def _tolerance(documented: str) -> float:
    found = _TOLERANCE.match(documented)
    return float(found.group(1)) if found else 0.0


def _same_line(printed: str, documented: str) -> bool:
    """A documented line may annotate its number (``500.0 (the expert's return)``), and
    give the spread it may show on another machine (``71.2 (±0.3 ...)``)."""
    number = re.match(r"-?[0-9.]+(?=\s|$)", documented)
    if number and documented != printed:
        try:
            return abs(float(printed) - float(number.group(0))) <= _tolerance(documented)
        except ValueError:
            return False
    return printed == documented


def run_fresh(name: str, cwd: Path) -> list[str]:
    """Run the block in a new interpreter in ``cwd``; its stdout lines, checked against
    the documented output (nothing printed before, after or between)."""
    src = next(p for p in sys.path if (Path(p) / "imitrl").is_dir())
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([src, os.environ.get("PYTHONPATH", "")])}
    code = "import torch; torch.set_num_threads(1)\n" + block(name)
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=cwd, capture_output=True, text=True, env=env,
        timeout=900,
    )  # fmt: skip
    assert done.returncode == 0, f"{name}: {done.stderr[-3000:]}"
    printed = done.stdout.splitlines()
    documented = documented_output(block(name))
    assert len(printed) == len(documented) and all(
        _same_line(p, d) for p, d in zip(printed, documented)
    ), f"{name} printed {printed}, {page_of(name).name} documents {documented}"
    return printed


def expected_numbers(code: str) -> list[float]:
    """The numbers the block promises, one ``# <number>`` comment line after each print."""
    return [float(m.group(1)) for m in re.finditer(r"^# (-?[0-9.]+)", code, flags=re.M)]


def same_numbers(code: str, printed: list[str]) -> bool:
    """``printed`` are the block's promised numbers, each within its documented spread."""
    lines = [m.group(1) for m in re.finditer(r"^# (-?[0-9.]+.*)$", code, flags=re.M)]
    return len(lines) == len(printed) and all(
        _same_line(p, d) for p, d in zip(printed, lines, strict=True)
    )


def run(name: str, cwd: Path) -> tuple[dict, list[str]]:
    """Run the block in a fresh interpreter (:func:`run_fresh`), then exec it again in
    ``cwd`` in this process; returns the second run's namespace and printed words."""
    run_fresh(name, cwd)
    code = block(name)
    namespace: dict = {"__name__": f"readme_{name}"}
    out = io.StringIO()
    here = os.getcwd()
    os.chdir(cwd)
    # torchrl logs INFO lines to stdout (storage initialisation): only the block's prints
    # count. Imported first: torchrl sets its logger's level when imported.
    import torchrl  # noqa: F401

    log = logging.getLogger("torchrl")
    level = log.level
    log.setLevel(logging.WARNING)
    try:
        with contextlib.redirect_stdout(out):
            exec(compile(code, f"{page_of(name).name}:{name}", "exec"), namespace)
    finally:
        os.chdir(here)
        log.setLevel(level)
    return namespace, out.getvalue().split()


def assert_prints_what_it_promises(name: str, printed: list[str]) -> None:
    code = block(name)
    assert same_numbers(code, printed), (
        f"{name}: printed {printed}, {page_of(name).name} says {expected_numbers(code)}"
    )
