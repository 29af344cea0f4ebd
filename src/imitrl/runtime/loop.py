"""The one rollout loop: whole episodes from any env, lanes under round-robin quotas.

Collection (:func:`~imitrl.runtime.rollout_episodes`), DAgger's relabel rounds (which
collect through it) and evaluation (:func:`~imitrl.runtime.episode_returns`, hence
:func:`~imitrl.evaluation.evaluate`) all play their episodes by :func:`play`. What differs
is what they keep: rows (the stepper records the trajectory) or per-episode summaries
(the ``on_reward`` / ``on_end`` callbacks).

**Lanes and quotas.** A batched env runs lanes in parallel. Taking "the first n
episodes to finish" favours short episodes (on FrozenLake the short ones are the falls
into a hole and the quick successes), so episodes are assigned to lanes up front,
round-robin (episode ``j`` is lane ``j % lanes``'s ``j // lanes``-th episode), and the
loop runs until every lane has finished its quota. Each lane's episodes are independent
of when the others finish, so the sample is unbiased.

**Bounds.** Episodes end by the env's own time limit
(:func:`~imitrl.envs.episode_limit`); ``max_steps=`` bounds each episode where the env
has none, and a rollout refuses to start on an env without a limit when it is not
given. Each lane counts the steps since its last reset, and an episode that runs past
the bound raises.

**Steppers.** The loop sees the env and its policy only through a :class:`Stepper`:
the reference one on public TorchRL (:class:`imitrl.runtime.reference.TorchRLStepper`:
``policy(td)`` and ``env.step_and_maybe_reset``) or the accelerated one
(:mod:`imitrl.runtime.fast`), chosen by :func:`imitrl.runtime.paths.stepper`. Both play
the same episodes, digit for digit (``tests/runtime/test_paths.py``).

**Fixed steps.** An on-policy learner (GAIL's and AIRL's PPO generator) wants batches of
a fixed number of steps that continue across rounds, episodes cut wherever a batch ends:
:func:`play_steps` steps the same stepper ``steps`` times per lane per call, from where
the last call left every lane, resetting the lanes that end.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

from imitrl import keys
from imitrl.envs.limits import episode_limit
from imitrl.policies.action_check import check_action

__all__ = [
    "NEXT_KEYS",
    "OPTIONAL_NEXT_KEYS",
    "OPTIONAL_ROW_KEYS",
    "ROW_KEYS",
    "STEP_ROW_KEYS",
    "Lanes",
    "Stepper",
    "episode_bound",
    "holds_non_finite",
    "lane_count",
    "play",
    "play_steps",
    "policy_errors_named",
    "quota",
]

ROW_KEYS = (
    keys.OBSERVATION,
    keys.ACTION,
    keys.EXPERT_ACTION,
    keys.EXPERT_EXECUTED,
)
NEXT_KEYS = (keys.REWARD, keys.DONE, keys.TERMINATED, keys.TRUNCATED)
STEP_ROW_KEYS = (keys.OBSERVATION, keys.ACTION)
"""what :func:`play_steps` records of the root (an on-policy learner's batch: no expert)"""
OPTIONAL_ROW_KEYS = (keys.PIXELS, keys.ENVIRONMENT_STATE, keys.EXPERT_PLAN, keys.EXPERT_PLAN_PAD)
"""kept in the rows when the env or the policy gives them (a pixel env's images, a Dict
env's ``environment_state`` beside its state, chunk-aware DAgger's expert plans)"""
OPTIONAL_NEXT_KEYS = ("success",)
"""kept under ``"next"`` when the env gives them (``make_env``'s ``success``)"""


class Stepper(ABC):
    """An env and the policy acting in it, stepped together: all the loop sees of them.

    Built with ``record=True``, it keeps every step's row entries (:data:`ROW_KEYS`, the
    ``("next", ...)`` flags and reward) for :meth:`trajectory`.
    """

    env: EnvBase
    policy: TensorDictModuleBase
    """the module that drives the env (an Expert's ``as_actor()``, a learner, a mixer)"""

    @abstractmethod
    def reset(self) -> None:
        """The first reset (``env.reset()``, through TorchRL on every path)."""

    @abstractmethod
    def act(self):
        """Call the policy on the current observations; the root's entries after it (a
        mapping with ``get`` and ``in``: the action, the expert's label, ...)."""

    @abstractmethod
    def step(self) -> tuple[np.ndarray, np.ndarray]:
        """Step every lane with the action :meth:`act` wrote: ``(reward, done)``, float32
        and bool ``[lanes]`` numpy arrays."""

    @abstractmethod
    def advance(self, done: np.ndarray | None) -> None:
        """Make the next step's root: each lane's next observation, and the lanes of the
        bool mask ``done`` reset (``done`` None: no lane finished at this step)."""

    @abstractmethod
    def step_tensordict(self) -> TensorDictBase:
        """What ``env.step_and_maybe_reset`` returned first for the last step (the root's
        entries and ``"next"``), for a success criterion at an episode's end."""

    @abstractmethod
    def trajectory(self) -> TensorDictBase | None:
        """The recorded steps ``[*batch, T]`` (None when none was taken)."""

    @abstractmethod
    def clear(self) -> None:
        """Forget the recorded steps (the env and the policy's state stay)."""

    def take(self) -> TensorDictBase | None:
        """The recorded steps, which the stepper then forgets (:func:`play_steps`)."""
        steps = self.trajectory()
        self.clear()
        return steps

    @contextmanager
    def running(self) -> Iterator[None]:
        """The context the whole loop runs in (a stepper may choose ``inference_mode``)."""
        yield


def lane_count(env: EnvBase) -> int:
    """The env's lanes: its one batch dimension, or 1 for an unbatched env."""
    if len(env.batch_size) > 1:
        raise ValueError(
            f"envs with more than one batch dimension are not supported, got {tuple(env.batch_size)}"
        )
    return int(env.batch_size.numel()) if len(env.batch_size) else 1


def quota(num_episodes: int, lanes: int) -> torch.Tensor:
    """Episodes lane ``i`` must finish under round-robin assignment: ceil((n - i) / lanes)."""
    i = torch.arange(lanes)
    return ((num_episodes - i + lanes - 1) // lanes).clamp_min(0)


def episode_bound(env: EnvBase, max_steps: int | None, num_episodes: int) -> tuple[int, str]:
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


def any_done(done: np.ndarray) -> bool:
    """Whether any lane ended at this step. ``True in done.tolist()`` is ``done.any()`` for
    a bool array at a tenth of its cost on one lane (a few lanes are the common case;
    this runs every step)."""
    return True in done.tolist() if done.dtype == np.bool_ else bool(done.any())


class Lanes:
    """Per-lane bookkeeping of a rollout under round-robin quotas (module docstring).

    Each lane counts the steps since its last reset and the episodes it finished; a lane
    still owed episodes that runs ``bound`` steps without ending one raises.
    """

    def __init__(self, quota: torch.Tensor, bound: int, bound_name: str) -> None:
        self.quota = quota.numpy()
        self.lanes = self.quota.size
        self.finished = np.zeros(self.lanes, dtype=np.int64)
        self.start = np.zeros(self.lanes, dtype=np.int64)  # step at which each episode began
        self.t = 0
        self.oldest = 0  # the smallest start: no lane is near the bound before t - oldest is
        self.bound, self.bound_name = bound, bound_name
        self.owing = bool((self.finished < self.quota).any())

    @classmethod
    def of(cls, env: EnvBase, num_episodes: int, max_steps: int | None) -> Lanes:
        """The bookkeeping of ``num_episodes`` episodes on ``env`` (bounds checked)."""
        bound, bound_name = episode_bound(env, max_steps, num_episodes)
        return cls(quota(int(num_episodes), lane_count(env)), bound, bound_name)

    def step(self, done: np.ndarray) -> np.ndarray | None:
        """Count one step of every lane (``done`` bool ``[lanes]``); the lanes that ended an
        episode at it, or None when none did."""
        self.t += 1
        if self.t - self.oldest >= self.bound:
            length = self.t - self.start
            if bool(((length >= self.bound) & ~done & (self.finished < self.quota)).any()):
                raise ValueError(
                    f"an episode ran past {self.bound_name} steps without ending (the bound is "
                    "per episode); pass a larger max_steps= or give the env a time limit"
                )
        return np.flatnonzero(done) if any_done(done) else None

    def kept(self, ended: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Of the ``ended`` lanes, those still owed episodes: (lanes, episode ids, lengths)."""
        lanes = ended[self.finished[ended] < self.quota[ended]]
        return lanes, self.finished[lanes] * self.lanes + lanes, self.t - self.start[lanes]

    def close(self, ended: np.ndarray) -> None:
        """The ``ended`` lanes start their next episode."""
        self.finished[ended] += 1
        self.start[ended] = self.t
        self.oldest = int(self.start.min())
        self.owing = bool((self.finished < self.quota).any())


def _action_spec(env: EnvBase):
    """One lane's action spec."""
    return env.full_action_spec_unbatched[env.action_key]


def check_first_step(env: EnvBase, values, labels: bool) -> None:
    """The policy's first action must have the env's action dtype and shape; with
    ``labels`` it must also have written the expert's label (``values``: the root's
    entries after the policy's call).

    Envs do not check: a gymnasium env may silently read the first entry of a longer
    action, or fail deep inside its own step. The policy is fixed: checked once.
    """
    action = values.get(env.action_key, None)
    if action is None:
        raise ValueError(f"the policy did not write the env's action key {env.action_key!r}")
    check_action(action, _action_spec(env), batch_shape=env.batch_size, name="the policy's action")
    for k in (keys.EXPERT_ACTION, keys.EXPERT_EXECUTED) if labels else ():
        if k not in values:
            raise ValueError(
                f"the rollout policy must write {k!r} (pass an Expert or a DAgger behaviour policy)"
            )


@contextmanager
def policy_errors_named(env: EnvBase, policy) -> Iterator[None]:
    """A policy module that cannot act on ``env``'s observations (a network of another
    width, a missing key) fails with a ValueError naming both, not a bare RuntimeError."""
    try:
        yield
    except (RuntimeError, KeyError) as err:
        params = policy.parameters() if isinstance(policy, torch.nn.Module) else ()
        if holds_non_finite(params):  # a diverged learner, not one of another env (a review)
            raise ValueError(
                f"the policy ({type(policy).__name__}) holds weights that are not finite "
                f"(NaN or inf: its training diverged) and cannot act: {type(err).__name__}: "
                f"{err}"
            ) from err
        obs = env.observation_spec_unbatched
        shapes = {
            str(k): (tuple(v.shape), str(v.dtype).removeprefix("torch."))
            for k, v in obs.items(include_nested=True, leaves_only=True)
        }
        name = type(policy).__name__
        raise ValueError(
            f"the policy ({name}, reading {list(getattr(policy, 'in_keys', []))}) failed on the "
            f"env's observations {shapes}: {type(err).__name__}: {err}; was it built for "
            "another env?"
        ) from err


def holds_non_finite(params: Iterable[torch.Tensor]) -> bool:
    """Whether any of ``params`` (a module's parameters) holds a NaN or an inf."""
    return any(not bool(torch.isfinite(p).all()) for p in params)


def play(
    stepper: Stepper,
    book: Lanes,
    *,
    labels: bool,
    on_reward: Callable[[np.ndarray], object] | None = None,
    on_end: Callable[[np.ndarray], object] | None = None,
) -> None:
    """Step ``stepper`` until every lane of ``book`` finished its quota.

    Args:
        labels: the policy must write the expert's label (a collection for a buffer).
        on_reward: called with each step's float32 ``[lanes]`` rewards.
        on_end: called with the lanes that ended an episode at a step, before they
            reset (``stepper.step_tensordict()`` is that step's tensordict).
    """
    env = stepper.env
    with policy_errors_named(env, stepper.policy):
        stepper.reset()  # outside ``running``: the env's state must not be inference tensors
        with stepper.running():
            _steps(stepper, book, labels, on_reward, on_end)


def _steps(stepper: Stepper, book: Lanes, labels: bool, on_reward, on_end) -> None:
    """:func:`play`'s loop, from the first reset on."""
    env, first = stepper.env, True
    while book.owing:
        values = stepper.act()
        if first:
            check_first_step(env, values, labels)
            first = False
        reward, done = stepper.step()
        if on_reward is not None:
            on_reward(reward)
        ended = book.step(done)
        if ended is not None:
            if on_end is not None:
                on_end(ended)
            book.close(ended)
        # the finished lanes reset even after the last step, as TorchRL's
        # step_and_maybe_reset does: the env's random state ends where it leaves it
        stepper.advance(None if ended is None else done)


def play_steps(stepper: Stepper, steps: int) -> TensorDictBase:
    """``steps`` steps of every lane from where the last call left them; the recorded
    steps ``[*batch, steps]``, which the stepper then forgets.

    Call ``stepper.reset()`` once before the first call (outside ``torch.inference_mode``).
    Lanes that end an episode reset and go on; an episode is bounded by the env's own
    time limit only (a batch may end inside an episode: the next call continues it).
    """
    if int(steps) != steps or steps < 1:
        raise ValueError(f"steps must be a positive integer, got {steps!r}")
    env, first = stepper.env, True
    with policy_errors_named(env, stepper.policy), stepper.running():
        for _ in range(int(steps)):
            values = stepper.act()
            if first:  # each call's first action (a batch's cost is thousands of steps)
                check_first_step(env, values, labels=False)
                first = False
            _, done = stepper.step()
            stepper.advance(done if any_done(done) else None)
    return stepper.take()
