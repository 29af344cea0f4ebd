"""Streaming LeRobot datasets: ``load_lerobot(..., into=buffer)`` and ``save_lerobot`` read a
few episodes at a time, with the same rows, checks and files as the in-memory paths."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch
from tensordict import TensorDict

from imitrl import keys
from imitrl.data import DemonstrationBuffer
from imitrl.datasets import load_lerobot, save_lerobot
from imitrl.datasets.lerobot import _stream, _write_frames
from imitrl.datasets.lerobot._stats import feature_stats, segment_stats
from tests._lerobot_files import episodes_data, write_v21, write_v30
from tests._peak import streamed_load_peak

LENGTHS = [5, 3, 7, 4, 6, 2]


@pytest.fixture
def small_pieces(monkeypatch):
    """Pieces and slices of a few frames: every dataset below spans several of them."""
    monkeypatch.setattr(_stream, "PIECE_ROWS", 8)
    monkeypatch.setattr(_write_frames, "SLICE_BYTES", 600)


def _v21(tmp_path: Path) -> Path:
    return write_v21(tmp_path / "v21", episodes_data(LENGTHS))


def _v30(tmp_path: Path) -> Path:
    files = [(0, 0), (0, 0), (0, 1), (0, 1), (0, 1), (0, 2)]  # three data files
    return write_v30(tmp_path / "v30", episodes_data(LENGTHS), files=files, meta_files=2)


def _same(a: TensorDict, b: TensorDict) -> None:
    assert set(a.keys(True, True)) == set(b.keys(True, True))
    for k in a.keys(True, True):
        assert a.get(k).dtype == b.get(k).dtype and torch.equal(a.get(k), b.get(k)), k


@pytest.mark.parametrize("layout", [_v21, _v30])
@pytest.mark.parametrize("on_disk", [False, True])
def test_streamed_load_equals_the_in_memory_load_row_for_row(
    tmp_path, small_pieces, layout, on_disk
):
    root = layout(tmp_path)
    whole = load_lerobot(root, first_episode=3)
    buf = DemonstrationBuffer(path=tmp_path / "buf" if on_disk else None)
    streamed = load_lerobot(root, first_episode=3, into=buf)
    assert len(buf) == sum(LENGTHS) and buf.num_episodes == len(LENGTHS)
    _same(buf.data, whole.rows)
    _same(streamed.rows, whole.rows)
    assert streamed.loaded == whole.loaded and streamed.num_episodes == whole.num_episodes


def test_streamed_load_appends_to_a_buffer_holding_rows(tmp_path, small_pieces):
    root = _v30(tmp_path)
    buf = DemonstrationBuffer()
    load_lerobot(root, into=buf)
    load_lerobot(root, into=buf, first_episode=buf.next_episode)
    assert len(buf) == 2 * sum(LENGTHS) and buf.num_episodes == 2 * len(LENGTHS)


def _nan_in(path: Path, frame: int) -> None:
    table = pq.read_table(path)
    reward = table.column("next.reward").to_pylist()
    reward[frame] = float("nan")
    i = table.column_names.index("next.reward")
    pq.write_table(table.set_column(i, "next.reward", pa.array(reward, pa.float32())), path)


def _bad_frame_index(path: Path, frame: int) -> None:
    table = pq.read_table(path)
    fi = table.column("frame_index").to_pylist()
    fi[frame] += 1
    i = table.column_names.index("frame_index")
    pq.write_table(table.set_column(i, "frame_index", pa.array(fi, pa.int64())), path)


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (_nan_in, r"file-002\.parquet: feature 'next\.reward': frame 1 holds nan"),
        (_bad_frame_index, r"file-002\.parquet: episode 5: frame 1 has frame_index 2"),
    ],
)
@pytest.mark.parametrize("on_disk", [False, True])
def test_a_bad_file_late_in_the_dataset_leaves_the_buffer_as_it_was(
    tmp_path, small_pieces, damage, message, on_disk
):
    root = _v30(tmp_path)
    damage(root / "data/chunk-000/file-002.parquet", 1)  # the last file, the last piece
    with pytest.raises(ValueError, match=message):
        load_lerobot(root)  # the in-memory load says the same
    buf = DemonstrationBuffer(path=tmp_path / "buf" if on_disk else None)
    first = TensorDict(
        {
            keys.OBSERVATION: torch.zeros(2, 4),
            keys.EXPERT_ACTION: torch.zeros(2, dtype=torch.int64),
            keys.ACTION: torch.zeros(2, dtype=torch.int64),
            keys.EXPERT_EXECUTED: torch.ones(2, dtype=torch.bool),
            (keys.NEXT, keys.REWARD): torch.zeros(2, 1),
            (keys.NEXT, keys.DONE): torch.zeros(2, 1, dtype=torch.bool),
            keys.EPISODE: torch.zeros(2, dtype=torch.int64),
            keys.ROUND: torch.zeros(2, dtype=torch.int64),
            keys.STEP: torch.arange(2),
            "task_index": torch.zeros(2, dtype=torch.int64),  # the dataset has two tasks
        },
        [2],
    )
    buf.extend(first)
    with pytest.raises(ValueError, match=message):
        load_lerobot(root, into=buf, first_episode=buf.next_episode)
    assert len(buf) == 2 and buf.next_episode == 1 and buf.num_episodes == 1
    _same(buf.data, first)
    if on_disk:  # what a later process resumes holds the same two rows
        assert json.loads((tmp_path / "buf/imitrl_buffer.json").read_text())["rows"] == 2


def test_rows_that_fail_the_buffers_own_checks_are_refused_before_any_is_added(
    tmp_path, small_pieces
):
    root = _v30(tmp_path)
    buf = DemonstrationBuffer(num_states=3)  # float observations: not states
    with pytest.raises(ValueError, match=r"do not fit the buffer.*integer states"):
        load_lerobot(root, into=buf)
    assert len(buf) == 0 and buf.schema is None


def _rows(lengths: list[int], seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    n = sum(lengths)
    step = torch.cat([torch.arange(k) for k in lengths])
    episode = torch.cat([torch.full((k,), 10 + e) for e, k in enumerate(lengths)])
    last = torch.cat([torch.arange(k) == k - 1 for k in lengths])[:, None]
    action = torch.randint(0, 2, (n,), generator=g)
    return TensorDict(
        {
            keys.OBSERVATION: torch.randn(n, 4, generator=g),
            keys.ACTION: action,
            keys.EXPERT_ACTION: action.clone(),
            keys.EXPERT_EXECUTED: torch.ones(n, dtype=torch.bool),
            (keys.NEXT, keys.REWARD): torch.randn(n, 1, generator=g),
            (keys.NEXT, keys.DONE): last,
            keys.EPISODE: episode,
            keys.ROUND: torch.zeros(n, dtype=torch.int64),
            keys.STEP: step,
            "aux": torch.randn(n, 3, 2, generator=g),
        },
        [n],
    )


def test_save_from_a_disk_buffer_equals_save_from_memory(tmp_path, small_pieces):
    rows = _rows(LENGTHS * 3)
    disk = DemonstrationBuffer(path=tmp_path / "buf")
    disk.extend(rows)
    a = save_lerobot(rows, tmp_path / "from_memory", fps=10, episodes_per_file=4)
    b = save_lerobot(disk, tmp_path / "from_disk", fps=10, episodes_per_file=4)
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    assert len([f for f in files if f.parts[0] == "data"]) == 5  # 18 episodes, 4 a file
    for f in files:
        assert (a / f).read_bytes() == (b / f).read_bytes(), f
    _same(load_lerobot(b).rows, rows)


def test_saved_files_hold_the_same_contents_whatever_the_slices(tmp_path, monkeypatch):
    rows = _rows(LENGTHS * 3)
    one = save_lerobot(rows, tmp_path / "one_slice", fps=10, episodes_per_file=4)
    monkeypatch.setattr(_write_frames, "SLICE_BYTES", 600)  # several slices per file
    many = save_lerobot(rows, tmp_path / "slices", fps=10, episodes_per_file=4)
    for f in sorted(one.rglob("*.parquet")):
        assert pq.read_table(f).equals(pq.read_table(many / f.relative_to(one))), f
    assert (one / "meta/stats.json").read_text() == (many / "meta/stats.json").read_text()


def test_vectorised_episode_stats_match_lerobots_per_episode_stats():
    """min, max, count and quantiles digit for digit; mean and std within 1e-15 relative
    (segment sums add in another order than numpy's pairwise ``ndarray.sum``)."""
    rng = np.random.default_rng(0)
    lengths = rng.integers(1, 300, size=40)
    n = int(lengths.sum())
    features = {
        "vector": rng.standard_normal((n, 4)).astype(np.float32),
        "scalar": rng.integers(-5, 5, n),
        "flag": rng.random(n) < 0.3,
        "array": rng.standard_normal((n, 3, 2)),
    }
    got = segment_stats(features, lengths)
    for name, values in features.items():
        begin = 0
        for e, length in enumerate(lengths):
            want = feature_stats(values[begin : begin + length])
            begin += length
            assert list(got[name]) == list(want)
            for stat, value in want.items():
                mine = got[name][stat][e].reshape(value.shape)
                assert mine.dtype == value.dtype or stat == "count"
                if stat in ("mean", "std"):
                    np.testing.assert_allclose(mine, value, rtol=1e-14, atol=1e-14)
                else:
                    np.testing.assert_array_equal(mine, value)


def _peak_growth(tmp_path: Path, frames: int) -> tuple[int, int]:
    """(rows' bytes, peak RssAnon growth) of a streamed load of ``frames`` frames into a disk
    buffer, in a fresh process."""
    g = torch.Generator().manual_seed(0)
    rows = TensorDict(
        {
            keys.OBSERVATION: torch.randn(frames, 64, generator=g),
            keys.EXPERT_ACTION: torch.randint(0, 2, (frames,), generator=g),
            keys.ACTION: torch.zeros(frames, dtype=torch.int64),
            keys.EXPERT_EXECUTED: torch.ones(frames, dtype=torch.bool),
            keys.EPISODE: torch.arange(frames) // 200,
            keys.ROUND: torch.zeros(frames, dtype=torch.int64),
            keys.STEP: torch.arange(frames) % 200,
        },
        [frames],
    )
    root = save_lerobot(rows, tmp_path / f"ds{frames}", fps=50, episodes_per_file=250)
    raw = sum(v.nbytes for v in rows.values(True, True))
    del rows
    count, grew = streamed_load_peak("lerobot", root, tmp_path / f"buf{frames}")
    assert count == frames
    return raw, grew


@pytest.mark.slow  # benchmarks/scale_datasets.py measures memory at 1M and 10M frames
def test_streamed_load_memory_does_not_grow_with_the_dataset(tmp_path):
    """Peak anonymous memory (RssAnon, sampled every 2 ms; the disk buffer's mapped files are
    page cache) of streamed loads of 40k and 200k frames (pieces of 4096): the 5x longer
    dataset may cost at most its extra rows' bytes more (measured: within the noise of
    the allocators, +-30 MB, over a fixed ~100-150 MB: pyarrow's pool, a row group of the
    file, a piece; a load into memory holds every row, its peak grows by twice the extra
    rows or more, so the bound keeps a 2x margin on both sides)."""
    small_raw, small = _peak_growth(tmp_path, 40_000)
    big_raw, big = _peak_growth(tmp_path, 200_000)
    extra = big_raw - small_raw  # 47 MB
    print(f"peak RssAnon growth {small / 1e6:.1f} MB, {big / 1e6:.1f} MB")
    assert big - small < extra, (
        f"peak RssAnon {small / 1e6:.0f} MB at 40k frames, {big / 1e6:.0f} MB at 200k "
        f"({extra / 1e6:.0f} MB more rows)"
    )
