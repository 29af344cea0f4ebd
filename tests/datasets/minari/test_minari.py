"""Minari datasets read from their HDF5 file (built here with h5py as Minari 0.5 lays it out)."""

from __future__ import annotations

import io
import json
import warnings

import h5py
import numpy as np
import pytest
import torch
from torchrl.envs import GymEnv

from imitrl import keys
from imitrl.data import DemonstrationBuffer
from imitrl.datasets import load_minari

BOX4 = {"type": "Box", "dtype": "float32", "shape": [4], "low": [-1.0] * 4, "high": [1.0] * 4}
DISCRETE2 = {"type": "Discrete", "dtype": "int64", "start": 0, "n": 2}


def _write(root, episodes, *, obs_space=BOX4, act_space=DISCRETE2, meta_in_attrs=False, **meta):
    """``episodes[i] = dict(observations=[T+1, ...] | nested dict, actions, rewards, ...)``
    written as ``minari.dataset._storages.hdf5_storage`` does (Minari 0.5.4)."""
    data = root / "data"
    data.mkdir(parents=True)
    metadata = {
        "total_episodes": len(episodes),
        "total_steps": int(sum(len(e["rewards"]) for e in episodes)),
        "data_format": "hdf5",
        "jpeg_encoding": True,
        "observation_space": json.dumps(obs_space),
        "action_space": json.dumps(act_space),
        "env_spec": json.dumps({"id": "CartPole-v1"}),
        "dataset_id": "test/demo-v0",
        "minari_version": "0.5.4",
        **meta,
    }

    def put(group, name, value):
        if isinstance(value, dict):
            sub = group.create_group(name)
            for k, v in value.items():
                put(sub, k, v)
        elif isinstance(value, list):  # encoded images: variable-length uint8
            ds = group.create_dataset(name, (len(value),), dtype=h5py.vlen_dtype(np.uint8))
            for i, v in enumerate(value):
                ds[i] = v
        else:
            group.create_dataset(name, data=value)

    with h5py.File(data / "main_data.hdf5", "w", track_order=True) as f:
        for i, ep in enumerate(episodes):
            g = f.create_group(f"episode_{ep.get('id', i)}")
            g.attrs["id"] = ep.get("id", i)
            g.attrs["seed"] = i
            g.attrs["total_steps"] = len(ep["rewards"])
            for k in ("observations", "actions", "rewards", "terminations", "truncations", "infos"):
                if k in ep:
                    put(g, k, ep[k])
        if meta_in_attrs:
            f.attrs.update(metadata)
    if not meta_in_attrs:
        (data / "metadata.json").write_text(json.dumps(metadata))
    return root


def _episode(n, seed, obs_dim=4, truncated=False):
    rng = np.random.default_rng(seed)
    term = np.zeros(n, dtype=bool)
    trunc = np.zeros(n, dtype=bool)
    (trunc if truncated else term)[-1] = True
    return {
        "observations": rng.standard_normal((n + 1, obs_dim)).astype(np.float32),
        "actions": rng.integers(0, 2, n).astype(np.int64),
        "rewards": np.ones(n),
        "terminations": term,
        "truncations": trunc,
        "infos": {},
    }


def test_box_discrete_values_and_episode_order(tmp_path):
    # 12 episodes: "episode_10" sorts before "episode_2" as text, not as ids
    episodes = [_episode(n, s, truncated=s % 2 == 1) for s, n in enumerate([3, 5, 2, 4] * 3)]
    root = _write(tmp_path / "ds", episodes)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        loaded = load_minari(root, next_observation=True)
    rows = loaded.rows
    assert loaded.num_episodes == 12 and loaded.format.startswith("minari hdf5")
    obs = np.concatenate([e["observations"][:-1] for e in episodes])
    nxt = np.concatenate([e["observations"][1:] for e in episodes])
    assert rows[keys.OBSERVATION].dtype == torch.float32
    assert torch.equal(rows[keys.OBSERVATION], torch.from_numpy(obs))
    assert torch.equal(rows[keys.NEXT, keys.OBSERVATION], torch.from_numpy(nxt))
    actions = torch.from_numpy(np.concatenate([e["actions"] for e in episodes]))
    assert torch.equal(rows[keys.EXPERT_ACTION], actions) and torch.equal(
        rows[keys.ACTION], actions
    )
    assert rows[keys.NEXT, keys.REWARD].dtype == torch.float64  # Minari's own dtype, [N, 1]
    assert rows[keys.NEXT, keys.REWARD].shape == (len(rows), 1)
    term = np.concatenate([e["terminations"] for e in episodes])
    trunc = np.concatenate([e["truncations"] for e in episodes])
    assert torch.equal(rows[keys.NEXT, keys.TERMINATED].squeeze(-1), torch.from_numpy(term))
    assert torch.equal(rows[keys.NEXT, keys.DONE].squeeze(-1), torch.from_numpy(term | trunc))
    ids = np.concatenate([np.full(len(e["rewards"]), i) for i, e in enumerate(episodes)])
    assert torch.equal(rows[keys.EPISODE], torch.from_numpy(ids))
    assert torch.equal(
        rows[keys.STEP], torch.cat([torch.arange(len(e["rewards"])) for e in episodes])
    )
    assert rows[keys.EXPERT_EXECUTED].all() and (rows[keys.ROUND] == 0).all()


def test_dict_and_tuple_observations_and_infos_reported(tmp_path):
    space = {
        "type": "Dict",
        "subspaces": {
            "inner": {"type": "Dict", "subspaces": {"k": {"type": "Discrete", "dtype": "int64", "start": 0, "n": 5}}},
            "pos": {"type": "Box", "dtype": "float32", "shape": [2], "low": [-1, -1], "high": [1, 1]},
            "tup": {"type": "Tuple", "subspaces": [
                {"type": "Discrete", "dtype": "int64", "start": 0, "n": 3},
                {"type": "Box", "dtype": "float64", "shape": [1], "low": [0.0], "high": [1.0]},
            ]},
        },
    }  # fmt: skip
    rng = np.random.default_rng(0)
    episodes = []
    for n in (4, 2):
        episodes.append(
            {
                "observations": {
                    "inner": {"k": rng.integers(0, 5, n + 1)},
                    "pos": rng.standard_normal((n + 1, 2)).astype(np.float32),
                    "tup": {
                        "_index_0": rng.integers(0, 3, n + 1),
                        "_index_1": rng.random((n + 1, 1)),
                    },
                },
                "actions": rng.integers(0, 2, n),
                "rewards": rng.random(n),
                "terminations": np.arange(n) == n - 1,
                "truncations": np.zeros(n, dtype=bool),
                "infos": {"x": rng.random(n + 1)},
            }
        )
    root = _write(tmp_path / "ds", episodes, obs_space=space)
    with pytest.warns(UserWarning, match="infos/x"):
        loaded = load_minari(root)
    obs = loaded.rows[keys.OBSERVATION]
    pos = np.concatenate([e["observations"]["pos"][:-1] for e in episodes])
    k = np.concatenate([e["observations"]["inner"]["k"][:-1] for e in episodes])
    t1 = np.concatenate([e["observations"]["tup"]["_index_1"][:-1] for e in episodes])
    assert torch.equal(obs["pos"], torch.from_numpy(pos))
    assert torch.equal(obs["inner", "k"], torch.from_numpy(k))
    assert obs["tup", "_index_1"].dtype == torch.float64 and torch.equal(
        obs["tup", "_index_1"], torch.from_numpy(t1)
    )
    assert loaded.skipped == {"infos/x": "per-step infos are not loaded"}
    DemonstrationBuffer().extend(loaded.rows)  # nested observations fit the buffer


def test_jpeg_images_decode_as_minari_does(tmp_path):
    from PIL import Image

    space = {"type": "Box", "dtype": "uint8", "shape": [32, 40, 3], "low": 0, "high": 255}
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 255, (4, 32, 40, 3), dtype=np.uint8)

    def jpeg(img):
        buf = io.BytesIO()
        Image.fromarray(img).save(buf, format="JPEG")
        return np.frombuffer(buf.getvalue(), dtype=np.uint8)

    ep = {
        "observations": [jpeg(f) for f in frames],
        "actions": np.zeros(3, dtype=np.int64),
        "rewards": np.zeros(3),
        "terminations": np.array([False, False, True]),
        "truncations": np.zeros(3, dtype=bool),
    }
    loaded = load_minari(_write(tmp_path / "ds", [ep], obs_space=space))
    decoded = np.stack([np.asarray(Image.open(io.BytesIO(jpeg(f).tobytes()))) for f in frames[:3]])
    assert loaded.rows[keys.OBSERVATION].dtype == torch.uint8
    assert torch.equal(loaded.rows[keys.OBSERVATION], torch.from_numpy(decoded))


def test_old_minari_metadata_in_hdf5_attributes(tmp_path):
    root = _write(tmp_path / "ds", [_episode(3, 0)], meta_in_attrs=True)
    assert not (root / "data/metadata.json").exists()
    assert len(load_minari(root / "data").rows) == 3


def test_dataset_id_under_minari_root(tmp_path, monkeypatch):
    _write(tmp_path / "datasets/cartpole/expert-v0", [_episode(2, 0)])
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "datasets"))
    assert len(load_minari("cartpole/expert-v0").rows) == 2
    with pytest.raises(ValueError, match="never downloads"):
        load_minari("cartpole/missing-v0")


def test_env_fits_rewards_and_checks_shapes(tmp_path):
    env = GymEnv("CartPole-v1", categorical_action_encoding=True)
    loaded = load_minari(_write(tmp_path / "ds", [_episode(3, 0), _episode(2, 1)]), env=env)
    assert loaded.rows[keys.NEXT, keys.REWARD].dtype == torch.float32
    assert any("float64 -> torch.float32" in n for n in loaded.notes)
    bad = _write(
        tmp_path / "bad",
        [_episode(3, 0, obs_dim=3)],
        obs_space={**BOX4, "shape": [3], "low": [-1.0] * 3, "high": [1.0] * 3},
    )
    with pytest.raises(ValueError, match=r"main_data\.hdf5.*'observation'.*\[3\].*expects \[4\]"):
        load_minari(bad, env=env)


def test_malformed(tmp_path):
    ep = _episode(3, 0)
    ep["observations"] = ep["observations"][:-1]  # T observations instead of T + 1
    with pytest.raises(ValueError, match=r"episode_0: 3 observations.*T \+ 1"):
        load_minari(_write(tmp_path / "a", [ep]))
    with pytest.raises(ValueError, match=r"declares 9 steps"):
        load_minari(_write(tmp_path / "b", [_episode(3, 0)], total_steps=9))
    wrong_shape = {**BOX4, "shape": [5], "low": [-1.0] * 5, "high": [1.0] * 5}
    with pytest.raises(ValueError, match=r"observations has shape \[4\].*declares \[5\]"):
        load_minari(_write(tmp_path / "c", [_episode(3, 0)], obs_space=wrong_shape))
    with pytest.raises(ValueError, match="'zarr' is not supported"):  # arrow is read since #13
        load_minari(_write(tmp_path / "d", [_episode(3, 0)], data_format="zarr"))
    root = _write(tmp_path / "e", [_episode(3, 0)])
    path = root / "data/main_data.hdf5"
    path.write_bytes(path.read_bytes()[:200])
    with pytest.raises(ValueError, match=r"main_data\.hdf5: not a readable HDF5 file"):
        load_minari(root)
    with pytest.raises(ValueError, match="no Minari dataset"):
        load_minari(tmp_path / "nowhere")


DISCRETE = {"type": "Discrete", "dtype": "int64", "start": 0}


def _taxi_like(tmp_path, rewards):
    """A Taxi-shaped dataset: Discrete(500) states and Discrete(6) actions, int64 rewards as
    Minari stores the Python ints gymnasium's Taxi returns."""
    rng = np.random.default_rng(0)
    n = len(rewards)
    ep = {
        "observations": rng.integers(0, 500, n + 1),
        "actions": rng.integers(0, 6, n),
        "rewards": np.asarray(rewards, dtype=np.int64),
        "terminations": np.arange(n) == n - 1,
        "truncations": np.zeros(n, dtype=bool),
    }
    space = {**DISCRETE, "n": 500}
    return _write(tmp_path, [ep], obs_space=space, act_space={**DISCRETE, "n": 6})


def test_integer_rewards_fit_a_float_env_and_share_its_buffer(tmp_path):
    from torchrl.envs.utils import ExplorationType

    from imitrl.policies import Expert
    from imitrl.runtime import rollout_episodes

    env = GymEnv("Taxi-v4", categorical_action_encoding=True)
    root = _taxi_like(tmp_path / "ds", [-1, -1, -10, 20])
    loaded = load_minari(root, env=env)
    reward = loaded.rows[keys.NEXT, keys.REWARD]
    assert reward.dtype == torch.float32
    assert reward.squeeze(-1).tolist() == [-1.0, -1.0, -10.0, 20.0]
    assert any("'rewards'" in n and "int64 -> torch.float32" in n for n in loaded.notes)
    buffer = DemonstrationBuffer(num_states=500)
    buffer.extend(loaded.rows)
    expert = Expert.from_table(torch.zeros(500, dtype=torch.int64))
    greedy = ExplorationType.DETERMINISTIC
    rows = rollout_episodes(
        env, expert.as_actor(), 1, exploration=greedy, max_steps=500, first_episode=1
    )
    buffer.extend(rows)  # the env's float32 rewards join the dataset's rows
    assert len(buffer) == 4 + len(rows)


def test_integer_rewards_that_a_float_cannot_hold_are_refused(tmp_path):
    env = GymEnv("Taxi-v4", categorical_action_encoding=True)
    root = _taxi_like(tmp_path / "ds", [-1, 2**24 + 1])  # float32 rounds it to 2**24
    with pytest.raises(
        ValueError, match=r"'next\.reward' \(from feature 'rewards'\) holds 16777217"
    ):
        load_minari(root, env=env)


def test_infos_stored_whole_and_spaces_without_a_shape(tmp_path):
    root = _write(tmp_path / "a", [_episode(3, 0)])
    with h5py.File(root / "data/main_data.hdf5", "a") as f:
        del f["episode_0/infos"]
        f["episode_0"].create_dataset("infos", data=['{"a": 1}'] * 4, dtype=h5py.string_dtype())
    with pytest.warns(UserWarning, match="infos"):
        loaded = load_minari(root)
    assert len(loaded.rows) == 3 and loaded.skipped == {"infos": "per-step infos are not loaded"}
    no_shape = {"type": "Box", "dtype": "float32"}
    with pytest.raises(ValueError, match=r"metadata\.json: observation_space: a Box space needs"):
        load_minari(_write(tmp_path / "b", [_episode(3, 0)], obs_space=no_shape))
    nested = {"type": "Dict", "subspaces": {"pos": no_shape}}
    with pytest.raises(ValueError, match=r"observation_space\['pos'\]: a Box space needs"):
        load_minari(_write(tmp_path / "c", [_episode(3, 0)], obs_space=nested))


def test_arrow_datasets_are_named_as_such(tmp_path):
    root = _write(tmp_path / "ds", [_episode(3, 0)], data_format="arrow")
    (root / "data/main_data.hdf5").unlink()  # Minari's arrow storage has <id>/ folders
    (root / "data/episode_0").mkdir()
    with pytest.raises(ValueError, match=r"data/episode_0: unexpected folder .*named by id"):
        load_minari(root)  # read since #13: tests/datasets/test_datasets_faults.py writes real ones
