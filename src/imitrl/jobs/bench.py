"""``imitrl bench NAME [args...]``: run ``benchmarks/NAME.py`` with the remaining arguments.

The benchmarks live in the source checkout, next to ``src/`` (they are scripts, not
part of the installed package); each runs as its own process with this Python, so
its ``import _report`` and its own argument parser work as when it is run directly.
A few scripts have a short name (:data:`ALIASES`): ``imitrl bench losses --task
name=...,env=...,expert=module:function`` runs ``loss_functions.py`` on a task from
outside.

``imitrl bench`` never writes inside the project unless told to: run in full, or with
``--render``, without ``--out`` (or ``--quick``, ``--help``), a script would refresh the committed
``benchmarks/results/`` and ``benchmarks/README.md``; the command gives it ``--out
results/bench/NAME`` under the current folder instead, and says so on stderr.
``--write-committed`` (taken out before the script sees its arguments) is the
maintainer's way to refresh the committed results through the command.
"""

from __future__ import annotations

import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import imitrl

__all__ = [
    "ALIASES",
    "BENCHMARKS_DIR",
    "WRITE_COMMITTED",
    "BenchJob",
    "available",
    "run_bench",
    "script_args",
]

BENCHMARKS_DIR = Path(imitrl.__file__).resolve().parents[2] / "benchmarks"
"""``<checkout>/benchmarks`` (``src/imitrl/__init__.py`` is two levels below the checkout)"""


ALIASES: dict[str, str] = {"losses": "loss_functions"}
"""short name -> benchmark script name"""


WRITE_COMMITTED = "--write-committed"
"""the flag that lets a full run refresh the committed results (module docstring)"""
_CHOSEN = ("--out", "--quick", "-h", "--help")
"""flags that already say where a run writes (or that it writes nothing); ``--render``
is not one: a script renders into the committed README unless given ``--out``"""


def script_args(name: str, args: tuple[str, ...], cwd: Path) -> tuple[list[str], Path | None]:
    """The script's arguments and the folder the command chose for it (None: the
    arguments already say where, or ``--write-committed`` was given)."""
    given = list(args)
    for a in given:  # argparse reads "--ou X" as --out X: an abbreviation is not a choice
        word = a.partition("=")[0]
        for flag in ("--out", "--quick"):
            if len(word) > 2 and word != flag and flag.startswith(word):
                raise ValueError(
                    f"{word}: spell {flag} in full (imitrl bench adds --out "
                    f"results/bench/{name} unless the arguments say --out or --quick)"
                )
    if WRITE_COMMITTED in given:
        return [a for a in given if a != WRITE_COMMITTED], None
    if any(a == flag or a.startswith(flag + "=") for a in given for flag in _CHOSEN):
        return given, None
    out = cwd / "results" / "bench" / name
    return [*given, "--out", str(out)], out


def available(directory: Path = BENCHMARKS_DIR) -> list[str]:
    """Benchmark names: the ``*.py`` scripts of ``directory`` not starting with ``_``."""
    if not directory.is_dir():
        return []
    return sorted(p.stem for p in directory.glob("*.py") if not p.name.startswith("_"))


@dataclass(frozen=True)
class BenchJob:
    """One benchmark script and its arguments."""

    name: str = field(metadata={"positional": True})
    """the benchmark: benchmarks/NAME.py (listed below; "losses" = loss_functions)"""
    args: tuple[str, ...] = field(default=(), metadata={"remainder": True})
    """every argument after NAME, passed on to the script (e.g. --quick --out DIR; NAME
    --help shows the script's own flags)"""


def run_bench(config: BenchJob) -> dict:
    """Run the benchmark as a subprocess; returns ``{"benchmark", "returncode"}``."""
    if not BENCHMARKS_DIR.is_dir():
        raise ValueError(
            f"no benchmarks directory at {BENCHMARKS_DIR}: imitrl bench runs from a "
            "source checkout (pip install -e .)"
        )
    names = available(BENCHMARKS_DIR)
    name = ALIASES.get(config.name, config.name)
    if name not in names:
        short = ", ".join(f"{a} ({n})" for a, n in ALIASES.items())
        raise ValueError(
            f"unknown benchmark {config.name!r}; available: {', '.join(names)}; short names: {short}"
        )
    script = BENCHMARKS_DIR / f"{name}.py"
    args, out = script_args(name, config.args, Path.cwd())
    if out is not None:
        print(
            f"imitrl bench: writing to {out} (the committed benchmarks/results/ are left "
            f"alone; {WRITE_COMMITTED} refreshes them)",
            file=sys.stderr,
        )
    proc = subprocess.run([sys.executable, str(script), *args], check=False)
    return {
        "benchmark": name,
        "returncode": proc.returncode,
        "out": None if out is None else str(out),
    }
