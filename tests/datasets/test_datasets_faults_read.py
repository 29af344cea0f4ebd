"""Faults and bad input at the dataset readers (issue 13): every value is checked before it
is converted, and what cannot be loaded exactly is refused with a ValueError naming the
file and the problem, before anything reaches ``loaded.rows``.

Every test here is a row of the fault table: the case, and what happens now.
"""

from __future__ import annotations

import json
import os
import shutil
import warnings
from pathlib import Path

import h5py
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch
from torchrl.envs import GymEnv

from imitrl import keys
from imitrl.datasets import load_lerobot, load_minari, save_lerobot
from tests._lerobot_files import episodes_data, write_v21, write_v30
from tests.datasets.minari.test_minari import BOX4, DISCRETE2, _episode, _write
from tests.datasets.test_datasets_faults import _load, _rows, _same


# ----------------------------------------------------------- LeRobot reader
def _v21(tmp_path, lengths=(4, 3)) -> Path:
    return write_v21(tmp_path / "ds", episodes_data(list(lengths)))


def _edit_info(root: Path, **changes) -> None:
    info = json.loads((root / "meta/info.json").read_text())
    for dotted, value in changes.items():
        node = info
        *path, last = dotted.split("__")
        for p in path:
            node = node[p]
        node[last] = value
    (root / "meta/info.json").write_text(json.dumps(info))


def _edit_column(path: Path, name: str, values, type_=None) -> None:
    table = pq.read_table(path)
    i = table.column_names.index(name)
    column = pa.array(values, type_ or table.schema.field(name).type)
    pq.write_table(table.set_column(i, name, column), path)


EPISODE_1 = "data/chunk-000/episode_000001.parquet"


@pytest.mark.parametrize(
    ("fps", "message"),
    [
        (30, r"episode_000000\.parquet: episode 0: timestamps .* fps 30 puts frames 1/fps"),
        (0, "fps must be positive"),
        (-50, "fps must be positive"),
        ("fifty", "fps must be a number"),
        (True, "fps must be a number"),
        (None, "fps must be a number"),
        (float("nan"), "fps must be a number"),
    ],
)
def test_fps_that_contradicts_the_timestamps_is_refused(tmp_path, fps, message):
    root = _v21(tmp_path)
    _edit_info(root, fps=fps)
    with pytest.raises(ValueError, match=message):
        load_lerobot(root)


def test_timestamps_within_lerobots_tolerance_load(tmp_path):
    root = _v21(tmp_path)
    path = root / EPISODE_1
    jitter = np.arange(3) / 50 + np.array([0, 9e-5, 0])  # < tolerance_s = 1e-4
    _edit_column(path, "timestamp", jitter.astype(np.float32))
    assert len(_load(root)) == 7


@pytest.mark.parametrize(
    ("column", "values", "message"),
    [
        ("timestamp", [0.3, 0.01, 0.77], r"episode_000001\.parquet: episode 1: timestamps"),
        ("timestamp", [0.0, float("nan"), 0.04], r"'timestamp': frame 1 holds nan"),
        ("frame_index", [0, 1, 3], r"episode 1: frame 2 has frame_index 3 .*without gaps"),
        ("frame_index", [1, 2, 3], r"episode 1: frame 0 has frame_index 1"),
        ("task_index", [0, 2, 0], r"task_index 2 is outside the task table \(2 task"),
        ("task_index", [0, -1, 0], r"task_index -1 is outside the task table"),
        ("next.reward", [1.0, float("inf"), 1.0], r"'next\.reward': frame 1 holds inf"),
        ("next.reward", [1.0, float("nan"), 1.0], r"'next\.reward': frame 1 holds nan"),
    ],
)
def test_frames_that_contradict_lerobots_bookkeeping_are_refused(tmp_path, column, values, message):
    root = _v21(tmp_path)
    _edit_column(root / EPISODE_1, column, values)
    with pytest.raises(ValueError, match=message):
        load_lerobot(root)


def test_nan_in_an_observation_is_refused_before_any_row(tmp_path):
    root = _v21(tmp_path)
    path = root / EPISODE_1
    obs = pq.read_table(path).column("observation.state").to_pylist()
    obs[2][1] = float("nan")
    _edit_column(path, "observation.state", obs)
    with pytest.raises(ValueError, match=r"episode_000001\.parquet: feature 'observation\.state'"):
        load_lerobot(root)


@pytest.mark.parametrize(
    ("feature", "dtype", "message"),
    [
        ("observation.state", "float16", r"does not fit the declared dtype 'float16'"),
        ("action", "bool", "value 2 does not fit the declared dtype 'bool'"),
        ("next.reward", "int64", "refusing to truncate floating data"),
        ("next.done", "float32", None),  # bool -> float32: every value exact, loads
        ("action", "int8", None),  # 0..2 in int8: exact, loads (as LeRobot casts it)
    ],
)
def test_declared_dtypes_must_hold_the_stored_values_exactly(tmp_path, feature, dtype, message):
    root = _v21(tmp_path)
    _edit_column(root / EPISODE_1, "action", [0, 2, 1])  # int64, as declared
    _edit_info(root, **{f"features__{feature}__dtype": dtype})
    if message is None:
        key = keys.EXPERT_ACTION if feature == "action" else (keys.NEXT, keys.DONE)
        assert load_lerobot(root).rows.get(key).dtype == getattr(torch, dtype)
        return
    with pytest.raises(ValueError, match=message):
        load_lerobot(root)


def test_float64_data_declared_float32_is_rounded_as_lerobot_rounds_it(tmp_path):
    root = _v21(tmp_path)
    path = root / EPISODE_1
    _edit_column(path, "next.reward", [0.1, 0.2, 0.3], pa.float64())
    reward = load_lerobot(root).rows[keys.NEXT, keys.REWARD]
    assert reward.dtype == torch.float32 and torch.equal(
        reward[4:, 0], torch.tensor([0.1, 0.2, 0.3], dtype=torch.float32)
    )


def test_an_empty_dataset_is_refused_by_name(tmp_path):
    root = _v21(tmp_path)
    (root / "meta/episodes.jsonl").write_text("")
    _edit_info(root, total_episodes=0, total_frames=0)
    with pytest.raises(ValueError, match=r"meta: the dataset has no episodes"):
        load_lerobot(root)
    root = write_v30(tmp_path / "v3", episodes_data([2]), files=[(0, 0)])
    path = root / "meta/episodes/chunk-000/file-000.parquet"
    pq.write_table(pq.read_table(path).slice(0, 0), path)
    _edit_info(root, total_episodes=0, total_frames=0)
    with pytest.raises(ValueError, match=r"meta: the dataset has no episodes"):
        load_lerobot(root)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"features__action": None}, "needs a dtype"),
        ({"data_path": "data/{episode_chunk:03d}/{nope}.parquet"}, r"data_path .* cannot be"),
        ({"data_path": 7}, "data_path must be a path template"),
        ({"chunks_size": 0}, "chunks_size must be >= 1"),
        ({"chunks_size": "1000"}, "chunks_size must be >= 1"),
    ],
)
def test_malformed_info_values_are_refused(tmp_path, change, message):
    root = _v21(tmp_path)
    _edit_info(root, **change)
    with pytest.raises(ValueError, match=message):
        load_lerobot(root)


def test_a_feature_renamed_in_the_metadata_only_is_refused(tmp_path):
    root = _v21(tmp_path)
    info = json.loads((root / "meta/info.json").read_text())
    info["features"]["actiom"] = info["features"].pop("action")
    (root / "meta/info.json").write_text(json.dumps(info))
    with pytest.raises(ValueError, match=r"\['actiom'\] absent from the file"):
        load_lerobot(root)


def test_a_byte_changed_after_save_lerobot_is_refused(tmp_path):
    root = save_lerobot(_rows(0), tmp_path / "ds", fps=10)
    data = root / "data/chunk-000/file-000.parquet"
    blob = bytearray(data.read_bytes())
    blob[len(blob) // 2] ^= 1
    data.write_bytes(bytes(blob))
    with pytest.raises(ValueError, match=r"file-000\.parquet: changed since save_lerobot"):
        load_lerobot(root)
    data.unlink()
    with pytest.raises(ValueError, match=r"file-000\.parquet: file not found \(listed in"):
        load_lerobot(root)


@pytest.mark.parametrize(
    ("entry", "message"),
    [
        ({"key": "observation_x", "shape": [4]}, "records key 'observation_x'"),
        ({"key": "observation", "shape": [5]}, r"has shape \[5\], meta/info\.json declares \[4\]"),
        ({"key": "observation", "shape": "4"}, "needs a shape"),
        ("observation", "records key None"),
    ],
)
def test_a_tampered_sidecar_is_refused(tmp_path, entry, message):
    root = save_lerobot(_rows(0), tmp_path / "ds", fps=10)
    sidecar = json.loads((root / "meta/imitrl.json").read_text())
    sidecar["columns"]["observation.state"] = entry
    (root / "meta/imitrl.json").write_text(json.dumps(sidecar))
    with pytest.raises(ValueError, match=r"imitrl\.json: changed since save_lerobot wrote it"):
        load_lerobot(root)  # its own digest
    del sidecar["digest"], sidecar["files"]  # as imitrl wrote it before checksums
    (root / "meta/imitrl.json").write_text(json.dumps(sidecar))
    with pytest.raises(ValueError, match=message):
        load_lerobot(root)


# ------------------------------------------------------ time-limit endings
def _limited_env(steps: int) -> GymEnv:
    return GymEnv("CartPole-v1", categorical_action_encoding=True, max_episode_steps=steps)


def test_episodes_ending_at_the_env_time_limit_load_as_truncated(tmp_path):
    root = write_v21(tmp_path / "ds", episodes_data([5, 3, 5]))  # next.done only
    loaded = load_lerobot(root, env=_limited_env(5))
    rows = loaded.rows
    last = torch.tensor([4, 7, 12])
    truncated = rows[keys.NEXT, keys.TRUNCATED].squeeze(-1)
    terminated = rows[keys.NEXT, keys.TERMINATED].squeeze(-1)
    assert truncated[last].tolist() == [True, False, True]
    assert terminated[last].tolist() == [False, True, False]
    assert int(truncated.sum()) == 2 and int(terminated.sum()) == 1
    assert any("2 episode(s) end at the env's time limit (5 steps)" in n for n in loaded.notes)
    longer = load_lerobot(root, env=_limited_env(500)).rows  # no episode reaches 500
    assert not longer[keys.NEXT, keys.TRUNCATED].any()
    assert torch.equal(longer[keys.NEXT, keys.TERMINATED], longer[keys.NEXT, keys.DONE])


def test_recorded_endings_are_used_as_they_are(tmp_path):
    rows = _rows(0, lengths=(5, 3))
    done = rows[keys.NEXT, keys.DONE]
    rows[keys.NEXT, keys.TERMINATED] = done.clone()  # ended by the task at the limit
    rows[keys.NEXT, keys.TRUNCATED] = torch.zeros_like(done)
    root = save_lerobot(rows, tmp_path / "both", fps=10)
    back = load_lerobot(root, env=_limited_env(5)).rows
    assert torch.equal(back[keys.NEXT, keys.TERMINATED], done)
    assert not back[keys.NEXT, keys.TRUNCATED].any()
    del rows[keys.NEXT, keys.TRUNCATED]
    rows[keys.NEXT, keys.TERMINATED][4] = False  # one recorded flag: the other is done & ~it
    root = save_lerobot(rows, tmp_path / "terminated_only", fps=10)
    back = load_lerobot(root, env=_limited_env(5)).rows
    assert back[keys.NEXT, keys.TRUNCATED].squeeze(-1).nonzero().flatten().tolist() == [4]


# ------------------------------------------------------------ Minari reader
def _minari(tmp_path, episodes=None, **kwargs) -> Path:
    return _write(tmp_path / "m", episodes or [_episode(3, 0), _episode(2, 1)], **kwargs)


def _with(field: str, value, n: int = 3) -> dict:
    ep = _episode(n, 0)
    ep[field] = value
    return ep


@pytest.mark.parametrize(
    ("episode", "spaces", "message"),
    [
        (None, {"obs_space": {**BOX4, "dtype": "int64"}}, "refusing to truncate floating"),
        (None, {"obs_space": {**BOX4, "dtype": "float16"}}, "does not fit .* 'float16'"),
        (None, {"obs_space": {**BOX4, "dtype": "float99"}}, "unsupported dtype 'float99'"),
        (_with("actions", np.array([0.0, 1.0, 0.7])), {}, "Discrete space holds integers"),
        (_with("actions", np.array([0, 1, 2])), {}, "value 2 lies outside the Discrete"),
        (_with("terminations", np.array([0.0, 0.0, 0.3])), {}, "terminations.*refusing"),
        (_with("truncations", np.array([0, 2, 0])), {}, "truncations: value 2 does not fit"),
        (_with("rewards", np.ones((3, 2))), {}, r"rewards have shape \[3, 2\].*one value"),
        (_with("rewards", np.array([1.0, np.inf, 1.0])), {}, "rewards: frame 1 holds inf"),
        (_with("rewards", np.array(["a", "b", "c"], dtype="S1")), {}, "expected numbers"),
        (
            _with("observations", np.full((4, 4), np.nan, np.float32)),
            {},
            "observations: frame 0 holds nan",
        ),
    ],
)
def test_minari_values_their_space_cannot_hold_are_refused(tmp_path, episode, spaces, message):
    root = _minari(tmp_path, [episode] if episode is not None else None, **spaces)
    with pytest.raises(ValueError, match=message):
        load_minari(root)


def test_minari_rewards_stored_2d_load_as_one_per_step(tmp_path):
    flat = load_minari(_minari(tmp_path / "a", [_episode(3, 0)])).rows
    ep = _episode(3, 0)
    ep["rewards"] = ep["rewards"].reshape(3, 1)
    assert _same(load_minari(_minari(tmp_path / "b", [ep])).rows, flat)


def test_minari_integer_flags_of_zero_and_one_load_as_booleans(tmp_path):
    ep = _episode(3, 0)
    ep["terminations"] = ep["terminations"].astype(np.int8)
    rows = load_minari(_minari(tmp_path, [ep])).rows
    assert rows[keys.NEXT, keys.TERMINATED].dtype == torch.bool
    assert rows[keys.NEXT, keys.TERMINATED].squeeze(-1).tolist() == [False, False, True]


def test_two_minari_episodes_with_one_id_are_refused(tmp_path):
    root = _minari(tmp_path, [_episode(3, 0), _episode(2, 1)])
    with h5py.File(root / "data/main_data.hdf5", "a") as f:
        f.move("episode_1", "episode_00")
        f["episode_00"].attrs["id"] = 0
    with pytest.raises(ValueError, match=r"episode id 0 is held twice \(.*episode_0.*episode_00"):
        load_minari(root)
    root = _minari(tmp_path / "attrs", [_episode(3, 0), _episode(2, 1)])
    with h5py.File(root / "data/main_data.hdf5", "a") as f:
        f["episode_1"].attrs["id"] = 0
    with pytest.raises(ValueError, match=r"episode_1: attrs id=0 contradicts the group's name"):
        load_minari(root)


@pytest.mark.parametrize(
    ("meta", "message"),
    [
        ({"total_steps": "five"}, "total_steps must be a non-negative integer"),
        ({"total_episodes": [2]}, "total_episodes must be a non-negative integer"),
        ({"total_episodes": 3}, "declares 3 episodes, the dataset holds 2"),
        ({"action_space": json.dumps({**DISCRETE2, "n": 0})}, "Discrete space needs integers"),
        ({"data_format": ["hdf5"]}, "data_format .* is not supported"),
    ],
)
def test_malformed_minari_metadata_is_refused(tmp_path, meta, message):
    with pytest.raises(ValueError, match=message):
        load_minari(_minari(tmp_path, **meta))


# ------------------------------------------------------ Minari arrow storage
def _minari_buffers():
    from minari.data_collector.episode_buffer import EpisodeBuffer

    rng = np.random.default_rng(0)

    def episode(e, n):
        obs = {
            "pos": [rng.standard_normal((2, 3)).astype(np.float32) for _ in range(n + 1)],
            "tup": (
                [int(rng.integers(1, 4)) for _ in range(n + 1)],
                [rng.random(1) for _ in range(n + 1)],
            ),
            "img": [np.full((32, 32, 3), 40 * e, np.uint8) for _ in range(n + 1)],
        }
        return EpisodeBuffer(
            id=e,
            observations=obs,
            actions=[int(a) for a in rng.integers(2, 6, n)],  # Discrete(4, start=2)
            rewards=list(rng.random(n)),
            terminations=[False] * (n - 1) + [e == 0],
            truncations=[False] * (n - 1) + [e == 1],
            infos={"x": np.arange(n + 1)},
        )

    return [episode(0, 4), episode(1, 2)]


@pytest.fixture(scope="module")
def minari_formats(tmp_path_factory):
    """One set of episodes written by the minari package in each of its storage formats."""
    minari = pytest.importorskip("minari")
    from gymnasium import spaces

    home = tmp_path_factory.mktemp("minari")
    obs = spaces.Dict(
        {
            "pos": spaces.Box(-9, 9, (2, 3), np.float32),
            "tup": spaces.Tuple((spaces.Discrete(3, start=1), spaces.Box(0, 1, (1,), np.float64))),
            "img": spaces.Box(0, 255, (32, 32, 3), np.uint8),
        }
    )
    before = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(home)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for fmt in ("hdf5", "arrow", "parquet"):
                minari.create_dataset_from_buffers(
                    f"test/{fmt}-v0",
                    _minari_buffers(),
                    observation_space=obs,
                    action_space=spaces.Discrete(4, start=2),
                    data_format=fmt,
                    algorithm_name="test",
                )
    finally:
        os.environ.pop("MINARI_DATASETS_PATH")
        if before is not None:
            os.environ["MINARI_DATASETS_PATH"] = before
    return {fmt: home / f"test/{fmt}-v0" for fmt in ("hdf5", "arrow", "parquet")}


def _quiet_minari(root: Path):
    with pytest.warns(UserWarning, match="infos/x"):
        return load_minari(root)


@pytest.mark.parametrize("fmt", ["arrow", "parquet"])
def test_minari_arrow_storage_loads_as_its_hdf5_twin(minari_formats, fmt):
    hdf5 = _quiet_minari(minari_formats["hdf5"])
    other = _quiet_minari(minari_formats[fmt])
    assert other.format == f"minari {fmt} (minari 0.5.4)" and other.num_episodes == 2
    assert _same(hdf5.rows, other.rows)
    rows = other.rows
    assert rows[keys.EXPERT_ACTION].min() >= 2  # the padding row (0) is not an action
    assert rows[keys.OBSERVATION, "tup", "_index_0"].dtype == torch.int64
    assert rows[keys.NEXT, keys.TRUNCATED].squeeze(-1).tolist() == [0, 0, 0, 0, 0, 1]


def test_damaged_minari_arrow_storage_is_refused_by_file(minari_formats, tmp_path):
    root = shutil.copytree(minari_formats["arrow"], tmp_path / "ds")
    part = root / "data/1/part-0.arrow"
    part.write_bytes(part.read_bytes()[:-100])
    with pytest.raises(ValueError, match=r"data/1/part-0\.arrow: not a readable arrow file"):
        load_minari(root)
    root = shutil.copytree(minari_formats["arrow"], tmp_path / "ids")
    (root / "data/1/metadata.json").write_text(json.dumps({"id": 0, "total_steps": 2}))
    with pytest.raises(ValueError, match=r"1/metadata\.json: id 0 contradicts the folder"):
        load_minari(root)
    root = shutil.copytree(minari_formats["arrow"], tmp_path / "steps")
    (root / "data/1/metadata.json").write_text(json.dumps({"id": 1, "total_steps": 3}))
    with pytest.raises(ValueError, match=r"data/1/part-\*\.arrow: total_steps=3 but 2 rewards"):
        load_minari(root)
    root = shutil.copytree(minari_formats["arrow"], tmp_path / "gone")
    shutil.rmtree(root / "data/0")
    with pytest.raises(ValueError, match="declares 2 episodes, the dataset holds 1"):
        load_minari(root)
