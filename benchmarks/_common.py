"""Shared by the benchmark scripts: rollouts, a seeded uniform policy, experts from the
command line, reference returns, slippery FrozenLake.

Rollouts: :func:`rollout`, :func:`returns`, :func:`summaries` and :func:`source` are the
only places the benchmarks call ``rollout_episodes``, ``episode_returns`` and ``EnvSource``; every
call states its ``max_steps`` (today: the most steps a lane may take in total).
"""

from __future__ import annotations

import importlib
import inspect
from collections.abc import Callable

import gymnasium
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Bounded, Categorical, TensorSpec
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType

from imitrl import keys
from imitrl.algorithms import EnvSource
from imitrl.experts import (
    acrobot_expert,
    cartpole_expert,
    inverted_double_pendulum_expert,
    inverted_pendulum_expert,
    mountaincar_expert,
    pendulum_expert,
)
from imitrl.policies import Expert, as_actor
from imitrl.runtime import episode_returns, rollout_episodes
from imitrl.tabular import TabularMDP, value_iteration

DET, RND = ExplorationType.DETERMINISTIC, ExplorationType.RANDOM


# ---------------------------------------------------------------------- rollouts
def rollout(
    env: EnvBase,
    policy: TensorDictModuleBase,
    episodes: int,
    *,
    exploration: ExplorationType,
    max_steps: int,
) -> TensorDict:
    """``episodes`` whole episodes as rows (``imitrl.data.rollout_episodes``)."""
    return rollout_episodes(env, policy, episodes, exploration=exploration, max_steps=max_steps)


def returns(
    env: EnvBase,
    policy: TensorDictModuleBase,
    episodes: int,
    *,
    exploration: ExplorationType,
    max_steps: int,
) -> torch.Tensor:
    """``[episodes]`` float64 undiscounted returns of ``policy`` (writes ``ACTION``)."""
    summary = episode_returns(env, policy, episodes, exploration=exploration, max_steps=max_steps)
    return summary.returns


def summaries(
    env: EnvBase,
    policy: TensorDictModuleBase,
    episodes: int,
    *,
    exploration: ExplorationType,
    max_steps: int,
    success_fn=None,
):
    """Per-episode returns, lengths and success (``success_fn``) of ``policy``."""
    return episode_returns(
        env, policy, episodes, exploration=exploration, max_steps=max_steps, success_fn=success_fn
    )


def source(env: EnvBase, *, exploration: ExplorationType | None, max_steps: int) -> EnvSource:
    """DAgger's episodes from ``env`` (``exploration`` None: as the learner acts)."""
    return EnvSource(env, exploration=exploration, max_steps=max_steps)


# ------------------------------------------------------------ the random baseline
class Uniform(TensorDictModuleBase):
    """A uniformly random policy writing ``ACTION``, drawing from its own seeded generator.

    Args:
        action: the number of discrete actions, a ``Categorical`` spec, or a ``Bounded``
            spec ``[m]`` (sampled uniformly in its box).
        seed: seed of the generator.
    """

    def __init__(self, action: int | Categorical | Bounded, seed: int) -> None:
        super().__init__()
        if isinstance(action, Categorical):
            action = int(action.space.n)
        if not isinstance(action, (int, Bounded)):
            raise ValueError(f"Uniform needs a number of actions or a Bounded spec, got {action!r}")
        self.action = action
        self.in_keys, self.out_keys = [keys.OBSERVATION], [keys.ACTION]
        self.generator = torch.Generator().manual_seed(seed)

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        if isinstance(self.action, int):
            a = torch.randint(self.action, td.batch_size, generator=self.generator)
        else:
            low, high = self.action.space.low, self.action.space.high
            u = torch.rand((*td.batch_size, *low.shape), generator=self.generator)
            a = low + (high - low) * u
        td.set(keys.ACTION, a)
        return td


def reference_returns(
    env: EnvBase,
    expert: TensorDictModuleBase,
    episodes: int,
    *,
    seed: int,
    max_steps: int,
) -> dict[str, torch.Tensor]:
    """``{"expert": [episodes], "random": [episodes]}`` returns from the same initial
    states: ``env`` is re-seeded with ``seed`` before each policy (greedy expert;
    uniform random actions drawn from ``seed``)."""
    action: TensorSpec = env.action_spec_unbatched
    out = {}
    for name, policy in (("expert", as_actor(expert)), ("random", Uniform(action, seed))):
        env.set_seed(seed)
        out[name] = returns(env, policy, episodes, exploration=DET, max_steps=max_steps)
    return out


# ------------------------------------------------------- experts and envs by name
ExpertBuilder = Callable[..., TensorDictModuleBase]

BUILT_IN_EXPERTS: dict[str, ExpertBuilder] = {
    "CartPole-v1": cartpole_expert,
    "MountainCar-v0": mountaincar_expert,
    "Acrobot-v1": acrobot_expert,
    "Pendulum-v1": pendulum_expert,
    "InvertedPendulum-v5": inverted_pendulum_expert,
    "InvertedDoublePendulum-v5": inverted_double_pendulum_expert,
}
"""every expert of ``imitrl.experts``, by the env it solves"""


def expert_for(env_id: str, spec: str | None) -> ExpertBuilder:
    """``--expert spec`` if given (see :func:`load_expert`), else the env's built-in expert."""
    if spec is not None:
        return load_expert(spec)
    if env_id not in BUILT_IN_EXPERTS:
        raise ValueError(
            f"no built-in expert for {env_id}; pass --expert module:function "
            "(an expert builder or a batched obs -> action callable)"
        )
    return BUILT_IN_EXPERTS[env_id]


def load_expert(spec: str) -> ExpertBuilder:
    """``"module:function"`` -> a builder of the expert (called with no arguments).

    ``function`` is either an expert builder (every parameter has a default, e.g.
    ``imitrl.experts.pendulum_expert``; it returns a module writing ``EXPERT_ACTION``)
    or a batched callable ``obs -> action``, wrapped with ``Expert.from_callable``.
    """
    module_name, sep, attr = spec.partition(":")
    if not sep or not module_name or not attr:
        raise ValueError(f"--expert takes module:function, got {spec!r}")
    try:
        fn = getattr(importlib.import_module(module_name), attr)
    except (ImportError, AttributeError) as err:
        raise ValueError(f"cannot load the expert {spec!r}: {err}") from err
    if not callable(fn):
        raise ValueError(f"{spec!r} is not callable")
    required = [
        p
        for p in inspect.signature(fn).parameters.values()
        if p.default is inspect.Parameter.empty and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
    ]
    if required:  # a batched obs -> action function

        def build() -> TensorDictModuleBase:
            return Expert.from_callable(fn)

    else:  # a builder: check what it builds

        def build(**kwargs) -> TensorDictModuleBase:
            expert = fn(**kwargs)
            if not isinstance(expert, TensorDictModuleBase) or (
                keys.EXPERT_ACTION not in expert.out_keys
            ):
                raise ValueError(
                    f"{spec}() must return a TensorDictModule writing {keys.EXPERT_ACTION!r} "
                    f"(or take a batch of observations and return actions), got {expert!r}"
                )
            return expert

        build.__signature__ = inspect.signature(fn)  # type: ignore[attr-defined]
    build.__name__ = build.__qualname__ = spec  # named in the results
    return build


def accepts(builder: ExpertBuilder, name: str) -> bool:
    """Whether the expert builder takes the keyword ``name`` (e.g. ``action_repeat``)."""
    return name in inspect.signature(builder).parameters


def time_limit(env_id: str) -> int:
    """The registered episode limit of a gymnasium id (``module:Env-v0`` imports ``module``)."""
    module, sep, name = env_id.rpartition(":")
    if sep:
        importlib.import_module(module)
    limit = gymnasium.spec(name).max_episode_steps
    if limit is None:
        raise ValueError(f"{env_id} has no time limit; register it with max_episode_steps")
    return int(limit)


def lake() -> tuple[TabularMDP, torch.Tensor]:
    """Slippery FrozenLake-v1 (gamma 0.95) and its optimal ``Q*[S, A]`` (1000 sweeps)."""
    mdp = TabularMDP.from_gym("FrozenLake-v1", 0.95)
    return mdp, mdp.backup(value_iteration(mdp, 1000)[-1])
