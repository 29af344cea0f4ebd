"""The LeRobot Hub download never hangs, never blows up memory and never follows a
redirect elsewhere (issue 42, finding 4): against a Hub on 127.0.0.1 that stalls,
trickles, sends a gzip bomb or redirects to ``ftp://`` and to another host; and
``HubLimits`` checks its fields (``imitrl.datasets.lerobot._hub_http``).
"""

from __future__ import annotations

import socket
from collections.abc import Iterator

import pytest

from imitrl.datasets import download_lerobot
from tests._hub_child import (
    FILES,
    _download,
    _in_child,
    _limits,
    forked,
)
from tests._lerobot_hub_server import BOMB_BYTES, Repo, gzip_bomb, hub_server, tcp_listener

pytest.importorskip("huggingface_hub")


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
