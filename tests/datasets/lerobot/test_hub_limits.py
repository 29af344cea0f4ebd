"""The Hub download's limits on what a listing may ask (``HubLimits``): concurrent
downloads of one dataset take turns; a file list that never ends, a file listed with a
size no file has, or a stopped download holding the cache's lock never hang it
(findings 5, 6 and 7 of the dataset readers' review).
"""

from __future__ import annotations

import hashlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator

import pytest

from imitrl.datasets import download_lerobot
from tests._hub_child import (
    FILES,
    _download,
    _fork,
    _in_child,
    _limits,
    _wait,
    forked,
)
from tests._lerobot_hub_server import Repo, hub_server

pytest.importorskip("huggingface_hub")


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
    # read line by line while it runs (tests/_child.py gives a pipe's output at the end)
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
