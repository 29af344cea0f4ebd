"""One rule for a job's ``--out`` (:func:`claimed`), the same for every command.

* ``--out`` absent or empty: the run writes there.
* ``--out`` holding a previous run's files (:data:`RUN_FILES`): refused, unless
  ``--overwrite`` (those files are removed when the new run starts) or, for ``imitrl
  dagger``, ``--resume`` (the saved run continues).
* ``--out`` holding anything else (a user's files): refused, with or without
  ``--overwrite``: a run never deletes what it did not write.

The run holds ``--out``'s lock (:func:`imitrl.fs.exclusive`) from the check to its last
file, so a second run given the same ``--out`` is refused at once instead of mixing
its files with the first's. (``imitrl frozenlake`` replaces its own previous output
atomically: :mod:`imitrl.experiments.frozenlake.outputs`.)
"""

from __future__ import annotations

import os
import re
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from imitrl.fs.lock import LOCK_SUFFIX, exclusive
from imitrl.fs.publish import OLD, TMP

__all__ = ["RUN_FILES", "claimed"]

RUN_FILES = frozenset(
    {"config.json", "learner.pt", "results.json", "curves.png", "logs", "run", "eval.json"}
)
"""what ``imitrl bc/dagger/gail/airl`` write into ``--out`` (``run/``: DAgger's checkpoint)"""

_LEFTOVER = re.compile(
    r"\.[^/]+("
    + "|".join([re.escape(LOCK_SUFFIX), re.escape(TMP) + r"\w+", re.escape(OLD) + r"\w+"])
    + ")"
)
"""what a killed writer of a run file leaves beside it (:mod:`imitrl.fs`): imitrl's own"""


def _check(out: Path, overwrite: bool, resume: bool) -> None:
    if out.is_symlink() or (out.exists() and not out.is_dir()):
        raise ValueError(f"--out {out} is not a folder (a file or a link): give a folder")
    entries = sorted(os.listdir(out)) if out.is_dir() else []
    if not entries:
        return
    foreign = [e for e in entries if e not in RUN_FILES and not _LEFTOVER.fullmatch(e)]
    if foreign:
        raise ValueError(
            f"--out {out} holds files an imitrl run did not write ({', '.join(foreign[:5])}); "
            "a run never deletes them: give another --out"
        )
    if resume:
        return
    if not overwrite:
        more = ", --resume to continue it" if "run" in entries else ""
        raise ValueError(
            f"--out {out} holds a previous run ({', '.join(entries)}): pass --overwrite to "
            f"replace it{more}, or give another --out"
        )
    for name in entries:
        path = out / name
        shutil.rmtree(path) if path.is_dir() else path.unlink()


@contextmanager
def claimed(out: Path, *, overwrite: bool, resume: bool = False) -> Iterator[Path]:
    """Hold ``out`` for a run and apply the module's rule; yields ``out``.

    Raises:
        ValueError: ``out`` is a file or a link, holds a previous run (without
            ``overwrite`` or ``resume``) or foreign files, or another run holds it.
    """
    out = Path(out).expanduser()
    made = [p for p in (out, *out.absolute().parents) if not p.exists()]  # deepest first
    try:
        with exclusive(out, what="written by another imitrl run"):
            _check(out, overwrite, resume)
            yield out
    except BaseException:
        for folder in made:  # a run refused or failed before writing leaves no folders
            if not folder.is_dir():
                continue
            try:
                folder.rmdir()
            except OSError:
                break  # not empty: the run wrote there, and what it wrote stays
        raise
