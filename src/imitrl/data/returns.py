"""Returns, lengths and success of whole episodes, without keeping their transitions.

:func:`episode_returns` plays episodes as :func:`~imitrl.data.rollout_episodes` does (the
same lanes, quotas, bounds and the same two paths, digit for digit) and keeps only each
episode's summary, so that 1e5+ evaluation episodes cost no memory. On a gymnasium
toy-text env a policy that is a fixed table of states plays its episodes by the stream
player (:mod:`imitrl.envs.toy_text`), with no step loop at all.
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
from tqdm.auto import tqdm

from imitrl import keys
from imitrl.data.rollout import (
    NEXT_KEYS,
    _check_first_step,
    _episode_bound,
    _Lanes,
    _lanes,
    _quota,
    _seeded,
    rollout_policy,
)
from imitrl.envs.direct import DirectSteps, RawStep, direct_steps
from imitrl.envs.toy_text import play_lanes, toy_text_lanes
from imitrl.policies.experts import Expert
from imitrl.policies.modules import TensorPolicy
from imitrl.rng import rng_from

__all__ = ["EpisodeSummary", "SuccessFn", "episode_returns"]

SuccessFn = Callable[[TensorDictBase], torch.Tensor]


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
    fast_path: bool = True,
    progress: bool = False,
) -> EpisodeSummary:
    """Play ``num_episodes`` whole episodes, keeping only returns, lengths and success.

    Args:
        policy: an :class:`~imitrl.policies.Expert` or a module writing ``ACTION``.
        success_fn: maps the step tensordict at an episode's end to a ``[lanes]``
            bool (e.g. "the next observation is a goal state"); None for no success.
        fast_path: as in :func:`rollout_episodes`; besides, on a gymnasium toy-text env
            (FrozenLake, Taxi, CliffWalking with a time limit) without ``success_fn``,
            a policy that is a fixed table of states plays its episodes by the stream
            player (:mod:`imitrl.envs.toy_text`): the same episodes, no step loop.
        progress: a progress bar on stderr, one tick per finished episode.
        (others as in :func:`rollout_episodes`)
    """
    bound, bound_name = _episode_bound(env, max_steps, num_episodes)
    actor, exploration = rollout_policy(env, policy, exploration)
    generator = _seeded(env, seed, generator)
    book = _Lanes(_quota(int(num_episodes), _lanes(env)), bound, bound_name)
    tally = _Tally(int(num_episodes), book.lanes, success_fn)
    # a bar only when asked: a tqdm, even disabled, starts a monitor thread
    bar = None
    if progress:
        bar = tqdm(total=int(num_episodes), desc="evaluate", unit="episode", leave=False)
        tally.on_end = bar.update
    with torch.no_grad(), set_exploration_type(exploration), rng_from(generator):
        direct = direct_steps(env) if fast_path else None
        if direct is None:
            _torchrl_returns(env, actor, book, tally)
        elif success_fn is not None or not _toy_text_returns(env, direct, actor, book, tally):
            _direct_returns(env, direct, actor, book, tally)
    if bar is not None:
        bar.update(bar.total - bar.n)  # episodes played without the step loop
        bar.close()
    return tally.summary()


class _Tally:
    """Returns, lengths and success of the episodes kept, by episode id."""

    def __init__(self, n: int, lanes: int, success_fn: SuccessFn | None) -> None:
        self.returns = np.zeros(n, dtype=np.float64)
        self.lengths = np.zeros(n, dtype=np.int64)
        self.success_fn = success_fn
        self.success = np.zeros(n, dtype=np.bool_) if success_fn is not None else None
        self.running = np.zeros(lanes, dtype=np.float64)  # each lane's return so far
        self.on_end: Callable[[int], object] | None = None  # told how many episodes ended

    def add(self, reward: torch.Tensor) -> None:
        self.running += reward.numpy().reshape(-1)  # float32 rewards summed in float64

    def add_raw(self, reward: np.ndarray) -> None:
        """:meth:`add` of a direct step's float32 ``[lanes]`` rewards."""
        if reward.shape == (1,):
            # one lane: the float32 reward as a Python float, the same float64 sum, without
            # numpy's mixed-dtype in-place add (a few microseconds a step)
            self.running[0] += reward.item()
        else:
            self.running += reward

    def end(self, book: _Lanes, ended: np.ndarray, out: Callable[[], TensorDictBase]) -> None:
        """The ``ended`` lanes' episodes end at this step (``out()``: the step tensordict)."""
        lanes, ids, lengths = book.kept(ended)
        if lanes.size:
            self.returns[ids] = self.running[lanes]
            self.lengths[ids] = lengths
            if self.success is not None:
                self.success[ids] = self.success_fn(out()).reshape(-1).numpy()[lanes]
            if self.on_end is not None:
                self.on_end(int(lanes.size))
        self.running[ended] = 0.0

    def summary(self) -> EpisodeSummary:
        success = None if self.success is None else torch.from_numpy(self.success)
        return EpisodeSummary(
            returns=torch.from_numpy(self.returns),
            lengths=torch.from_numpy(self.lengths),
            success=success,
        )


def _torchrl_returns(env: EnvBase, actor, book: _Lanes, tally: _Tally) -> None:
    td = env.reset()
    first = True
    while book.owing:
        td = actor(td)
        if first:
            _check_first_step(env, td.get(env.action_key, None), (), labels=False)
            first = False
        out, td = env.step_and_maybe_reset(td)
        nxt = out.get(keys.NEXT)
        tally.add(nxt.get(keys.REWARD))
        ended = book.step(nxt.get(keys.DONE).reshape(book.lanes).numpy())
        if ended is not None:
            tally.end(book, ended, lambda out=out: out)
            book.close(ended)


def _direct_returns(env: EnvBase, direct: DirectSteps, actor, book: _Lanes, tally: _Tally) -> None:
    """:func:`_torchrl_returns` with the env stepped directly (see :func:`_direct_trajectory`).

    A policy replayed module by module (not ``opaque``) runs under ``torch.inference_mode``
    (a fifth of a small network's call at batch 1): only returns leave the loop. An opaque
    module may keep tensors between calls (a chunked policy's plan, updated in place) that
    a later rollout outside inference mode could not update, so it keeps ``no_grad``.
    """
    policy = TensorPolicy(actor, env.batch_size)
    values = dict(env.reset().items(include_nested=True, leaves_only=True))
    if policy.opaque:
        _direct_returns_loop(env, direct, policy, values, book, tally)
        return
    with torch.inference_mode():
        _direct_returns_loop(env, direct, policy, values, book, tally)


def _direct_returns_loop(
    env: EnvBase, direct: DirectSteps, policy: TensorPolicy, values: dict, book: _Lanes, tally
) -> None:
    action_key, first = env.action_key, True
    while book.owing:
        policy(values)
        action = values.get(action_key)
        if first:
            _check_first_step(env, action, values, labels=False)
            first = False
        step = direct.step_raw(action)
        tally.add_raw(step.reward)
        ended = book.step(step.done)
        if ended is None:
            values[keys.OBSERVATION] = step.observation
            continue
        tally.end(book, ended, lambda v=values, s=step: _step_tensordict(env, direct, v, s))
        values[keys.OBSERVATION] = direct.reset_lanes(step.done)
        book.close(ended)


def _toy_text_returns(
    env: EnvBase, direct: DirectSteps, actor, book: _Lanes, tally: _Tally
) -> bool:
    """The returns and lengths by the stream player (:mod:`imitrl.envs.toy_text`) when the
    env is a plain toy-text env and the policy a fixed function of the state; False (and
    nothing played) otherwise."""
    envs = toy_text_lanes(direct)
    if envs is None:
        return False
    policy = TensorPolicy(actor, env.batch_size)
    if policy.opaque or policy.draws or list(actor.in_keys) != [keys.OBSERVATION]:
        return False
    # the action in every state, each state at every lane at once: the batch the step
    # loop calls the policy with, so that the table is its actions to the bit
    false = torch.zeros((*env.batch_size, 1), dtype=torch.bool)
    columns = []
    for s in range(int(envs[0].observation_space.n)):
        values = {keys.OBSERVATION: torch.full(env.batch_size, s, dtype=torch.int64)}
        values.update({keys.DONE: false, keys.TERMINATED: false, keys.TRUNCATED: false})
        policy(values)
        action = values.get(env.action_key)
        if not columns:
            _check_first_step(env, action, values, labels=False)
        columns.append(action.reshape(book.lanes))
    tables = torch.stack(columns, dim=1)  # [lanes, S]
    if bool(((tables < 0) | (tables >= envs[0].action_space.n)).any()):
        return False  # stepped, gymnasium refuses the action as it would on the other path
    returns, lengths = play_lanes(envs, tables, book.quota, book.bound, book.bound_name)
    tally.returns[:], tally.lengths[:] = returns, lengths
    return True


def _step_tensordict(env: EnvBase, direct: DirectSteps, values: dict, step: RawStep) -> TensorDict:
    """What ``step_and_maybe_reset`` returns first: the root's entries and ``"next"``."""
    nxt = {keys.OBSERVATION: step.observation, **dict(zip(NEXT_KEYS, direct.step_tensors(step)))}
    return TensorDict({**values, keys.NEXT: nxt}, batch_size=env.batch_size)
