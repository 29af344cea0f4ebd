"""A small Hugging Face Hub on 127.0.0.1, for downloads in tests (never the real Hub).

It answers the requests huggingface_hub makes (``HfApi.list_repo_refs``,
``dataset_info``, ``list_repo_tree``, ``hf_hub_download``/``snapshot_download``), as the
Hub answers them:

* ``GET /api/datasets/<org>/<name>/refs``: ``{"branches", "tags", "converts"}``, each
  ``{"name", "ref", "targetCommit"}``;
* ``GET /api/datasets/<org>/<name>/revision/<rev>``: ``{"id", "sha", "siblings":
  [{"rfilename"}], ...}``, 404 with ``X-Error-Code: RevisionNotFound`` for an unknown one;
* ``GET /api/datasets/<org>/<name>/tree/<rev>?recursive=true``: files ``{"type": "file",
  "oid": <git blob sha1>, "size", "path"}`` (binary files with ``"lfs": {"oid": <sha256>,
  "size", "pointerSize"}``, as ``.gitattributes`` puts parquet and mp4 files in LFS) and
  folders ``{"type": "directory", "oid", "path"}``;
* ``HEAD``/``GET /datasets/<org>/<name>/resolve/<rev>/<path>``: the bytes, with
  ``X-Repo-Commit``, ``ETag`` (the git blob sha1, or for an LFS file ``X-Linked-Etag``,
  its sha256), ``Content-Length``/``X-Linked-Size``.

Unknown repositories answer 404 with ``X-Error-Code: RepoNotFound``. The server runs in a
daemon thread and shuts itself down after ``lifetime_s`` whatever the test does. Its log
has one line per request, ``"<method> <path>"``, with `` +auth`` when it carried a token.

Hostile behaviours, per :class:`Repo`: ``misbehave`` makes one kind of request (``refs``,
``revision``, ``tree``, ``resolve``) stall, trickle, answer with a gzip bomb or announce a
huge body, or makes the file list never end (``tree``: every page names a next one);
``redirects`` answers a file's ``resolve`` with a 302 elsewhere (another
scheme: :func:`tcp_listener` counts who connects; another host: ``localhost``, whose
``/elsewhere/<org>/<name>/<rev>/<path>`` serves the file's right bytes).
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import socket
import struct
import threading
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, unquote, urlsplit

LFS_SUFFIXES = (".parquet", ".mp4", ".png")
MISBEHAVIOURS = ("stall", "trickle", "gzip-bomb", "huge", "endless", "empty-pages")
BOMB_BYTES = 1 << 30
"""what the gzip bomb inflates to: 1 GiB of zeros, in about 1 MB"""


@dataclass
class Commit:
    """One commit of a dataset repository: path -> bytes."""

    files: dict[str, bytes]
    sha: str = ""

    def __post_init__(self) -> None:
        if not self.sha:
            listing = json.dumps(
                sorted((p, hashlib.sha1(b).hexdigest()) for p, b in self.files.items())
            )
            self.sha = hashlib.sha1(listing.encode()).hexdigest()

    @classmethod
    def of_folder(cls, root: Path) -> Commit:
        """Every file under ``root`` (a dataset folder), as pushed to the Hub."""
        return cls(
            {
                p.relative_to(root).as_posix(): p.read_bytes()
                for p in sorted(root.rglob("*"))
                if p.is_file()
            }
        )


@dataclass
class Repo:
    """A dataset repository: its commits by branch or tag name."""

    branches: dict[str, Commit]
    tags: dict[str, Commit] = field(default_factory=dict)
    listing: dict[str, dict] = field(default_factory=dict)
    """path -> fields replacing what the tree listing says of that file (hostile servers)"""
    served: dict[str, bytes] = field(default_factory=dict)
    """path -> bytes served instead of the file's (hostile servers)"""
    headers: dict[str, str] = field(default_factory=dict)
    """headers added to every file response (hostile servers)"""
    misbehave: dict[str, str] = field(default_factory=dict)
    """request kind (``refs``, ``revision``, ``tree``, ``resolve``) -> how it is answered
    (hostile servers): ``stall`` (nothing, until the server stops), ``trickle`` (headers at
    once, then the body a byte per ``trickle_s``), ``gzip-bomb`` (``Content-Encoding:
    gzip``, :data:`BOMB_BYTES` of zeros), ``huge`` (``Content-Length: 2**40``, no body);
    for ``tree`` only, pages that never end, each naming the next (``?cursor=<n + 1>``)
    after the first (the real entries): ``endless`` (a new folder a page), ``empty-pages``
    (no entry)"""
    trickle_s: float = 0.2
    redirects: dict[str, str] = field(default_factory=dict)
    """path -> the ``Location`` its ``resolve`` answers with a 302 (``{port}``: this
    server's) (hostile servers)"""
    pace_s: float = 0.0
    """seconds each answer's body pauses halfway (so that concurrent downloads overlap)"""

    def commit(self, rev: str) -> Commit | None:
        everything = [*self.branches.values(), *self.tags.values()]
        named = {**self.branches, **self.tags}
        return named.get(rev) or next((c for c in everything if c.sha == rev), None)


def git_blob_sha1(data: bytes) -> str:
    return hashlib.sha1(b"blob %d\0" % len(data) + data).hexdigest()


@functools.cache
def gzip_bomb(size: int = BOMB_BYTES) -> bytes:
    """A gzip stream of ``size`` zeros (a multiple of 1 MiB) in about ``size / 1000`` bytes,
    made in a fraction of a second: one fully flushed deflate block of 1 MiB of zeros
    (always the same bytes) repeated, then the trailer."""
    block = bytes(1 << 20)
    deflate = zlib.compressobj(9, zlib.DEFLATED, -zlib.MAX_WBITS)
    repeated = deflate.compress(block) + deflate.flush(zlib.Z_FULL_FLUSH)
    crc = 0
    for _ in range(size >> 20):
        crc = zlib.crc32(block, crc)
    header = b"\x1f\x8b\x08\x00\x00\x00\x00\x00\x00\xff"
    end = b"\x03\x00" + struct.pack("<II", crc, size & 0xFFFFFFFF)  # an empty final block
    return header + repeated * (size >> 20) + end


class _Handler(BaseHTTPRequestHandler):
    repos: dict[str, Repo] = {}
    log: list[str] = []
    stop: threading.Event = threading.Event()
    """set when the server stops: stalled and trickling answers end"""

    def log_message(self, *args) -> None:  # quiet
        pass

    def _send(self, status: int, body: bytes, headers: dict[str, str], head: bool = False) -> None:
        how = self.misbehaving
        if how == "stall":
            self.stop.wait()
            return
        if how == "gzip-bomb":
            body, headers = gzip_bomb(), {**headers, "Content-Encoding": "gzip"}
            headers.pop("Content-Length", None)
        if how == "huge":
            body, headers = b"", {**headers, "Content-Length": str(1 << 40)}
        self.send_response(status)
        for k, v in headers.items():
            self.send_header(k, v)
        if "Content-Length" not in headers:
            self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        if head:
            return
        if how == "trickle":
            for i in range(len(body)):
                self.wfile.write(body[i : i + 1])
                self.wfile.flush()
                if self.stop.wait(self.misbehaving_repo.trickle_s):
                    return
        elif self.misbehaving_repo is not None and self.misbehaving_repo.pace_s:
            self.wfile.write(body[: len(body) // 2])
            self.wfile.flush()
            if self.stop.wait(self.misbehaving_repo.pace_s):
                return
            self.wfile.write(body[len(body) // 2 :])
        else:
            self.wfile.write(body)

    def _json(self, value, status: int = 200, headers: dict | None = None) -> None:
        body = json.dumps(value).encode()
        self._send(status, body, {"Content-Type": "application/json", **(headers or {})})

    def _missing(self, code: str) -> None:
        self._json({"error": code}, 404, {"X-Error-Code": code, "X-Error-Message": code})

    def do_HEAD(self) -> None:
        self._route(head=True)

    def do_GET(self) -> None:
        self._route(head=False)

    def _route(self, head: bool) -> None:
        parts = [unquote(p) for p in urlsplit(self.path).path.split("/")[1:]]
        auth = " +auth" if self.headers.get("Authorization") else ""
        self.log.append(f"{self.command} {self.path}{auth}")
        self.misbehaving, self.misbehaving_repo = None, None
        if parts[:2] == ["api", "datasets"] and len(parts) >= 5:
            repo_id, what, rest = f"{parts[2]}/{parts[3]}", parts[4], parts[5:]
        elif parts[:1] == ["datasets"] and len(parts) >= 6 and parts[3] == "resolve":
            repo_id, what, rest = f"{parts[1]}/{parts[2]}", "resolve", parts[4:]
        elif parts[:1] == ["elsewhere"] and len(parts) >= 5:  # a redirect's other host
            repo_id, what, rest = f"{parts[1]}/{parts[2]}", "elsewhere", parts[3:]
        else:
            return self._missing("EntryNotFound")
        repo = self.repos.get(repo_id)
        if repo is None:
            return self._missing("RepoNotFound")
        self.misbehaving = repo.misbehave.get(what)
        self.misbehaving_repo = repo
        if what == "refs":

            def refs(named, kind):
                return [
                    {"name": n, "ref": f"refs/{kind}/{n}", "targetCommit": c.sha}
                    for n, c in named.items()
                ]

            return self._json(
                {
                    "branches": refs(repo.branches, "heads"),
                    "tags": refs(repo.tags, "tags"),
                    "converts": [],
                }
            )
        commit = repo.commit(rest[0]) if rest else None
        if commit is None:
            return self._missing("RevisionNotFound")
        if what == "revision":
            return self._json(
                {
                    "_id": commit.sha[:24],
                    "id": repo_id,
                    "author": repo_id.split("/")[0],
                    "sha": commit.sha,
                    "private": False,
                    "gated": False,
                    "disabled": False,
                    "downloads": 0,
                    "likes": 0,
                    "tags": [],
                    "lastModified": "2025-01-01T00:00:00.000Z",
                    "siblings": [{"rfilename": p} for p in commit.files],
                }
            )
        if what == "tree":
            return self._tree_page(repo, commit)
        path = "/".join(rest[1:])
        if what == "resolve" and path in repo.redirects:
            where = repo.redirects[path].format(port=self.server.server_address[1])
            return self._send(302, b"", {"Location": where})
        if what in ("resolve", "elsewhere"):
            return self._file(repo, commit, path, head)
        return self._missing("EntryNotFound")

    def _tree_page(self, repo: Repo, commit: Commit) -> None:
        """The whole list in one page, or (``endless``, ``empty-pages``) page ``cursor`` of
        a list that never ends."""
        entries = self._tree(repo, commit)
        how = self.misbehaving
        if how not in ("endless", "empty-pages"):
            return self._json(entries)
        url = urlsplit(self.path)
        n = int(parse_qs(url.query).get("cursor", ["0"])[0])
        if n == 0:
            page = entries
        elif how == "endless":
            page = [{"type": "directory", "oid": "0" * 40, "path": f"more/{n}"}]
        else:
            page = []
        link = f'<{url.path}?recursive=true&expand=false&cursor={n + 1}>; rel="next"'
        return self._json(page, headers={"Link": link})

    def _tree(self, repo: Repo, commit: Commit) -> list[dict]:
        folders = sorted(
            {"/".join(p.split("/")[:i]) for p in commit.files for i in range(1, p.count("/") + 1)}
        )
        out = [{"type": "directory", "oid": "0" * 40, "path": d} for d in folders]
        for path, data in commit.files.items():
            entry = {"type": "file", "oid": git_blob_sha1(data), "size": len(data), "path": path}
            if path.endswith(LFS_SUFFIXES):
                entry["lfs"] = {
                    "oid": hashlib.sha256(data).hexdigest(),
                    "size": len(data),
                    "pointerSize": 134,
                }
            out.append({**entry, **repo.listing.get(path, {})})
        return out

    def _file(self, repo: Repo, commit: Commit, path: str, head: bool) -> None:
        if path not in commit.files:
            return self._missing("EntryNotFound")
        data = repo.served.get(path, commit.files[path])
        headers = {
            "X-Repo-Commit": commit.sha,
            "Accept-Ranges": "bytes",
            "Content-Length": str(len(data)),
        }
        if path.endswith(LFS_SUFFIXES):
            digest = hashlib.sha256(commit.files[path]).hexdigest()
            headers.update(
                {
                    "X-Linked-Etag": f'"{digest}"',
                    "X-Linked-Size": str(len(data)),
                    "ETag": f'"{digest}"',
                }
            )
        else:
            headers["ETag"] = f'"{git_blob_sha1(commit.files[path])}"'
        self._send(200, data, {**headers, **repo.headers}, head=head)


@contextlib.contextmanager
def hub_server(
    repos: dict[str, Repo], *, lifetime_s: float = 60.0
) -> Iterator[tuple[str, list[str]]]:
    """``(endpoint, request log)`` of a Hub serving ``repos`` on 127.0.0.1; stopped on exit,
    or after ``lifetime_s`` seconds at the latest."""
    stop = threading.Event()
    handler = type("Handler", (_Handler,), {"repos": repos, "log": [], "stop": stop})
    server = ThreadingHTTPServer(("127.0.0.1", 0), handler)
    server.daemon_threads = True
    thread = threading.Thread(
        target=server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True
    )

    def shut() -> None:
        stop.set()
        server.shutdown()

    timer = threading.Timer(lifetime_s, shut)
    timer.daemon = True
    thread.start()
    timer.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}", handler.log
    finally:
        timer.cancel()
        stop.set()
        server.shutdown()
        server.server_close()
        thread.join(timeout=5)


@contextlib.contextmanager
def tcp_listener() -> Iterator[tuple[int, list[str]]]:
    """``(port, connections)`` of a listener on 127.0.0.1 that closes every connection at
    once, noting its peer: a redirect's target (``ftp://``) that must never be reached."""
    listener = socket.create_server(("127.0.0.1", 0))
    listener.settimeout(0.05)
    connections: list[str] = []
    done = threading.Event()

    def accept() -> None:
        while not done.is_set():
            try:
                peer, address = listener.accept()
            except (TimeoutError, OSError):
                continue
            connections.append(f"{address[0]}:{address[1]}")
            peer.close()

    thread = threading.Thread(target=accept, daemon=True)
    thread.start()
    try:
        yield listener.getsockname()[1], connections
    finally:
        done.set()
        thread.join(timeout=5)
        listener.close()
