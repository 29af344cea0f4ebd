"""Environments: the batched tabular simulator and helpers to build TorchRL envs."""

from imitrl.envs.gym_stream import GymnasiumStream, GymnasiumStreamSource, play_episodes
from imitrl.envs.limits import episode_limit
from imitrl.envs.make import make_env
from imitrl.envs.tabular_env import TabularEnv

__all__ = [
    "GymnasiumStream",
    "GymnasiumStreamSource",
    "TabularEnv",
    "episode_limit",
    "make_env",
    "play_episodes",
]
