"""One rule for a job's ``--out`` (:func:`claimed`), the same for every command.

A run never writes into ``--out`` while it runs. It writes into a staging folder beside
it, ``.<name>.imitrl-run``, and when it finishes that folder takes ``--out``'s place in
one step (:func:`imitrl.fs.publish.swap_in`: an atomic exchange), as every dataset and
checkpoint writer of this library does. So:

* a kill, an error or a full disk at any instant leaves ``--out`` as it was: a finished
  run there (with ``--overwrite``) is whole until the new one is;
* ``--out`` holds only finished runs (``results.json`` is their mark), so a failed or
  killed run never blocks its own rerun;
* ``--out`` absent or empty: the run is published there;
* ``--out`` holding a finished run (its ``results.json``): refused unless ``--overwrite``
  (it is replaced when the new run finishes) or, for ``imitrl dagger``, ``--resume`` (the
  saved run continues);
* ``--out`` holding anything else (a user's files, an ``eval.json``, a run's files
  without ``results.json``): refused, with or without ``--overwrite``: a run never
  deletes what it did not finish. (A DAgger checkpoint ``run/`` left there by a killed
  run of an older imitrl, which wrote into ``--out`` directly, is continued by
  ``--resume``.)

The staging folder of a run that did not finish is removed by the next run of the same
``--out`` (with a warning), except when it holds saved work: a DAgger checkpoint
(``run/``), so the next run is refused unless ``--resume`` (it continues there) or
``--overwrite`` (it is discarded); or a fitted learner (``config.json`` and
``learner.pt``, which ``imitrl bc``, ``gail`` and ``airl`` save before they evaluate it),
so a failed or interrupted evaluation never loses the fit: ``imitrl eval --checkpoint``
reads it there, and the next run is refused unless ``--overwrite``. A ``--resume`` of a
finished run continues in a copy of it; refused or failed before it saved a round, it
leaves no copy (``--out`` holds the same checkpoint). Logs of a run in progress are in
its staging folder (the command says where on stderr).

The run holds ``--out``'s lock (:func:`imitrl.fs.exclusive`) from the check to the
exchange, so a second run given the same ``--out`` is refused at once. The staging
folder is made with the user's umask; a planted symbolic link at it, at ``--out`` or at
the lock is refused, naming it, and a folder a run continues (``--resume``) must hold
plain folders and regular files only (:func:`imitrl.fs.files.check_plain_tree`), so none
of its writes goes through a link. Once exchanged, the replaced run is renamed to a
temporary name before it is removed: a kill then never leaves it where ``--resume``
would continue it. (``imitrl frozenlake`` stages
its output the same way: :mod:`imitrl.experiments.frozenlake.outputs`.)
"""

from __future__ import annotations

import os
import re
import secrets
import shutil
import sys
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from imitrl.fs.files import PlantedLinkError, check_plain_tree, remove_tree
from imitrl.fs.lock import LOCK_SUFFIX, absolute, exclusive
from imitrl.fs.publish import OLD, TMP, fsync_dir, recover, swap_in
from imitrl.fs.write_errors import DiskFullError, reporting_disk_full

__all__ = ["FINISHED", "RUN_FILES", "STAGE", "claimed", "staging_folder"]

RUN_FILES = frozenset(
    {
        "config.json",
        "learner.pt",
        "results.json",
        "curves.png",
        "logs",
        "run",
        "eval.json",
        "lerobot",
    }
)
"""what ``imitrl bc/dagger/gail/airl`` write into ``--out`` (``run/``: DAgger's checkpoint)"""

FINISHED = "results.json"
"""a run's last file: a folder holding it holds a finished run"""

STAGE = ".imitrl-run"
"""``.<name>.imitrl-run`` beside ``--out``: the run in progress"""

_LEFTOVER = re.compile(
    r"\.[^/]+("
    + "|".join([re.escape(LOCK_SUFFIX), re.escape(TMP) + r"\w+", re.escape(OLD) + r"\w+"])
    + ")"
)
"""what a killed writer of a run file leaves beside it (:mod:`imitrl.fs`): imitrl's own"""


def staging_folder(out: Path) -> Path:
    """Where a run of ``--out`` writes until it finishes."""
    return out.parent / f".{out.name}{STAGE}"


def _entries(folder: Path, name: str) -> list[str]:
    if folder.is_symlink():
        raise PlantedLinkError(
            f"{name} {folder} is a symbolic link (to {os.readlink(folder)}); a run writes "
            "only into a folder of its own: give a folder"
        )
    if os.path.lexists(folder) and not folder.is_dir():
        raise ValueError(f"{name} {folder} is not a folder (a file): give a folder")
    return sorted(os.listdir(folder)) if folder.is_dir() else []


def _check(out: Path, overwrite: bool, resume: bool) -> str | None:
    """Apply the module's rule to ``--out``: what it holds that a run may continue or
    replace (``"finished"``, ``"unfinished"``: an older imitrl's killed DAgger run), or
    None (absent or empty)."""
    entries = _entries(out, "--out")
    if not entries:
        return None
    foreign = [e for e in entries if e not in RUN_FILES and not _LEFTOVER.fullmatch(e)]
    finished = FINISHED in entries
    old_layout = not finished and "run" in entries and resume  # a killed older run
    if foreign or not (finished or old_layout):
        shown = ", ".join((foreign or entries)[:5])
        raise ValueError(
            f"--out {out} holds files no finished imitrl run left there ({shown}); a run "
            "never deletes them: give another --out"
        )
    if finished and not (overwrite or resume):
        more = ", --resume to continue it" if "run" in entries else ""
        raise ValueError(
            f"--out {out} holds a previous run, finished ({', '.join(entries)}): pass "
            f"--overwrite to replace it (it stays whole until the new run finishes){more}, "
            f"or give another --out{_kept_beside(out)}"
        )
    return "finished" if finished else "unfinished"


def _kept_beside(out: Path) -> str:
    """What a refusal of ``out`` adds about the saved work a stopped run left beside it
    (``--overwrite`` discards it at once, not when the new run finishes)."""
    stage = staging_folder(out)
    kept = _kept(stage) if stage.is_dir() and not stage.is_symlink() else None
    if kept == "learner":
        return (
            f"; beside it, {stage} holds a fitted learner a stopped run kept (imitrl eval "
            "--checkpoint reads it there), which --overwrite discards when the new run starts"
        )
    if kept == "checkpoint":
        return (
            f"; beside it, {stage} holds an unfinished DAgger run's checkpoint, which "
            "--resume continues and --overwrite discards when the new run starts"
        )
    return ""


def _kept(stage: Path) -> str | None:
    """The saved work a stopped run left in ``stage`` (module docstring): ``"checkpoint"``
    (DAgger's ``run/``), ``"learner"`` (a fitted ``learner.pt``), or None."""
    if (stage / "run").is_dir():
        return "checkpoint"
    return "learner" if (stage / "learner.pt").is_file() else None


def _stage(out: Path, overwrite: bool, resume: bool, held: str | None) -> tuple[Path, bool]:
    """The folder the run writes into (module docstring), and whether it is a copy of
    ``--out``'s finished run made now (``--resume`` of a finished run)."""
    stage = staging_folder(out)
    left = _entries(stage, "the staging folder")
    if FINISHED in left:  # a replaced run a kill caught before its removal: never resumed
        remove_tree(stage)
        left = []
    elif os.path.lexists(stage):
        kept = _kept(stage)
        if resume and kept != "learner":
            check_plain_tree(stage, what="the unfinished run")  # no write through a link
            print(f"imitrl: continuing the unfinished run in {stage}", file=sys.stderr)
            return stage, False
        if kept == "checkpoint" and not overwrite:
            raise ValueError(
                f"--out {out}: a run was stopped before it finished and its DAgger checkpoint "
                f"lies in {stage}: pass --resume to continue it, --overwrite to discard it, or "
                "give another --out"
            )
        if kept == "learner" and not overwrite:
            raise ValueError(
                f"--out {out}: a run was stopped after its fit, before it finished, and its "
                f"fitted learner lies in {stage} (imitrl eval --checkpoint reads it there): "
                "move that folder elsewhere to keep it, pass --overwrite to discard it, or "
                "give another --out"
            )
        remove_tree(stage)
        warnings.warn(
            f"{out}: removed an unfinished run's files ({', '.join(left) or 'empty'}) from "
            f"{stage.name}: it was killed or failed",
            UserWarning,
            stacklevel=4,
        )
    if resume and held is not None and (out / "run").is_dir():
        check_plain_tree(out, what=f"--out {out}")  # links and FIFOs are never copied
        shutil.copytree(out, stage)  # the run continues in a copy; --out stays as it is
        return stage, True
    os.mkdir(stage, 0o777)  # the user's umask, as the published run keeps
    return stage, False


def _publish(stage: Path, out: Path) -> None:
    fsync_dir(stage)
    swap_in(stage, out)  # ``out`` absent: a rename; present: an atomic exchange
    if os.path.lexists(stage):  # the replaced run, now at the staging name: renamed to a
        gone = out.parent / f".{out.name}{TMP}{secrets.token_hex(6)}"  # name --resume
        os.rename(stage, gone)  # never continues (publish.recover removes it if killed)
        remove_tree(gone)
    fsync_dir(out.parent)


def _check_parents(out: Path) -> None:
    """Each existing folder above ``out`` is a folder (one line otherwise, exit 2)."""
    for parent in reversed(out.parents):
        if os.path.lexists(parent) and not parent.is_dir():
            raise ValueError(f"--out {out} is under {parent}, which is not a folder: give a folder")


@contextmanager
def claimed(out: Path, *, overwrite: bool, resume: bool = False) -> Iterator[Path]:
    """Hold ``out`` for a run and apply the module's rule; yields the folder the run
    writes into, published as ``out`` when the block ends without error.

    Raises:
        ValueError: ``out`` is a file or a link, holds a finished run (without
            ``overwrite`` or ``resume``) or foreign files, an unfinished DAgger run lies
            beside it (without ``resume`` or ``overwrite``), or another run holds it.
        imitrl.fs.DiskFullError, imitrl.fs.NotWritableError: the file system refused the
            run's files; ``out`` is as it was.
    """
    out = absolute(out)  # a path this system can write (its length checked)
    _check_parents(out)
    made = [p for p in (out, *out.parents) if not p.exists()]  # deepest first
    stage: Path | None = None
    copied = None
    try:
        with (
            exclusive(out, what="written by another imitrl run"),
            reporting_disk_full(out, what="the run's files", left="--out is as it was"),
        ):
            recover(out)  # a killed exchange of an earlier run (imitrl.fs.publish)
            held = _check(out, overwrite, resume)
            stage, copy = _stage(out, overwrite, resume, held)
            copied = _files_of(stage / "run") if copy else None  # --out's run, copied
            yield stage
            _publish(stage, out)
    except BaseException as err:
        _clean_up(stage, made, err, copied, out)
        raise


def _files_of(folder: Path) -> dict[str, tuple[int, int]] | None:
    """``{path: (size, mtime_ns)}`` of every file under ``folder`` (None: no folder)."""
    if not folder.is_dir():
        return None
    return {
        str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns)
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def _clean_up(
    stage: Path | None,
    made: list[Path],
    err: BaseException,
    copied: dict[str, tuple[int, int]] | None,
    out: Path,
) -> None:
    """After a failed or refused run: its staging folder goes, unless it holds saved work
    (:func:`_kept`: a DAgger checkpoint, continued by ``--resume``, or a fitted learner)
    that is not the unchanged copy of ``--out``'s it started from (``copied``: a resumed
    finished run refused before it saved a round; ``--out`` holds that checkpoint still);
    folders made for it go if empty."""
    unchanged = (  # and --out still holds it: nothing was exchanged
        copied is not None
        and stage is not None
        and _files_of(stage / "run") == copied == _files_of(out / "run")
    )
    if (
        stage is not None
        and stage.is_dir()
        and not stage.is_symlink()
        and (unchanged or _kept(stage) is None)
    ):
        remove_tree(stage)
    elif stage is not None and stage.is_dir() and not isinstance(err, DiskFullError):
        said = (
            f"the unfinished run is kept in {stage} (--resume continues it)"
            if _kept(stage) == "checkpoint"
            else f"the fitted learner is kept in {stage} (imitrl eval --checkpoint {stage} "
            "evaluates it; the next run of --out refuses to discard it without --overwrite)"
        )
        print(f"imitrl: {said}", file=sys.stderr)
    for folder in made:  # a run refused or failed before writing leaves no folders
        if not folder.is_dir():
            continue
        try:
            folder.rmdir()
        except OSError:
            break  # not empty: something else was written there, and it stays
