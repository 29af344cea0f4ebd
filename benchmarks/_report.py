"""Shared by the benchmark scripts: where a run writes, raw results, README tables.

A full run writes ``benchmarks/results/<name>.json`` (machine-readable, with the
machine and package versions) and replaces the block between
``<!-- BEGIN <name> -->`` and ``<!-- END <name> -->`` in ``benchmarks/README.md``,
so every number in the README is produced by the script as it is now. ``--out DIR``
writes the JSON (and figures) to ``DIR`` and leaves the README alone; ``--quick``
without ``--out`` writes to a fresh temporary directory: a smoke run never touches
the committed ``README.md`` or ``results/``.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import os
import platform
import re
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
README = HERE / "README.md"


# ------------------------------------------------------------------ where to write
def parser(doc: str | None) -> argparse.ArgumentParser:
    """An argument parser with the two flags every benchmark takes, ``--quick`` and ``--out``."""
    p = argparse.ArgumentParser(description=(doc or "").splitlines()[0])
    p.add_argument(
        "--quick",
        action="store_true",
        help="smoke run on a tiny budget (without --out: into a temporary directory)",
    )
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="write results here and leave benchmarks/README.md alone",
    )
    return p


def check_least(p: argparse.ArgumentParser, args: argparse.Namespace, **least: float) -> None:
    """``p.error`` (one line, before anything runs) for a numeric flag given below its least
    value, or not a number (a hostile review: ``--seeds 0`` was a traceback blaming the
    tasks, ``--reps 0`` failed after every cell had trained, ``--timeout nan`` at the end)."""
    for name, low in least.items():
        value = getattr(args, name, None)
        if value is not None and not value >= low:  # NaN is not >= anything
            p.error(f"--{name.replace('_', '-')} must be >= {low:g}, got {value}")


def destination(name: str, *, quick: bool, out: Path | None) -> Path | None:
    """Where a run writes: ``out`` if given; for a ``quick`` run a new temporary
    directory (printed); otherwise None, meaning ``results/`` and the README block."""
    if out is not None:
        return Path(out)
    if quick:
        path = Path(tempfile.mkdtemp(prefix=f"{name}-quick-"))
        print(f"--quick without --out: writing to {path} (README.md and results/ untouched)")
        return path
    return None


def read_results(path: Path, error: Callable[[str], Any]) -> dict[str, Any]:
    """A results file given to ``--render`` or ``--merge``, read; ``error`` (argparse's
    ``p.error``: one line, exit 2) for one that is not: missing, a folder, not JSON,
    nested too deep, not an object, or holding NaN or Infinity (a results file the
    scripts write holds finite numbers: a hostile review rendered NaN cells as met)."""

    def refuse(name: str) -> None:
        raise ValueError(f"{name} is not a finite number")

    try:
        payload = json.loads(Path(path).read_text(), parse_constant=refuse)
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as err:
        error(f"{path}: not a results file ({type(err).__name__}: {err})"[:400])
    if not isinstance(payload, dict):
        error(f"{path}: not a results file (a JSON {type(payload).__name__}, not an object)")
    return payload


def merge_refused(err: Exception) -> str:
    """The one line of a ``--merge`` whose parts do not join (a ``ValueError`` naming what
    differs; a part missing a field its script writes names the field)."""
    said = str(err) if isinstance(err, ValueError) else f"{type(err).__name__}: {err}"
    return f"--merge: {said}"[:400]


def render_safely(
    render: Callable[[Path | None], Any], out: Path | None, error: Callable[[str], Any], what: str
) -> Any:
    """``render(out)`` (``out`` None: ``results/`` and the README block), after a rehearsal
    into a scratch folder: a file the report cannot read is one line (``error``) and
    nothing is written (a hostile review: a failing render had already replaced the
    committed figure, then gave a traceback)."""
    with tempfile.TemporaryDirectory() as scratch:
        try:
            with contextlib.redirect_stdout(io.StringIO()):
                render(Path(scratch))
        except (KeyError, TypeError, ValueError, IndexError, AttributeError, OverflowError,
                RecursionError) as err:  # fmt: skip
            error(
                f"{what}: not a results file this report reads ({type(err).__name__}: {err})"[:400]
            )
    return render(out)


def results_dir(out_dir: Path | None) -> Path:
    """The directory a run's files go to (created): ``out_dir``, or ``results/``."""
    target = RESULTS if out_dir is None else Path(out_dir)
    target.mkdir(parents=True, exist_ok=True)
    return target


# ------------------------------------------------------------------------ writing
REPO = Path(__file__).resolve().parents[1]
"""this checkout's root: the paths a report records are relative to it"""


def portable(path: str | Path) -> str:
    """``path`` as a committed report may name it: relative to this checkout when inside
    it, else its last three parts (``imitrl_venv/bin/python``): never one machine's
    absolute path."""
    resolved = Path(path).absolute()
    if resolved.is_relative_to(REPO):
        return resolved.relative_to(REPO).as_posix()
    return Path(*resolved.parts[1:][-3:]).as_posix()  # never the root: /tmp/x is tmp/x


def portable_args(args: list[str]) -> list[str]:
    """``args`` with every absolute path made :func:`portable` (what a report records of a
    command line)."""
    return [portable(a) if Path(a).is_absolute() else a for a in args]


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
    path = results_dir(out_dir) / f"{name}.json"
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


# ------------------------------------------------------------------------- tables
def table(header: list[str], rows: list[list[Any]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def section(title: str, body: str) -> str:
    """A bold-titled paragraph, a blank line, then ``body`` (a table)."""
    return f"{title}\n\n{body}"


def fmt_ci(ci: tuple[float, float, float], digits: int = 2, *, unit: bool = False) -> str:
    """``mean [lo, hi]`` of a ``t_interval``; the mean alone without bounds (one seed),
    ``-`` without a mean; ``unit``: a probability, its interval clipped to [0, 1]."""
    mean, lo, hi = ci
    if math.isnan(mean):
        return "-"
    if math.isnan(lo):
        return f"{mean:.{digits}f}"
    if unit:
        lo, hi = max(lo, 0.0), min(hi, 1.0)
    return f"{mean:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"


def env_label(env_id: str) -> str:
    """``module:Env-v0`` without its module, for tables."""
    return env_id.split(":", 1)[-1]


def panels(n: int, cols: int, size: tuple[float, float]):
    """A figure of ``n`` panels, ``cols`` to a row (fewer when ``n`` is smaller), each
    ``size`` inches; the unused cells of the grid hidden. Returns ``(figure, the n axes)``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = min(cols, n)
    grid = -(-n // cols)
    fig, axes = plt.subplots(grid, cols, figsize=(size[0] * cols, size[1] * grid), squeeze=False)
    for ax in axes.flat[n:]:
        ax.axis("off")
    return fig, list(axes.flat[:n])
