"""End to end: BC from a LeRobot dataset of CartPole expert episodes, then DAgger on the same buffer.

Offline start, interactive repair: the buffer starts as the recorded dataset (round 0),
DAgger extends it with relabelled rounds of the learner's own states, and the final
buffer (every round, with its flags) is written back as a LeRobot dataset.
"""

from __future__ import annotations

import torch
from torchrl.envs import GymEnv
from torchrl.envs.utils import ExplorationType

from imitrl import keys
from imitrl.algorithms import BCConfig, DAggerConfig, EnvSource, dagger, fit_bc
from imitrl.data import DemonstrationBuffer, rollout_episodes
from imitrl.datasets import load_lerobot, save_lerobot
from imitrl.evaluation import evaluate
from imitrl.experts import cartpole_expert
from imitrl.policies import ActorCritic

FIT = BCConfig(num_steps=300, batch_size=256, seed=0)


def _env(seed: int) -> GymEnv:
    env = GymEnv("CartPole-v1", categorical_action_encoding=True)
    env.set_seed(seed)
    return env


def test_bc_from_lerobot_then_dagger_reaches_the_experts_return(tmp_path):
    expert = cartpole_expert()
    env = _env(0)
    # a recorded dataset: two expert episodes written as LeRobot v3.0
    recorded = rollout_episodes(
        env, expert.as_actor(), 2, exploration=ExplorationType.DETERMINISTIC, max_steps=2_000
    )
    save_lerobot(recorded, tmp_path / "cartpole", fps=50, tasks="balance the pole")

    # offline start: the buffer is the dataset
    loaded = load_lerobot(tmp_path / "cartpole", env=env)
    buffer = DemonstrationBuffer(action_spec=env.action_spec)
    buffer.extend(loaded.rows)
    for k in recorded.keys(True, True):
        assert torch.equal(buffer.data.get(k), recorded.get(k)), k
    clone = ActorCritic.mlp(4, 2, seed=0)
    fit_bc(clone, buffer, FIT)
    expert_return = evaluate(
        _env(1000), expert.as_actor(), 3, exploration=ExplorationType.DETERMINISTIC, max_steps=2_000
    ).mean_return
    assert expert_return == 500.0

    # interactive repair: relabelled rounds extend the same buffer
    result = dagger(
        EnvSource(env, exploration=ExplorationType.DETERMINISTIC, max_steps=5_000),
        expert,
        lambda: ActorCritic.mlp(4, 2, seed=0),
        buffer,
        DAggerConfig(rounds=4, episodes_per_round=2, fit=FIT, seed=0),
    )
    final = evaluate(
        _env(1000),
        result.learner.policy,
        10,
        exploration=ExplorationType.DETERMINISTIC,
        max_steps=6_000,
    )
    assert final.mean_return == expert_return  # every one of the 10 episodes lasts 500 steps
    data = buffer.data
    assert data[keys.ROUND].unique().tolist() == [0, 1, 2, 3]
    assert torch.equal(data[: len(recorded)][keys.OBSERVATION], recorded[keys.OBSERVATION])
    relabelled = data[data[keys.ROUND] > 0]
    assert torch.equal(
        relabelled[keys.EXPERT_ACTION], expert(relabelled.clone())[keys.EXPERT_ACTION]
    )
    assert not relabelled[keys.EXPERT_EXECUTED].any()  # beta = 0: the learner drove

    # the aggregated buffer, every round with its flags, goes back to LeRobot
    back = load_lerobot(save_lerobot(buffer, tmp_path / "dagger", fps=50), env=env).rows
    for k in data.keys(True, True):
        assert torch.equal(back.get(k), data.get(k)), k
