"""What a streamed ``save_lerobot`` / ``load_lerobot`` keeps in memory: running totals of
``meta/stats.json`` with the digits of LeRobot's aggregation over all episodes at once,
an episode table written a slice at a time, a memory-mapped source's pages let go, and
an episode table read without its statistics."""

from __future__ import annotations

import gc
import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch
from tensordict import TensorDict

from imitrl import keys
from imitrl.data import DemonstrationBuffer
from imitrl.datasets import load_lerobot, save_lerobot
from imitrl.datasets.lerobot import _episode_table, _stream, _write, _write_frames
from imitrl.datasets.lerobot._stats import STAT_NAMES, aggregate_arrays
from imitrl.datasets.lerobot._stats_totals import DatasetStats, EpisodeSum
from tests._lerobot_files import episodes_data, write_v30

EPISODES = "meta/episodes/chunk-000/file-000.parquet"


def _cuts(n: int, rng: np.random.Generator) -> list[tuple[int, int]]:
    """``[begin, end)`` slices of ``range(n)`` of random sizes (1 to 300)."""
    edges = [0]
    while edges[-1] < n:
        edges.append(min(n, edges[-1] + int(rng.integers(1, 300))))
    return list(zip(edges[:-1], edges[1:]))


@pytest.mark.parametrize("n", [1, 5, 8, 9, 127, 128, 129, 137, 1000, 4099])
def test_episode_sum_has_numpys_digits_whatever_the_slices(n):
    """numpy sums ``[n, 1]`` pairwise and ``[n, C]`` row after row; given in random slices,
    :class:`EpisodeSum` adds in the same order (float64 sums of values spanning 16 orders
    of magnitude differ in the last digits when the order differs)."""
    rng = np.random.default_rng(n)
    for columns, pairwise in ((1, True), (3, False)):
        terms = rng.standard_normal((n, columns)) * 10.0 ** rng.integers(-8, 8, (n, 1))
        total = EpisodeSum(n, pairwise=pairwise)
        for begin, end in _cuts(n, rng):
            total.add(terms[begin:end])
        assert np.array_equal(total.total(), terms.sum(axis=0)), (n, columns)
    with pytest.raises(ValueError, match="never added"):
        EpisodeSum(n + 1, pairwise=True).total()


def _episode_stats(n: int, shape: tuple[int, ...], rng: np.random.Generator) -> dict:
    """Per-episode statistics ``stat -> [n, *shape]`` (``count``: ``[n, 1]``), as
    ``segment_stats`` gives them (float min/max here; integer and bool below)."""
    out = {s: rng.standard_normal((n, *shape)) * 10.0 ** rng.integers(-4, 4) for s in STAT_NAMES}
    out["std"] = np.abs(out["std"])
    out["count"] = rng.integers(1, 400, (n, 1))
    return out


@pytest.mark.parametrize("n", [1, 9, 129, 1000, 3001])
def test_running_totals_give_lerobots_aggregate_digit_for_digit(n):
    rng = np.random.default_rng(n)
    features = {
        "scalar": _episode_stats(n, (1,), rng),
        "vector": _episode_stats(n, (4,), rng),
        "image": _episode_stats(n, (3, 1, 1), rng),
        "flags": {**_episode_stats(n, (1,), rng), "min": rng.random((n, 1)) < 0.5},
        "ints": {**_episode_stats(n, (2,), rng), "max": rng.integers(-9, 9, (n, 2))},
    }
    totals = DatasetStats(n)
    cuts = _cuts(n, rng)
    for begin, end in cuts:
        totals.add({f: {s: v[begin:end] for s, v in per.items()} for f, per in features.items()})
    for begin, end in _cuts(n, rng):  # pass 2 in other slices (the episode table's row groups)
        part = {s: {f: per[s][begin:end] for f, per in features.items()} for s in STAT_NAMES}
        totals.add_spread(part["mean"], part["std"], part["count"])
    assert totals.names() == list(features)
    for name, per in features.items():
        want, got = aggregate_arrays(per), totals.result(name)
        assert list(got) == list(want)
        for stat in want:
            assert got[stat].dtype == want[stat].dtype, (name, stat)
            assert np.array_equal(got[stat], want[stat]), (name, stat)


def _rows(lengths: list[int], obs_dim: int = 4, seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    n = sum(lengths)
    action = torch.randint(0, 2, (n,), generator=g)
    return TensorDict(
        {
            keys.OBSERVATION: torch.randn(n, obs_dim, generator=g),
            keys.ACTION: action,
            keys.EXPERT_ACTION: action.clone(),
            keys.EXPERT_EXECUTED: torch.ones(n, dtype=torch.bool),
            (keys.NEXT, keys.REWARD): torch.randn(n, 1, generator=g),
            keys.EPISODE: torch.cat([torch.full((k,), e) for e, k in enumerate(lengths)]),
            keys.ROUND: torch.zeros(n, dtype=torch.int64),
            keys.STEP: torch.cat([torch.arange(k) for k in lengths]),
        },
        [n],
    )


def test_episode_table_reads_the_same_whatever_its_row_groups(tmp_path, monkeypatch):
    """Episodes that fit one row group are written as one (as ``pq.write_table`` of the
    whole table wrote them before the writer streamed); in many row groups, the table and
    the statistics read the same."""
    rows = _rows([5, 3, 7, 4, 6, 2] * 5)
    one = save_lerobot(rows, tmp_path / "one", fps=10, episodes_per_file=4)
    assert pq.ParquetFile(one / EPISODES).num_row_groups == 1
    table = pq.read_table(one / EPISODES)
    assert table.num_rows == 30 and table.column("episode_index").to_pylist() == list(range(30))
    monkeypatch.setattr(_write_frames, "SLICE_BYTES", 600)
    monkeypatch.setattr(_episode_table, "ROW_GROUP_BYTES", 2000)
    many = save_lerobot(rows, tmp_path / "many", fps=10, episodes_per_file=4)
    assert pq.ParquetFile(many / EPISODES).num_row_groups > 3
    assert pq.read_table(many / EPISODES).equals(table)
    assert (many / "meta/stats.json").read_text() == (one / "meta/stats.json").read_text()


def _rss_file() -> int:
    fields = dict(line.split(":", 1) for line in open("/proc/self/status"))
    return int(fields["RssFile"].split()[0]) << 10


@pytest.mark.parametrize("release", [True, False])
def test_save_from_a_disk_buffer_lets_its_pages_go(tmp_path, monkeypatch, release):
    """The source buffer's pages a save reads leave the process after each slice (the
    control, with the release switched off, keeps them: the test can fail)."""
    if not Path("/proc/self/status").is_file():
        pytest.skip("needs Linux's /proc")
    buf = DemonstrationBuffer(path=tmp_path / "buf")
    buf.extend(_rows([200] * 750, obs_dim=48))  # 150k rows, 36 MB
    source = sum(v.nbytes for v in buf.data.values(True, True))
    del buf
    gc.collect()
    buf = DemonstrationBuffer(path=tmp_path / "buf", resume=True)  # nothing mapped yet
    if not release:
        monkeypatch.setattr(_write_frames, "release_pages", lambda rows: None)
        monkeypatch.setattr(_write, "release_pages", lambda rows: None)
    before = _rss_file()
    save_lerobot(buf, tmp_path / "ds", fps=50, episodes_per_file=100)
    grew = _rss_file() - before
    if release:
        assert grew < source / 4, f"{grew / 1e6:.1f} MB of {source / 1e6:.1f} MB stayed mapped"
    else:
        assert grew > source / 2, f"control: only {grew / 1e6:.1f} MB of {source / 1e6:.1f} MB"


def test_episode_files_that_disagree_on_frame_ranges_load_alike(tmp_path, monkeypatch):
    """v3.0 episode table over two files, one without ``dataset_from_index``/``to_index``
    (read as null for its episodes): both loads find the frames from ``episode_index``."""
    monkeypatch.setattr(_stream, "PIECE_ROWS", 8)
    files = [(0, 0), (0, 0), (0, 1), (0, 1), (0, 1), (0, 2)]
    root = write_v30(tmp_path / "v30", episodes_data([5, 3, 7, 4, 6, 2]), files=files, meta_files=2)
    second = root / "meta/episodes/chunk-000/file-001.parquet"
    table = pq.read_table(second)
    pq.write_table(table.drop(["dataset_from_index", "dataset_to_index"]), second)
    whole = load_lerobot(root)
    buf = DemonstrationBuffer()
    load_lerobot(root, into=buf)
    assert len(buf) == len(whole.rows) == 27
    for k in whole.rows.keys(True, True):
        assert torch.equal(buf.data.get(k), whole.rows.get(k)), k
    info = json.loads((root / "meta/info.json").read_text())
    assert info["total_episodes"] == whole.num_episodes == 6
