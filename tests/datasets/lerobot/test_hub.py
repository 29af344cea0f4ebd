"""A LeRobot ``repo_id``: found where lerobot 0.6 downloads, named on the command line,
downloaded when online; against a Hub on 127.0.0.1 (``_lerobot_hub_server``), never the
real one."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import pytest
import torch
from tensordict.nn.probabilistic import InteractionType as ExplorationType

from imitrl.datasets import load_lerobot, resolve_lerobot_root, save_lerobot
from imitrl.envs import make_env
from imitrl.experts import cartpole_expert
from imitrl.runtime import rollout_episodes
from tests._lerobot_hub_server import Commit, Repo, hub_server
from tests.cli.test_cli import TINY, run
from tests.datasets.lerobot.test_lerobot_interop_edits import _rows, _same

pytest.importorskip("huggingface_hub")
torch.set_num_threads(1)
FPS = 10


@pytest.fixture
def home(tmp_path, monkeypatch) -> Path:
    """Every Hugging Face folder under ``tmp_path``; online, no token, progress shown."""
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    monkeypatch.setenv("HF_LEROBOT_HOME", str(tmp_path / "hf/lerobot"))
    for name in ("HF_HUB_CACHE", "HF_HUB_OFFLINE", "HF_TOKEN", "HF_HUB_DISABLE_PROGRESS_BARS"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("HF_ENDPOINT", "http://127.0.0.1:9")  # nothing listens: never the Hub
    return tmp_path / "hf/lerobot"


@pytest.fixture
def demo(tmp_path):
    """``org/demo``: tag ``v3.0`` holds two episodes, branch ``main`` three."""
    two, three = _rows([3, 2]), _rows([3, 2, 4], seed=1)
    v30 = Commit.of_folder(save_lerobot(two, tmp_path / "two", fps=FPS))
    main_ = Commit.of_folder(save_lerobot(three, tmp_path / "three", fps=FPS))
    return Repo(branches={"main": main_}, tags={"v3.0": v30}), two, three


def _files_outside(tmp_path: Path, cache: Path) -> set[str]:
    return {
        p.relative_to(tmp_path).as_posix()
        for p in tmp_path.rglob("*")
        if p.is_file() and cache not in p.parents
    }


# ------------------------------------------- where lerobot 0.6 downloads to
def test_a_dataset_lerobot_downloaded_is_found_under_hf_lerobot_home_hub(home, demo, monkeypatch):
    from huggingface_hub import snapshot_download

    repo, two, _ = demo
    with hub_server({"org/demo": repo}) as (url, _):
        # lerobot 0.6.1's LeRobotDatasetMetadata._pull_from_repo / LeRobotDataset._download
        snapshot = snapshot_download(
            "org/demo", repo_type="dataset", revision="v3.0", cache_dir=home / "hub", endpoint=url
        )
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    assert resolve_lerobot_root("org/demo") == Path(snapshot)
    _same(load_lerobot("org/demo").rows, two)


# ---------------------------------------------------------------- download
def test_load_lerobot_downloads_a_dataset_it_does_not_have(
    home, demo, tmp_path, capfd, monkeypatch
):
    from huggingface_hub import snapshot_download

    repo, two, three = demo
    with hub_server({"org/demo": repo}) as (url, log):
        monkeypatch.setenv("HF_ENDPOINT", url)
        loaded = load_lerobot("org/demo")  # the best version tag, as lerobot asks for it
        assert "Downloading org/demo" in capfd.readouterr().err  # progress
        _same(loaded.rows, two)
        snapshot = home / "hub/datasets--org--demo/snapshots" / repo.tags["v3.0"].sha
        assert loaded.source == snapshot
        assert (home / "hub/datasets--org--demo/refs/v3.0").read_text() == repo.tags["v3.0"].sha
        # the same files, links and blobs as huggingface_hub's own snapshot_download makes
        theirs = Path(snapshot_download("org/demo", repo_type="dataset", revision="v3.0",
                                        cache_dir=tmp_path / "theirs", endpoint=url))  # fmt: skip
        mine = {p.relative_to(snapshot).as_posix(): p for p in snapshot.rglob("*") if p.is_file()}
        assert sorted(mine) == sorted(
            p.relative_to(theirs).as_posix() for p in theirs.rglob("*") if p.is_file()
        )
        for name, path in mine.items():
            assert path.is_symlink() and path.read_bytes() == (theirs / name).read_bytes()
            assert os.readlink(path) == os.readlink(theirs / name)  # ../../blobs/<digest>
        _same(load_lerobot("org/demo", revision="main").rows, three)
        before = len(log)
        load_lerobot("org/demo", revision="main")  # found in the cache: no request
        assert len(log) == before
        custom = load_lerobot("org/demo", cache_dir=tmp_path / "mine")
        assert custom.source.is_relative_to(tmp_path / "mine")
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")  # offline: from the caches, as before
    _same(load_lerobot("org/demo").rows, two)


def test_the_command_line_takes_a_repo_id_and_downloads_it(home, tmp_path, monkeypatch):
    env = make_env("CartPole-v1", seed=3, max_episode_steps=30)
    rows = rollout_episodes(
        env, cartpole_expert().as_actor(), 2, exploration=ExplorationType.DETERMINISTIC,
        max_steps=100,
    )  # fmt: skip
    folder = save_lerobot(rows, tmp_path / "demos", fps=50)
    repo = Repo(
        branches={"main": Commit.of_folder(folder)}, tags={"v3.0": Commit.of_folder(folder)}
    )
    argv = ["bc", *TINY, "--expert", "none", "--dataset", "org/cartpole", "--no-progress"]
    with hub_server({"org/cartpole": repo}) as (url, _):
        monkeypatch.setenv("HF_ENDPOINT", url)
        status, _, stderr = run([*argv, "--out", str(tmp_path / "online")])
        assert status == 0, stderr
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    status, _, stderr = run([*argv, "--out", str(tmp_path / "offline")])
    assert status == 0, stderr
    results = json.loads((tmp_path / "offline/results.json").read_text())
    assert results["demonstrations"] == {"source": "org/cartpole", "episodes": 2, "rows": 60}


def test_offline_without_a_copy_names_where_it_looked(home, tmp_path, monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    with pytest.raises(ValueError, match=r"no local copy .*'org/demo'.*HF_HUB_OFFLINE is set"):
        load_lerobot("org/demo")
    status, _, stderr = run(
        ["bc", "--expert", "none", "--dataset", "org/demo", "--out", str(tmp_path / "x")]
    )
    assert status == 2 and "HF_HUB_OFFLINE is set" in stderr and stderr.count("\n") == 1


def test_without_huggingface_hub_the_message_says_how_to_install_it(home, monkeypatch):
    monkeypatch.setitem(sys.modules, "huggingface_hub", None)
    with pytest.raises(ImportError, match=r"pip install 'imitrl\[hub\]'"):
        load_lerobot("org/demo")


def test_an_unknown_repo_or_revision_is_named(home, demo, monkeypatch):
    repo, _, _ = demo
    with hub_server({"org/demo": repo}) as (url, _):
        monkeypatch.setenv("HF_ENDPOINT", url)
        with pytest.raises(ValueError, match=r"datasets/org/nope: cannot list its revisions"):
            load_lerobot("org/nope")
        with pytest.raises(ValueError, match=r"datasets/org/demo: cannot resolve revision 'v9'"):
            load_lerobot("org/demo", revision="v9")
    for bad in ("org/../x", "-org/x", "org/a--b"):
        with pytest.raises(ValueError, match="is not a Hub dataset repo_id"):
            resolve_lerobot_root(bad)


# ---------------------------------------------------------- hostile servers
def _hostile(repo: Repo, how: str) -> None:
    commit = repo.tags["v3.0"]
    if how == "path":
        repo.listing["meta/stats.json"] = {"path": "../../../escape.json"}
    elif how == "absolute":
        repo.listing["meta/stats.json"] = {"path": "/tmp/escape.json"}
    elif how == "digest":
        repo.listing["meta/stats.json"] = {"oid": "../../../escape"}
    elif how == "bytes":
        repo.served["data/chunk-000/file-000.parquet"] = b"PAR1" + b"\0" * 100
    elif how == "headers":  # huggingface_hub would name a blob after the ETag
        repo.headers.update({"ETag": '"../../../escape"', "X-Linked-Etag": '"../../../escape"'})
        repo.headers["X-Repo-Commit"] = "../../../escape"
    elif how == "commit":
        repo.tags["v3.0"] = Commit(commit.files, sha="../../../escape")


@pytest.mark.parametrize(
    ("how", "message"),
    [
        ("path", "names '../../../escape.json', outside the dataset folder"),
        ("absolute", "names '/tmp/escape.json', outside the dataset folder"),
        ("digest", "'meta/stats.json' is listed with digest '../../../escape', not hex"),
        ("bytes", r"file-000\.parquet arrived with 104 bytes .* refusing altered data"),
        ("headers", "served from commit '../../../escape'"),
        ("commit", "names commit '../../../escape', not 40 hex digits"),
    ],
)
def test_a_hostile_server_cannot_write_outside_the_cache(
    home, demo, tmp_path, monkeypatch, how, message
):
    repo, _, _ = demo
    _hostile(repo, how)
    before = _files_outside(tmp_path, home / "hub")
    with hub_server({"org/demo": repo}) as (url, _):
        monkeypatch.setenv("HF_ENDPOINT", url)
        with pytest.raises(ValueError, match=message):
            load_lerobot("org/demo")
    assert _files_outside(tmp_path, home / "hub") == before
    assert not Path("/tmp/escape.json").exists()
    assert not (home / "hub/datasets--org--demo/snapshots").exists()  # nothing half-built
    assert not list(home.rglob("*.incomplete"))
