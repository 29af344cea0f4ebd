"""Returns of gymnasium toy-text episodes played by the stream player, not step by step.

Accelerated internals of :mod:`imitrl.runtime.paths` (import them from there, nowhere else).

gymnasium's FrozenLake, Taxi and CliffWalking draw one uniform from the env's numpy
generator per reset and one per step (:mod:`imitrl.envs.gym_stream`). So when a rollout
keeps only returns (:func:`~imitrl.runtime.episode_returns`, hence ``evaluate``), its policy
acts as a fixed table of states, and its env is a plain :func:`~imitrl.envs.make_env`
env of one of these with a time limit, the episodes each lane would play step by step
are walked on that lane's generator by the stream player's scalar path
(:class:`~imitrl.envs.gym_stream.StreamWalk`): a 1000-episode evaluation is a table walk
in plain Python instead of thousands of env and policy steps.

The lane's own generator is then advanced by exactly the uniforms the step-by-step loop
draws (:func:`play_lanes`), so a later rollout on the env plays the same episodes too.
Only the generators are carried over: the envs' current states are not (every rollout
starts with a reset). ``tests/runtime/test_paths.py`` checks the returns, lengths and the
next evaluation against TorchRL's path on all three envs, at one and several lanes.
"""

from __future__ import annotations

import gymnasium
import numpy as np
import torch
from gymnasium.spaces import Discrete
from gymnasium.wrappers import OrderEnforcing, PassiveEnvChecker, TimeLimit
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

from imitrl import keys
from imitrl.envs.gym_stream import GymnasiumStream, StreamWalk
from imitrl.runtime.fast.env_steps import DirectSteps, GymSteps, direct_steps
from imitrl.runtime.fast.policy_call import TensorPolicy
from imitrl.runtime.loop import Lanes, check_first_step
from imitrl.tabular.mdp import TabularMDP
from imitrl.tabular.sampling import OutcomeSampler

__all__ = ["play_lanes", "table_returns", "toy_text_lanes"]

_WRAPPERS = (TimeLimit, OrderEnforcing, PassiveEnvChecker)
"""what ``gymnasium.make`` wraps them in: none of these draws or changes an outcome"""


def _plain_toy_text(env: gymnasium.Env) -> bool:
    # imported here: a rollout on any other env need not load gymnasium's toy-text envs
    from gymnasium.envs.toy_text import CliffWalkingEnv, FrozenLakeEnv, TaxiEnv

    # one uniform per reset and per step (Taxi: without its fickle passenger)
    toy_text = (FrozenLakeEnv, TaxiEnv, CliffWalkingEnv)
    inner, limited = env, False
    while isinstance(inner, gymnasium.Wrapper):
        if type(inner) not in _WRAPPERS:
            return False
        limited = limited or type(inner) is TimeLimit
        inner = inner.env
    if type(inner) not in toy_text or (isinstance(inner, TaxiEnv) and inner.fickle_passenger):
        return False
    return limited and env.spec is not None and env.spec.max_episode_steps is not None


def toy_text_lanes(direct: DirectSteps | None) -> list[gymnasium.Env] | None:
    """Each lane's gymnasium env when ``direct`` steps plain toy-text envs with a time
    limit (module docstring), else None."""
    if not isinstance(direct, GymSteps):
        return None
    envs = direct.lane_envs()
    return envs if all(_plain_toy_text(e) for e in envs) else None


def play_lanes(
    envs: list[gymnasium.Env],
    tables: torch.Tensor,
    quota: np.ndarray,
    bound: int,
    bound_name: str,
) -> tuple[np.ndarray, np.ndarray]:
    """Lane ``i`` plays ``quota[i]`` episodes of ``tables[i]`` on ``envs[i]``'s stream.

    The step-by-step loop steps every lane until the last one finished its quota, ``G``
    steps: lane ``i`` draws ``1 + G + d_i`` uniforms (the first reset, the steps, a reset
    after each of the ``d_i`` episodes that ended within them); its generator is advanced
    by as many.

    Args:
        envs: the lanes' gymnasium envs (:func:`toy_text_lanes`).
        tables: ``[lanes, S]`` int64 action of each lane's policy in each state.
        quota: ``[lanes]`` episodes each lane plays (round robin).
        bound, bound_name: an episode a lane is owed may not run past ``bound`` steps.

    Returns:
        returns ``[n]`` float64 and lengths ``[n]`` int64 by episode id (episode ``j`` is
        lane ``j % lanes``'s ``j // lanes``-th).
    """
    mdp = TabularMDP.from_gym(envs[0], 1.0)  # every lane is a copy of one env
    assert mdp.max_steps is not None  # the player takes toy-text envs with a time limit
    sampler = OutcomeSampler(mdp)
    lists, lanes = sampler.as_lists(), len(envs)
    generators = [e.unwrapped.np_random for e in envs]
    walks = [
        StreamWalk(sampler, lists, tables[i], GymnasiumStream.following(g), mdp.max_steps)
        for i, g in enumerate(generators)
    ]
    played = [[walks[i].episode() for _ in range(int(quota[i]))] for i in range(lanes)]
    if any(length > bound for lane in played for _, length in lane):
        raise ValueError(
            f"an episode ran past {bound_name} steps without ending (the bound is per "
            "episode); pass a larger max_steps= or give the env a time limit"
        )
    G = max(sum(length for _, length in lane) for lane in played)
    returns = np.zeros(int(quota.sum()), dtype=np.float64)
    lengths = np.zeros(int(quota.sum()), dtype=np.int64)
    for i, (lane, walk) in enumerate(zip(played, walks)):
        for k, (ret, length) in enumerate(lane):
            returns[k * lanes + i], lengths[k * lanes + i] = ret, length
        steps, ended = sum(length for _, length in lane), len(lane)
        while steps < G:  # the episodes the lane goes on with until the last lane is done
            steps += walk.episode()[1]
            ended += steps <= G
        generators[i].random(1 + G + ended)  # the uniforms the step-by-step loop draws
    return returns, lengths


def table_returns(
    env: EnvBase, policy: TensorDictModuleBase, book: Lanes
) -> tuple[np.ndarray, np.ndarray] | None:
    """Returns and lengths of ``book``'s episodes by the stream player when ``env`` is a
    plain toy-text env and ``policy`` a fixed function of the state; None (and nothing
    played) otherwise. Call it inside the rollout's exploration type and ``no_grad``."""
    envs = toy_text_lanes(direct_steps(env))
    if envs is None:
        return None
    call = TensorPolicy(policy, env.batch_size)
    if call.opaque or call.draws or list(policy.in_keys) != [keys.OBSERVATION]:
        return None
    # the action in every state, each state at every lane at once: the batch the step
    # loop calls the policy with, so that the table is its actions to the bit
    false = torch.zeros((*env.batch_size, 1), dtype=torch.bool)
    columns: list[torch.Tensor] = []
    states, actions = envs[0].observation_space, envs[0].action_space
    assert isinstance(states, Discrete) and isinstance(actions, Discrete)  # toy-text spaces
    for s in range(int(states.n)):
        values = {keys.OBSERVATION: torch.full(env.batch_size, s, dtype=torch.int64)}
        values.update({keys.DONE: false, keys.TERMINATED: false, keys.TRUNCATED: false})
        call(values)
        if not columns:
            check_first_step(env, values, labels=False)
        columns.append(values[env.action_key].reshape(book.lanes))
    tables = torch.stack(columns, dim=1)  # [lanes, S]
    if bool(((tables < 0) | (tables >= actions.n)).any()):
        return None  # stepped, gymnasium refuses the action as it would on the other path
    return play_lanes(envs, tables, book.quota, book.bound, book.bound_name)
