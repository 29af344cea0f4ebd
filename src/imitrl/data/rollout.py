"""Whole episodes from any TorchRL env, batched or not, without length bias.

A batched env runs lanes in parallel. Taking "the first n episodes to finish"
favours short episodes (on FrozenLake the short ones are the falls into a hole and
the quick successes), so episodes are assigned to lanes up front, round-robin
(episode ``j`` is lane ``j % lanes``'s ``j // lanes``-th episode), and the rollout
runs until every lane has finished its quota. Each lane's episodes are independent
of when the others finish, so the sample is unbiased.

Episodes end by the env's own time limit (:func:`~imitrl.envs.episode_limit`);
``max_steps=`` bounds each episode where the env has none, and a rollout refuses to
start on an env without a limit when it is not given. Each lane counts the steps
since its last reset, and an episode that runs past the bound raises.

:func:`rollout_episodes` keeps every transition as demonstration rows;
:func:`episode_returns` keeps only per-episode summaries (cheap for 1e5+ episodes).
Both take an :class:`~imitrl.policies.Expert` (it drives the env through
``as_actor()``, its labels cast to the env's action spec) or any policy module.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from imitrl import keys
from imitrl.envs.limits import episode_limit
from imitrl.policies.action_check import check_action
from imitrl.policies.experts import Expert
from imitrl.rng import rng_from

__all__ = ["EpisodeSummary", "episode_returns", "rollout_episodes", "rollout_policy"]

ROW_KEYS = (
    keys.OBSERVATION,
    keys.ACTION,
    keys.EXPERT_ACTION,
    keys.EXPERT_EXECUTED,
)
NEXT_KEYS = (keys.REWARD, keys.DONE, keys.TERMINATED, keys.TRUNCATED)
OPTIONAL_ROW_KEYS = (keys.PIXELS,)
"""kept in the rows when the env gives them (a pixel env's images beside its state)"""

SuccessFn = Callable[[TensorDictBase], torch.Tensor]


def _lanes(env: EnvBase) -> int:
    if len(env.batch_size) > 1:
        raise ValueError(
            f"envs with more than one batch dimension are not supported, got {tuple(env.batch_size)}"
        )
    return int(env.batch_size.numel()) if len(env.batch_size) else 1


def _action_spec(env: EnvBase):
    """One lane's action spec."""
    return env.full_action_spec_unbatched[env.action_key]


def _check_action(env: EnvBase, td: TensorDictBase) -> None:
    """The policy's first action must have the env's action dtype and shape.

    Envs do not check: a gymnasium env may silently read the first entry of a longer
    action, or fail deep inside its own step.
    """
    if env.action_key not in td.keys(include_nested=True):
        raise ValueError(f"the policy did not write the env's action key {env.action_key!r}")
    check_action(
        td.get(env.action_key),
        _action_spec(env),
        batch_shape=env.batch_size,
        name="the policy's action",
    )


def rollout_policy(
    env: EnvBase,
    policy: Expert | TensorDictModuleBase,
    exploration: ExplorationType | None,
) -> tuple[TensorDictModuleBase, ExplorationType]:
    """The module that drives ``env`` and the exploration type it runs under.

    An :class:`Expert` is bound to the env's action spec (:meth:`Expert.bind`: its
    labels are cast to it) and drives the env through ``as_actor()``; it acts
    deterministically, so ``exploration`` None means ``DETERMINISTIC``. Any other
    module runs as given and ``exploration`` must be stated.
    """
    if isinstance(policy, Expert):
        policy.bind(_action_spec(env))
        return policy.as_actor(), exploration or ExplorationType.DETERMINISTIC
    if not isinstance(policy, TensorDictModuleBase):
        raise ValueError(
            f"the policy must be an imitrl Expert or a TensorDict module, got {type(policy).__name__}"
        )
    if exploration is None:
        raise ValueError(
            "exploration is required for a policy module (DETERMINISTIC: greedy, "
            "RANDOM: sampled); only an Expert may leave it out"
        )
    return policy, exploration


def _episode_bound(env: EnvBase, max_steps: int | None, num_episodes: int) -> tuple[int, str]:
    """The most steps one episode may take, and how to name it in an error."""
    if int(num_episodes) != num_episodes or num_episodes < 0:
        raise ValueError(f"num_episodes must be a non-negative integer, got {num_episodes!r}")
    if max_steps is not None:
        if int(max_steps) != max_steps or max_steps < 1:
            raise ValueError(f"max_steps must be a positive integer or None, got {max_steps!r}")
        return int(max_steps), f"max_steps={int(max_steps)}"
    limit = episode_limit(env)
    if limit is None:
        raise ValueError(
            f"{type(env).__name__} has no time limit of its own (a gymnasium TimeLimit, a "
            "StepCounter(max_steps=...), TabularEnv.max_steps): pass max_steps= (the most "
            "steps one episode may take)"
        )
    return limit, f"the env's own time limit of {limit}"


def _overrun(
    length: torch.Tensor, done: torch.Tensor, needed: torch.Tensor, bound: int, name: str
) -> None:
    """Raise when a lane still owed episodes took ``bound`` steps without ending one."""
    if bool(((length >= bound) & ~done & needed).any()):
        raise ValueError(
            f"an episode ran past {name} steps without ending (the bound is per episode); "
            "pass a larger max_steps= or give the env a time limit"
        )


def policy_generator(seed: int) -> torch.Generator:
    """The policy's sampling generator for ``seed=``: a stream apart from the env's.

    The env is seeded with ``seed`` itself; seeding the policy's generator with the
    same number would make its draws repeat the env's (a TabularEnv's generator is
    ``manual_seed(seed)``), so the policy's seed is derived by numpy's ``SeedSequence``.
    """
    derived = np.random.SeedSequence([int(seed), 1]).generate_state(1, np.uint64)[0]
    return torch.Generator().manual_seed(int(derived >> np.uint64(1)))


def _seeded(
    env: EnvBase, seed: int | None, generator: torch.Generator | None
) -> torch.Generator | None:
    """Seed ``env`` (and a policy generator, unless one is given) from ``seed``."""
    if seed is None:
        return generator
    env.set_seed(int(seed))
    return generator if generator is not None else policy_generator(int(seed))


def rollout_episodes(
    env: EnvBase,
    policy: Expert | TensorDictModuleBase,
    num_episodes: int,
    *,
    exploration: ExplorationType | None = None,
    max_steps: int | None = None,
    seed: int | None = None,
    round_index: int = 0,
    first_episode: int = 0,
    generator: torch.Generator | None = None,
) -> TensorDict:
    """Play ``num_episodes`` whole episodes and return their transitions as rows.

    Args:
        env: any TorchRL env with zero or one batch dimension.
        policy: an :class:`~imitrl.policies.Expert` (drives the env; bound to the env's
            action spec), or a module writing ``ACTION``, ``EXPERT_ACTION`` and
            ``EXPERT_EXECUTED`` (a DAgger behaviour policy, an expert's ``as_actor()``).
        num_episodes: episodes to keep.
        exploration: how probabilistic modules act (``RANDOM`` samples,
            ``DETERMINISTIC`` takes the greedy action). Required unless ``policy`` is an
            Expert (then ``DETERMINISTIC``).
        max_steps: most steps ONE episode may take; None: the env's own time limit
            (:func:`~imitrl.envs.episode_limit`), refused when the env has none.
        seed: if given, ``env.set_seed(seed)`` before the first reset and, unless
            ``generator`` is given, the policy samples from :func:`policy_generator`
            of it: the same seed gives the same initial states whatever the policy.
        round_index: written to ``ROUND``.
        first_episode: id of the first episode (``buffer.next_episode``).
        generator: source of the policy's sampling in ``RANDOM`` mode (torch
            distributions draw from the global RNG; this runs them on ``generator``
            instead and advances it). None: torch's global RNG (or ``seed``'s).

    Returns:
        rows ``[R]`` with ``OBSERVATION, ACTION, EXPERT_ACTION, EXPERT_EXECUTED,
        EPISODE, ROUND, STEP`` and ``("next", reward|done|terminated|truncated)``
        (and ``PIXELS`` when the env gives images), episodes back to back in id order.

    Raises:
        ValueError: the policy does not write an expert label or the env's action; the
            env has no time limit and ``max_steps`` is None; an episode ran past the bound.
    """
    bound, bound_name = _episode_bound(env, max_steps, num_episodes)
    actor, exploration = rollout_policy(env, policy, exploration)
    generator = _seeded(env, seed, generator)
    lanes = _lanes(env)
    quota = _quota(int(num_episodes), lanes)
    steps: list[TensorDictBase] = []
    row_keys = list(ROW_KEYS)
    finished = torch.zeros(lanes, dtype=torch.int64)
    length = torch.zeros(lanes, dtype=torch.int64)  # steps since the lane's last reset
    with torch.no_grad(), set_exploration_type(exploration), rng_from(generator):
        td = env.reset()
        while bool((finished < quota).any()):
            td = actor(td)
            first = not steps
            if first:
                _check_action(env, td)
                row_keys += [k for k in OPTIONAL_ROW_KEYS if k in td.keys()]
            out, td = env.step_and_maybe_reset(td)
            for k in (keys.EXPERT_ACTION, keys.EXPERT_EXECUTED) if first else ():
                if k not in out.keys():  # the policy is fixed: checked once, not every step
                    raise ValueError(
                        f"the rollout policy must write {k!r} (pass an Expert or a DAgger behaviour policy)"
                    )
            steps.append(out.select(*row_keys, *[(keys.NEXT, k) for k in NEXT_KEYS]))
            done = out.get((keys.NEXT, keys.DONE)).reshape(lanes)
            length += 1
            _overrun(length, done, finished < quota, bound, bound_name)
            finished += done
            length = torch.where(done, 0, length)
    if not steps:
        raise ValueError("num_episodes must be positive to collect rows")
    return _rows(env, steps, quota, round_index, first_episode)


def _quota(num_episodes: int, lanes: int) -> torch.Tensor:
    """Episodes lane ``i`` must finish under round-robin assignment: ceil((n - i) / lanes)."""
    i = torch.arange(lanes)
    return ((num_episodes - i + lanes - 1) // lanes).clamp_min(0)


def _rows(
    env: EnvBase,
    steps: list[TensorDictBase],
    quota: torch.Tensor,
    round_index: int,
    first_episode: int,
) -> TensorDict:
    """The steps ``[T]`` of every lane as rows of the episodes each lane owes, in id order."""
    lanes = quota.numel()
    traj = torch.stack(steps, dim=len(env.batch_size)).contiguous()  # [lanes?, T]
    if len(env.batch_size) == 0:
        traj = traj.unsqueeze(0)  # [1, T]
    T = traj.shape[1]
    done = traj.get((keys.NEXT, keys.DONE)).reshape(lanes, T)
    ep_in_lane = done.long().cumsum(1) - done.long()  # episode index of each row, per lane
    keep = ep_in_lane < quota[:, None]
    t = torch.arange(T).expand(lanes, T)
    prev_done = torch.zeros_like(done)
    prev_done[:, 1:] = done[:, :-1]
    start = torch.where(prev_done, t, torch.zeros_like(t)).cummax(dim=1).values
    step = t - start
    episode = first_episode + ep_in_lane * lanes + torch.arange(lanes)[:, None]
    rows = traj[keep]
    rows.set(keys.EPISODE, episode[keep])
    rows.set(keys.ROUND, torch.full((rows.shape[0],), int(round_index), dtype=torch.int64))
    rows.set(keys.STEP, step[keep])
    order = torch.argsort(rows.get(keys.EPISODE) * (T + 1) + rows.get(keys.STEP))
    return rows[order]


@dataclass(frozen=True)
class EpisodeSummary:
    """Per-episode results of :func:`episode_returns` (episode ``j`` ran on lane ``j % lanes``)."""

    returns: torch.Tensor
    """``[n]`` float64 undiscounted returns"""
    lengths: torch.Tensor
    """``[n]`` int64 steps"""
    success: torch.Tensor | None
    """``[n]`` bool, or None when no success criterion applies"""


def episode_returns(
    env: EnvBase,
    policy: Expert | TensorDictModuleBase,
    num_episodes: int,
    *,
    exploration: ExplorationType | None = None,
    max_steps: int | None = None,
    seed: int | None = None,
    success_fn: SuccessFn | None = None,
    generator: torch.Generator | None = None,
) -> EpisodeSummary:
    """Play ``num_episodes`` whole episodes, keeping only returns, lengths and success.

    Args:
        policy: an :class:`~imitrl.policies.Expert` or a module writing ``ACTION``.
        success_fn: maps the step tensordict at an episode's end to a ``[lanes]``
            bool (e.g. "the next observation is a goal state"); None for no success.
        (others as in :func:`rollout_episodes`)
    """
    bound, bound_name = _episode_bound(env, max_steps, num_episodes)
    actor, exploration = rollout_policy(env, policy, exploration)
    generator = _seeded(env, seed, generator)
    n = int(num_episodes)
    lanes = _lanes(env)
    quota = _quota(n, lanes)
    returns = torch.zeros(n, dtype=torch.float64)
    lengths = torch.zeros(n, dtype=torch.int64)
    success = torch.zeros(n, dtype=torch.bool) if success_fn is not None else None
    running = torch.zeros(lanes, dtype=torch.float64)
    length = torch.zeros(lanes, dtype=torch.int64)  # steps since the lane's last reset
    finished = torch.zeros(lanes, dtype=torch.int64)
    lane_ids = torch.arange(lanes)
    with torch.no_grad(), set_exploration_type(exploration), rng_from(generator):
        td = env.reset()
        first = True
        while bool((finished < quota).any()):
            td = actor(td)
            if first:
                _check_action(env, td)
                first = False
            out, td = env.step_and_maybe_reset(td)
            nxt = out.get(keys.NEXT)
            running += nxt.get(keys.REWARD).reshape(lanes).double()
            length += 1
            done = nxt.get(keys.DONE).reshape(lanes)
            _overrun(length, done, finished < quota, bound, bound_name)
            record = done & (finished < quota)
            if bool(record.any()):
                idx = finished[record] * lanes + lane_ids[record]
                returns[idx] = running[record]
                lengths[idx] = length[record]
                if success is not None:
                    success[idx] = success_fn(out).reshape(lanes)[record]
            finished += done
            running = torch.where(done, 0.0, running)
            length = torch.where(done, 0, length)
    return EpisodeSummary(returns=returns, lengths=lengths, success=success)
