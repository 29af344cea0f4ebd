"""Environments: the batched tabular simulator and helpers to build TorchRL envs (gymnasium
ids through :func:`make_env`, Dict observations renamed as LeRobot names them)."""

from imitrl.envs.dict_obs import ENVIRONMENT_STATE, DictObservation
from imitrl.envs.gym_stream import GymnasiumStream, GymnasiumStreamSource, play_episodes
from imitrl.envs.limits import episode_limit
from imitrl.envs.make import make_env
from imitrl.envs.tabular_env import TabularEnv

__all__ = [
    "ENVIRONMENT_STATE",
    "DictObservation",
    "GymnasiumStream",
    "GymnasiumStreamSource",
    "TabularEnv",
    "episode_limit",
    "make_env",
    "play_episodes",
]
