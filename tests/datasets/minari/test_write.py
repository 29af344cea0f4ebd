"""``save_minari``: demonstration rows written as a Minari 0.5 hdf5 dataset, read back by
imitrl's ``load_minari`` and by the real ``minari`` package (issue item 7)."""

from __future__ import annotations

import json
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch
from tensordict import TensorDict

from imitrl import keys
from imitrl.data import DemonstrationBuffer
from imitrl.datasets import load_minari, save_minari

torch.set_num_threads(1)
minari = pytest.importorskip("minari")

DICT_SPACE = gym.spaces.Dict(
    {
        "agent_pos": gym.spaces.Box(-1.0, 1.0, (2,), np.float32),
        "goal": gym.spaces.Discrete(4),
    }
)


def _play(env_id: str, lengths: list[int], *, seed: int, first_id: int = 0) -> TensorDict:
    """Rows of episodes played in gymnasium with random actions, each cut after
    ``lengths[e]`` steps (truncated there unless the env terminated), keeping every
    ``("next", "observation")`` (the final one included, as Minari needs it)."""
    env = gym.make(env_id)
    env.action_space.seed(seed)
    rows = []
    for e, length in enumerate(lengths):
        obs, _ = env.reset(seed=seed + e)
        for t in range(length):
            action = env.action_space.sample()
            nxt, reward, terminated, truncated, _ = env.step(action)
            truncated = truncated or (t == length - 1 and not terminated)
            rows.append((obs, action, nxt, reward, terminated, truncated, first_id + e, t))
            obs = nxt
            if terminated or truncated:
                break
    columns = list(zip(*rows, strict=True))
    obs, act, nxt = (torch.tensor(np.array(c)) for c in columns[:3])
    term = torch.tensor(columns[4]).reshape(-1, 1)
    trunc = torch.tensor(columns[5]).reshape(-1, 1)
    return TensorDict(
        {
            keys.OBSERVATION: obs,
            keys.EXPERT_ACTION: act,
            keys.ACTION: act.clone(),
            keys.EXPERT_EXECUTED: torch.ones(len(rows), dtype=torch.bool),
            keys.ROUND: torch.zeros(len(rows), dtype=torch.int64),
            keys.EPISODE: torch.tensor(columns[6]),
            keys.STEP: torch.tensor(columns[7]),
            keys.NEXT: {
                keys.OBSERVATION: nxt,
                keys.REWARD: torch.tensor(columns[3], dtype=torch.float32).reshape(-1, 1),
                keys.DONE: term | trunc,
                keys.TERMINATED: term,
                keys.TRUNCATED: trunc,
            },
        },
        [len(rows)],
    )


def _dict_rows(lengths: list[int], seed: int = 0) -> TensorDict:
    """Rows whose observation is a nested TensorDict (a Dict space), built by hand."""
    g = torch.Generator().manual_seed(seed)
    n = sum(lengths)
    episode = torch.cat([torch.full((k,), e) for e, k in enumerate(lengths)])
    step = torch.cat([torch.arange(k) for k in lengths])
    pos = torch.rand(n + len(lengths), 2, generator=g) * 2 - 1  # one extra per episode
    goal = torch.randint(0, 4, (n + len(lengths),), generator=g)
    cur = torch.cat([torch.arange(k) + sum(lengths[:e]) + e for e, k in enumerate(lengths)])
    last = torch.zeros(n, 1, dtype=torch.bool)
    last[torch.cumsum(torch.tensor(lengths), 0) - 1] = True
    obs = TensorDict({"agent_pos": pos[cur], "goal": goal[cur]}, [n])
    nxt = TensorDict({"agent_pos": pos[cur + 1], "goal": goal[cur + 1]}, [n])
    action = torch.randint(0, 3, (n,), generator=g)
    return TensorDict(
        {
            keys.OBSERVATION: obs,
            keys.EXPERT_ACTION: action,
            keys.EPISODE: episode,
            keys.STEP: step,
            keys.NEXT: {
                keys.OBSERVATION: nxt,
                keys.REWARD: torch.randn(n, 1, generator=g, dtype=torch.float64),
                keys.TERMINATED: last,
                keys.TRUNCATED: torch.zeros(n, 1, dtype=torch.bool),
            },
        },
        [n],
    )


def _assert_same_rows(loaded: TensorDict, rows: TensorDict) -> None:
    for key in rows.keys(include_nested=True, leaves_only=True):
        a, b = loaded.get(key), rows.get(key)
        assert a.dtype == b.dtype and torch.equal(a, b), key


# ---------------------------------------------------------- round trips
@pytest.mark.parametrize("env_id", ["CartPole-v1", "Pendulum-v1"])
def test_save_minari_round_trips_through_load_minari_value_for_value(tmp_path, env_id):
    rows = _play(env_id, [30, 7, 12], seed=3, first_id=5)
    path = save_minari(rows, tmp_path / "ds", env_id=env_id)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing left out, nothing skipped on load
        loaded = load_minari(path, next_observation=True, first_episode=5)
    assert loaded.num_episodes == 3
    _assert_same_rows(loaded.rows, rows)  # values, dtypes, shapes, ids, steps, flags
    meta = json.loads((path / "data" / "metadata.json").read_text())
    assert meta["total_steps"] == len(rows) and meta["data_format"] == "hdf5"
    assert json.loads(meta["env_spec"])["id"] == env_id

    # a buffer holding the loaded rows writes the same dataset again
    buffer = DemonstrationBuffer(action_spec=None)
    buffer.extend(load_minari(path, next_observation=True).rows)
    again = save_minari(buffer, tmp_path / "again", env_id=env_id)
    _assert_same_rows(load_minari(again, next_observation=True, first_episode=5).rows, rows)


def test_a_dict_observation_space_round_trips(tmp_path):
    rows = _dict_rows([4, 9, 1])
    space = {"observation_space": DICT_SPACE, "action_space": gym.spaces.Discrete(3)}
    path = save_minari(rows, tmp_path / "ds", **space)
    _assert_same_rows(load_minari(path, next_observation=True).rows, rows)


def test_the_minari_package_reads_what_save_minari_writes(tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    rows = _play("Pendulum-v1", [25, 40, 3], seed=0)
    save_minari(rows, tmp_path / "imitrl" / "pendulum-v0", env_id="Pendulum-v1")
    dataset = minari.load_dataset("imitrl/pendulum-v0")
    assert dataset.total_episodes == 3 and dataset.total_steps == len(rows)
    assert dataset.observation_space == gym.make("Pendulum-v1").observation_space
    assert dataset.recover_environment().spec.id == "Pendulum-v1"
    for e, episode in enumerate(dataset.iterate_episodes()):
        mine = rows[rows.get(keys.EPISODE) == e]
        final = mine.get((keys.NEXT, keys.OBSERVATION))[-1:]
        want = torch.cat([mine.get(keys.OBSERVATION), final]).numpy()
        assert np.array_equal(episode.observations, want)
        assert np.array_equal(episode.actions, mine.get(keys.EXPERT_ACTION).numpy())
        assert np.array_equal(episode.rewards, mine.get((keys.NEXT, keys.REWARD)).numpy()[:, 0])
        for name, key in (("terminations", keys.TERMINATED), ("truncations", keys.TRUNCATED)):
            assert np.array_equal(getattr(episode, name), mine.get((keys.NEXT, key)).numpy()[:, 0])

    # a Dict observation space too, opened by path
    dict_rows = _dict_rows([6, 2])
    path = save_minari(
        dict_rows,
        tmp_path / "dict",
        observation_space=DICT_SPACE,
        action_space=gym.spaces.Discrete(3),
    )
    dataset = minari.MinariDataset(path / "data")
    assert dataset.observation_space == DICT_SPACE
    episode = dataset[1]
    mine = dict_rows[dict_rows.get(keys.EPISODE) == 1]
    for entry in ("agent_pos", "goal"):
        want = torch.cat(
            [
                mine.get((keys.OBSERVATION, entry)),
                mine.get((keys.NEXT, keys.OBSERVATION, entry))[-1:],
            ]
        )
        assert np.array_equal(episode.observations[entry], want.numpy())


def test_a_dataset_minari_wrote_is_written_back_identical(tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    from minari.data_collector import EpisodeBuffer

    played = _play("CartPole-v1", [60, 60, 60, 60], seed=0)
    buffers = []
    for e in range(4):
        mine = played[played.get(keys.EPISODE) == e]
        final = mine.get((keys.NEXT, keys.OBSERVATION))[-1:]
        buffers.append(
            EpisodeBuffer(
                observations=torch.cat([mine.get(keys.OBSERVATION), final]).numpy(),
                actions=mine.get(keys.EXPERT_ACTION).numpy(),
                rewards=mine.get((keys.NEXT, keys.REWARD)).double().numpy()[:, 0],
                terminations=mine.get((keys.NEXT, keys.TERMINATED)).numpy()[:, 0],
                truncations=mine.get((keys.NEXT, keys.TRUNCATED)).numpy()[:, 0],
                infos={},
            )
        )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # minari asks for an author, a description, ...
        theirs = minari.create_dataset_from_buffers(
            "minari/cartpole-v0", buffers, env="CartPole-v1", data_format="hdf5"
        )
    source = tmp_path / "minari" / "cartpole-v0"
    rows = load_minari(source, next_observation=True).rows
    ours = minari.MinariDataset(save_minari(rows, tmp_path / "ours", env_id="CartPole-v1") / "data")
    assert ours.total_steps == theirs.total_steps
    for a, b in zip(theirs.iterate_episodes(), ours.iterate_episodes(), strict=True):
        for name in ("observations", "actions", "rewards", "terminations", "truncations"):
            x, y = getattr(a, name), getattr(b, name)
            assert x.dtype == y.dtype and np.array_equal(x, y), name


# ------------------------------------------------------------ bad input
def test_bad_rows_are_refused_naming_what_is_wrong(tmp_path):
    rows = _play("CartPole-v1", [5, 5, 5], seed=0)
    spaces = {"env_id": "CartPole-v1"}

    def refused(bad, match, **kwargs):
        with pytest.raises(ValueError, match=match):
            save_minari(bad, tmp_path / "bad", **{**spaces, **kwargs})
        assert not (tmp_path / "bad").exists()  # nothing written, nothing left behind
        assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".bad")] == []

    refused(
        rows.exclude((keys.NEXT, keys.OBSERVATION)),
        r"lack \['next.observation'\].*final observation",
    )
    refused(rows.exclude(keys.STEP, keys.EPISODE), r"lack \['episode', 'step'\]")
    shuffled = rows.clone()
    shuffled.set(keys.EPISODE, torch.tensor([0] * 5 + [1] * 5 + [0] * 5))
    refused(shuffled, "contiguous block")
    skipped = rows.clone()
    skipped.get(keys.STEP)[3] = 7
    refused(skipped, r"episode 0: 'step' must run 0..length-1, got 7 at its row 3")
    nan = rows.clone()
    nan.get(keys.OBSERVATION)[12, 1] = float("nan")
    refused(nan, r"episode 2/observations: frame 2 holds nan")
    nan_reward = rows.clone()
    nan_reward.get((keys.NEXT, keys.REWARD))[6] = float("inf")
    refused(nan_reward, r"episode 1: the reward at step 1 is inf")
    outside = rows.clone()
    outside.get(keys.EXPERT_ACTION)[2] = 2
    refused(outside, r"episode 0/actions.*step 2 holds 2, outside the space Discrete\(2\)")
    floats = rows.clone()
    floats.set(keys.EXPERT_ACTION, rows.get(keys.EXPERT_ACTION).float() + 0.5)
    refused(floats, "refusing to truncate floating data")
    early = rows.clone()
    early.get((keys.NEXT, keys.TERMINATED))[1] = True
    early.get((keys.NEXT, keys.DONE))[1] = True
    refused(early, r"episode 0: terminated or truncated at step 1, before the episode's last row")
    jump = rows.clone()
    jump.get((keys.NEXT, keys.OBSERVATION))[0] += 1.0
    refused(jump, r"episode 0: \('next', 'observation'\) differs from the next row's")
    refused(rows, r"per-step shape \[4\].*declares \[3\]", env_id="Pendulum-v1")
    refused(rows, "needs observation_space and action_space", env_id=None)
    tuple_space = {
        "observation_space": gym.spaces.Tuple([]),
        "action_space": gym.spaces.Discrete(2),
    }
    refused(
        rows, "observation_space must be a gymnasium Box.*got Tuple", env_id=None, **tuple_space
    )
    refused(rows, "not a registered gymnasium id", env_id="NoSuchEnv-v7")
    refused(TensorDict({}, [0]), "non-empty")


def test_an_existing_path_is_replaced_only_when_asked_and_only_a_dataset(tmp_path):
    first = _play("CartPole-v1", [5], seed=0)
    second = _play("CartPole-v1", [8, 3], seed=1)
    path = save_minari(first, tmp_path / "ds", env_id="CartPole-v1")
    with pytest.raises(ValueError, match="exists; pass overwrite=True"):
        save_minari(second, path, env_id="CartPole-v1")
    _assert_same_rows(load_minari(path, next_observation=True).rows, first)
    broken = second.clone()
    broken.get(keys.OBSERVATION)[9, 0] = float("nan")  # in the last episode
    with pytest.raises(ValueError, match="holds nan"):
        save_minari(broken, path, env_id="CartPole-v1", overwrite=True)
    _assert_same_rows(load_minari(path, next_observation=True).rows, first)  # old one whole
    save_minari(second, path, env_id="CartPole-v1", overwrite=True)
    _assert_same_rows(load_minari(path, next_observation=True).rows, second)

    folder = tmp_path / "mine"
    folder.mkdir()
    (folder / "notes.txt").write_text("keep me")
    with pytest.raises(ValueError, match="not a Minari dataset"):
        save_minari(first, folder, env_id="CartPole-v1", overwrite=True)
    assert (folder / "notes.txt").read_text() == "keep me"


def test_keys_minari_cannot_hold_are_named_in_a_warning(tmp_path):
    rows = _play("CartPole-v1", [6, 4], seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # round 0, expert-executed, equal actions: nothing lost
        save_minari(rows, tmp_path / "plain", env_id="CartPole-v1")
    dagger = rows.clone()
    dagger.get(keys.ACTION)[2] = 1 - dagger.get(keys.ACTION)[2]  # the learner acted
    dagger.get(keys.EXPERT_EXECUTED)[2] = False
    dagger.set(keys.WEIGHT, torch.ones(len(rows)))
    with pytest.warns(UserWarning, match=r"no place for \['action', 'expert_executed', 'weight'\]"):
        save_minari(dagger, tmp_path / "dagger", env_id="CartPole-v1")
    with pytest.warns(UserWarning, match=r"no place for \['expert_action', 'expert_executed'"):
        executed = save_minari(
            dagger, tmp_path / "executed", env_id="CartPole-v1", action_key="action"
        )
    loaded = load_minari(executed, next_observation=True).rows
    assert torch.equal(loaded.get(keys.EXPERT_ACTION), dagger.get(keys.ACTION))
