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
:func:`~imitrl.data.returns.episode_returns` (its own module) keeps only per-episode
summaries (cheap for 1e5+ episodes).
Both take an :class:`~imitrl.policies.Expert` (it drives the env through
``as_actor()``, its labels cast to the env's action spec) or any policy module.

**Two paths, the same episodes.** On a plain gymnasium env from
:func:`~imitrl.envs.make_env` and on a :class:`~imitrl.envs.TabularEnv`, each step
skips TorchRL's TensorDict round trips: the simulator is stepped directly
(:mod:`imitrl.envs.direct`) and the policy is called on a dict of tensors
(:class:`~imitrl.policies.modules.TensorPolicy`). Every other env goes through
``env.step_and_maybe_reset`` and calls the policy on TensorDicts, and so does every env
with ``fast_path=False``: the reference the direct path is tested against, digit for
digit (``tests/test_fast_path.py``).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Bounded, TensorSpec
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from imitrl import keys
from imitrl.envs.direct import DirectSteps, direct_steps
from imitrl.envs.limits import episode_limit
from imitrl.policies.action_check import check_action
from imitrl.policies.experts import Expert
from imitrl.policies.modules import TensorPolicy
from imitrl.rng import rng_from
from imitrl.runtime.device import acting

__all__ = ["rollout_episodes", "rollout_policy"]

ROW_KEYS = (
    keys.OBSERVATION,
    keys.ACTION,
    keys.EXPERT_ACTION,
    keys.EXPERT_EXECUTED,
)
NEXT_KEYS = (keys.REWARD, keys.DONE, keys.TERMINATED, keys.TRUNCATED)
OPTIONAL_ROW_KEYS = (keys.PIXELS,)
"""kept in the rows when the env gives them (a pixel env's images beside its state)"""


def _lanes(env: EnvBase) -> int:
    if len(env.batch_size) > 1:
        raise ValueError(
            f"envs with more than one batch dimension are not supported, got {tuple(env.batch_size)}"
        )
    return int(env.batch_size.numel()) if len(env.batch_size) else 1


def _action_spec(env: EnvBase):
    """One lane's action spec."""
    return env.full_action_spec_unbatched[env.action_key]


def _check_first_step(env: EnvBase, action: torch.Tensor | None, written, labels: bool) -> None:
    """The policy's first action must have the env's action dtype and shape; with
    ``labels`` it must also have written the expert's label (``written``: its keys).

    Envs do not check: a gymnasium env may silently read the first entry of a longer
    action, or fail deep inside its own step. The policy is fixed: checked once.
    """
    if action is None:
        raise ValueError(f"the policy did not write the env's action key {env.action_key!r}")
    check_action(action, _action_spec(env), batch_shape=env.batch_size, name="the policy's action")
    for k in (keys.EXPERT_ACTION, keys.EXPERT_EXECUTED) if labels else ():
        if k not in written:
            raise ValueError(
                f"the rollout policy must write {k!r} (pass an Expert or a DAgger behaviour policy)"
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
    module runs as given (on another device than the env's: through
    :class:`~imitrl.runtime.device.OnDevice`) and ``exploration`` must be stated.
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
    # a learner on another device than the env (a GPU): its inputs cross there and its
    # actions back, once per step (imitrl.runtime.device); on the CPU the module itself
    return acting(policy, env.device), exploration


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


class _Lanes:
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
        # ``True in done.tolist()`` is ``done.any()`` for a bool array at a tenth of its
        # cost on one lane (a few lanes are the common case; this runs every step)
        ended = True in done.tolist() if done.dtype == np.bool_ else bool(done.any())
        return np.flatnonzero(done) if ended else None

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
    fast_path: bool = True,
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
        fast_path: step a plain gymnasium env or a TabularEnv directly (module
            docstring); False: through TorchRL (the same rows, slower).

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
    book = _Lanes(_quota(int(num_episodes), _lanes(env)), bound, bound_name)
    with torch.no_grad(), set_exploration_type(exploration), rng_from(generator):
        direct = direct_steps(env) if fast_path else None
        with policy_errors_named(env, actor):
            if direct is None:
                traj = _torchrl_trajectory(env, actor, book)
            else:
                traj = _direct_trajectory(env, direct, actor, book)
    if traj is None:
        raise ValueError("num_episodes must be positive to collect rows")
    rows = _rows(env, traj, book, round_index, first_episode)
    check_labels(rows, _action_spec(env))
    return rows


def check_labels(rows: TensorDictBase, spec: TensorSpec) -> None:
    """The expert's labels (``EXPERT_ACTION``) are finite and inside the action spec;
    ValueError naming the first bad row's episode and step otherwise (a recorded label
    outside the bounds would train every learner towards an action the env clips)."""
    labels = rows.get(keys.EXPERT_ACTION, None)
    if labels is None or labels.numel() == 0:
        return
    flat = labels.reshape(labels.shape[0], -1)
    bad = ~torch.isfinite(flat).all(-1) if flat.is_floating_point() else None
    what, hint = "NaN or inf", "the expert must return finite actions"
    if (bad is None or not bad.any()) and isinstance(spec, Bounded):
        low = spec.space.low.reshape(-1).to(flat.dtype)
        high = spec.space.high.reshape(-1).to(flat.dtype)
        bad = ((flat < low) | (flat > high)).any(-1)
        what = f"outside the action bounds [{low.tolist()}, {high.tolist()}]"
        hint = "fix the expert, or clip its labels on purpose (Expert.from_callable(fn, clip=True))"
    if bad is None or not bad.any():
        return
    i = int(bad.nonzero()[0])
    episode, step = int(rows.get(keys.EPISODE)[i]), int(rows.get(keys.STEP)[i])
    raise ValueError(
        f"the expert labelled episode {episode}, step {step} with {flat[i].tolist()}, {what} "
        f"({int(bad.sum())} of {len(bad)} rows): {hint}"
    )


@contextmanager
def policy_errors_named(env: EnvBase, policy: TensorDictModuleBase) -> Iterator[None]:
    """A policy module that cannot act on ``env``'s observations (a network of another
    width, a missing key) fails with a ValueError naming both, not a bare RuntimeError."""
    try:
        yield
    except (RuntimeError, KeyError) as err:
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


def _torchrl_trajectory(env: EnvBase, actor, book: _Lanes) -> TensorDictBase | None:
    """The steps ``[*batch, T]`` until every lane finished its quota, through TorchRL."""
    steps: list[TensorDictBase] = []
    row_keys = list(ROW_KEYS)
    td = env.reset()
    while book.owing:
        td = actor(td)
        if not steps:
            written = td.keys(include_nested=True)
            _check_first_step(env, td.get(env.action_key, None), written, labels=True)
            row_keys += [k for k in OPTIONAL_ROW_KEYS if k in td.keys()]
        out, td = env.step_and_maybe_reset(td)
        steps.append(out.select(*row_keys, *[(keys.NEXT, k) for k in NEXT_KEYS]))
        ended = book.step(out.get((keys.NEXT, keys.DONE)).reshape(book.lanes).numpy())
        if ended is not None:
            book.close(ended)
    return torch.stack(steps, dim=len(env.batch_size)).contiguous() if steps else None


def _direct_trajectory(
    env: EnvBase, direct: DirectSteps, actor, book: _Lanes
) -> TensorDictBase | None:
    """The same steps as :func:`_torchrl_trajectory`: the env stepped directly, the policy
    called on a dict of the root's entries (what ``step_and_maybe_reset`` leaves there)."""
    policy, action_key = TensorPolicy(actor, env.batch_size), env.action_key
    values = dict(env.reset().items(include_nested=True, leaves_only=True))
    columns: dict = {k: [] for k in ROW_KEYS}
    raw_steps = []  # the next entries are made tensors once, at the end
    while book.owing:
        policy(values)
        action = values.get(action_key)
        if not columns[keys.ACTION]:
            _check_first_step(env, action, values, labels=True)
        for k in ROW_KEYS:
            columns[k].append(values[k])
        step = direct.step_raw(action)
        raw_steps.append(step)
        ended = book.step(step.done)
        if ended is None:
            values[keys.OBSERVATION] = step.observation
        else:
            values[keys.OBSERVATION] = direct.reset_lanes(step.done)
            book.close(ended)
    if not columns[keys.ACTION]:
        return None
    dim = len(env.batch_size)
    stacked = {k: torch.stack(v, dim=dim) for k, v in columns.items()}
    return TensorDict(
        {
            **{k: stacked[k] for k in ROW_KEYS},
            keys.NEXT: dict(zip(NEXT_KEYS, direct.next_tensors(raw_steps))),
        },
        batch_size=stacked[keys.ACTION].shape[: dim + 1],
    )


def _quota(num_episodes: int, lanes: int) -> torch.Tensor:
    """Episodes lane ``i`` must finish under round-robin assignment: ceil((n - i) / lanes)."""
    i = torch.arange(lanes)
    return ((num_episodes - i + lanes - 1) // lanes).clamp_min(0)


def _rows(
    env: EnvBase,
    traj: TensorDictBase,
    book: _Lanes,
    round_index: int,
    first_episode: int,
) -> TensorDict:
    """The steps ``traj`` ``[*batch, T]`` of every lane as rows of the episodes each lane
    owes, in id order."""
    lanes = book.lanes
    quota = torch.from_numpy(book.quota)
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
