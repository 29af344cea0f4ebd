"""One small DAgger run, built the same way in a test and in a subprocess the test kills.

``python -m tests._resume_run KIND CHECKPOINT_DIR KILL_AT`` runs it with a checkpoint
after every round and SIGKILLs itself in round ``KILL_AT``'s ``on_fit`` (after that
round's fit, before its collection: the last checkpoint is round ``KILL_AT - 1``'s).
"""

from __future__ import annotations

import os
import signal
import sys

import torch
from torchrl.envs.utils import ExplorationType

from imitrl.algorithms import BCConfig, Constant, DAggerConfig, EnvSource, dagger
from imitrl.data import DemonstrationBuffer
from imitrl.envs import GymnasiumStream, GymnasiumStreamSource, make_env
from imitrl.experts import cartpole_expert
from imitrl.learners import TaskSpec
from imitrl.learners import build as build_learner
from imitrl.policies import Expert
from imitrl.runtime import rollout_episodes
from imitrl.tabular import TabularMDP, greedy, value_iteration

ROUNDS = 5


def build(kind: str):
    """``(source, expert, make_learner, buffer, config)`` of the run, from scratch."""
    torch.manual_seed(0)
    if kind == "cartpole":
        env = make_env("CartPole-v1", seed=0, num_envs=2, max_episode_steps=40)
        expert = cartpole_expert()
        buffer = DemonstrationBuffer(action_spec=env.action_spec_unbatched)
        demo_env = make_env("CartPole-v1", seed=1, max_episode_steps=40)
        buffer.extend(rollout_episodes(demo_env, expert, 1))
        # sampled learner actions and coin flips: every generator a resume must restore
        generator = torch.Generator().manual_seed(7)
        source = EnvSource(env, exploration=ExplorationType.RANDOM, generator=generator)
        config = DAggerConfig(
            rounds=ROUNDS,
            episodes_per_round=2,
            beta=Constant(0.5),
            bc=BCConfig(num_steps=30, batch_size=32),
        )
        return (
            source,
            expert,
            lambda: build_learner("for_env", env, hidden=(16, 16)),
            buffer,
            config,
        )
    mdp = TabularMDP.from_gym("FrozenLake-v1", gamma=0.95)
    expert = Expert.from_table(greedy(mdp.backup(value_iteration(mdp, 1000)[-1])))
    source = GymnasiumStreamSource(mdp, GymnasiumStream(4))
    buffer = DemonstrationBuffer(num_states=mdp.num_states)
    buffer.extend(source.collect(expert.as_actor(), 3, round_index=0, first_episode=0))
    config = DAggerConfig(rounds=ROUNDS, episodes_per_round=3, bc=BCConfig(num_steps=50))
    return (
        source,
        expert,
        lambda: build_learner("cross_entropy", TaskSpec(action=4, num_states=16)),
        buffer,
        config,
    )


def run(kind: str, checkpoint_dir=None, *, resume: bool = False, on_fit=None):
    source, expert, make_learner, buffer, config = build(kind)
    return dagger(
        source, expert, make_learner, buffer, config,
        checkpoint_dir=checkpoint_dir, resume=resume, on_fit=on_fit,
    )  # fmt: skip


if __name__ == "__main__":
    kind, directory, kill_at = sys.argv[1], sys.argv[2], int(sys.argv[3])

    def die(k, learner):
        if k == kill_at:
            os.kill(os.getpid(), signal.SIGKILL)

    run(kind, directory, on_fit=die)
    sys.exit(3)  # not killed: the test fails on this status
