"""Where a LeRobot dataset lives on this machine: lerobot's own folder and the Hugging
Face hub caches (:func:`resolve_lerobot_root`), and what a ``repo_id`` may look like.
Nothing here uses the network (downloading: :mod:`~imitrl.datasets.lerobot._hub`).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

__all__ = ["check_repo_id", "hub_caches", "is_repo_id", "lerobot_home", "resolve_lerobot_root"]


def resolve_lerobot_root(
    repo_id: str, *, revision: str | None = None, cache_dir: str | Path | None = None
) -> Path:
    """Find a LeRobot dataset already on disk for ``repo_id``, without any network access.

    Looks, in order, in ``$HF_LEROBOT_HOME/<repo_id>`` (LeRobot's default ``root``,
    ``$HF_HOME/lerobot``), then the hub caches: ``$HF_LEROBOT_HOME/hub`` (where lerobot
    0.6 and :func:`~imitrl.datasets.lerobot._hub.download_lerobot` download), then the
    Hugging Face hub cache (``$HF_HUB_CACHE`` or ``$HF_HOME/hub``); with ``cache_dir``,
    in that cache only. In a hub cache: ``datasets--<org>--<name>/snapshots/<commit>/``
    with ``revision`` (or ``v3.0``, ``v2.1``, ``main``) resolved through ``refs/``, else
    the newest snapshot holding ``meta/info.json``.

    Raises:
        ValueError: ``repo_id`` is not ``<org>/<name>``, or nothing found (the message
            lists where it looked).
    """
    check_repo_id(repo_id)
    looked: list[str] = []
    if cache_dir is None:
        candidate = lerobot_home() / repo_id
        looked.append(str(candidate))
        if (candidate / "meta" / "info.json").is_file():
            return candidate
    for hub in hub_caches(cache_dir):
        repo_dir = hub / ("datasets--" + repo_id.replace("/", "--"))
        looked.append(str(repo_dir))
        found = _hub_snapshot(repo_dir, revision)
        if found is not None:
            return found
    raise ValueError(
        f"no local copy of LeRobot dataset {repo_id!r}"
        + (f" at revision {revision!r}" if revision else "")
        + f" (looked in {looked}); resolve_lerobot_root never uses the network "
        "(load_lerobot downloads it when online, with huggingface_hub)"
    )


def lerobot_home() -> Path:
    """``$HF_LEROBOT_HOME``, else ``$HF_HOME/lerobot`` (LeRobot's ``HF_LEROBOT_HOME``)."""
    hf_home = Path(os.environ.get("HF_HOME", Path.home() / ".cache" / "huggingface"))
    return Path(os.environ.get("HF_LEROBOT_HOME", hf_home / "lerobot")).expanduser()


def hub_caches(cache_dir: str | Path | None) -> list[Path]:
    """The hub caches a ``repo_id`` is looked up in, in order: ``[cache_dir]`` when given,
    else ``$HF_LEROBOT_HOME/hub`` (lerobot >= 0.6 downloads there) and the Hugging Face
    hub cache (``$HF_HUB_CACHE``, else ``$HF_HOME/hub``)."""
    if cache_dir is not None:
        return [Path(cache_dir).expanduser()]
    hf_home = Path(os.environ.get("HF_HOME", Path.home() / ".cache" / "huggingface"))
    hub = Path(os.environ.get("HF_HUB_CACHE", hf_home / "hub")).expanduser()
    return list(dict.fromkeys([lerobot_home() / "hub", hub]))


REPO_ID = re.compile(r"[\w.-]{1,96}/[\w.-]{1,96}")
"""``<org>/<name>``, as the Hub spells a dataset's ``repo_id``"""


def is_repo_id(text: str) -> bool:
    """Whether ``text`` has the shape of a Hub ``repo_id`` (``<org>/<name>``)."""
    return REPO_ID.fullmatch(text) is not None


def check_repo_id(repo_id: object) -> str:
    """``repo_id`` when it is ``<org>/<name>`` as the Hub allows them (letters, digits,
    ``_.-``; no part ``.``/``..``, none starting or ending with ``.`` or ``-``, no ``--``):
    it becomes a folder name of the caches; ValueError otherwise."""
    parts = repo_id.split("/") if isinstance(repo_id, str) else []
    if (
        not isinstance(repo_id, str)
        or not is_repo_id(repo_id)
        or any(p[0] in ".-" or p[-1] in ".-" or "--" in p or ".." in p for p in parts)
    ):
        raise ValueError(
            f"{repo_id!r} is not a Hub dataset repo_id (expected <org>/<name>: letters, digits, "
            "'_', '.', '-'; no '..' or '--', no part starting or ending with '.' or '-')"
        )
    return repo_id


_SNAPSHOT_NAME = re.compile(r"[\w.-]{1,128}")
"""a snapshot folder's name: a commit hash, or a revision the hub cache names one by"""


def _commit_of(ref_file: Path) -> str:
    """The commit a hub cache's ``refs/<ref>`` names (its first 256 bytes: a hash is 40)."""
    with open(ref_file, "rb") as f:
        return f.read(256).decode("utf-8", "replace").strip()


def _hub_snapshot(repo_dir: Path, revision: str | None) -> Path | None:
    """The snapshot of a hub cache's ``datasets--<org>--<name>`` that holds the dataset:
    ``revision`` (or ``v3.0``, ``v2.1``, ``main``) through ``refs/``, else (no revision
    asked for) the newest one holding ``meta/info.json``; None if there is none."""
    snapshots = repo_dir / "snapshots"
    if not snapshots.is_dir():
        return None
    refs = [revision] if revision is not None else ["v3.0", "v2.1", "main"]
    for ref in refs:
        ref_file = repo_dir / "refs" / ref
        commit = _commit_of(ref_file) if ref_file.is_file() else ref
        if not _SNAPSHOT_NAME.fullmatch(commit) or commit in (".", ".."):
            raise ValueError(
                f"{ref_file if ref_file.is_file() else repo_dir}: revision {commit[:80]!r} is "
                "not a snapshot's name (a commit hash or a tag): refusing to look outside "
                f"{snapshots}"
            )
        candidate = snapshots / commit
        if (candidate / "meta" / "info.json").is_file():
            return candidate
    if revision is None:
        found = [  # not a snapshot still being built (a hidden name)
            p
            for p in snapshots.iterdir()
            if not p.name.startswith(".") and (p / "meta" / "info.json").is_file()
        ]
        if found:
            return max(found, key=lambda p: (p / "meta" / "info.json").stat().st_mtime)
    return None
