"""Shared by the benchmark scripts: write raw results and refresh README tables.

Each script writes ``benchmarks/results/<name>.json`` (machine-readable, with the
machine and package versions) and replaces the block between
``<!-- BEGIN <name> -->`` and ``<!-- END <name> -->`` in ``benchmarks/README.md``,
so every number in the README is produced by the script as it is now.
"""

from __future__ import annotations

import json
import os
import platform
import re
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
README = HERE / "README.md"


def machine() -> dict[str, Any]:
    import gymnasium
    import tensordict
    import torch
    import torchrl

    return {
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "torchrl": torchrl.__version__,
        "tensordict": tensordict.__version__,
        "gymnasium": gymnasium.__version__,
    }


def write(
    name: str, payload: dict[str, Any], markdown: str, *, out_dir: Path | None = None
) -> Path:
    """Write ``<out_dir or results>/<name>.json``; refresh the README block unless ``out_dir`` is given."""
    target = RESULTS if out_dir is None else Path(out_dir)
    target.mkdir(parents=True, exist_ok=True)
    path = target / f"{name}.json"
    path.write_text(json.dumps({"machine": machine(), **payload}, indent=2) + "\n")
    if out_dir is None:
        update_readme(name, markdown)
    return path


def update_readme(name: str, markdown: str) -> None:
    text = README.read_text() if README.exists() else ""
    begin, end = f"<!-- BEGIN {name} -->", f"<!-- END {name} -->"
    block = f"{begin}\n{markdown.rstrip()}\n{end}"
    if begin in text and end in text:
        text = re.sub(re.escape(begin) + r".*?" + re.escape(end), lambda _: block, text, flags=re.S)
    else:
        text = text.rstrip() + f"\n\n{block}\n"
    README.write_text(text)


def table(header: list[str], rows: list[list[Any]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)
