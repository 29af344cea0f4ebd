"""Where a LeRobot dataset comes from: a folder, a local cache, or the Hub.

:func:`dataset_root` takes a folder as it is; a ``repo_id`` is looked up in the local
caches (:func:`~imitrl.datasets.lerobot._locate.resolve_lerobot_root`) and, when none holds
it and the machine is online, downloaded by :func:`download_lerobot` into
``$HF_LEROBOT_HOME/hub`` (or ``cache_dir``), where lerobot 0.6 downloads
(``snapshot_download(repo_id, repo_type="dataset", revision=..., cache_dir=
HF_LEROBOT_HUB_CACHE)``), in the Hugging Face cache layout::

    datasets--<org>--<name>/blobs/<sha256 or git blob sha1>      file contents
    datasets--<org>--<name>/snapshots/<commit>/<path>            relative links to blobs/
    datasets--<org>--<name>/refs/<revision>                      the commit a revision names

The Hub is asked through ``huggingface_hub`` (the ``hub`` extra): the revision's commit
(``/api/datasets/<repo_id>/revision/<revision>``), its file list
(``/api/datasets/<repo_id>/tree/<commit>``), and each file
(``/datasets/<repo_id>/resolve/<commit>/<path>``). Everything the server says is hostile
until checked, before anything is written: the commit is 40 hex digits, every file name a
plain relative path (:func:`imitrl.fs.contained.inside`), every blob name a hex digest;
each file's bytes must hash to the digest the listing gave, and only then does it become
a blob. Nothing is written outside ``datasets--<org>--<name>/`` of the cache (unlike
``snapshot_download``, which names blobs after the server's ``ETag`` header).
"""

from __future__ import annotations

import hashlib
import os
import re
import urllib.error
import urllib.request
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import quote

from imitrl.datasets.lerobot._locate import (
    check_repo_id,
    is_repo_id,
    lerobot_home,
    resolve_lerobot_root,
)
from imitrl.fs.contained import inside, links_stay_inside
from imitrl.fs.publish import OLD

REVISIONS = ("v3.0", "v2.1", "v2.0")
"""the version tags a LeRobot dataset's revision defaults to, best first (lerobot asks for
its ``CODEBASE_VERSION`` through ``get_safe_version``; imitrl reads these three)"""

_COMMIT = re.compile(r"[0-9a-f]{40}")
_DIGEST = re.compile(r"[0-9a-f]{40}|[0-9a-f]{64}")
TIMEOUT_S = 30.0
"""seconds a Hub request may stay silent before the download is abandoned"""


def dataset_root(
    path_or_repo: str | Path, revision: str | None, cache_dir: str | Path | None
) -> Path:
    """The dataset directory: ``path_or_repo`` itself, or a ``repo_id`` found locally or,
    online, downloaded (:func:`download_lerobot`); refused when a symbolic link in it points
    outside it (:func:`imitrl.fs.contained.links_stay_inside`; a hub snapshot's links into
    its own ``blobs/`` are its own)."""
    root = _find_root(path_or_repo, revision, cache_dir)
    links_stay_inside(root, what="dataset")
    return root


def _find_root(
    path_or_repo: str | Path, revision: str | None, cache_dir: str | Path | None
) -> Path:
    path = Path(path_or_repo).expanduser()
    if path.is_dir():
        return path
    text = str(path_or_repo)
    if is_repo_id(text) and not path.exists():
        try:
            return resolve_lerobot_root(text, revision=revision, cache_dir=cache_dir)
        except ValueError as missing:
            if offline():
                raise ValueError(
                    f"{missing}; HF_HUB_OFFLINE is set, so it is not downloaded"
                ) from None
            return download_lerobot(text, revision=revision, cache_dir=cache_dir)
    aside = sorted(path.parent.glob(f".{path.name}{OLD}*")) if path.name else []
    if aside:  # a save_lerobot killed between its two renames (imitrl.fs.publish)
        raise ValueError(
            f"{path}: no such dataset directory; a killed save_lerobot left the previous one "
            f"beside it as {aside[0].name}: the next save_lerobot to {path.name} moves it back"
        )
    raise ValueError(f"{path}: no such dataset directory")


def offline() -> bool:
    """``HF_HUB_OFFLINE`` is set (``1``/``true``/``yes``/``on``), as huggingface_hub reads it."""
    return os.environ.get("HF_HUB_OFFLINE", "").strip().upper() in ("1", "ON", "YES", "TRUE")


def _hub() -> Any:
    try:
        import huggingface_hub
    except ImportError as err:
        raise ImportError(
            "downloading a LeRobot dataset needs huggingface_hub: pip install 'imitrl[hub]' "
            "(or download it yourself and pass its folder)"
        ) from err
    return huggingface_hub


@dataclass(frozen=True)
class _File:
    """One file of the snapshot, as the Hub lists it."""

    path: str
    """its name in the repository, a plain relative path"""
    size: int
    blob: str
    """the blob it is stored as: the LFS SHA-256, else the git blob SHA-1"""
    lfs: bool


def download_lerobot(
    repo_id: str, *, revision: str | None = None, cache_dir: str | Path | None = None
) -> Path:
    """Download a LeRobot dataset from the Hugging Face Hub (``$HF_ENDPOINT``) and return
    its snapshot folder, as lerobot 0.6 does (see the module docstring for the layout).

    Args:
        repo_id: ``<org>/<name>``.
        revision: a branch, tag or commit; None takes the dataset's best version tag
            (``v3.0``, else ``v2.1``, else ``v2.0``, as lerobot's ``get_safe_version``
            would), else ``main``.
        cache_dir: the hub cache to download into; default ``$HF_LEROBOT_HOME/hub``.

    Files already in the cache's ``blobs/`` are not downloaded again; progress is shown
    with huggingface_hub's progress bar (``HF_HUB_DISABLE_PROGRESS_BARS=1`` hides it).

    Raises:
        ImportError: huggingface_hub is not installed (the message says how).
        ValueError: the repository or revision is unknown or unreachable; the server names
            a commit, file or digest that is not one (refused before anything is written);
            a file's bytes differ from the digest or size listed.
    """
    hub = _hub()
    check_repo_id(repo_id)
    endpoint = (os.environ.get("HF_ENDPOINT") or hub.constants.ENDPOINT).rstrip("/")
    api = hub.HfApi(endpoint=endpoint)
    where = f"{endpoint}/datasets/{repo_id}"
    rev = revision if revision is not None else _default_revision(api, repo_id, where)
    try:
        commit = api.dataset_info(repo_id, revision=rev).sha
    except Exception as err:  # the Hub's errors: not found, gated, unreachable
        raise ValueError(f"{where}: cannot resolve revision {rev!r} ({err})") from err
    if not isinstance(commit, str) or not _COMMIT.fullmatch(commit):
        raise ValueError(f"{where}: revision {rev!r} names commit {commit!r}, not 40 hex digits")
    cache = Path(cache_dir).expanduser() if cache_dir is not None else lerobot_home() / "hub"
    repo_dir = cache / ("datasets--" + repo_id.replace("/", "--"))
    snapshot = repo_dir / "snapshots" / commit
    files = _listing(api, repo_id, commit, snapshot, where)
    _fetch_blobs(hub, endpoint, repo_id, commit, repo_dir / "blobs", files, token=hub.get_token())
    _link_snapshot(repo_dir, snapshot, files)
    if rev != commit:
        ref = inside(repo_dir / "refs", rev, named_by=f"revision {rev!r}")
        ref.parent.mkdir(parents=True, exist_ok=True)
        ref.write_text(commit)
    return snapshot


def _default_revision(api: Any, repo_id: str, where: str) -> str:
    """The best of :data:`REVISIONS` among the repository's branches and tags, else
    ``main``."""
    try:
        refs = api.list_repo_refs(repo_id, repo_type="dataset")
    except Exception as err:  # the Hub's errors: not found, gated, unreachable
        raise ValueError(f"{where}: cannot list its revisions ({err})") from err
    names = {r.name for r in [*refs.branches, *refs.tags]}
    return next((v for v in REVISIONS if v in names), "main")


def _listing(api: Any, repo_id: str, commit: str, snapshot: Path, where: str) -> list[_File]:
    """Every file of the commit, each name and digest checked before anything is written."""
    try:
        entries = list(
            api.list_repo_tree(repo_id, repo_type="dataset", revision=commit, recursive=True)
        )
    except Exception as err:  # the Hub's errors: not found, gated, unreachable
        raise ValueError(f"{where}: cannot list the files of commit {commit} ({err})") from err
    files = []
    for entry in entries:
        if not hasattr(entry, "blob_id"):
            continue  # a folder
        named_by = f"{where}'s file list"
        inside(snapshot, entry.path, named_by=named_by)
        lfs = getattr(entry, "lfs", None)
        blob = lfs.sha256 if lfs is not None else entry.blob_id
        size = lfs.size if lfs is not None else entry.size
        if not isinstance(blob, str) or not _DIGEST.fullmatch(blob):
            raise ValueError(f"{where}: {entry.path!r} is listed with digest {blob!r}, not hex")
        if isinstance(size, bool) or not isinstance(size, int) or size < 0:
            raise ValueError(f"{where}: {entry.path!r} is listed with size {size!r}")
        files.append(_File(entry.path, size, blob, lfs is not None))
    if not any(f.path == "meta/info.json" for f in files):
        raise ValueError(f"{where}: commit {commit} holds no meta/info.json: not a LeRobot dataset")
    return files


def _fetch_blobs(
    hub: Any,
    endpoint: str,
    repo_id: str,
    commit: str,
    blobs: Path,
    files: list[_File],
    *,
    token: str | None,
) -> None:
    """Each file's bytes into ``blobs/<digest>``, once they hash to it (blobs already there
    are kept), with one progress bar over the bytes to fetch."""
    blobs.mkdir(parents=True, exist_ok=True)
    todo = {f.blob: f for f in files if not (blobs / f.blob).is_file()}
    total = sum(f.size for f in todo.values())
    with hub.utils.tqdm(
        total=total, unit="B", unit_scale=True, desc=f"Downloading {repo_id}"
    ) as bar:
        for blob, f in todo.items():
            url = f"{endpoint}/datasets/{repo_id}/resolve/{commit}/{quote(f.path)}"
            _fetch_one(url, f, commit, blobs / blob, token=token, progress=bar.update)


def _fetch_one(
    url: str, f: _File, commit: str, blob: Path, *, token: str | None, progress: Any
) -> None:
    """One file into ``blob``: streamed into ``<blob>.incomplete``, hashed on the way,
    renamed once its size and digest are the listed ones."""
    request = urllib.request.Request(url, headers={"User-Agent": "imitrl"})
    if token:  # never sent on to a redirect's host (the Hub's CDN)
        request.add_unredirected_header("Authorization", f"Bearer {token}")
    digest = hashlib.sha256() if f.lfs else hashlib.sha1(b"blob %d\0" % f.size)
    part = blob.with_name(blob.name + ".incomplete")
    got = 0
    try:
        with (
            urllib.request.urlopen(request, timeout=TIMEOUT_S) as response,
            open(part, "wb") as out,
        ):
            served = response.headers.get("X-Repo-Commit")
            if served is not None and served != commit:
                raise ValueError(f"{url}: served from commit {served!r}, not {commit}")
            for block in iter(lambda: response.read(1 << 20), b""):
                got += len(block)
                if got > f.size:
                    break
                digest.update(block)
                out.write(block)
                progress(len(block))
        if got != f.size or digest.hexdigest() != f.blob:
            raise ValueError(
                f"{url}: {f.path} arrived with {got} bytes and digest {digest.hexdigest()}, the "
                f"file list says {f.size} bytes and {f.blob}; refusing altered data"
            )
    except (urllib.error.URLError, OSError) as err:
        raise ValueError(f"{url}: download failed ({err})") from err
    finally:
        if got != f.size or digest.hexdigest() != f.blob:
            part.unlink(missing_ok=True)  # nothing half-downloaded stays behind
    os.replace(part, blob)


def _link_snapshot(repo_dir: Path, snapshot: Path, files: list[_File]) -> None:
    """``snapshots/<commit>/<path>`` -> ``../blobs/<digest>`` (relative links, as the Hub's
    cache has them); links already there are kept. A new snapshot is built beside and
    renamed into place, so that a half-built one is never found by
    :func:`~imitrl.datasets.lerobot._locate.resolve_lerobot_root`."""
    target = snapshot
    if not snapshot.exists():
        target = snapshot.with_name(f".{snapshot.name}.imitrl-{os.getpid()}")
    for f in files:
        link = inside(target, f.path, named_by="the Hub's file list")
        if link.is_symlink() or link.exists():
            continue
        link.parent.mkdir(parents=True, exist_ok=True)
        link.symlink_to(os.path.relpath(repo_dir / "blobs" / f.blob, link.parent))
    if target != snapshot:
        os.replace(target, snapshot)
