"""`episode_limit`: the most steps one episode of an env takes before the env itself ends it.

Rollouts play whole episodes. When the env has a time limit of its own, every
episode ends by it and a rollout needs no bound; when it has none, a policy that
never ends an episode would hang the rollout, so the rollout asks for ``max_steps=``
(per episode) up front. Limits found:

* a gymnasium ``TimeLimit`` (``spec.max_episode_steps``, what ``gymnasium.make`` and
  :func:`~imitrl.envs.make_env`'s ``max_episode_steps=`` set) inside a TorchRL
  ``GymWrapper``/``GymEnv``, single or vectorised (``SyncVectorEnv``), divided by the
  wrapper's action repeat (``frame_skip``), rounded up;
* a TorchRL ``StepCounter(max_steps=N)`` transform (the smallest of all limits along
  a ``TransformedEnv`` chain counts);
* :class:`~imitrl.envs.TabularEnv`'s ``max_steps``;
* :class:`~imitrl.envs.pixel_tasks.PixelBalanceEnv`'s ``hill.horizon`` (it truncates
  there);
* a ``SerialEnv``/``ParallelEnv`` (e.g. ``make_env(..., parallel=True)``): the
  largest limit of its sub-envs, read from one copy of each built in this process
  (its workers cannot be asked before they start).
"""

from __future__ import annotations

import math

import gymnasium
from torchrl.envs import Compose, EnvBase, GymWrapper, StepCounter, TransformedEnv
from torchrl.envs.batched_envs import BatchedEnvBase

from imitrl.compat import wrapped_gym_env
from imitrl.envs.tabular_env import TabularEnv

__all__ = ["episode_limit"]


def _smallest(limits: list[int | None]) -> int | None:
    found = [int(x) for x in limits if x is not None]
    return min(found) if found else None


def _step_counters(transform) -> list[int | None]:
    if isinstance(transform, Compose):
        return [m for t in transform.transforms for m in _step_counters(t)]
    return [transform.max_steps] if isinstance(transform, StepCounter) else []


def _gym_limit(gym_env) -> int | None:
    """``spec.max_episode_steps`` of a gymnasium env; of every copy of a vector env."""
    if isinstance(gym_env, gymnasium.vector.VectorEnv):
        # gymnasium declares get_attr on SyncVectorEnv and AsyncVectorEnv, not on their base
        specs = gym_env.get_attr("spec")  # type: ignore[attr-defined]
    else:
        specs = [gym_env.spec]
    limits = [None if s is None else s.max_episode_steps for s in specs]
    found = [x for x in limits if x is not None]
    if not limits or len(found) < len(limits):
        return None
    return max(found)


def _batched_limit(env: BatchedEnvBase) -> int | None:
    limits: list[int | None] = []
    for i, (fn, kwargs) in enumerate(zip(env.create_env_fn, env.create_env_kwargs)):
        if i and fn is env.create_env_fn[0] and kwargs == env.create_env_kwargs[0]:
            limits.append(limits[0])  # SerialEnv(n, fn): one copy tells for all
            continue
        copy = fn(**kwargs)
        limits.append(episode_limit(copy))
        copy.close()
    found = [x for x in limits if x is not None]
    if not limits or len(found) < len(limits):
        return None
    return max(found)


def episode_limit(env: EnvBase) -> int | None:
    """The env's own time limit in env steps (see the module docstring), or None.

    Returns:
        the most steps one episode can take (an episode is truncated there), or None
        when the env has no limit this function can find.
    """
    if isinstance(env, TransformedEnv):
        return _smallest([*_step_counters(env.transform), episode_limit(env.base_env)])
    if isinstance(env, TabularEnv):
        return env.max_steps
    # imported here: the pixel tasks import the policies (their experts), which
    # ``import imitrl.envs`` should not load
    from imitrl.envs.pixel_tasks import PixelBalanceEnv

    if isinstance(env, PixelBalanceEnv):
        return env.hill.horizon
    if isinstance(env, GymWrapper):
        limit = _gym_limit(wrapped_gym_env(env))
        # a gymnasium step per action repeat: the TimeLimit ends the repeat loop too
        return None if limit is None else math.ceil(limit / env.wrapper_frame_skip)
    if isinstance(env, BatchedEnvBase):
        return _batched_limit(env)
    return None
