"""A dataset save_lerobot wrote, then edited in place by LeRobot; camera-only rows saved.

LeRobot leaves ``meta/imitrl.json`` behind when it resumes recording into a dataset or
recomputes its statistics (``_lerobot_edits`` does what lerobot 0.6.1 does, file for
file). Such a dataset is a LeRobot dataset: it loads, with one warning saying what of
imitrl's record no longer applies; changes LeRobot never makes are still refused by name.
"""

from __future__ import annotations

import json
import warnings

import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch
from tensordict import TensorDict

from imitrl import keys
from imitrl.data import DemonstrationBuffer
from imitrl.datasets import load_lerobot, save_lerobot
from tests._lerobot_edits import (
    recompute_stats_like_lerobot,
    resume_like_lerobot,
    write_info_like_lerobot,
)

torch.set_num_threads(1)
FPS = 10
EDITED = "LeRobot edited this dataset since save_lerobot wrote it"


def _rows(lengths: list[int], *, first: int = 0, seed: int = 0, dagger: bool = True) -> TensorDict:
    """Episodes ``first, first + 1, ...``; ``dagger``: relabelled rounds (the learner acted),
    else as a LeRobot user fills imitrl's columns when recording (the expert acting)."""
    g = torch.Generator().manual_seed(seed)
    parts = []
    for i, n in enumerate(lengths):
        label = torch.randint(0, 2, (n,), generator=g)
        done = torch.arange(n).eq(n - 1).unsqueeze(-1)
        parts.append(
            TensorDict(
                {
                    keys.OBSERVATION: torch.randn(n, 4, generator=g),
                    keys.EXPERT_ACTION: label,
                    keys.ACTION: 1 - label if dagger else label.clone(),
                    keys.EXPERT_EXECUTED: torch.full((n,), not dagger),
                    keys.ROUND: torch.full((n,), 2 if dagger else 0),
                    keys.EPISODE: torch.full((n,), first + i),
                    keys.STEP: torch.arange(n),
                    (keys.NEXT, keys.REWARD): torch.randn(n, 1, generator=g),
                    (keys.NEXT, keys.DONE): done,
                },
                batch_size=[n],
            )
        )
    return torch.cat(parts)


def _load(root, **kwargs):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        loaded = load_lerobot(root, **kwargs)
    return loaded, [str(w.message) for w in caught]


def _same(a: TensorDict, b: TensorDict) -> None:
    assert set(a.keys(True, True)) == set(b.keys(True, True))
    for key in a.keys(True, True):
        x, y = a.get(key), b.get(key)
        assert x.dtype == y.dtype and x.shape == y.shape, key
        assert torch.equal(x, y), key


@pytest.fixture
def resumed(tmp_path):
    """A DAgger buffer saved by imitrl, then one episode recorded into it by LeRobot."""
    before, added = _rows([4, 3]), _rows([5], first=2, seed=1, dagger=False)
    root = save_lerobot(before, tmp_path / "ds", fps=FPS)
    resume_like_lerobot(root, before, added, fps=FPS)
    return root, torch.cat([before, added])


# ------------------------------------------------------ LeRobot's own edits
def test_a_dataset_lerobot_resumed_recording_into_loads_with_a_warning(resumed):
    root, rows = resumed
    loaded, messages = _load(root)
    _same(loaded.rows, rows)  # every round and expert flag, the new episode's as recorded
    assert loaded.num_episodes == 3
    (message,) = [m for m in messages if EDITED in m]
    assert "rewrote ['meta/info.json', 'meta/stats.json']" in message
    assert "data/chunk-000/file-001.parquet" in message
    assert "meta/episodes/chunk-000/file-001.parquet" in message
    assert "checksums no longer cover those files" in message
    assert "imitrl's own columns ['imitrl.executed_action', 'imitrl.round'" in message


def test_a_resumed_dataset_streams_into_a_buffer_with_the_same_rows(resumed):
    root, rows = resumed
    buffer = DemonstrationBuffer()
    loaded, messages = _load(root, into=buffer)
    _same(buffer.data[: len(buffer)].to_tensordict(), loaded.rows.to_tensordict())
    _same(loaded.rows.to_tensordict(), rows)
    assert any(EDITED in m for m in messages)


def test_statistics_lerobot_recomputed_load_with_a_warning_naming_them(tmp_path):
    rows = _rows([4, 3])
    root = save_lerobot(rows, tmp_path / "ds", fps=FPS)
    recompute_stats_like_lerobot(root)
    loaded, messages = _load(root)
    _same(loaded.rows, rows)
    (message,) = [m for m in messages if EDITED in m]
    assert "rewrote ['meta/stats.json']" in message and "added" not in message


# ------------------------------------- what LeRobot never does: still refused
def _edit_info(root, **fields):
    info = json.loads((root / "meta/info.json").read_text())
    for path, value in fields.items():
        node = info
        *parents, last = path.split("__")
        for p in parents:
            node = node[p.replace("_DOT_", ".")]
        node[last] = value
    write_info_like_lerobot(root, info)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (
            {"features__observation_DOT_state__dtype": "float64"},
            r"info\.json: feature 'observation\.state' is \{'dtype': 'float64'.*LeRobot changes "
            r"only \['total_episodes', 'total_frames', 'total_tasks', 'splits'\]",
        ),
        ({"fps": 20}, r"info\.json: 'fps' is 20, save_lerobot wrote 10"),
        ({"total_frames": 13}, r"info\.json declares 13 frames, the data files hold 12"),
    ],
)
def test_a_changed_info_json_lerobot_would_not_write_is_refused(resumed, change, message):
    root, _ = resumed
    _edit_info(root, **change)
    with pytest.raises(ValueError, match=message):
        _load(root)


def test_a_byte_changed_in_a_file_lerobot_never_rewrites_is_refused(resumed):
    root, _ = resumed
    data = root / "data/chunk-000/file-000.parquet"
    blob = bytearray(data.read_bytes())
    blob[len(blob) // 2] ^= 1
    data.write_bytes(bytes(blob))
    with pytest.raises(ValueError, match=r"file-000\.parquet: changed since save_lerobot.*never"):
        _load(root)


def test_rewritten_statistics_that_are_not_statistics_are_refused(resumed):
    root, _ = resumed
    (root / "meta/stats.json").write_text('{"action": {"mean": [0.5,')
    with pytest.raises(ValueError, match=r"stats\.json: not JSON"):
        _load(root)
    (root / "meta/stats.json").write_text('{"action": {"mean": "half"}}')
    with pytest.raises(ValueError, match=r"stats\.json: expected LeRobot's statistics"):
        _load(root)


def test_added_frames_that_break_lerobots_invariants_are_refused_by_name(resumed):
    root, _ = resumed
    path = root / "data/chunk-000/file-001.parquet"
    table = pq.read_table(path)
    i = table.schema.get_field_index("timestamp")
    slow = pa.array([2 * t for t in table.column("timestamp").to_pylist()], pa.float32())
    pq.write_table(table.set_column(i, "timestamp", slow), path)
    with pytest.raises(ValueError, match=r"file-001\.parquet: episode 2: timestamps .* fps 10"):
        _load(root)


def test_the_sidecar_itself_changed_is_still_refused(resumed):
    root, _ = resumed
    sidecar = json.loads((root / "meta/imitrl.json").read_text())
    sidecar["columns"]["observation.state"]["shape"] = [2, 2]
    (root / "meta/imitrl.json").write_text(json.dumps(sidecar))
    with pytest.raises(ValueError, match=r"imitrl\.json: changed since save_lerobot wrote it"):
        _load(root)


# ------------------------------------------------------------ camera-only rows
def test_camera_only_rows_from_load_lerobot_can_be_saved(tmp_path):
    rows = _rows([4, 3])
    g = torch.Generator().manual_seed(3)
    rows.set(
        (keys.PIXELS, "cam"), torch.randint(0, 256, (7, 8, 8, 3), dtype=torch.uint8, generator=g)
    )
    root = save_lerobot(rows, tmp_path / "with_state", fps=FPS)
    cameras = load_lerobot(root, key_map={"observation.state": None}, images="load").rows
    assert keys.OBSERVATION not in cameras.keys()
    again = save_lerobot(cameras, tmp_path / "camera_only", fps=FPS)
    back, _ = _load(again, images="load")
    _same(back.rows, cameras)


def test_rows_with_neither_an_observation_nor_a_camera_are_refused(tmp_path):
    rows = _rows([3]).exclude(keys.OBSERVATION)
    with pytest.raises(ValueError, match=r"rows need 'observation' or a camera 'pixels'"):
        save_lerobot(rows, tmp_path / "ds", fps=FPS)
