"""The LeRobot Hub download never hangs, never blows up memory, never follows a redirect
elsewhere, and lets concurrent downloads take turns (issue 42, finding 4): against a Hub
on 127.0.0.1 (``_lerobot_hub_server``) that stalls, trickles, sends a gzip bomb or
redirects to ``ftp://`` and to another host. Nor does it hang on a file list that never
ends, a file listed with a size no file has, or a stopped download holding the cache's
lock (findings 5, 6 and 7 of the dataset readers' review).

Every download that could hang runs in a forked child that the test kills past its own
bound (and past a memory bound), so that a regression fails the test instead of hanging
or swapping the machine.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from imitrl.datasets import download_lerobot

from ._lerobot_hub_server import BOMB_BYTES, Commit, Repo, gzip_bomb, hub_server, tcp_listener

pytest.importorskip("huggingface_hub")

FILES = {
    "meta/info.json": b'{"codebase_version": "v3.0"}',
    "meta/stats.json": b"{}",
    "data/chunk-000/file-000.parquet": bytes(range(256)) * 64,
    "videos/observation.images.top/chunk-000/file-000.mp4": bytes(range(7, 250)) * 40,
}
"""a dataset's files as the download sees them (never parsed: only listed and hashed)"""
CHILD_S = 15.0
"""seconds a forked download may run before the test kills it and fails"""
CHILD_GROWTH_MB = 768
"""resident memory a forked download may add before the test kills it and fails"""
forked = pytest.mark.skipif(
    not hasattr(os, "fork") or not Path("/proc/self/status").exists(),
    reason="runs the download in a forked child watched through /proc (Linux)",
)


@pytest.fixture
def hub_env(tmp_path, monkeypatch) -> Path:
    """Every Hugging Face folder under ``tmp_path``, no token; returns the cache to
    download into. (Progress bars stay as they are: huggingface_hub reads
    ``HF_HUB_DISABLE_PROGRESS_BARS`` once, on first use, for the whole session.)"""
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    monkeypatch.setenv("HF_LEROBOT_HOME", str(tmp_path / "hf/lerobot"))
    for name in ("HF_HUB_CACHE", "HF_HUB_OFFLINE", "HF_TOKEN", "HF_HUB_DOWNLOAD_TIMEOUT"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("HF_ENDPOINT", "http://127.0.0.1:9")  # nothing listens: never the Hub
    return tmp_path / "cache"


@pytest.fixture
def repo() -> Repo:
    commit = Commit(dict(FILES))
    return Repo(branches={"main": commit}, tags={"v3.0": commit})


def _limits(**fields: object):
    from imitrl.datasets.lerobot._hub_http import HubLimits

    return HubLimits(**fields)


# ------------------------------------------------- a download in a forked child
@dataclass
class _Outcome:
    """What a forked download did."""

    result: str
    """``ok: <value>``, ``error: <type>: <message>`` or ``killed: <why>``"""
    seconds: float
    growth_mb: float
    """its peak resident memory less its resident memory when it started"""


def _memory_mb(field: str, pid: int | str = "self") -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    return 0.0


def _fork(fn: Callable[[], object]) -> tuple[int, int]:
    """``(pid, read end of its pipe)`` of a child running ``fn()``, which writes its
    outcome to the pipe and exits without ever returning into pytest."""
    read, write = os.pipe()
    pid = os.fork()
    if pid:
        os.close(write)
        return pid, read
    try:
        os.close(read)
        with contextlib.suppress(OSError):
            Path("/proc/self/clear_refs").write_text("5")  # VmHWM := VmRSS
        start, t0 = _memory_mb("VmRSS"), time.monotonic()
        try:
            result = f"ok: {fn()}"
        except BaseException as err:
            result = f"error: {type(err).__name__}: {err}"
        report = [result, time.monotonic() - t0, _memory_mb("VmHWM") - start]
        os.write(write, json.dumps(report).encode()[:60000])
    finally:
        os._exit(0)


def _wait(pid: int, read: int, *, timeout_s: float = CHILD_S) -> _Outcome:
    """The child's outcome; it is killed past ``timeout_s`` or past
    :data:`CHILD_GROWTH_MB` more resident memory than this process has."""
    t0, base, killed = time.monotonic(), _memory_mb("VmRSS"), None
    while not os.waitpid(pid, os.WNOHANG)[0]:
        waited = time.monotonic() - t0
        rss = _memory_mb("VmRSS", pid)
        if waited > timeout_s or rss - base > CHILD_GROWTH_MB:
            killed = (
                f"killed: past {timeout_s} s" if waited > timeout_s else f"killed: {rss:.0f} MB"
            )
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            break
        time.sleep(0.02)
    data = b""
    while chunk := os.read(read, 1 << 16):
        data += chunk
    os.close(read)
    if killed is not None:
        return _Outcome(killed, time.monotonic() - t0, _memory_mb("VmRSS") - base)
    result, seconds, growth = json.loads(data)
    return _Outcome(result, seconds, growth)


def _in_child(fn: Callable[[], object], *, timeout_s: float = CHILD_S) -> _Outcome:
    return _wait(*_fork(fn), timeout_s=timeout_s)


def _download(cache: Path, **limits: object) -> Callable[[], object]:
    """``download_lerobot`` of ``org/demo`` into ``cache``, under ``HubLimits(**limits)``
    (none given: under the defaults, without a ``limits`` argument)."""

    def run() -> object:
        if not limits:
            return download_lerobot("org/demo", cache_dir=cache)
        return download_lerobot("org/demo", cache_dir=cache, limits=_limits(**limits))

    return run


# --------------------------------------------------------------- time
@forked
@pytest.mark.parametrize("kind", ["refs", "resolve"])
def test_a_stalled_answer_is_abandoned_after_the_read_timeout(hub_env, repo, monkeypatch, kind):
    repo.misbehave[kind] = "stall"  # the connection is made, then nothing is ever said
    with hub_server({"org/demo": repo}) as (url, _):
        monkeypatch.setenv("HF_ENDPOINT", url)
        got = _in_child(_download(hub_env, read_s=0.5))
    assert got.result.startswith("error: ValueError"), got
    assert "no answer in 0.5 s (read timeout; set HF_HUB_DOWNLOAD_TIMEOUT or" in got.result
    assert got.seconds < 3.0, got
    assert not list(hub_env.rglob("*.incomplete"))


@pytest.fixture
def unanswered() -> Iterator[int]:
    """The port of a listener whose backlog is full: a connection to it is never made."""
    listener = socket.create_server(("127.0.0.1", 0), backlog=0)
    port, held = listener.getsockname()[1], []
    for _ in range(16):
        peer = socket.socket()
        peer.settimeout(0.2)
        held.append(peer)
        try:
            peer.connect(("127.0.0.1", port))
        except TimeoutError:
            break
    else:
        pytest.skip("this system completes every connection: no connect timeout to show")
    try:
        yield port
    finally:
        for peer in held:
            peer.close()
        listener.close()


@forked
def test_a_connection_never_made_is_abandoned_after_the_connect_timeout(
    hub_env, unanswered, monkeypatch
):
    monkeypatch.setenv("HF_ENDPOINT", f"http://127.0.0.1:{unanswered}")
    got = _in_child(_download(hub_env, connect_s=0.5))
    assert "no answer in 0.5 s (connect timeout; set HubLimits(connect_s=...)" in got.result, got
    assert got.seconds < 3.0, got


@forked
@pytest.mark.parametrize("kind", ["tree", "resolve"])
def test_a_trickled_answer_is_abandoned_at_its_deadline(hub_env, repo, monkeypatch, kind):
    # a byte every 0.1 s: the read timeout (2 s) never fires; the deadline (1 s, and for a
    # file 1 s per million bytes more) does
    repo.misbehave[kind], repo.trickle_s = "trickle", 0.1
    with hub_server({"org/demo": repo}) as (url, _):
        monkeypatch.setenv("HF_ENDPOINT", url)
        got = _in_child(_download(hub_env, read_s=2, deadline_s=1, min_bytes_per_s=1e6))
    assert got.result.startswith("error: ValueError"), got
    assert "not received in 1" in got.result and "(deadline: 1 s" in got.result, got
    assert got.seconds < 2.5, got
    assert not list(hub_env.rglob("*.incomplete"))


# --------------------------------------------------------------- memory
@forked
def test_a_gzip_bomb_is_refused_before_it_is_decoded(hub_env, repo, monkeypatch):
    repo.misbehave["tree"] = "gzip-bomb"  # ~1 MB that inflates to 1 GiB
    gzip_bomb()  # made here, not in the child's time
    with hub_server({"org/demo": repo}) as (url, _):
        monkeypatch.setenv("HF_ENDPOINT", url)
        got = _in_child(_download(hub_env))  # the default bound: 64 MiB
    assert "larger than 67108864 bytes once decoded (Content-Encoding gzip)" in got.result, got
    assert got.growth_mb < 200 < BOMB_BYTES >> 20, got  # about twice the bound, not 1 GiB


def test_an_answer_larger_than_the_bound_is_refused_unread(hub_env, repo, monkeypatch):
    with hub_server({"org/demo": repo}) as (url, log):
        monkeypatch.setenv("HF_ENDPOINT", url)
        repo.misbehave["tree"] = "huge"  # Content-Length 2**40, no body
        with pytest.raises(ValueError, match=r"larger than 67108864 bytes: Content-Length 1099"):
            download_lerobot("org/demo", cache_dir=hub_env)
        repo.misbehave.clear()
        with pytest.raises(ValueError, match=r"refs: the answer is larger than 50 bytes"):
            download_lerobot("org/demo", cache_dir=hub_env, limits=_limits(max_answer_bytes=50))
    assert not any("resolve" in line for line in log)


# --------------------------------------------------------------- redirects
def _redirect_every_file(repo: Repo, location: str) -> None:
    for path in FILES:
        repo.redirects[path] = location + path


def test_a_redirect_to_ftp_is_refused_and_never_followed(hub_env, repo, monkeypatch):
    with tcp_listener() as (ftp, connections), hub_server({"org/demo": repo}) as (url, _):
        monkeypatch.setenv("HF_ENDPOINT", url)
        _redirect_every_file(repo, f"ftp://127.0.0.1:{ftp}/")
        with pytest.raises(ValueError, match=rf"redirects to ftp://127\.0\.0\.1:{ftp}/.*, a "
                           "scheme other than http or https; refused"):  # fmt: skip
            download_lerobot("org/demo", cache_dir=hub_env)
    assert connections == []  # nothing ever connected to the ftp:// target
    assert not (hub_env / "datasets--org--demo/snapshots").exists()


def test_a_redirect_to_another_host_is_refused_unless_allowed(hub_env, repo, monkeypatch):
    monkeypatch.setenv("HF_TOKEN", "hf_secret")
    with hub_server({"org/demo": repo}) as (url, log):
        monkeypatch.setenv("HF_ENDPOINT", url)
        # localhost serves the right bytes: only the rule stands between them and the cache
        _redirect_every_file(repo, "http://localhost:{port}/elsewhere/org/demo/v3.0/")
        refused = r"localhost:\d+/elsewhere/.*a host other than the endpoint's \(127\.0\.0\.1\)"
        with pytest.raises(ValueError, match=refused):
            download_lerobot("org/demo", cache_dir=hub_env)
        assert not any("/elsewhere/" in line for line in log)
        snapshot = download_lerobot(
            "org/demo", cache_dir=hub_env, limits=_limits(redirect_hosts=("localhost",))
        )
        elsewhere = [line for line in log if "/elsewhere/" in line]
        assert len(elsewhere) == len(FILES)
        assert not any("+auth" in line for line in elsewhere)  # the token stays home
        assert all(line.endswith("+auth") for line in log if "/api/" in line)
        # on the endpoint's own host, the token goes with the redirect (/api/resolve-cache)
        _redirect_every_file(repo, "http://127.0.0.1:{port}/elsewhere/org/demo/v3.0/")
        download_lerobot("org/demo", cache_dir=hub_env / "again")
        again = [line for line in log if "/elsewhere/" in line][len(FILES) :]
        assert len(again) == len(FILES) and all(line.endswith("+auth") for line in again)
    for path, data in FILES.items():
        assert (snapshot / path).read_bytes() == data


def test_the_official_hub_may_redirect_to_its_cdn_and_nowhere_else():
    from imitrl.datasets.lerobot._hub_http import check_redirect

    hub, source = "https://huggingface.co", "https://huggingface.co/datasets/o/n/resolve/c/f"
    for target in (
        "https://cdn-lfs.hf.co/repos/ab/cd/ef?X-Amz-Signature=1",
        "https://cdn-lfs-us-1.hf.co/repos/ab/cd/ef",
        "https://cas-bridge.xethub.hf.co/xet-bridge-us/abc?sig=1",
        "https://cdn-lfs.huggingface.co/repos/ab/cd/ef",
        "https://huggingface.co/api/resolve-cache/datasets/o/n/c/f",
        "https://hf.co/x",
    ):
        check_redirect(hub, source, target, _limits())
    for target, why in (
        ("ftp://cdn-lfs.hf.co/x", "a scheme other than https"),
        ("http://cdn-lfs.hf.co/x", "a scheme other than https"),  # never down to http
        (
            "https://evil.example/x",
            r"a host other than the endpoint's \(huggingface.co\) and "
            r"hf.co, huggingface.co \(with their subdomains\); refused",
        ),
        ("https://hf.co.evil.example/x", "a host other than"),
        ("https://evilhf.co/x", "a host other than"),
        ("https://huggingface.co.evil.example/x", "a host other than"),
    ):
        with pytest.raises(ValueError, match=f"redirects to {target}, {why}"):
            check_redirect(hub, source, target, _limits())
    # a mirror's redirects stay on the mirror, unless told otherwise; () forbids the CDN
    mirror = "https://hf-mirror.example"
    with pytest.raises(
        ValueError, match=r"other than the endpoint's \(hf-mirror.example\); refused"
    ):
        check_redirect(mirror, mirror + "/f", "https://cdn-lfs.hf.co/x", _limits())
    check_redirect(mirror, mirror + "/f", "https://cdn.mirror.example/x",
                   _limits(redirect_hosts=("mirror.example",)))  # fmt: skip
    with pytest.raises(ValueError, match=r"other than the endpoint's \(huggingface.co\); refused"):
        check_redirect(hub, source, "https://cdn-lfs.hf.co/x", _limits(redirect_hosts=()))
    check_redirect("http://127.0.0.1:8000", "", "https://127.0.0.1/x", _limits())  # upgrade


def test_limits_are_checked_and_read_from_the_environment(monkeypatch):
    from imitrl.datasets.lerobot._hub_http import HubLimits

    for bad in ({"read_s": 0}, {"connect_s": float("inf")}, {"deadline_s": "5"},
                {"max_answer_bytes": 0}, {"redirect_hosts": "hf.co"}, {"max_file_s": 0},
                {"max_file_bytes": 1.5}, {"listing_deadline_s": float("nan")},
                {"max_pages": 0}, {"lock_wait_s": -1}, {"lock_wait_s": True}):  # fmt: skip
        with pytest.raises(ValueError, match=f"HubLimits.{next(iter(bad))} must be"):
            HubLimits(**bad)
    assert HubLimits(lock_wait_s=0).lock_wait_s == 0  # refused at once
    monkeypatch.delenv("HF_HUB_DOWNLOAD_TIMEOUT", raising=False)
    assert HubLimits.from_env() == HubLimits()
    assert HubLimits().file_deadline_s(2 << 30) == pytest.approx(120 + 65536)  # 18 h for 2 GiB
    assert HubLimits().file_deadline_s(50 << 30) == 24 * 3600  # not 19 days: capped at 24 h
    monkeypatch.setenv("HF_HUB_DOWNLOAD_TIMEOUT", "7.5")
    assert HubLimits.from_env() == HubLimits(read_s=7.5)
    monkeypatch.setenv("HF_HUB_DOWNLOAD_TIMEOUT", "soon")
    with pytest.raises(ValueError, match="HF_HUB_DOWNLOAD_TIMEOUT='soon': expected a positive"):
        HubLimits.from_env()


# --------------------------------------------------------------- concurrency
@forked
def test_concurrent_downloads_of_one_dataset_wait_for_each_other_and_all_succeed(
    hub_env, repo, monkeypatch
):
    repo.pace_s = 0.1  # every answer pauses halfway: the four downloads overlap
    start = time.monotonic() + 0.3

    def download() -> object:
        time.sleep(max(start - time.monotonic(), 0))  # all four at once
        return download_lerobot("org/demo", cache_dir=hub_env)

    with hub_server({"org/demo": repo}) as (url, log):
        monkeypatch.setenv("HF_ENDPOINT", url)
        children = [_fork(download) for _ in range(4)]
        got = [_wait(*child) for child in children]
    snapshot = hub_env / "datasets--org--demo/snapshots" / repo.tags["v3.0"].sha
    assert [g.result for g in got] == [f"ok: {snapshot}"] * 4
    for path, data in FILES.items():
        assert (snapshot / path).read_bytes() == data
    assert sum("/resolve/" in line for line in log) == len(FILES)  # each file fetched once
    assert not list(hub_env.rglob("*.incomplete")) and not list(hub_env.rglob(".*imitrl*"))


# ------------------------------------------------- a file list that never ends (finding 5)
@forked
def test_a_file_list_of_empty_pages_without_end_is_refused(hub_env, repo, monkeypatch):
    """Every page after the first is empty and names a next one (a new URL each time, so
    the "same page again" check never fires): 63,000 pages in 75 s on 7278396, never
    refused (here: killed after 8 s)."""
    repo.misbehave["tree"] = "empty-pages"
    with hub_server({"org/demo": repo}) as (url, log):
        monkeypatch.setenv("HF_ENDPOINT", url)
        got = _in_child(_download(hub_env), timeout_s=8)  # the defaults
    assert "empty pages in a row, each naming a next page" in got.result, got
    from imitrl.datasets.lerobot._hub_limits import MAX_EMPTY_PAGES

    assert f"its file list sends {MAX_EMPTY_PAGES + 1} empty pages" in got.result, got
    assert got.seconds < 3, got
    assert sum("/tree/" in line for line in log) == MAX_EMPTY_PAGES + 2  # the first page too
    assert not any("/resolve/" in line for line in log)


@forked
def test_a_file_list_without_end_is_refused_past_its_pages_or_its_deadline(
    hub_env, repo, monkeypatch
):
    """Every page names one new folder and a next page: refused at ``max_pages``, or at
    ``listing_deadline_s`` for the whole list however fast each page comes; on 7278396
    (no such limits) it never ended."""
    repo.misbehave["tree"] = "endless"
    with hub_server({"org/demo": repo}) as (url, log):
        monkeypatch.setenv("HF_ENDPOINT", url)
        by_pages = _in_child(_download(hub_env, max_pages=200), timeout_s=8)
        pages = sum("/tree/" in line for line in log)
        by_time = _in_child(_download(hub_env, listing_deadline_s=1), timeout_s=8)
    assert "its file list goes on past 200 pages (" in by_pages.result, by_pages
    assert pages == 200 and by_pages.seconds < 5, (pages, by_pages)
    assert "1 s for the whole file list; set HubLimits(listing_deadline_s" in by_time.result, (
        by_time
    )
    assert 1 <= by_time.seconds < 3, by_time
    assert not any("/resolve/" in line for line in log)


# ------------------------------------------ a file listed with a huge size (finding 6)
DATA = "data/chunk-000/file-000.parquet"


def _list_size(repo: Repo, path: str, size: int) -> None:
    """The tree listing gives ``path`` (an LFS file) ``size`` bytes; its digest stays."""
    digest = hashlib.sha256(FILES[path]).hexdigest()
    repo.listing[path] = {"lfs": {"oid": digest, "size": size, "pointerSize": 134}}


@forked
def test_a_file_listed_larger_than_any_file_is_refused_before_anything_is_fetched(
    hub_env, repo, monkeypatch
):
    """Listed with 2**60 bytes and trickled a byte a second: its deadline was 120 s + 2**60 /
    32 KiB (1.1 million years) on 7278396, so the trickle was never cut (here: killed
    after 8 s); now past ``max_file_bytes`` (50 GiB), refused from the list."""
    _list_size(repo, DATA, 1 << 60)
    repo.misbehave["resolve"], repo.trickle_s = "trickle", 1.0
    with hub_server({"org/demo": repo}) as (url, log):
        monkeypatch.setenv("HF_ENDPOINT", url)
        got = _in_child(_download(hub_env, read_s=5), timeout_s=8)
    said = f"{DATA!r} is listed with 1,152,921,504,606,846,976 bytes, more than the 53,687,091,200"
    assert said in got.result and "refused before downloading" in got.result, got
    assert got.seconds < 3, got
    assert not any("/resolve/" in line for line in log)
    assert not (hub_env / "datasets--org--demo").exists()


def test_files_larger_than_the_free_disk_are_refused_before_any_is_fetched(
    hub_env, repo, monkeypatch
):
    _list_size(repo, DATA, 1 << 55)  # 32 PiB: more than any disk here holds
    with hub_server({"org/demo": repo}) as (url, log):
        monkeypatch.setenv("HF_ENDPOINT", url)
        total = (1 << 55) + sum(len(data) for path, data in FILES.items() if path != DATA)
        with pytest.raises(ValueError, match=rf"its files take {total:,} bytes, the disk of "
                           r".*/blobs has [\d,]+ free; refused before downloading"):  # fmt: skip
            download_lerobot("org/demo", cache_dir=hub_env, limits=_limits(max_file_bytes=1 << 60))
    assert not any("/resolve/" in line for line in log)


@forked
def test_a_files_deadline_is_capped_whatever_its_size_says(hub_env, repo, monkeypatch):
    """1 s per byte would give the first file a deadline of 30 s + its size in seconds;
    ``max_file_s`` cuts its trickle at 1 s (on 7278396 no cap existed)."""
    repo.misbehave["resolve"], repo.trickle_s = "trickle", 0.1
    with hub_server({"org/demo": repo}) as (url, _):
        monkeypatch.setenv("HF_ENDPOINT", url)
        limits = {"read_s": 2, "deadline_s": 30, "min_bytes_per_s": 1, "max_file_s": 1}
        got = _in_child(_download(hub_env, **limits))
    size = len(FILES["meta/info.json"])
    said = (
        f"not received in 1 s (deadline: 30 s + 1 s per 1 bytes of a {size}-byte file, at most 1 s"
    )
    assert said in got.result, got
    assert got.seconds < 2.5, got
    assert not list(hub_env.rglob("*.incomplete"))


# ---------------------------------- a stopped download holding the cache (finding 7)
_HOLD = r"""
import fcntl, os, sys, time
fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT)
fcntl.flock(fd, fcntl.LOCK_EX)
os.write(fd, b"pid %d" % os.getpid())  # what imitrl.fs.lock writes there
print("held", flush=True)
time.sleep(60)
"""


@pytest.fixture
def stopped_holder(hub_env) -> Iterator[int]:
    """The pid of a process holding the cache's lock on ``org/demo``, stopped (SIGSTOP, as
    Ctrl-Z stops a download); killed after the test."""
    from imitrl.fs.lock import absolute, lock_file

    lock = lock_file(absolute(hub_env / "datasets--org--demo"))
    lock.parent.mkdir(parents=True)
    holder = subprocess.Popen(
        [sys.executable, "-c", _HOLD, str(lock)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        os.kill(holder.pid, signal.SIGSTOP)
        yield holder.pid
    finally:
        holder.kill()
        holder.wait()
        holder.stdout.close()


@forked
@pytest.mark.parametrize("wait", ["lock_wait_s", "the download's deadline"])
def test_a_stopped_download_holding_the_cache_is_waited_for_within_a_bound(
    hub_env, repo, monkeypatch, stopped_holder, wait
):
    """On 7278396 the lock was waited for without end (``wait=None``): killed after 8 s
    here. Now ``lock_wait_s``, or by default the deadline of the files to fetch (here
    0.3 s each, and 0.3 s more), then an error naming the holder's pid."""
    limits = {"lock_wait_s": 0.5} if wait == "lock_wait_s" else {}
    with hub_server({"org/demo": repo}) as (url, log):
        monkeypatch.setenv("HF_ENDPOINT", url)
        got = _in_child(
            _download(hub_env, deadline_s=0.3, min_bytes_per_s=1e9, **limits), timeout_s=8
        )
    waited = 0.5 if limits else 0.3 * (len(FILES) + 1)
    assert f"gave up after waiting {waited:g}" in got.result, got
    assert f"(pid {stopped_holder}, holding " in got.result, got
    assert "HubLimits(lock_wait_s=...)" in got.result, got
    assert waited <= got.seconds < waited + 1.5, got
    assert not any("/resolve/" in line for line in log)
