"""The forked-download harness of the Hub tests (``tests/datasets/lerobot/test_hub_*``):
a Hub on 127.0.0.1 (``_lerobot_hub_server``), its dataset's files, and every download
that could hang run in a forked child the test kills past its own bound (and past a
memory bound), so that a regression fails the test instead of hanging or swapping the
machine.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

from imitrl.datasets import download_lerobot
from tests._lerobot_hub_server import Commit, Repo

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
