"""Where the study writes: a staging folder beside ``--out``, moved into place when the run completes.

A run writes into a fresh folder beside ``--out`` and swaps it in only once report.txt,
results.json and every figure are written (:func:`staged`, on
:func:`imitrl.fs.publish.publishing`: the path's lock for the whole run, an atomic
exchange with the previous results), so an interrupted run (an exception, Ctrl-C, a
kill) leaves the previous results whole and nothing at ``--out`` that looks finished,
and a second run given the same ``--out`` while one runs is refused at once.

Only a folder the study wrote (its file names, a ``results.json`` with the study's
config) or an empty one is ever replaced; anything else at ``--out`` is refused. That
``results.json`` is read through the folder's descriptor, as a regular file of at most
:data:`RESULTS_LIMIT` bytes (:class:`imitrl.fs.reading.OpenedFolder`): a link there (to
``/dev/zero``, say) or a FIFO makes the folder not a study's output, read no further.
A folder that cannot be written (read-only, not this user's) is a
:class:`imitrl.fs.NotWritableError` before any work, as for every other command.
The next run removes what a killed run left beside ``--out`` (with a warning).
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from imitrl.fs.publish import publishing
from imitrl.fs.reading import OpenedFolder, parse_json
from imitrl.fs.write_errors import NotWritableError, not_writable

__all__ = ["FIGURES", "OUTPUT_FILES", "RESULTS_LIMIT", "is_study_output", "staged"]

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
RESULTS_LIMIT = 16 << 20
"""bytes a previous run's ``results.json`` may hold (a run writes tens of kB)"""


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
    try:  # by descriptor, no link followed, a FIFO never waited on, the size bounded
        with OpenedFolder(out, what="study output", links=False) as folder:
            data = folder.read_bytes("results.json", named_by="results.json", limit=RESULTS_LIMIT)
        config = parse_json(data, where=str(out / "results.json")).get("config", {})
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
        imitrl.fs.NotWritableError: the folder beside ``out`` is read-only or not this
            user's to write.
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
        refused = not_writable(err)  # read-only, not this user's: exit 1 like every command
        if refused is not None:
            folder = OSError(refused.errno, refused.strerror, str(out.parent.absolute()))
            raise NotWritableError(out.absolute(), "the study's results", folder) from err
        raise ValueError(
            f"--out {out}: cannot create the output folder beside it "
            f"({err.strerror or err}: {err.filename or out.parent})"
        ) from err
    with publishing(
        out, overwrite=True, replaceable=_replaceable, what="the study's results", empty_ok=True
    ) as staging:
        yield staging
