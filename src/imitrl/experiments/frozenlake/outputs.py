"""Where the study writes: a staging folder beside ``--out``, moved into place when the run completes.

A run writes into ``.<name>.partial-<pid>-<token>`` next to ``--out`` and renames
it to ``--out`` only once report.txt, results.json and every figure are written, so
an interrupted run (an exception, Ctrl-C, a kill) leaves the previous results whole
and nothing at ``--out`` that looks finished. A previous run at ``--out`` is first
renamed aside to ``.<name>.previous-<pid>-<token>``, then removed once the new
results are in place.

Only a folder the study wrote (its file names, a ``results.json`` with the study's
config) or an empty one is ever replaced; anything else at ``--out`` is refused.
The next run removes the staging folders of runs no longer alive, and puts back
a previous run that a kill between the two renames left aside.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import sys
from pathlib import Path

__all__ = ["FIGURES", "OUTPUT_FILES", "discard", "install", "is_study_output", "prepare"]

FIGURES = (
    "chain",
    "occupancy",
    "sweep",
    "dagger",
    "ex_demo_counts",
    "ex_state_errors",
    "ex_budget",
    "ex_corruption",
    "irl_reward",
    "irl_sweep",
)
"""The figures a run may draw, each ``<name>.png``."""
OUTPUT_FILES = frozenset({"report.txt", "results.json", *(f"{f}.png" for f in FIGURES)})
"""Every file name a run writes into ``--out``."""

_PARTIAL, _PREVIOUS = "partial", "previous"


def _refusal(out: Path) -> str | None:
    """Why ``out`` may not be replaced by a run (None: absent, empty, or a study's output)."""
    if out.is_symlink():
        return f"--out {out} is a symbolic link: give the folder itself"
    if not out.exists():
        return None
    if not out.is_dir():
        return f"--out {out} is a file, not a folder"
    names = {p.name for p in out.iterdir()}
    if not names:
        return None
    foreign = sorted(names - OUTPUT_FILES)
    if foreign:
        shown = ", ".join(foreign[:5]) + (", ..." if len(foreign) > 5 else "")
        return (
            f"--out {out} holds files the study did not write ({shown}); the study replaces "
            "only its own output: choose another --out"
        )
    try:
        config = json.loads((out / "results.json").read_text()).get("config", {})
    except (OSError, ValueError, AttributeError):
        config = {}
    if not isinstance(config, dict) or "protocol" not in config:
        return f"--out {out} has no results.json of the study: choose another --out"
    return None


def is_study_output(out: Path) -> bool:
    """Whether ``out`` is a folder a run of the study wrote (and may replace)."""
    return Path(out).is_dir() and _refusal(Path(out)) is None


def _sibling(out: Path, kind: str) -> Path:
    return out.parent / f".{out.name}.{kind}-{os.getpid()}-{secrets.token_hex(4)}"


def _owner_alive(path: Path) -> bool:
    """Whether the run that named ``path`` (``...-<pid>-<token>``) may still be running."""
    try:
        pid = int(path.name.rsplit("-", 2)[-2])
    except (IndexError, ValueError):
        return True  # not one of ours: leave it
    if pid == os.getpid() or os.name != "posix":
        return True
    try:
        os.kill(pid, 0)  # signal 0: existence check only
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _tidy(out: Path) -> None:
    """Remove the staging folders of dead runs; put back a previous run one left aside."""
    pattern = f".{out.name}.{{}}-*"
    for path in sorted(out.parent.glob(pattern.format(_PARTIAL))):
        if path.is_dir() and not _owner_alive(path):
            shutil.rmtree(path, ignore_errors=True)
            print(f"removed {path}, the unfinished output of an interrupted run", file=sys.stderr)
    aside = [p for p in out.parent.glob(pattern.format(_PREVIOUS)) if not _owner_alive(p)]
    for path in sorted(aside, key=lambda p: p.stat().st_mtime, reverse=True):
        if not out.exists() and not out.is_symlink():
            path.rename(out)
            print(f"put back {out}, left aside by a run killed while replacing it", file=sys.stderr)
        else:
            shutil.rmtree(path, ignore_errors=True)


def prepare(out: Path) -> Path:
    """Check ``out`` can take the results, tidy leftovers, create the staging folder.

    Raises:
        ValueError: ``out`` is a file, a link, a folder the study did not write, the
            working directory (or holds it), or no folder can be created beside it.
    """
    out = Path(out)
    if out.resolve() in (Path.cwd(), *Path.cwd().parents):
        raise ValueError(f"--out {out} is the working directory or holds it: give a new folder")
    reason = _refusal(out)
    if reason is not None:
        raise ValueError(reason)
    above = next(p for p in out.absolute().parents if p.exists())
    if not above.is_dir():
        raise ValueError(f"--out {out} is under {above}, a file: give a folder")
    staging = _sibling(out, _PARTIAL)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        _tidy(out)
        staging.mkdir()
    except OSError as err:
        raise ValueError(
            f"--out {out}: cannot create the output folder beside it "
            f"({err.strerror or err}: {err.filename or staging})"
        ) from err
    return staging


def install(staging: Path, out: Path) -> None:
    """Move the finished ``staging`` folder to ``out``, replacing a previous run there."""
    out = Path(out)
    reason = _refusal(out)  # checked again: the folder may have changed during the run
    if reason is not None:
        raise ValueError(reason)
    if not out.exists():
        staging.rename(out)
        return
    aside = _sibling(out, _PREVIOUS)
    out.rename(aside)
    try:
        staging.rename(out)
    except OSError:
        aside.rename(out)  # put the previous results back before reporting the failure
        raise
    shutil.rmtree(aside, ignore_errors=True)


def discard(staging: Path) -> None:
    """Remove an unfinished staging folder."""
    shutil.rmtree(staging, ignore_errors=True)
