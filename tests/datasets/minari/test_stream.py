"""``load_minari(..., into=buffer)``: a Minari dataset streamed into a buffer episode by
episode, with the same rows and checks as the load into memory, and nothing added when
any episode is bad."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import GymEnv

from imitrl import keys
from imitrl.data import DemonstrationBuffer
from imitrl.datasets import load_minari
from imitrl.datasets.minari import _stream
from tests._peak import streamed_load_peak
from tests.datasets.minari.test_minari import _episode, _write

LENGTHS = [3, 5, 2, 4, 7, 6, 1, 3, 5, 2, 4, 3]


@pytest.fixture
def small_pieces(monkeypatch):
    """Pieces of a few steps: every dataset below spans several of them."""
    monkeypatch.setattr(_stream, "PIECE_ROWS", 7)


def _dataset(root: Path, **meta) -> Path:
    episodes = [_episode(n, s, truncated=s % 3 == 0) for s, n in enumerate(LENGTHS)]
    return _write(root, episodes, **meta)


def _same(a: TensorDict, b: TensorDict) -> None:
    assert set(a.keys(True, True)) == set(b.keys(True, True))
    for k in a.keys(True, True):
        assert a.get(k).dtype == b.get(k).dtype and torch.equal(a.get(k), b.get(k)), k


@pytest.mark.parametrize("on_disk", [False, True])
@pytest.mark.parametrize("with_env", [False, True])
def test_streamed_load_equals_the_in_memory_load_row_for_row(
    tmp_path, small_pieces, on_disk, with_env
):
    root = _dataset(tmp_path / "ds")
    env = GymEnv("CartPole-v1", categorical_action_encoding=True) if with_env else None
    whole = load_minari(root, env=env, first_episode=3, next_observation=True)
    buf = DemonstrationBuffer(path=tmp_path / "buf" if on_disk else None)
    streamed = load_minari(root, env=env, first_episode=3, next_observation=True, into=buf)
    assert len(buf) == sum(LENGTHS) and buf.num_episodes == len(LENGTHS)
    _same(buf.data, whole.rows)
    _same(streamed.rows, whole.rows)
    assert streamed.num_episodes == whole.num_episodes == len(LENGTHS)
    assert streamed.notes == whole.notes and streamed.skipped == whole.skipped
    assert (buf.data[keys.NEXT, keys.REWARD].dtype == torch.float32) == with_env
    again = load_minari(
        root, env=env, next_observation=True, into=buf, first_episode=buf.next_episode
    )
    assert len(buf) == 2 * sum(LENGTHS) and len(again.rows) == sum(LENGTHS)


def test_streamed_arrow_dataset_equals_the_in_memory_load(tmp_path, monkeypatch):
    pytest.importorskip("minari")
    from tests.datasets.test_datasets_properties import _minari_arrow

    monkeypatch.setattr(_stream, "PIECE_ROWS", 2)  # one piece per episode
    root = _minari_arrow(tmp_path / "arrow")
    buf = DemonstrationBuffer(path=tmp_path / "buf")
    streamed = load_minari(root, into=buf)
    assert streamed.format.startswith("minari arrow")
    _same(buf.data, load_minari(root).rows)


def _nan_reward(root: Path) -> None:
    with h5py.File(root / "data/main_data.hdf5", "a") as f:
        f["episode_9/rewards"][1] = np.nan


def _corrupt_chunk(root: Path) -> None:
    """Episode 9's observations rewritten compressed, then bytes of that chunk overwritten:
    HDF5 itself fails to read it (a damaged file), the other episodes read fine."""
    with h5py.File(root / "data/main_data.hdf5", "a") as f:
        values = f["episode_9/observations"][()]
        del f["episode_9/observations"]
        ds = f["episode_9"].create_dataset(
            "observations", data=values, compression="gzip", chunks=values.shape
        )
        chunk = ds.id.get_chunk_info(0)
    with open(root / "data/main_data.hdf5", "r+b") as fh:
        fh.seek(chunk.byte_offset + 4)
        fh.write(b"\xff" * (chunk.size - 8))


def _wrong_total_steps(root: Path) -> None:
    meta = json.loads((root / "data/metadata.json").read_text())
    meta["total_steps"] += 1  # seen only once every episode has been read
    (root / "data/metadata.json").write_text(json.dumps(meta))


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (_nan_reward, r"episode_9/rewards: frame 1 holds nan"),
        (_corrupt_chunk, r"main_data\.hdf5: unreadable HDF5 data \(OSError"),
        (_wrong_total_steps, r"metadata declares 46 steps, the episodes hold 45"),
    ],
)
def test_a_damaged_episode_late_in_the_file_leaves_the_buffer_as_it_was(
    tmp_path, small_pieces, damage, message
):
    root = _dataset(tmp_path / "ds")
    damage(root)
    with pytest.raises(ValueError, match=message):
        load_minari(root)  # the load into memory says the same
    buf = DemonstrationBuffer(path=tmp_path / "buf")
    first = load_minari(_write(tmp_path / "first", [_episode(2, 0)])).rows
    buf.extend(first)
    with pytest.raises(ValueError, match=message):
        load_minari(root, into=buf, first_episode=buf.next_episode)
    assert len(buf) == 2 and buf.next_episode == 1 and buf.num_episodes == 1
    _same(buf.data, first)
    assert json.loads((tmp_path / "buf/imitrl_buffer.json").read_text())["rows"] == 2


def test_rows_that_fail_the_buffers_own_checks_are_refused_before_any_is_added(
    tmp_path, small_pieces
):
    root = _dataset(tmp_path / "ds")
    buf = DemonstrationBuffer(num_states=3)  # float observations: not states
    with pytest.raises(ValueError, match=r"do not fit the buffer.*integer states"):
        load_minari(root, into=buf)
    assert len(buf) == 0 and buf.schema is None
    taken = DemonstrationBuffer()
    load_minari(root, into=taken)
    with pytest.raises(ValueError, match=r"do not fit the buffer.*episode"):
        load_minari(root, into=taken)  # its episode ids are the buffer's already
    assert len(taken) == sum(LENGTHS)


def _peak_growth(tmp_path: Path, steps: int) -> tuple[int, int]:
    """(observations' bytes, peak RssAnon growth) of a streamed load of ``steps`` steps
    (episodes of 200) into a disk buffer, in a fresh process."""
    rng = np.random.default_rng(0)
    n = 200
    episodes = []
    for _ in range(steps // n):
        ep = _episode(n, 0, obs_dim=64)
        ep["observations"] = rng.standard_normal((n + 1, 64)).astype(np.float32)
        episodes.append(ep)
    box = {"type": "Box", "dtype": "float32", "shape": [64], "low": [-9.0] * 64, "high": [9.0] * 64}
    root = _write(tmp_path / f"ds{steps}", episodes, obs_space=box, jpeg_encoding=False)
    raw = sum(ep["observations"].nbytes for ep in episodes)
    del episodes
    count, grew = streamed_load_peak("minari", root, tmp_path / f"buf{steps}")
    assert count == steps
    return raw, grew


@pytest.mark.slow  # a few seconds of subprocesses; the LeRobot twin is in test_dataset_streaming
def test_streamed_load_memory_does_not_grow_with_the_dataset(tmp_path):
    """Peak anonymous memory (RssAnon sampled every 2 ms) of streamed loads of 40k and 200k
    steps (pieces of 4096): the 5x longer dataset may cost less than its extra
    observations' bytes more (a load into memory holds every row: its peak grows by
    at least that, twice with the concatenation)."""
    small_raw, small = _peak_growth(tmp_path, 40_000)
    big_raw, big = _peak_growth(tmp_path, 200_000)
    extra = big_raw - small_raw  # 41 MB
    print(f"peak RssAnon growth {small / 1e6:.1f} MB, {big / 1e6:.1f} MB")
    assert big - small < extra, (
        f"peak RssAnon {small / 1e6:.0f} MB at 40k steps, {big / 1e6:.0f} MB at 200k "
        f"({extra / 1e6:.0f} MB more observations)"
    )
