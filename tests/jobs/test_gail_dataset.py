"""``imitrl gail --dataset`` reads a dataset's recorded next observations: the last row of
an episode a time limit cut is a transition the discriminator sees (a hostile review: the
CLI kept only the rollout keys, so each cut episode lost its last transition, though
``expert_transitions`` reads ``("next", OBSERVATION)`` where the data records it)."""

from __future__ import annotations

import warnings

import pytest

from imitrl import keys
from imitrl.algorithms.adversarial import loop
from imitrl.envs import make_env
from imitrl.experts import cartpole_expert
from imitrl.runtime import rollout_episodes
from tests._cli import run_main

LIMIT, EPISODES = 10, 2


@pytest.fixture
def minari_demos(tmp_path):
    pytest.importorskip("h5py")
    from imitrl.datasets import save_minari

    env = make_env("CartPole-v1", seed=0, max_episode_steps=LIMIT)
    rows = rollout_episodes(env, cartpole_expert(), EPISODES, next_observation=True)
    assert bool(rows.get((keys.NEXT, keys.TRUNCATED)).any())  # the expert outlives the limit
    return save_minari(rows, tmp_path / "demos", env_id="CartPole-v1")


def _counted(monkeypatch) -> list[int]:
    """The number of expert transitions each call of ``expert_transitions`` returns."""
    seen: list[int] = []
    original = loop.expert_transitions

    def counted(rows):
        out = original(rows)
        seen.append(out.shape[0])
        return out

    monkeypatch.setattr(loop, "expert_transitions", counted)
    return seen


def _train(command: str, env: str, *source: str, out) -> None:
    """``imitrl COMMAND --env ENV SOURCE...`` on a tiny budget, which must succeed."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        status, _, err = run_main(
            command, "--env", env, *source, "--total-steps", "64", "--rollout-steps", "64",
            "--eval-episodes", "1", "--eval-every", "0", "--max-episode-steps", str(LIMIT),
            "--no-progress", "--out", str(out),
        )  # fmt: skip
    assert status == 0, err


@pytest.mark.parametrize("command", ["gail", "airl"])
def test_a_cut_episodes_last_row_is_a_transition(minari_demos, tmp_path, monkeypatch, command):
    seen = _counted(monkeypatch)
    _train(command, "CartPole-v1", "--dataset", str(minari_demos), out=tmp_path / command)
    assert seen == [LIMIT * EPISODES]  # was LIMIT * EPISODES - EPISODES: each cut end dropped


def test_expert_episodes_keep_their_cut_last_transition(tmp_path, monkeypatch):
    """The same for ``--demos`` episodes the expert plays: each is cut by the time limit."""
    seen = _counted(monkeypatch)
    _train("gail", "CartPole-v1", "--demos", str(EPISODES), out=tmp_path / "g")
    assert seen == [LIMIT * EPISODES]


def test_a_float64_minari_dataset_trains_with_its_recorded_successors(tmp_path, monkeypatch):
    """A hostile review: a MuJoCo env's Minari dataset stores float64 observations; the
    observation was cast to the env's float32 and its recorded next one was not, and
    comparing the two raised ``Double did not match Float`` through imitrl."""
    pytest.importorskip("h5py")
    pytest.importorskip("mujoco")
    from imitrl.datasets import load_minari, save_minari
    from imitrl.experts import inverted_pendulum_expert

    env = make_env("InvertedPendulum-v5", seed=0, max_episode_steps=LIMIT)
    rows = rollout_episodes(env, inverted_pendulum_expert(), EPISODES, next_observation=True)
    path = save_minari(rows, tmp_path / "demos", env_id="InvertedPendulum-v5")
    loaded = load_minari(path, env=env, next_observation=True).rows
    assert loaded[keys.NEXT, keys.OBSERVATION].dtype == loaded[keys.OBSERVATION].dtype
    seen = _counted(monkeypatch)
    _train("gail", "InvertedPendulum-v5", "--dataset", str(path), "--hidden", "16,16",
           out=tmp_path / "g")  # fmt: skip
    assert seen == [rows.shape[0]]  # every row a transition: each episode ends cut or fallen
