"""Paths a downloaded file names: inside its folder, or refused.

A dataset's metadata names other files (LeRobot's ``data_path`` and ``video_path``
templates, a camera feature's name, an image's ``path``, the checksummed files of
``meta/imitrl.json``, Minari's episode folders). Everything downloaded is hostile until
checked, so every such name goes through :func:`inside` before it is opened, and a
name that becomes a file of ours (``decode_dir/<feature>.uint8``) through
:func:`plain_name`. The rules:

* a relative name of plain parts: no absolute path, no drive, no ``..``, no NUL, no
  backslash (a Windows separator on one machine is a file name on another);
* the file it names, symbolic links followed, lies inside the folder's real path, or,
  for a Hugging Face hub snapshot (``.../datasets--<org>--<name>/snapshots/<commit>``),
  inside its repository folder, where the hub keeps the ``blobs/`` its snapshot files
  link to. A link out of the folder is refused like ``..``.

A reader calls :func:`links_stay_inside` once on the folder before reading it (every
symbolic link in the tree, files and folders, must point inside), so that the fixed
names of a layout (``meta/info.json``) and the files it finds by listing folders are
covered too, then :func:`inside` on every name the metadata gives.

A refusal is a ``ValueError`` naming the folder, the offending name and who named it.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path, PurePosixPath

from imitrl.fs.files import walk_tree

__all__ = ["check_relative", "inside", "links_stay_inside", "plain_name", "trusted_bases"]


def trusted_bases(root: str | Path) -> tuple[Path, ...]:
    """The real folders a dataset at ``root`` may reach through symbolic links: its own
    real path, and for a hub snapshot the repository folder holding ``blobs/``."""
    real = Path(os.path.realpath(root))
    bases = [real]
    given = Path(os.path.abspath(root))
    for candidate in (given, real):
        if candidate.parent.name == "snapshots" and candidate.parent.parent.name.startswith(
            ("datasets--", "models--")
        ):
            bases.append(Path(os.path.realpath(candidate.parent.parent)))
    return tuple(dict.fromkeys(bases))


def _within(path: Path, bases: tuple[Path, ...]) -> bool:
    return any(path == b or b in path.parents for b in bases)


def plain_name(name: object, *, what: str, where: str) -> str:
    """``name`` when it can be one file name in a folder of ours: a non-empty string
    without ``/``, ``\\`` or NUL that is not ``.`` or ``..``; ValueError otherwise."""
    if (
        not isinstance(name, str)
        or not name
        or name in (".", "..")
        or any(c in name for c in "/\\\x00")
    ):
        raise ValueError(
            f"{where}: {what} {name!r} cannot name a file (expected a plain name without "
            "'/', '\\', NUL, '.' or '..')"
        )
    return name


def check_relative(root: str | Path, relative: object, *, named_by: str) -> tuple[str, ...]:
    """The parts of ``relative`` when it is a plain relative path (no absolute path, no
    ``..``, no backslash or NUL); ValueError naming ``root`` and ``named_by`` otherwise.
    Only the text is checked: :func:`inside` and :class:`imitrl.fs.reading.OpenedFolder`
    check where it leads."""
    text = str(relative) if isinstance(relative, os.PathLike | str) else None
    if not text or "\x00" in text or "\\" in text:
        raise ValueError(
            f"{root}: {named_by} names {relative!r}, not a relative path inside the dataset"
        )
    parts = PurePosixPath(text).parts
    if PurePosixPath(text).is_absolute() or ".." in parts or not parts:
        raise ValueError(
            f"{root}: {named_by} names {text!r}, outside the dataset folder (an absolute "
            "path or '..'); a dataset may only name its own files"
        )
    return parts


def inside(root: str | Path, relative: object, *, named_by: str) -> Path:
    """``root / relative``, once ``relative`` is a plain relative path whose file (links
    followed) lies inside ``root`` (see the module docstring).

    Args:
        root: the dataset folder.
        relative: the name the metadata gave (a str or a path relative to ``root``).
        named_by: who named it, for the message (``"meta/info.json's data_path"``).

    Raises:
        ValueError: the name is absolute, climbs out with ``..``, holds a backslash or NUL,
            or resolves (through a symbolic link) outside the folder.
    """
    path = Path(root, *check_relative(root, relative, named_by=named_by))
    real = _resolved(path)
    bases = trusted_bases(root)
    if not _within(real, bases):
        raise ValueError(
            f"{path}: a symbolic link out of the dataset folder (to {real}; {named_by} names "
            f"it); a dataset may only name its own files"
        )
    return path


def links_stay_inside(root: str | Path, *, what: str = "dataset") -> None:
    """Refuse (ValueError) a folder holding a symbolic link, anywhere in its tree, whose
    target lies outside it (or outside its hub repository, for a snapshot). Links are not
    followed into folders: each link is checked where it is."""
    bases = trusted_bases(root)
    for path, st in walk_tree(root):  # no recursion: any depth of folders
        if not stat.S_ISLNK(st.st_mode):
            continue
        try:
            real = _resolved(path)
        except FileNotFoundError:  # the link removed between its lstat and its readlink
            continue  # (realpath reads it unguarded): gone, nothing of it is read later
        if not _within(real, bases):
            raise ValueError(
                f"{path}: a symbolic link out of the {what} folder (to {real}); a "
                f"downloaded {what} may only link to its own files (copy the files in, "
                "or point to the folder itself)"
            )


def _resolved(path: Path) -> Path:
    """``os.path.realpath(path)``; a path replaced as it is resolved (a link turned into
    a file between realpath's lstat and its readlink: EINVAL) is refused (ValueError), a
    removed one raises FileNotFoundError for the caller to judge."""
    try:
        return Path(os.path.realpath(path))
    except FileNotFoundError:
        raise
    except OSError as err:
        raise ValueError(
            f"{path}: changed while it was checked (a symbolic link and a file swapped as it "
            f"was resolved: {err.strerror}); refused"
        ) from None
