"""Returns, lengths and success of whole episodes, without keeping their transitions.

:func:`episode_returns` plays episodes by the one rollout loop, as
:func:`~imitrl.runtime.rollout_episodes` does (the same lanes, quotas, bounds and the same
two steppers, digit for digit), and keeps only each episode's summary, so that 1e5+
evaluation episodes cost no memory. On a gymnasium toy-text env a policy that is a fixed
table of states plays its episodes by the stream player, with no step loop at all
(:func:`imitrl.runtime.paths.table_returns`, an accelerated path of the seam).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type
from tqdm.auto import tqdm

from imitrl.policies.experts import Expert
from imitrl.rng import rng_from
from imitrl.runtime import paths
from imitrl.runtime.loop import Lanes, Stepper, play
from imitrl.runtime.rollout import _seeded, init_tracked, rollout_policy

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
    progress: bool = False,
) -> EpisodeSummary:
    """Play ``num_episodes`` whole episodes, keeping only returns, lengths and success.

    Args:
        policy: an :class:`~imitrl.policies.Expert` or a module writing ``ACTION``.
        success_fn: maps the step tensordict at an episode's end to a ``[lanes]``
            bool (e.g. "the next observation is a goal state"); None for no success.
        progress: a progress bar on stderr, one tick per finished episode.
        (others as in :func:`rollout_episodes`)
    """
    book = Lanes.of(env, num_episodes, max_steps)
    actor, exploration = rollout_policy(env, policy, exploration)
    generator = _seeded(env, seed, generator)
    tally = _Tally(int(num_episodes), book, success_fn)
    # a bar only when asked: a tqdm, even disabled, starts a monitor thread
    bar = None
    if progress:
        bar = tqdm(total=int(num_episodes), desc="evaluate", unit="episode", leave=False)
        tally.on_end = bar.update
    with torch.no_grad(), set_exploration_type(exploration), rng_from(generator):
        table = None
        if success_fn is None:
            table = paths.table_returns(env, actor, book)
        if table is not None:
            tally.returns[:], tally.lengths[:] = table
        else:
            stepper = paths.stepper(init_tracked(env, actor), actor, record=False)
            tally.stepper = stepper
            play(stepper, book, labels=False, on_reward=tally.add, on_end=tally.end)
    if bar is not None:
        bar.update(bar.total - bar.n)  # episodes played without the step loop
        bar.close()
    return tally.summary()


class _Tally:
    """Returns, lengths and success of the episodes kept, by episode id."""

    def __init__(self, n: int, book: Lanes, success_fn: SuccessFn | None) -> None:
        lanes = book.lanes
        self.book = book
        self.stepper: Stepper | None = None  # the step tensordict at an episode's end
        self.returns = np.zeros(n, dtype=np.float64)
        self.lengths = np.zeros(n, dtype=np.int64)
        self.success_fn = success_fn
        self.success = np.zeros(n, dtype=np.bool_) if success_fn is not None else None
        self.running = np.zeros(lanes, dtype=np.float64)  # each lane's return so far
        self.on_end: Callable[[int], object] | None = None  # told how many episodes ended

    def add(self, reward: np.ndarray) -> None:
        """A step's ``[lanes]`` rewards, summed in float64 per lane."""
        if reward.shape == (1,):
            # one lane: the float32 reward as a Python float, the same float64 sum, without
            # numpy's mixed-dtype in-place add (a few microseconds a step)
            self.running[0] += reward.item()
        else:
            self.running += reward

    def end(self, ended: np.ndarray) -> None:
        """The ``ended`` lanes' episodes end at this step."""
        lanes, ids, lengths = self.book.kept(ended)
        if lanes.size:
            self.returns[ids] = self.running[lanes]
            self.lengths[ids] = lengths
            if self.success is not None:
                # a success criterion plays the step loop, which sets the stepper first
                assert self.stepper is not None and self.success_fn is not None
                out = self.stepper.step_tensordict()
                self.success[ids] = self.success_fn(out).reshape(-1).cpu().numpy()[lanes]
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
