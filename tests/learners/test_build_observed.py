"""A learner built for an env whose observation holds an entry its policy never reads is
reported (``IgnoredObservationWarning``), naming the entry and what to do: LeRobot's
Meta-World ``environment_state_agent_pos`` gives the state learner the hand's 4 numbers
and hides the goal in ``environment_state``, and nothing said so."""

from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
import pytest

from imitrl.envs import make_env
from imitrl.jobs.bc import run_bc
from imitrl.jobs.configs import BCJob
from imitrl.learners import build
from imitrl.learners.task import IgnoredObservationWarning


class Reach(gym.Env):
    """Move a point to a goal: ``agent_pos`` the point [2], ``environment_state`` point
    and goal [4] (Meta-World's ``environment_state_agent_pos`` layout, in small);
    ``pixels``: a 16x16 camera too."""

    def __init__(self, pixels: bool = False):
        entries: dict = {
            "agent_pos": gym.spaces.Box(-1.0, 1.0, (2,), np.float64),
            "environment_state": gym.spaces.Box(-1.0, 1.0, (4,), np.float64),
        }
        if pixels:
            entries["pixels"] = gym.spaces.Box(0, 255, (16, 16, 3), np.uint8)
        self.observation_space = gym.spaces.Dict(entries)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.pixels = pixels

    def _obs(self) -> dict:
        obs = {"agent_pos": self.pos.copy(), "environment_state": np.r_[self.pos, self.goal]}
        if self.pixels:
            obs["pixels"] = np.zeros((16, 16, 3), np.uint8)
        return obs

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.pos, self.goal = self.np_random.uniform(-1.0, 1.0, size=(2, 2))
        return self._obs(), {}

    def step(self, action):
        self.pos = np.clip(self.pos + 0.2 * np.clip(action, -1, 1), -1.0, 1.0)
        return self._obs(), -float(np.linalg.norm(self.pos - self.goal)), False, False, {}


STATE, PIXELS = "imitrl-test/ReachState-v0", "imitrl-test/ReachPixels-v0"
for _id, _kwargs in ((STATE, {}), (PIXELS, {"pixels": True})):
    if _id not in gym.registry:
        gym.register(_id, entry_point=Reach, kwargs=_kwargs, max_episode_steps=10)


def test_a_state_learner_that_cannot_see_environment_state_is_told_so():
    env = make_env(STATE, seed=0)
    with pytest.warns(IgnoredObservationWarning) as caught:
        learner = build("default", env, hidden=(8,))
    assert learner.policy.in_keys == ["observation"]
    message = str(caught[0].message)
    assert "'environment_state' [4]" in message and "obs_type=state" in message
    assert "FlattenObservation" in message


def test_a_learner_that_reads_every_entry_is_not_warned():
    flat = make_env("Pendulum-v1", seed=0)  # one state: nothing left unread
    with warnings.catch_warnings():
        warnings.simplefilter("error", IgnoredObservationWarning)
        build("default", flat, hidden=(8,))
        # a vision learner goes without the privileged state on purpose
        build("default", make_env(PIXELS, seed=0), state=True, channels=(4,), hidden=(8,))


def test_the_bc_command_passes_the_warning_on(tmp_path):
    job = BCJob(env=STATE, expert=f"{__name__}:expert", num_steps=5, eval_episodes=1,
                demos=2, out=tmp_path / "run", progress=False)  # fmt: skip
    with pytest.warns(IgnoredObservationWarning, match="environment_state"):
        run_bc(job)


def expert():
    """The goal-reaching expert of :class:`Reach`, from its ``environment_state``."""
    import torch

    from imitrl.policies.experts import Expert

    def act(state: torch.Tensor) -> torch.Tensor:
        return (2.0 * (state[..., 2:] - state[..., :2])).clamp(-1.0, 1.0)

    return Expert.from_callable(act, observation_key="environment_state")
