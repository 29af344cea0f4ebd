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
daemon thread and shuts itself down after ``lifetime_s`` whatever the test does.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import unquote, urlsplit

LFS_SUFFIXES = (".parquet", ".mp4", ".png")


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

    def commit(self, rev: str) -> Commit | None:
        everything = [*self.branches.values(), *self.tags.values()]
        named = {**self.branches, **self.tags}
        return named.get(rev) or next((c for c in everything if c.sha == rev), None)


def git_blob_sha1(data: bytes) -> str:
    return hashlib.sha1(b"blob %d\0" % len(data) + data).hexdigest()


class _Handler(BaseHTTPRequestHandler):
    repos: dict[str, Repo] = {}
    log: list[str] = []

    def log_message(self, *args) -> None:  # quiet
        pass

    def _send(self, status: int, body: bytes, headers: dict[str, str], head: bool = False) -> None:
        self.send_response(status)
        for k, v in headers.items():
            self.send_header(k, v)
        if "Content-Length" not in headers:
            self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        if not head:
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
        self.log.append(f"{self.command} {self.path}")
        if parts[:2] == ["api", "datasets"] and len(parts) >= 5:
            repo_id, what, rest = f"{parts[2]}/{parts[3]}", parts[4], parts[5:]
        elif parts[:1] == ["datasets"] and len(parts) >= 6 and parts[3] == "resolve":
            repo_id, what, rest = f"{parts[1]}/{parts[2]}", "resolve", parts[4:]
        else:
            return self._missing("EntryNotFound")
        repo = self.repos.get(repo_id)
        if repo is None:
            return self._missing("RepoNotFound")
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
            return self._json(self._tree(repo, commit))
        if what == "resolve":
            return self._file(repo, commit, "/".join(rest[1:]), head)
        return self._missing("EntryNotFound")

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
    handler = type("Handler", (_Handler,), {"repos": repos, "log": []})
    server = ThreadingHTTPServer(("127.0.0.1", 0), handler)
    server.daemon_threads = True
    thread = threading.Thread(
        target=server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True
    )
    timer = threading.Timer(lifetime_s, server.shutdown)
    timer.daemon = True
    thread.start()
    timer.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}", handler.log
    finally:
        timer.cancel()
        server.shutdown()
        server.server_close()
        thread.join(timeout=5)
