"""The random state of an env, read and restored: what a resumed run needs to draw the
same episodes as an uninterrupted one.

After a rollout, imitrl's next collection starts with ``env.reset()``, so an env's
future episodes are a function of its random generators alone (the simulator's own
state is re-drawn at reset). :func:`env_random_state` returns those generators' states
as JSON-able data; :func:`set_env_random_state` puts them back.

Supported: :class:`~imitrl.envs.TabularEnv`, TorchRL ``GymWrapper``/``GymEnv`` around a
gymnasium env or a ``SyncVectorEnv`` (what :func:`~imitrl.envs.make_env` builds), and
``TransformedEnv`` over either. Worker-process envs (``ParallelEnv``) keep their
generators in other processes and are refused.
"""

from __future__ import annotations

from typing import Any

import gymnasium
from torchrl.envs import EnvBase, GymWrapper, TransformedEnv

from imitrl.compat import wrapped_gym_env
from imitrl.envs.tabular_env import TabularEnv

__all__ = ["env_random_state", "set_env_random_state"]


def _gym_envs(env: GymWrapper) -> list:
    """The gymnasium envs (unwrapped) inside a ``GymWrapper``: one, or each of a vector env's."""
    inner = wrapped_gym_env(env)
    if isinstance(inner, gymnasium.vector.SyncVectorEnv):
        return [e.unwrapped for e in inner.envs]
    if isinstance(inner, gymnasium.vector.VectorEnv):
        raise ValueError(
            f"cannot read the random state of a {type(inner).__name__} (its envs live in "
            "other processes): use make_env(..., num_envs=N) without parallel=True"
        )
    assert isinstance(inner, gymnasium.Env)  # GymWrapper wraps a gymnasium env or vector env
    return [inner.unwrapped]


def _base(env: EnvBase) -> EnvBase:
    while isinstance(env, TransformedEnv):
        env = env.base_env
    return env


def env_random_state(env: EnvBase) -> dict[str, Any]:
    """The env's random generators' states (JSON-able); ValueError for an unsupported env."""
    base = _base(env)
    if isinstance(base, TabularEnv):
        return {"tabular": base.random_state()}
    if isinstance(base, GymWrapper):
        return {"gymnasium": [e.np_random.bit_generator.state for e in _gym_envs(base)]}
    raise ValueError(
        f"cannot read the random state of a {type(base).__name__}: resumable runs need a "
        "TabularEnv or an in-process gymnasium env (make_env without parallel=True)"
    )


def set_env_random_state(env: EnvBase, state: dict[str, Any]) -> None:
    """Restore :func:`env_random_state`'s output into ``env`` (the same kind of env)."""
    base = _base(env)
    if isinstance(base, TabularEnv) and "tabular" in state:
        base.set_random_state(state["tabular"])
        return
    if isinstance(base, GymWrapper) and "gymnasium" in state:
        envs = _gym_envs(base)
        if len(envs) != len(state["gymnasium"]):
            raise ValueError(
                f"the saved random state has {len(state['gymnasium'])} gymnasium envs, "
                f"the env {len(envs)}"
            )
        for e, st in zip(envs, state["gymnasium"]):
            e.np_random.bit_generator.state = st
        return
    raise ValueError(
        f"the saved random state ({sorted(state)}) does not fit a {type(base).__name__}"
    )
