"""Where the study writes: a staging folder beside ``--out``, moved into place when the run completes.

A run writes into a fresh folder beside ``--out`` and swaps it in only once report.txt,
results.json and every figure are written (:func:`staged`, on
:func:`imitrl.fs.publish.publishing`: the path's lock for the whole run, an atomic
exchange with the previous results), so an interrupted run (an exception, Ctrl-C, a
kill) leaves the previous results whole and nothing at ``--out`` that looks finished,
and a second run given the same ``--out`` while one runs is refused at once.

Only a folder the study wrote (its file names, a ``results.json`` with the study's
config) or an empty one is ever replaced; anything else at ``--out`` is refused.
The next run removes what a killed run left beside ``--out`` (with a warning).
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from imitrl.fs.publish import publishing

__all__ = ["FIGURES", "OUTPUT_FILES", "is_study_output", "staged"]

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
    "airl_transfer",
)
"""The figures a run may draw, each ``<name>.png``."""
OUTPUT_FILES = frozenset({"report.txt", "results.json", *(f"{f}.png" for f in FIGURES)})
"""Every file name a run writes into ``--out``."""


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


def _replaceable(out: Path) -> None:
    reason = _refusal(out)  # checked again: the folder may have changed during the run
    if reason is not None:
        raise ValueError(reason)


@contextmanager
def staged(out: Path) -> Iterator[Path]:
    """Check ``out`` can take the results; yield the staging folder, swapped in for
    ``out`` when the block ends without error (removed otherwise).

    Raises:
        ValueError: ``out`` is a file, a link, a folder the study did not write, the
            working directory (or holds it), no folder can be created beside it, or
            another run is writing it.
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
    try:  # a folder can be made beside it (the staging folder will be)
        out.parent.mkdir(parents=True, exist_ok=True)
        os.rmdir(tempfile.mkdtemp(prefix=f".{out.name}.probe-", dir=out.parent))
    except OSError as err:
        raise ValueError(
            f"--out {out}: cannot create the output folder beside it "
            f"({err.strerror or err}: {err.filename or out.parent})"
        ) from err
    with publishing(
        out, overwrite=True, replaceable=_replaceable, what="the study's results", empty_ok=True
    ) as staging:
        yield staging
