"""Whole episodes from any TorchRL env, batched or not, without length bias.

A batched env runs lanes in parallel. Taking "the first n episodes to finish"
favours short episodes (on FrozenLake the short ones are the falls into a hole and
the quick successes), so episodes are assigned to lanes up front, round-robin
(episode ``j`` is lane ``j % lanes``'s ``j // lanes``-th episode), and the rollout
runs until every lane has finished its quota. Each lane's episodes are independent
of when the others finish, so the sample is unbiased.

:func:`rollout_episodes` keeps every transition as demonstration rows;
:func:`episode_returns` keeps only per-episode summaries (cheap for 1e5+ episodes).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from imitrl import keys
from imitrl.rng import rng_from

__all__ = ["EpisodeSummary", "episode_returns", "rollout_episodes"]

ROW_KEYS = (
    keys.OBSERVATION,
    keys.ACTION,
    keys.EXPERT_ACTION,
    keys.EXPERT_EXECUTED,
)
NEXT_KEYS = (keys.REWARD, keys.DONE, keys.TERMINATED, keys.TRUNCATED)

SuccessFn = Callable[[TensorDictBase], torch.Tensor]


def _lanes(env: EnvBase) -> int:
    if len(env.batch_size) > 1:
        raise ValueError(
            f"envs with more than one batch dimension are not supported, got {tuple(env.batch_size)}"
        )
    return int(env.batch_size.numel()) if len(env.batch_size) else 1


def _check_action(env: EnvBase, td: TensorDictBase) -> None:
    """The policy's first action must have the env's action shape and dtype.

    Envs do not check: a gymnasium env may silently read the first entry of a longer
    action, or fail deep inside its own step.
    """
    spec = env.full_action_spec[env.action_key]
    if env.action_key not in td.keys(include_nested=True):
        raise ValueError(f"the policy did not write the env's action key {env.action_key!r}")
    action = td.get(env.action_key)
    if tuple(action.shape) != tuple(spec.shape) or action.dtype != spec.dtype:
        raise ValueError(
            f"the policy's action has shape {tuple(action.shape)} and dtype {action.dtype}; "
            f"the env expects shape {tuple(spec.shape)} and dtype {spec.dtype}"
        )


def _quota(num_episodes: int, lanes: int) -> torch.Tensor:
    """Episodes lane ``i`` must finish under round-robin assignment: ceil((n - i) / lanes)."""
    i = torch.arange(lanes)
    return ((num_episodes - i + lanes - 1) // lanes).clamp_min(0)


def _check_steps(max_steps: int | None, num_episodes: int) -> int:
    if int(num_episodes) != num_episodes or num_episodes < 0:
        raise ValueError(f"num_episodes must be a non-negative integer, got {num_episodes!r}")
    if max_steps is None:
        raise ValueError(
            "max_steps is required: the most steps a lane may take in total, so that a "
            "policy that never ends an episode cannot hang the rollout"
        )
    return int(max_steps)


def rollout_episodes(
    env: EnvBase,
    policy: TensorDictModuleBase,
    num_episodes: int,
    *,
    exploration: ExplorationType,
    max_steps: int,
    round_index: int = 0,
    first_episode: int = 0,
    generator: torch.Generator | None = None,
) -> TensorDict:
    """Play ``num_episodes`` whole episodes and return their transitions as rows.

    Args:
        env: any TorchRL env with zero or one batch dimension.
        policy: writes ``ACTION``, ``EXPERT_ACTION`` and ``EXPERT_EXECUTED`` (an
            expert's ``as_actor()`` or a DAgger behaviour policy).
        num_episodes: episodes to keep.
        exploration: how probabilistic modules act (``RANDOM`` samples,
            ``DETERMINISTIC`` takes the greedy action). Stated at every call.
        max_steps: most steps any lane may take in total (a safety bound; episodes
            end by the env's own time limit).
        round_index: written to ``ROUND``.
        first_episode: id of the first episode (``buffer.next_episode``).
        generator: source of the policy's sampling in ``RANDOM`` mode (torch
            distributions draw from the global RNG; this runs them on ``generator``
            instead and advances it). None: torch's global RNG.

    Returns:
        rows ``[R]`` with ``OBSERVATION, ACTION, EXPERT_ACTION, EXPERT_EXECUTED,
        EPISODE, ROUND, STEP`` and ``("next", reward|done|terminated|truncated)``,
        episodes back to back in id order.

    Raises:
        ValueError: the policy does not write an expert label; a lane exceeded ``max_steps``.
    """
    max_steps = _check_steps(max_steps, num_episodes)
    lanes = _lanes(env)
    quota = _quota(int(num_episodes), lanes)
    steps: list[TensorDictBase] = []
    finished = torch.zeros(lanes, dtype=torch.int64)
    with torch.no_grad(), set_exploration_type(exploration), rng_from(generator):
        td = env.reset()
        while bool((finished < quota).any()):
            if len(steps) >= max_steps:
                raise ValueError(
                    f"episodes did not finish within max_steps={max_steps} steps per lane"
                )
            td = policy(td)
            if not steps:
                _check_action(env, td)
            out, td = env.step_and_maybe_reset(td)
            for k in (keys.EXPERT_ACTION, keys.EXPERT_EXECUTED):
                if k not in out.keys():
                    raise ValueError(
                        f"the rollout policy must write {k!r} (use an expert's as_actor() or a DAgger behaviour policy)"
                    )
            steps.append(out.select(*ROW_KEYS, *[(keys.NEXT, k) for k in NEXT_KEYS]))
            finished += out.get((keys.NEXT, keys.DONE)).reshape(lanes)
    if not steps:
        raise ValueError("num_episodes must be positive to collect rows")
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
    policy: TensorDictModuleBase,
    num_episodes: int,
    *,
    exploration: ExplorationType,
    max_steps: int,
    success_fn: SuccessFn | None = None,
    generator: torch.Generator | None = None,
) -> EpisodeSummary:
    """Play ``num_episodes`` whole episodes, keeping only returns, lengths and success.

    Args:
        success_fn: maps the step tensordict at an episode's end to a ``[lanes]``
            bool (e.g. "the next observation is a goal state"); None for no success.
        (others as in :func:`rollout_episodes`)
    """
    max_steps = _check_steps(max_steps, num_episodes)
    n = int(num_episodes)
    lanes = _lanes(env)
    quota = _quota(n, lanes)
    returns = torch.zeros(n, dtype=torch.float64)
    lengths = torch.zeros(n, dtype=torch.int64)
    success = torch.zeros(n, dtype=torch.bool) if success_fn is not None else None
    running = torch.zeros(lanes, dtype=torch.float64)
    length = torch.zeros(lanes, dtype=torch.int64)
    finished = torch.zeros(lanes, dtype=torch.int64)
    lane_ids = torch.arange(lanes)
    with torch.no_grad(), set_exploration_type(exploration), rng_from(generator):
        td = env.reset()
        t = 0
        while bool((finished < quota).any()):
            if t >= max_steps:
                raise ValueError(
                    f"episodes did not finish within max_steps={max_steps} steps per lane"
                )
            td = policy(td)
            if t == 0:
                _check_action(env, td)
            out, td = env.step_and_maybe_reset(td)
            nxt = out.get(keys.NEXT)
            running += nxt.get(keys.REWARD).reshape(lanes).double()
            length += 1
            done = nxt.get(keys.DONE).reshape(lanes)
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
            t += 1
    return EpisodeSummary(returns=returns, lengths=lengths, success=success)
