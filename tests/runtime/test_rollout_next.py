"""``rollout_episodes(..., next_observation=True)`` keeps each row's next observation,
the episode's final one included, so rows just collected are written to Minari as they
are (issue 44: save_minari refused them, and the final observation was gone)."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
import torch

from imitrl import keys
from imitrl.envs import make_env
from imitrl.experts import cartpole_expert
from imitrl.runtime import paths, rollout_episodes

NEXT_OBS = (keys.NEXT, keys.OBSERVATION)


def _rows(num_envs: int, limit: int | None = None):
    env = make_env("CartPole-v1", seed=4, num_envs=num_envs, max_episode_steps=limit)
    return rollout_episodes(env, cartpole_expert(), 5, next_observation=True)


def _physics_step(obs: torch.Tensor, action: int) -> np.ndarray:
    """CartPole's own step from state ``obs`` (gymnasium's dynamics, no learning)."""
    raw = gymnasium.make("CartPole-v1").unwrapped
    raw.reset(seed=0)
    raw.state = obs.double().numpy()
    return raw.step(int(action))[0]


@pytest.mark.parametrize("num_envs", [1, 3])
def test_next_observations_chain_and_end_in_the_envs_final_observation(num_envs):
    rows = _rows(num_envs, limit=30)  # the expert never falls: every episode truncated
    obs, nxt, episode = rows.get(keys.OBSERVATION), rows.get(NEXT_OBS), rows.get(keys.EPISODE)
    same = episode[1:] == episode[:-1]
    assert torch.equal(nxt[:-1][same], obs[1:][same])  # within an episode: the next row's
    last = torch.cat([~same, torch.tensor([True])])
    assert int(last.sum()) == 5 and bool(rows.get((keys.NEXT, keys.TRUNCATED))[last].all())
    for i in last.nonzero().flatten().tolist():  # the final one: the physics' next state
        want = _physics_step(obs[i], rows.get(keys.ACTION)[i])
        assert np.allclose(nxt[i].numpy(), want, atol=1e-6), (i, nxt[i], want)


def test_the_reference_path_keeps_the_same_next_observations():
    fast = _rows(2, limit=25)
    with paths.reference():
        slow = _rows(2, limit=25)
    assert torch.equal(fast.get(NEXT_OBS), slow.get(NEXT_OBS))


def test_rows_just_collected_are_written_to_minari_and_read_back(tmp_path):
    pytest.importorskip("h5py")
    from imitrl.datasets import load_minari, save_minari

    rows = _rows(2, limit=40)
    path = save_minari(rows, tmp_path / "demos", env_id="CartPole-v1")
    back = load_minari(path, next_observation=True).rows
    for key in (keys.OBSERVATION, NEXT_OBS, keys.EPISODE):
        assert torch.equal(back.get(key).to(rows.get(key).dtype), rows.get(key)), key
    plain = _rows(1, limit=10).exclude(NEXT_OBS)  # without it: refused, naming the option
    with pytest.raises(ValueError, match="next_observation=True"):
        save_minari(plain, tmp_path / "plain", env_id="CartPole-v1")
