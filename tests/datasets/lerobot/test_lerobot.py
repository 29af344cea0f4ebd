"""LeRobot datasets as files: v2.1 / v3.0 reading, v3.0 writing, round trips, malformed input."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import GymEnv

from imitrl import keys
from imitrl.data import DemonstrationBuffer
from imitrl.datasets import load_lerobot, resolve_lerobot_root, save_lerobot
from tests._lerobot_files import TASKS, episodes_data, write_v21, write_v30

LENGTHS = [5, 3, 7, 1, 4]


def _quiet_load(*args, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the plain datasets here skip nothing worth a warning
        return load_lerobot(*args, **kwargs)


def _check_against(loaded, episodes):
    rows = loaded.rows
    cat = {k: np.concatenate([ep[k] for ep in episodes]) for k in episodes[0]}
    assert rows[keys.OBSERVATION].dtype == torch.float32
    assert torch.equal(rows[keys.OBSERVATION], torch.from_numpy(cat["observation.state"]))
    assert rows[keys.EXPERT_ACTION].dtype == torch.int64 and rows[keys.EXPERT_ACTION].shape == (
        len(rows),
    )
    assert torch.equal(rows[keys.EXPERT_ACTION], torch.from_numpy(cat["action"]))
    assert torch.equal(rows[keys.ACTION], rows[keys.EXPERT_ACTION])
    assert rows[keys.EXPERT_EXECUTED].all() and (rows[keys.ROUND] == 0).all()
    assert rows[keys.NEXT, keys.REWARD].shape == (len(rows), 1)
    assert torch.equal(rows[keys.NEXT, keys.DONE].squeeze(-1), torch.from_numpy(cat["next.done"]))
    ids = np.concatenate([np.full(len(ep["action"]), e) for e, ep in enumerate(episodes)])
    steps = np.concatenate([np.arange(len(ep["action"])) for ep in episodes])
    assert torch.equal(rows[keys.EPISODE], torch.from_numpy(ids))
    assert torch.equal(rows[keys.STEP], torch.from_numpy(steps))
    assert loaded.tasks == TASKS
    assert torch.equal(rows["task_index"], torch.from_numpy(cat["task_index"]))  # two tasks: loaded
    assert loaded.num_episodes == len(episodes) and loaded.fps == 50


# ------------------------------------------------------------------ reading
def test_v21_as_lerobot_03_writes_it(tmp_path):
    episodes = episodes_data(LENGTHS)
    loaded = _quiet_load(write_v21(tmp_path / "ds", episodes, chunks_size=2))  # 3 chunk dirs
    assert loaded.format == "lerobot v2.1"
    _check_against(loaded, episodes)


@pytest.mark.parametrize("layout", ["fixed", "variable"])
def test_v30_multi_file_multi_chunk_loads_in_episode_order(tmp_path, layout):
    episodes = episodes_data(LENGTHS, seed=1)
    # episodes spread over 3 chunks and 4 files, episode table over 2 files
    files = [(0, 0), (0, 0), (0, 1), (1, 0), (2, 0)]
    root = write_v30(tmp_path / "ds", episodes, files=files, meta_files=2, vector_layout=layout)
    loaded = _quiet_load(root)
    assert loaded.format == "lerobot v3.0"
    _check_against(loaded, episodes)


def test_first_episode_offsets_ids_for_an_existing_buffer(tmp_path):
    root = write_v21(tmp_path / "ds", episodes_data(LENGTHS))
    loaded = _quiet_load(root, first_episode=7)
    assert loaded.rows[keys.EPISODE].unique().tolist() == [7, 8, 9, 10, 11]


def test_images_loaded_or_skipped_with_a_warning(tmp_path):
    episodes = episodes_data([3, 2], image=(6, 5))
    root = write_v30(tmp_path / "ds", episodes, files=[(0, 0), (0, 0)], image=(6, 5))
    with pytest.warns(UserWarning, match=r"observation\.images\.cam"):
        skipped = load_lerobot(root)
    assert "observation.images.cam" in skipped.skipped
    assert "observation.images.cam" not in skipped.rows.keys()
    loaded = _quiet_load(root, images="load")
    pixels = loaded.rows["observation.images.cam"]
    assert pixels.dtype == torch.uint8 and pixels.shape == (5, 6, 5, 3)  # declared (H, W, C)
    expected = np.concatenate([ep["observation.images.cam"] for ep in episodes])
    assert torch.equal(pixels, torch.from_numpy(expected))


def test_video_features_are_reported_not_dropped(tmp_path):
    root = write_v30(tmp_path / "ds", episodes_data([2, 2]), files=[(0, 0), (0, 0)])
    info = json.loads((root / "meta/info.json").read_text())
    info["features"]["observation.images.top"] = {
        "dtype": "video",
        "shape": [8, 8, 3],
        "names": None,
    }
    (root / "meta/info.json").write_text(json.dumps(info))
    with pytest.warns(UserWarning, match=r"observation\.images\.top.*video"):
        loaded = load_lerobot(root, images="load", videos="skip")
    assert "video" in loaded.skipped["observation.images.top"]


def test_key_map_adds_and_removes_features(tmp_path):
    root = write_v21(tmp_path / "ds", episodes_data(LENGTHS))
    loaded = _quiet_load(root, key_map={"timestamp": "time", "task_index": None})
    assert loaded.rows["time"].dtype == torch.float32
    assert torch.allclose(loaded.rows["time"], loaded.rows[keys.STEP].float() / 50)
    assert "task_index" not in loaded.rows.keys()
    with pytest.raises(ValueError, match="does not declare"):
        load_lerobot(root, key_map={"observation.nope": "x"})
    without_done = _quiet_load(root, key_map={"next.done": None})  # on purpose: no warning
    assert without_done.skipped["next.done"] == "left out by key_map"
    assert (keys.NEXT, keys.DONE) not in without_done.rows.keys(True)


def test_observation_must_map_somewhere(tmp_path):
    root = write_v21(tmp_path / "ds", episodes_data([2]))
    with pytest.raises(ValueError, match="no feature maps to 'observation'"):
        load_lerobot(root, key_map={"observation.state": None})


def test_env_checks_shapes_and_fits_reward_and_done(tmp_path):
    env = GymEnv("CartPole-v1", categorical_action_encoding=True)
    root = write_v21(tmp_path / "ds", episodes_data(LENGTHS))
    loaded = _quiet_load(root, env=env)
    rows = loaded.rows
    assert rows[keys.NEXT, keys.TERMINATED].shape == (len(rows), 1)
    assert torch.equal(rows[keys.NEXT, keys.TERMINATED], rows[keys.NEXT, keys.DONE])
    assert not rows[keys.NEXT, keys.TRUNCATED].any()
    assert any("terminated" in n for n in loaded.notes)
    bad = write_v21(tmp_path / "bad", episodes_data([3], obs_dim=3))
    with pytest.raises(ValueError, match=r"info\.json.*'observation'.*\[3\].*expects \[4\]"):
        load_lerobot(bad, env=env)


# ------------------------------------------------------------------ writing
def _dagger_like_buffer() -> DemonstrationBuffer:
    """Round 0 demonstrations and two relabelled rounds with mixed expert/learner actions."""
    g = torch.Generator().manual_seed(0)
    buf = DemonstrationBuffer()
    episode = 0
    for rnd, lengths in enumerate([[6, 4], [3, 5], [2]]):
        parts = []
        for n in lengths:
            executed = (
                torch.ones(n, dtype=torch.bool) if rnd == 0 else torch.rand(n, generator=g) < 0.5
            )
            label = torch.randint(0, 2, (n,), generator=g)
            done = torch.arange(n).eq(n - 1).unsqueeze(-1)
            parts.append(
                TensorDict(
                    {
                        keys.OBSERVATION: torch.randn(n, 4, generator=g),
                        keys.EXPERT_ACTION: label,
                        keys.ACTION: torch.where(executed, label, 1 - label),
                        keys.EXPERT_EXECUTED: executed,
                        keys.EPISODE: torch.full((n,), episode),
                        keys.ROUND: torch.full((n,), rnd),
                        keys.STEP: torch.arange(n),
                        "aux": torch.randn(n, 2, 3, dtype=torch.float64, generator=g),
                        "one": torch.randn(n, 1, generator=g),
                        (keys.NEXT, keys.REWARD): torch.ones(n, 1),
                        (keys.NEXT, keys.DONE): done,
                        (keys.NEXT, keys.TERMINATED): done.clone(),
                        (keys.NEXT, keys.TRUNCATED): torch.zeros(n, 1, dtype=torch.bool),
                    },
                    batch_size=[n],
                )
            )
            episode += 1
        buf.extend(torch.cat(parts))
    return buf


def _assert_identical(a: TensorDict, b: TensorDict):
    assert set(a.keys(True, True)) == set(b.keys(True, True))
    for k in a.keys(True, True):
        x, y = a.get(k), b.get(k)
        assert x.dtype == y.dtype and x.shape == y.shape and torch.equal(x, y), k


@pytest.mark.parametrize("episodes_per_file", [None, 1])
def test_round_trip_keeps_every_round(tmp_path, episodes_per_file):
    buf = _dagger_like_buffer()
    root = save_lerobot(
        buf, tmp_path / "ds", fps=50, episodes_per_file=episodes_per_file, chunks_size=2
    )
    loaded = _quiet_load(root)
    _assert_identical(buf.data, loaded.rows)
    assert loaded.rows[keys.ROUND].unique().tolist() == [0, 1, 2]
    n_files = len(list((root / "data").glob("chunk-*/file-*.parquet")))
    assert n_files == (1 if episodes_per_file is None else 5)
    if episodes_per_file == 1:
        assert (root / "data/chunk-002/file-000.parquet").is_file()  # 5 files, 2 per chunk
    again = DemonstrationBuffer()
    again.extend(loaded.rows)  # extends a fresh buffer with the same schema
    assert again.schema == buf.schema


def test_written_layout_is_lerobots(tmp_path):
    buf = _dagger_like_buffer()
    root = save_lerobot(buf, tmp_path / "ds", fps=50, tasks="balance", episodes_per_file=2)
    info = json.loads((root / "meta/info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["fps"] == 50
    assert (info["total_episodes"], info["total_frames"], info["total_tasks"]) == (5, 20, 1)
    assert info["splits"] == {"train": "0:5"}
    assert info["data_path"] == "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
    feats = info["features"]
    assert feats["observation.state"] == {"dtype": "float32", "shape": [4], "names": None}
    assert feats["action"]["shape"] == [1] and feats["action"]["dtype"] == "int64"
    assert feats["imitrl.round"]["dtype"] == "int64" and feats["intervention"] == {
        "dtype": "bool",
        "shape": [1],
        "names": None,
    }  # LeRobot's DAgger column (rollout/strategies/dagger.py), as LeRobot declares it
    assert "imitrl.expert_executed" not in feats
    assert list(feats)[-5:] == ["timestamp", "frame_index", "episode_index", "index", "task_index"]
    # data: LeRobot's column types and Hugging Face schema metadata
    schema = pq.read_schema(root / "data/chunk-000/file-000.parquet")
    assert schema.field("observation.state").type == pa.list_(pa.float32(), 4)
    assert schema.field("action").type == pa.int64()
    assert schema.field("aux").type == pa.list_(pa.list_(pa.float64()))
    hf = json.loads(schema.metadata[b"huggingface"])["info"]["features"]
    assert hf["aux"] == {"shape": [2, 3], "dtype": "float64", "_type": "Array2D"}
    data = pa.concat_tables(pq.read_table(p) for p in sorted((root / "data").glob("*/*.parquet")))
    assert data.column("index").to_pylist() == list(range(20))
    expected = [e for e, n in enumerate([6, 4, 3, 5, 2]) for _ in range(n)]
    assert data.column("episode_index").to_pylist() == expected
    # episode table
    eps = pq.read_table(root / "meta/episodes/chunk-000/file-000.parquet")
    assert eps.column_names[:7] == [
        "episode_index", "tasks", "length", "data/chunk_index", "data/file_index",
        "dataset_from_index", "dataset_to_index",
    ]  # fmt: skip
    assert eps.column("dataset_from_index").to_pylist() == [0, 6, 10, 13, 18]
    assert eps.column("data/file_index").to_pylist() == [0, 0, 1, 1, 2]
    assert eps.column("tasks").to_pylist() == [["balance"]] * 5
    assert eps.column("stats/observation.state/mean").type == pa.list_(pa.float64())
    assert eps.column("stats/action/min").type == pa.list_(pa.int64())
    assert eps.column("meta/episodes/chunk_index").to_pylist() == [0] * 5
    # tasks: the task string is the pandas index
    tasks = pq.read_table(root / "meta/tasks.parquet")
    assert json.loads(tasks.schema.metadata[b"pandas"])["index_columns"] == ["__index_level_0__"]
    assert tasks.column("__index_level_0__").to_pylist() == ["balance"]
    stats = json.loads((root / "meta/stats.json").read_text())
    obs = buf.data[keys.OBSERVATION].double()
    assert np.allclose(stats["observation.state"]["mean"], obs.mean(0).numpy())
    assert stats["observation.state"]["count"] == [20]
    assert len(stats["aux"]["mean"]) == 3  # lerobot 0.4 reduces 2-d features to the last axis


def test_tasks_round_trip(tmp_path):
    root = write_v21(tmp_path / "ds", episodes_data(LENGTHS))
    loaded = _quiet_load(root)
    back = _quiet_load(save_lerobot(loaded.rows, tmp_path / "out", fps=50, tasks=loaded.tasks))
    _assert_identical(loaded.rows, back.rows)
    assert back.tasks == TASKS


def _dict_observation_rows() -> TensorDict:
    """The DAgger-like rows with a Dict observation (as Minari's Dict spaces load)."""
    rows = _dagger_like_buffer().data
    obs = rows[keys.OBSERVATION]
    out = rows.exclude(keys.OBSERVATION)
    out[keys.OBSERVATION, "pos"] = obs[:, :2]
    out[keys.OBSERVATION, "goal", "xy"] = obs[:, 2:].double()
    return out


def test_dict_observations_round_trip_and_load_without_imitrl_json(tmp_path):
    rows = _dict_observation_rows()
    root = save_lerobot(rows, tmp_path / "ds", fps=50)
    _assert_identical(rows, _quiet_load(root).rows)
    # LeRobot datasets from elsewhere: every observation.<sub> feature nests under "observation"
    (root / "meta/imitrl.json").unlink()
    with pytest.warns(UserWarning, match="'aux'"):
        loaded = load_lerobot(root)
    assert loaded.loaded["observation.goal.xy"] == "observation.goal.xy"
    assert torch.equal(loaded.rows[keys.OBSERVATION, "pos"], rows[keys.OBSERVATION, "pos"])
    assert torch.equal(
        loaded.rows[keys.OBSERVATION, "goal", "xy"], rows[keys.OBSERVATION, "goal", "xy"]
    )
    with pytest.raises(ValueError, match="both a tensor and a group"):
        load_lerobot(
            root,
            key_map={"observation.pos": ("observation", "p"), "aux": ("observation", "p", "q")},
        )


def _validate_stats_as_lerobot(stats: dict, feature: str) -> None:
    """lerobot 0.4's ``compute_stats._validate_stat_value``, run by ``aggregate_stats`` when a
    dataset is merged or resumed."""
    for stat, value in stats.items():
        value = np.asarray(value)
        assert value.ndim >= 1
        assert stat != "count" or value.shape == (1,)
        assert "image" not in feature or stat == "count" or value.shape == (3, 1, 1), (stat, value)


def test_images_round_trip_as_lerobot_image_features(tmp_path):
    episodes = episodes_data([3, 2], image=(6, 5))
    source = write_v30(tmp_path / "src", episodes, files=[(0, 0), (0, 0)], image=(6, 5))
    loaded = _quiet_load(source, images="load")
    root = save_lerobot(loaded.rows, tmp_path / "ds", fps=50, tasks=loaded.tasks)
    _assert_identical(loaded.rows, _quiet_load(root, images="load").rows)
    info = json.loads((root / "meta/info.json").read_text())
    assert info["features"]["observation.images.cam"] == {
        "dtype": "image",
        "shape": [6, 5, 3],
        "names": ["height", "width", "channels"],
    }
    schema = pq.read_schema(root / "data/chunk-000/file-000.parquet")
    assert schema.field("observation.images.cam").type == pa.struct(
        [("bytes", pa.binary()), ("path", pa.string())]
    )
    hf = json.loads(schema.metadata[b"huggingface"])["info"]["features"]
    assert hf["observation.images.cam"] == {"_type": "Image"}
    # statistics per channel in [0, 1], (3, 1, 1), over every frame of these short episodes
    pixels = [ep["observation.images.cam"].astype(np.float64) / 255 for ep in episodes]
    eps = pq.read_table(root / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
    for row, ep_pixels in zip(eps, pixels):
        per_feature: dict[str, dict] = {}
        for column, value in row.items():
            if column.startswith("stats/"):
                _, feature, stat = column.split("/")
                per_feature.setdefault(feature, {})[stat] = value
        for feature, stats in per_feature.items():
            _validate_stats_as_lerobot(stats, feature)
        image = per_feature["observation.images.cam"]
        assert np.allclose(image["mean"], ep_pixels.mean(axis=(0, 1, 2)).reshape(3, 1, 1))
        assert image["count"] == [len(ep_pixels)]
    totals = json.loads((root / "meta/stats.json").read_text())
    for feature, stats in totals.items():
        _validate_stats_as_lerobot(stats, feature)
    everything = np.concatenate(pixels)
    std = np.asarray(totals["observation.images.cam"]["std"])
    assert np.allclose(std, everything.std(axis=(0, 1, 2)).reshape(3, 1, 1))
    with pytest.warns(UserWarning, match=r"observation\.images\.cam.*images='load'"):
        skipped = load_lerobot(root)
    assert "observation.images.cam" not in skipped.rows.keys()


def test_channel_first_images_and_source_names(tmp_path):
    rows = _dagger_like_buffer().data
    g = torch.Generator().manual_seed(1)
    rows["observation.image"] = torch.randint(0, 256, (len(rows), 3, 4, 7), generator=g).to(
        torch.uint8
    )
    names = {"observation.state": {"motors": ["a", "b", "c", "d"]}, "action": ["push"]}
    root = save_lerobot(rows, tmp_path / "ds", fps=50, names={**names, "not.written": ["x"]})
    features = json.loads((root / "meta/info.json").read_text())["features"]
    assert features["observation.image"]["shape"] == [3, 4, 7]
    assert features["observation.image"]["names"] == ["channels", "height", "width"]
    assert {k: features[k]["names"] for k in names} == names
    _assert_identical(rows, _quiet_load(root, images="load").rows)
    with pytest.raises(ValueError, match=r"names\['aux'\] must be"):
        save_lerobot(rows, tmp_path / "a", fps=50, names={"aux": "xyz"})
    with pytest.raises(ValueError, match=r"names\['observation\.state'\] has 2 entries"):
        save_lerobot(rows, tmp_path / "b", fps=50, names={"observation.state": ["a", "b"]})


def test_writer_refuses_what_lerobot_cannot_hold(tmp_path):
    buf = _dagger_like_buffer()
    with pytest.raises(ValueError, match="exists"):
        save_lerobot(buf, tmp_path, fps=50)
    rows = buf.data.clone()
    rows[keys.STEP] = rows[keys.STEP] + 1
    with pytest.raises(ValueError, match="frame_index"):
        save_lerobot(rows, tmp_path / "a", fps=50)
    shuffled = buf.data[torch.tensor([0, 7, 1, 2, 3, 4, 5, 6])]
    with pytest.raises(ValueError, match="contiguous"):
        save_lerobot(shuffled, tmp_path / "b", fps=50)
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


# ---------------------------------------------------------------- malformed
def test_missing_info_json(tmp_path):
    root = write_v21(tmp_path / "ds", episodes_data([2]))
    (root / "meta/info.json").unlink()
    with pytest.raises(ValueError, match=r"meta/info\.json not found"):
        load_lerobot(root)


def test_feature_declared_but_absent(tmp_path):
    root = write_v30(tmp_path / "ds", episodes_data([2, 3]), files=[(0, 0), (0, 1)])
    path = root / "data/chunk-000/file-001.parquet"
    pq.write_table(pq.read_table(path).drop_columns(["next.reward"]), path)
    with pytest.raises(ValueError, match=r"file-001\.parquet.*'next\.reward'.*absent"):
        load_lerobot(root)


def test_truncated_parquet(tmp_path):
    root = write_v21(tmp_path / "ds", episodes_data([4, 4]))
    path = root / "data/chunk-000/episode_000001.parquet"
    path.write_bytes(path.read_bytes()[:-40])
    with pytest.raises(ValueError, match=r"episode_000001\.parquet"):
        load_lerobot(root)


def test_length_and_shape_contradictions(tmp_path):
    root = write_v21(tmp_path / "ds", episodes_data([4, 4]))
    lines = (root / "meta/episodes.jsonl").read_text().splitlines()
    lines[1] = json.dumps({"episode_index": 1, "tasks": [TASKS[1]], "length": 5})
    (root / "meta/episodes.jsonl").write_text("\n".join(lines))
    with pytest.raises(ValueError, match=r"episode_000001\.parquet.*4 frames.*says 5"):
        load_lerobot(root)
    root = write_v21(tmp_path / "ds2", episodes_data([3]))
    info = json.loads((root / "meta/info.json").read_text())
    info["features"]["observation.state"]["shape"] = [5]
    (root / "meta/info.json").write_text(json.dumps(info))
    with pytest.raises(ValueError, match=r"'observation\.state'.*4 entries.*\[5\]"):
        load_lerobot(root)


@pytest.mark.parametrize("version", ["v1.6", "v3.1", "v2.2"])
def test_unsupported_version(tmp_path, version):
    root = write_v21(tmp_path / "ds", episodes_data([2]))
    info = json.loads((root / "meta/info.json").read_text())
    info["codebase_version"] = version
    (root / "meta/info.json").write_text(json.dumps(info))
    with pytest.raises(ValueError, match=rf"info\.json: codebase_version '{version}' is not"):
        load_lerobot(root)


def test_malformed_metadata_is_named(tmp_path):
    root = write_v21(tmp_path / "tasks", episodes_data([2]))
    (root / "meta/tasks.jsonl").write_text(json.dumps({"task_index": 0, "name": "t"}) + "\n")
    with pytest.raises(ValueError, match=r"tasks\.jsonl: entry .* 'task'"):
        load_lerobot(root)
    root = write_v21(tmp_path / "episodes", episodes_data([2, 3]))
    (root / "meta/episodes.jsonl").write_text(json.dumps({"tasks": [], "length": 2}) + "\n")
    with pytest.raises(ValueError, match=r"episodes\.jsonl: entry .* 'episode_index'"):
        load_lerobot(root)
    root = write_v30(tmp_path / "shape", episodes_data([2]), files=[(0, 0)])
    info = json.loads((root / "meta/info.json").read_text())
    info["features"]["action"]["shape"] = None
    (root / "meta/info.json").write_text(json.dumps(info))
    with pytest.raises(ValueError, match=r"info\.json: feature 'action' needs a shape"):
        load_lerobot(root)
    root = write_v30(tmp_path / "null", episodes_data([2, 3]), files=[(0, 0), (0, 0)])
    path = root / "meta/episodes/chunk-000/file-000.parquet"
    table = pq.read_table(path)
    i = table.column_names.index("dataset_from_index")
    pq.write_table(table.set_column(i, "dataset_from_index", pa.array([0, None])), path)
    with pytest.raises(ValueError, match=r"file-000\.parquet: .*'dataset_from_index'.* null"):
        load_lerobot(root)


def test_missing_v30_data_file_is_named(tmp_path):
    root = write_v30(tmp_path / "ds", episodes_data([2, 3, 4]), files=[(0, 0), (0, 1), (1, 0)])
    (root / "data/chunk-000/file-001.parquet").unlink()
    with pytest.raises(
        ValueError, match=r"chunk-000/file-001\.parquet: file not found .*episode\(s\) \[1\]"
    ):
        load_lerobot(root)


# ------------------------------------------------------------- repo_id cache
def test_repo_id_resolves_from_local_caches_only(tmp_path, monkeypatch):
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    monkeypatch.delenv("HF_LEROBOT_HOME", raising=False)
    monkeypatch.delenv("HF_HUB_CACHE", raising=False)
    with pytest.raises(ValueError, match="never uses the network"):
        resolve_lerobot_root("org/demo")
    repo = tmp_path / "hf/hub/datasets--org--demo"
    write_v21(repo / "snapshots/abc123", episodes_data([2, 3]))
    (repo / "refs").mkdir()
    (repo / "refs/main").write_text("abc123")
    assert resolve_lerobot_root("org/demo") == repo / "snapshots/abc123"
    assert _quiet_load("org/demo").num_episodes == 2
    local = write_v21(tmp_path / "hf/lerobot/org/demo", episodes_data([1]))
    assert resolve_lerobot_root("org/demo") == local  # LeRobot's own root comes first


def test_v30_episodes_are_slices_of_the_concatenated_files(tmp_path):
    """As LeRobot reads it: [dataset_from_index, dataset_to_index) of the sorted data files;
    the episode table's file pointers may be stale (lerobot 0.4.4's aggregate leaves them so)."""
    episodes = episodes_data(LENGTHS, seed=2)
    root = write_v30(tmp_path / "ds", episodes, files=[(0, 0), (0, 0), (0, 1), (0, 1), (0, 1)])
    path = root / "meta/episodes/chunk-000/file-000.parquet"
    table = pq.read_table(path)
    stale = pa.array([7] * len(LENGTHS), pa.int64())
    table = table.set_column(table.column_names.index("data/file_index"), "data/file_index", stale)
    pq.write_table(table, path)
    _check_against(_quiet_load(root), episodes)
    shifted = table.set_column(
        table.column_names.index("dataset_from_index"),
        "dataset_from_index",
        pa.array([0, 4, 8, 15, 16], pa.int64()),
    )
    pq.write_table(shifted, path)
    with pytest.raises(ValueError, match=r"episode 1 spans frames \[4, 8\) with length 3"):
        load_lerobot(root)


def test_values_that_do_not_fit_the_declared_dtype_are_refused():
    import pyarrow as pa

    from imitrl.datasets._arrow import column_to_tensor

    col = pa.array([1, 300, 2], type=pa.int64())
    with pytest.raises(ValueError, match="value 300 does not fit the declared dtype 'int8'"):
        column_to_tensor(col, shape=(), dtype="int8", where="data/file.parquet: 'x'")
    ok = column_to_tensor(pa.array([0.1, 0.2]), shape=(), dtype="float32", where="w")
    assert ok.dtype == torch.float32


def test_image_stats_sample_frames_as_lerobot_does():
    from imitrl.datasets.lerobot._stats import sample_frames as _sample_frames

    # lerobot's estimate_num_samples: 1000 frames -> 177 evenly spaced; 320 px wide -> every 2nd
    frames = np.broadcast_to(
        np.arange(1000, dtype=np.int32)[:, None, None, None], (1000, 3, 4, 320)
    )
    sampled = _sample_frames(frames)
    assert sampled.shape == (177, 3, 2, 160)
    assert sampled[[0, 1, -1], 0, 0, 0].tolist() == [0, 6, 999]  # round(linspace(0, 999, 177))
    assert _sample_frames(frames[:40]).shape == (40, 3, 2, 160)  # short episodes: every frame
