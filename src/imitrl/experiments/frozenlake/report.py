"""The study's printed report and its machine-readable twin, results.json."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = ["Report"]


def _plain(value: Any) -> Any:
    """JSON-ready copy: tensors to lists, floats kept at full precision."""
    if isinstance(value, (torch.Tensor, np.ndarray)):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        return _plain(value.item())
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, Path):
        return str(value)
    return value


class Report:
    """Collects printed lines and named results; writes report.txt and results.json."""

    def __init__(self, out: Path, *, echo: bool = True) -> None:
        self.out = Path(out)
        self.echo = echo
        self.lines: list[str] = []
        self.results: dict[str, Any] = {}

    def section(self, title: str) -> None:
        self.line("")
        self.line(title)
        self.line("-" * len(title))

    def line(self, text: str = "") -> None:
        self.lines.append(text)
        if self.echo:
            print(text, flush=True)

    def set(self, path: str, value: Any) -> Any:
        """Store ``value`` under a dotted ``path`` (``"evaluation.expert.rate"``)."""
        node = self.results
        *parents, leaf = path.split(".")
        for key in parents:
            node = node.setdefault(key, {})
        node[leaf] = _plain(value)
        return value

    def write(self) -> tuple[Path, Path]:
        self.out.mkdir(parents=True, exist_ok=True)
        text = self.out / "report.txt"
        text.write_text("\n".join(self.lines) + "\n")
        data = self.out / "results.json"
        data.write_text(json.dumps(self.results, indent=2) + "\n")
        return text, data
