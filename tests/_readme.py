"""Run the README's code blocks as tests: extract, exec, compare printed numbers."""

from __future__ import annotations

import contextlib
import io
import logging
import os
import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def block(name: str) -> str:
    """The python code between ``<!-- BEGIN name -->`` and ``<!-- END name -->``."""
    text = README.read_text()
    found = re.search(rf"<!-- BEGIN {name} -->(.*?)<!-- END {name} -->", text, flags=re.S)
    assert found is not None, f"README.md lacks the {name} block"
    code = re.search(r"```python\n(.*?)```", found.group(1), flags=re.S)
    assert code is not None, f"the {name} block has no python code"
    return code.group(1)


def expected_numbers(code: str) -> list[float]:
    """The numbers the block promises, one ``# <number>`` comment line after each print."""
    return [float(m.group(1)) for m in re.finditer(r"^# (-?[0-9.]+)", code, flags=re.M)]


def run(name: str, cwd: Path) -> tuple[dict, list[str]]:
    """Exec the block in ``cwd``; returns its namespace and printed lines."""
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
            exec(compile(code, f"README.md:{name}", "exec"), namespace)
    finally:
        os.chdir(here)
        log.setLevel(level)
    return namespace, out.getvalue().split()


def assert_prints_what_it_promises(name: str, printed: list[str]) -> None:
    promised = expected_numbers(block(name))
    assert [float(x) for x in printed] == promised, (
        f"{name}: printed {printed}, README says {promised}"
    )
