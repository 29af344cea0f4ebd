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

The Hub (``$HF_ENDPOINT``) is asked for the revision's commit
(``/api/datasets/<repo_id>/revision/<revision>``), its file list
(``/api/datasets/<repo_id>/tree/<commit>?recursive=true``, page by page as its ``Link``
header says), and each file (``/datasets/<repo_id>/resolve/<commit>/<path>``), through
:class:`~imitrl.datasets.lerobot._hub_http.HubClient`: urllib with connect and read
timeouts, a deadline over every answer, answers bounded in decoded size and redirects
only to the endpoint's host (or the official Hub's CDN), all set by
:class:`~imitrl.datasets.lerobot._hub_http.HubLimits` (its module docstring says why not
``HfApi``: none of that can be set through it). huggingface_hub (the ``hub`` extra) gives
the token and the progress bar.

Everything the server says is hostile until checked, before anything is written: the
commit is 40 hex digits, every file name a plain relative path
(:func:`imitrl.fs.contained.inside`), every blob name a hex digest; each file's bytes must
hash to the digest the listing gave, and only then does it become a blob. Nothing is
written outside ``datasets--<org>--<name>/`` of the cache (unlike ``snapshot_download``,
which names blobs after the server's ``ETag`` header), nor through a link planted there
(:mod:`imitrl.fs.files`). Downloads of one dataset into one cache, from any number of
processes, take turns (:func:`imitrl.fs.lock.exclusive` on its repository folder, as
huggingface_hub locks its cache): the second finds the first's blobs and fetches nothing.
It waits at most ``HubLimits.lock_wait_s`` (by default as long as the files it lacks may
take to download), then gives up naming the process that holds the lock (a stopped
download, say). The file list is bounded in pages and in time, each file's listed size
in bytes (and, all together, by the cache's free disk space) before any is fetched.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import quote

from imitrl.datasets.lerobot._hub_http import HubClient
from imitrl.datasets.lerobot._hub_limits import MAX_EMPTY_PAGES, HubLimits
from imitrl.datasets.lerobot._locate import (
    check_repo_id,
    is_repo_id,
    lerobot_home,
    resolve_lerobot_root,
)
from imitrl.fs.contained import inside, links_stay_inside
from imitrl.fs.files import PlantedLinkError, create_file, make_folder, replace_file
from imitrl.fs.lock import exclusive
from imitrl.fs.publish import OLD

__all__ = ["REVISIONS", "HubLimits", "dataset_root", "download_lerobot", "offline"]

REVISIONS = ("v3.0", "v2.1", "v2.0")
"""the version tags a LeRobot dataset's revision defaults to, best first (lerobot asks for
its ``CODEBASE_VERSION`` through ``get_safe_version``; imitrl reads these three)"""

_COMMIT = re.compile(r"[0-9a-f]{40}")
_DIGEST = re.compile(r"[0-9a-f]{40}|[0-9a-f]{64}")
MAX_ENTRIES = 1_000_000
"""files and folders a dataset's file list may name (the largest LeRobot datasets, v2.1
with a file per episode and camera, name a few hundred thousand)"""


def dataset_root(
    path_or_repo: str | Path,
    revision: str | None,
    cache_dir: str | Path | None,
    *,
    limits: HubLimits | None = None,
) -> Path:
    """The dataset directory: ``path_or_repo`` itself, or a ``repo_id`` found locally or,
    online, downloaded (:func:`download_lerobot`, under ``limits``); refused when a
    symbolic link in it points outside it (:func:`imitrl.fs.contained.links_stay_inside`;
    a hub snapshot's links into its own ``blobs/`` are its own)."""
    root = _find_root(path_or_repo, revision, cache_dir, limits)
    links_stay_inside(root, what="dataset")
    return root


def _find_root(
    path_or_repo: str | Path,
    revision: str | None,
    cache_dir: str | Path | None,
    limits: HubLimits | None,
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
            return download_lerobot(text, revision=revision, cache_dir=cache_dir, limits=limits)
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
    repo_id: str,
    *,
    revision: str | None = None,
    cache_dir: str | Path | None = None,
    limits: HubLimits | None = None,
) -> Path:
    """Download a LeRobot dataset from the Hugging Face Hub (``$HF_ENDPOINT``) and return
    its snapshot folder, as lerobot 0.6 does (see the module docstring for the layout).

    Args:
        repo_id: ``<org>/<name>``.
        revision: a branch, tag or commit; None takes the dataset's best version tag
            (``v3.0``, else ``v2.1``, else ``v2.0``, as lerobot's ``get_safe_version``
            would), else ``main``.
        cache_dir: the hub cache to download into; default ``$HF_LEROBOT_HOME/hub``.
        limits: timeouts, deadlines, the bounds on API answers, the file list and file
            sizes, where redirects may go and how long to wait for another download
            (:class:`~imitrl.datasets.lerobot._hub_limits.HubLimits`); None:
            ``HubLimits.from_env()`` (connect 10 s, read 30 s or
            ``$HF_HUB_DOWNLOAD_TIMEOUT``, 120 s per API answer, a file that plus 1 s per
            32 KiB and at most 24 h, the file list 30 min and 10,000 pages, answers up to
            64 MiB, files up to 50 GiB, redirects to the endpoint's host or the official
            Hub's CDN).

    Files already in the cache's ``blobs/`` are not downloaded again; progress is shown
    with huggingface_hub's progress bar (``HF_HUB_DISABLE_PROGRESS_BARS=1`` hides it). A
    second download of the same dataset into the same cache waits for the first (saying
    so on stderr), at most ``limits.lock_wait_s``, and then fetches only what is still
    missing.

    Raises:
        ImportError: huggingface_hub is not installed (the message says how).
        ValueError: the repository or revision is unknown or unreachable; the server stays
            silent or slow past ``limits``, sends an answer larger than them, a file list
            longer than them, or redirects elsewhere; it names a commit, file or digest
            that is not one, or a file larger than ``limits.max_file_bytes`` (refused
            before anything is written); the files need more than the cache's disk has
            free; another download into the cache holds its lock past
            ``limits.lock_wait_s`` (the message names its process); a file's bytes differ
            from the digest or size listed.
    """
    hub = _hub()
    check_repo_id(repo_id)
    endpoint = (os.environ.get("HF_ENDPOINT") or hub.constants.ENDPOINT).rstrip("/")
    limits = limits if limits is not None else HubLimits.from_env()
    client = HubClient(endpoint, limits, token=hub.get_token())
    where = f"{endpoint}/datasets/{repo_id}"
    api = f"{endpoint}/api/datasets/{repo_id}"
    rev = revision if revision is not None else _default_revision(client, api, where)
    try:
        info, _ = client.get_json(f"{api}/revision/{quote(rev, safe='')}")
    except ValueError as err:
        raise ValueError(f"{where}: cannot resolve revision {rev!r} ({err})") from None
    commit = info.get("sha") if isinstance(info, dict) else None
    if not isinstance(commit, str) or not _COMMIT.fullmatch(commit):
        raise ValueError(f"{where}: revision {rev!r} names commit {commit!r}, not 40 hex digits")
    cache = Path(cache_dir).expanduser() if cache_dir is not None else lerobot_home() / "hub"
    repo_dir = cache / ("datasets--" + repo_id.replace("/", "--"))
    snapshot = repo_dir / "snapshots" / commit
    files = _listing(client, f"{api}/tree/{commit}", commit, snapshot, where)
    with _repository_lock(repo_dir, files, limits, where):  # one download at a time
        resolve = f"{endpoint}/datasets/{repo_id}/resolve/{commit}"
        _fetch_blobs(hub, client, resolve, repo_id, commit, repo_dir / "blobs", files, where)
        _link_snapshot(repo_dir, snapshot, files)
        if rev != commit:
            ref = inside(repo_dir / "refs", rev, named_by=f"revision {rev!r}")
            make_folder(ref.parent)
            replace_file(ref, commit, what=f"the commit of revision {rev!r}")
    return snapshot


def _missing(blobs: Path, files: list[_File]) -> dict[str, _File]:
    """blob -> a file stored as it, for each blob not yet in ``blobs``."""
    return {f.blob: f for f in files if not (blobs / f.blob).is_file()}


@contextmanager
def _repository_lock(
    repo_dir: Path, files: list[_File], limits: HubLimits, where: str
) -> Iterator[None]:
    """The cache's lock on ``repo_dir``, waited for at most ``limits.lock_wait_s`` (None:
    ``deadline_s`` plus the deadline of each file the cache lacks, what another download
    of them may take); ValueError naming the process that holds it past that."""
    wait = limits.lock_wait_s
    if wait is None:
        todo = _missing(repo_dir / "blobs", files).values()
        wait = limits.deadline_s + sum(limits.file_deadline_s(f.size) for f in todo)
    with ExitStack() as stack:
        try:
            stack.enter_context(exclusive(repo_dir, what="downloaded", wait=wait))
        except PlantedLinkError:
            raise
        except ValueError as err:
            raise ValueError(
                f"{where}: gave up after waiting {wait:g} s for another download into the same "
                f"cache: {err} (a stopped or hung download holds it: end that process, or "
                "wait longer with HubLimits(lock_wait_s=...))"
            ) from None
        yield


def _default_revision(client: HubClient, api: str, where: str) -> str:
    """The best of :data:`REVISIONS` among the repository's branches and tags, else
    ``main``."""
    try:
        refs, _ = client.get_json(f"{api}/refs")
    except ValueError as err:
        raise ValueError(f"{where}: cannot list its revisions ({err})") from None
    if not isinstance(refs, dict):
        raise ValueError(f"{where}: its revisions are {type(refs).__name__}, not an object")
    names: set[str] = set()
    for kind in ("branches", "tags"):
        listed = refs.get(kind, [])
        if not isinstance(listed, list) or not all(isinstance(r, dict) for r in listed):
            raise ValueError(f"{where}: its revisions' {kind!r} are not a list of objects")
        names.update(r.get("name") for r in listed if isinstance(r.get("name"), str))
    return next((v for v in REVISIONS if v in names), "main")


def _tree_entries(client: HubClient, tree: str, where: str) -> Iterator[dict]:
    """Every entry of the recursive tree listing, page by page; refused past
    :data:`MAX_ENTRIES`, past ``max_pages`` pages or :data:`MAX_EMPTY_PAGES` empty ones in
    a row, past ``listing_deadline_s`` for them all, or when a page comes round again."""
    limits = client.limits
    url: str | None = f"{tree}?recursive=true&expand=false"
    seen: set[str] = set()
    listed = empty = 0
    end = time.monotonic() + limits.listing_deadline_s
    rule = (
        f"{limits.listing_deadline_s:g} s for the whole file list; set "
        "HubLimits(listing_deadline_s=...) to wait longer"
    )
    while url is not None:
        if url in seen:
            raise ValueError(f"{where}: its file list comes back to page {url}; refused")
        if len(seen) == limits.max_pages:
            raise ValueError(
                f"{where}: its file list goes on past {limits.max_pages} pages ({listed} "
                "entries so far; HubLimits(max_pages=...)); refused"
            )
        left = end - time.monotonic()
        if left <= 0:
            raise ValueError(
                f"{where}: its file list is not over after {len(seen)} pages ({listed} entries) "
                f"in {limits.listing_deadline_s:g} s (deadline: {rule})"
            )
        seen.add(url)
        page, url = client.get_json(url, within=(left, rule))
        if not isinstance(page, list) or not all(isinstance(e, dict) for e in page):
            raise ValueError(f"{where}: its file list is not a list of objects")
        listed += len(page)
        if listed > MAX_ENTRIES:
            raise ValueError(f"{where}: its file list names more than {MAX_ENTRIES} entries")
        empty = empty + 1 if not page and url is not None else 0
        if empty > MAX_EMPTY_PAGES:
            raise ValueError(
                f"{where}: its file list sends {empty} empty pages in a row, each naming a next "
                f"page (at most {MAX_EMPTY_PAGES}); refused"
            )
        yield from page


def _listing(client: HubClient, tree: str, commit: str, snapshot: Path, where: str) -> list[_File]:
    """Every file of the commit, each name and digest checked before anything is written."""
    files = []
    entries = _tree_entries(client, tree, where)
    while True:
        try:
            entry = next(entries, None)
        except ValueError as err:
            raise ValueError(f"{where}: cannot list the files of commit {commit} ({err})") from None
        if entry is None:
            break
        if entry.get("type") == "file":  # else a folder
            files.append(_file(entry, snapshot, client.limits.max_file_bytes, where))
    if not any(f.path == "meta/info.json" for f in files):
        raise ValueError(f"{where}: commit {commit} holds no meta/info.json: not a LeRobot dataset")
    return files


def _file(entry: dict, snapshot: Path, max_bytes: int, where: str) -> _File:
    """A file entry of the tree listing, its path, digest and size (at most ``max_bytes``)
    checked."""
    path = entry.get("path")
    if not isinstance(path, str):
        raise ValueError(f"{where}: a file is listed with path {path!r}")
    inside(snapshot, path, named_by=f"{where}'s file list")
    lfs = entry.get("lfs")
    if lfs is not None and not isinstance(lfs, dict):
        raise ValueError(f"{where}: {path!r} is listed with lfs {lfs!r}")
    blob = lfs.get("oid") if lfs is not None else entry.get("oid")
    size = lfs.get("size") if lfs is not None else entry.get("size")
    if not isinstance(blob, str) or not _DIGEST.fullmatch(blob):
        raise ValueError(f"{where}: {path!r} is listed with digest {blob!r}, not hex")
    if isinstance(size, bool) or not isinstance(size, int) or size < 0:
        raise ValueError(f"{where}: {path!r} is listed with size {size!r}")
    if size > max_bytes:
        raise ValueError(
            f"{where}: {path!r} is listed with {size:,} bytes, more than the {max_bytes:,} a "
            "file may hold (HubLimits(max_file_bytes=...)); refused before downloading"
        )
    return _File(path, size, blob, lfs is not None)


def _fetch_blobs(
    hub: Any,
    client: HubClient,
    resolve: str,
    repo_id: str,
    commit: str,
    blobs: Path,
    files: list[_File],
    where: str,
) -> None:
    """Each file's bytes into ``blobs/<digest>``, once they hash to it (blobs already there
    are kept), with one progress bar over the bytes to fetch; refused before any is
    fetched when they need more than the cache's disk has free."""
    make_folder(blobs)
    todo = _missing(blobs, files)
    total = sum(f.size for f in todo.values())
    free = shutil.disk_usage(blobs).free
    if total > free:
        raise ValueError(
            f"{where}: its files take {total:,} bytes, the disk of {blobs} has {free:,} free; "
            "refused before downloading"
        )
    with hub.utils.tqdm(
        total=total, unit="B", unit_scale=True, desc=f"Downloading {repo_id}"
    ) as bar:
        for blob, f in todo.items():
            url = f"{resolve}/{quote(f.path)}"
            _fetch_one(client, url, f, commit, blobs / blob, progress=bar.update)


def _fetch_one(
    client: HubClient,
    url: str,
    f: _File,
    commit: str,
    blob: Path,
    *,
    progress: Callable[[int], object],
) -> None:
    """One file into ``blob``: streamed into ``<blob>.incomplete`` (created new, never
    through a link), hashed on the way, renamed once its size and digest are the listed
    ones. The caller holds the repository's lock: an ``.incomplete`` found is a killed
    download's."""
    digest = hashlib.sha256() if f.lfs else hashlib.sha1(b"blob %d\0" % f.size)
    part = blob.with_name(blob.name + ".incomplete")
    part.unlink(missing_ok=True)  # a killed download's (unlink removes a link, not its target)
    got = 0
    try:
        with client.stream(url, f.size) as response:
            served = response.headers.get("X-Repo-Commit")
            if served is not None and served != commit:
                raise ValueError(f"{url}: served from commit {served!r}, not {commit}")
            with os.fdopen(create_file(part, what="a blob being downloaded"), "wb") as out:
                while block := response.read(1 << 20):
                    got += len(block)
                    if got > f.size:
                        break
                    digest.update(block)
                    out.write(block)
                    progress(len(block))
            if got != f.size or digest.hexdigest() != f.blob:
                raise ValueError(
                    f"{url}: {f.path} arrived with {got} bytes and digest {digest.hexdigest()}, "
                    f"the file list says {f.size} bytes and {f.blob}; refusing altered data"
                )
        os.replace(part, blob)
    finally:
        part.unlink(missing_ok=True)  # nothing half-downloaded stays behind


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
        make_folder(link.parent)
        link.symlink_to(os.path.relpath(repo_dir / "blobs" / f.blob, link.parent))
    if target != snapshot:
        os.replace(target, snapshot)
