"""Whole episodes from any TorchRL env, batched or not, kept as demonstration rows.

:func:`rollout_episodes` plays episodes by the one rollout loop
(:func:`imitrl.runtime.loop.play`: lanes under round-robin quotas, so that the sample is
not biased towards short episodes, and a per-episode step bound) and keeps every
transition as demonstration rows; :func:`~imitrl.runtime.returns.episode_returns` (its own
module) plays them by the same loop and keeps only per-episode summaries (cheap for 1e5+
episodes). Both take an :class:`~imitrl.policies.Expert` (it drives the env through
``as_actor()``, its labels cast to the env's action spec) or any policy module.

**Two paths, the same episodes.** The loop steps the env through the stepper the seam
chooses (:func:`imitrl.runtime.paths.stepper`): on a plain gymnasium env from
:func:`~imitrl.envs.make_env` and on a :class:`~imitrl.envs.TabularEnv` the accelerated
one (the simulator stepped directly, the policy called on a dict of tensors), on every
other env and inside :func:`imitrl.runtime.paths.reference` (``"stepper"``, or all) TorchRL's own ``env.step_and_maybe_reset`` and ``policy(td)``: the reference the
accelerated path is tested against, digit for digit (``tests/runtime/test_paths.py``).
"""

from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Bounded, TensorSpec
from torchrl.envs import EnvBase, InitTracker, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from imitrl import keys
from imitrl.data.chunks import IS_INIT
from imitrl.policies.experts import Expert
from imitrl.rng import rng_from
from imitrl.runtime import paths
from imitrl.runtime.loop import (
    NEXT_KEYS,
    OPTIONAL_ROW_KEYS,
    ROW_KEYS,
    Lanes,
    play,
    policy_errors_named,
)
from imitrl.system.device import acting

__all__ = [
    "NEXT_KEYS",
    "OPTIONAL_ROW_KEYS",
    "ROW_KEYS",
    "policy_errors_named",
    "rollout_episodes",
    "rollout_policy",
]


def _action_spec(env: EnvBase):
    """One lane's action spec."""
    return env.full_action_spec_unbatched[env.action_key]


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
    :class:`~imitrl.system.device.OnDevice`) and ``exploration`` must be stated.
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
    # actions back, once per step (imitrl.system.device); on the CPU the module itself
    return acting(policy, env.device), exploration


def init_tracked(env: EnvBase, policy: TensorDictModuleBase) -> EnvBase:
    """``env``, or ``env`` with TorchRL's ``InitTracker`` when ``policy`` reads
    ``"is_init"`` (a chunked policy, which must know where each lane was reset) and the
    env does not write it: so every rollout and evaluation of a chunked learner works on
    any env, as :func:`~imitrl.policies.chunking.chunk_env` would wrap it (the wrapper
    shares the env; the direct stepper does not apply to it)."""
    if IS_INIT not in policy.in_keys or IS_INIT in env.observation_spec.keys(True):
        return env
    # auto_unwrap=False: a TransformedEnv around env, not a copy of env's own transforms
    return TransformedEnv(env, InitTracker(), auto_unwrap=False)


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
    next_observation: bool = False,
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
        next_observation: also keep each row's ``("next", OBSERVATION)`` (the next row's
            observation, and at an episode's last row its final observation, which no
            row holds otherwise): what Minari stores (:func:`~imitrl.datasets.save_minari`
            needs it). Off by default: a buffer's rows and a dataset's share one schema.

    Returns:
        rows ``[R]`` with ``OBSERVATION, ACTION, EXPERT_ACTION, EXPERT_EXECUTED,
        EPISODE, ROUND, STEP`` and ``("next", reward|done|terminated|truncated)``
        (and ``PIXELS`` when the env gives images), episodes back to back in id order.

    Raises:
        ValueError: the policy does not write an expert label or the env's action; the
            env has no time limit and ``max_steps`` is None; an episode ran past the bound.
    """
    book = Lanes.of(env, num_episodes, max_steps)
    actor, exploration = rollout_policy(env, policy, exploration)
    generator = _seeded(env, seed, generator)
    with torch.no_grad(), set_exploration_type(exploration), rng_from(generator):
        stepper = paths.stepper(init_tracked(env, actor), actor, record=True)
        finals = FinalObservations(stepper, book, first_episode) if next_observation else None
        play(stepper, book, labels=True, on_end=finals)
        traj = stepper.trajectory()
    if traj is None:
        raise ValueError("num_episodes must be positive to collect rows")
    rows = _rows(env, traj, book, round_index, first_episode)
    if finals is not None:
        finals.add_to(rows)
    check_labels(rows, _action_spec(env))
    return rows


class FinalObservations:
    """Each kept episode's final observation, taken as its lane ends (``play``'s
    ``on_end``: the step's ``("next", OBSERVATION)`` before the lane resets), and
    :meth:`add_to` rows: ``("next", OBSERVATION)`` of every row."""

    def __init__(self, stepper, book: Lanes, first_episode: int) -> None:
        self.stepper, self.book, self.first = stepper, book, int(first_episode)
        self.finals: dict[int, torch.Tensor] = {}
        self.batched = len(stepper.env.batch_size) > 0

    def __call__(self, ended: np.ndarray) -> None:
        """Keep the final observation of each ``ended`` lane's episode, if it is kept."""
        nxt = self.stepper.step_tensordict().get((keys.NEXT, keys.OBSERVATION))
        for lane in ended.tolist():
            k = int(self.book.finished[lane])  # the lane's episode that just ended
            if k < int(self.book.quota[lane]):
                episode = self.first + k * self.book.lanes + lane
                self.finals[episode] = (nxt[lane] if self.batched else nxt).clone()

    def add_to(self, rows: TensorDictBase) -> None:
        """Set ``("next", OBSERVATION)`` on ``rows`` (episodes back to back, in order)."""
        obs, episode = rows.get(keys.OBSERVATION), rows.get(keys.EPISODE)
        nxt = torch.empty_like(obs)
        nxt[:-1] = obs[1:]
        last = torch.ones_like(episode, dtype=torch.bool)
        last[:-1] = episode[1:] != episode[:-1]
        for i in last.nonzero().flatten().tolist():
            nxt[i] = self.finals[int(episode[i])]
        rows.set((keys.NEXT, keys.OBSERVATION), nxt)


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


def _rows(
    env: EnvBase,
    traj: TensorDictBase,
    book: Lanes,
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
