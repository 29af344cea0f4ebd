"""The adversarial imitation loop GAIL and AIRL share: collect, discriminate, reinforce.

Round after round, until ``total_steps`` environment steps:

1. the one rollout loop (:func:`~imitrl.runtime.loop.play_steps`) plays ``rollout_steps``
   steps of the learner's policy on the env's lanes (``rollout_steps / lanes`` each,
   continuing where the last round left every lane), sampling its actions
   (``ExplorationType.RANDOM``) batched over the lanes; the accelerated stepper where
   the seam (:mod:`imitrl.runtime.paths`) has one, TorchRL's ``step_and_maybe_reset``
   elsewhere, with the same digits;
2. ``discriminator_updates`` steps of the discriminator, each on ``discriminator_batch``
   expert transitions and as many of this round's policy transitions, drawn with
   replacement;
3. the updated discriminator's reward is written under ``("next", LEARNED_REWARD)`` and
   the generator (:class:`~imitrl.algorithms.adversarial.generator.PPOGenerator`) takes
   its PPO epochs on the batch.

With ``config.absorbing`` (by default on where a demonstration ends by termination) both sides' transitions carry DAC's absorbing
state and a terminated step's reward carries its value
(:mod:`~imitrl.algorithms.adversarial.absorbing`: why, and what changes); truncated
steps are bootstrapped by GAE either way.

Before the first round the learner fits its observation normaliser to the
demonstrations (``learner.prepare``, as behaviour cloning does; a learner already fitted
keeps its statistics); both discriminators read observations through it. With
``normalizer_warmup`` steps, the untrained learner first plays that many steps and their
observations join the demonstrations' in the statistics (the steps are counted): for
demonstrations that barely move, which would scale the learner's own states up by
orders of magnitude. Expert queries are the demonstration rows only: neither method asks
the expert anything afterwards.

Every random draw comes from ``config.seed``: the torch global RNG (the policy's samples,
GAILLoss's penalty interpolations) is seeded with it inside ``fork_rng`` (the caller's
global state is left untouched) and the minibatch draws use generators seeded from it;
the env is seeded by whoever built it. Same seed, same env seed: same numbers.

On ``N`` data-parallel ranks (``torch.distributed``, ``imitrl gail --nproc N``) every rank
plays ``rollout_steps`` steps of its own lanes a round (its env seeded apart by the
caller: ``imitrl gail`` gives rank ``r`` the seeds ``seed + r * lanes + i``) and holds the
same demonstrations: a round is ``N * rollout_steps`` env steps, ``total_steps`` counts
every rank's. The normaliser's warm-up statistics are every rank's steps; each
discriminator step's expert rows are this rank's share of ``N * discriminator_batch``
(drawn as one process draws them), its policy rows its own; the discriminator's and
PPO's gradients are averaged over the ranks, so every rank holds the same networks
after every step. The policy's samples are seeded ``seed * N + rank`` (``seed`` itself in
a single process), the minibatch draws ``seed`` on every rank.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Protocol

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.record.loggers import Logger
from tqdm.auto import tqdm

from imitrl import keys
from imitrl.algorithms.adversarial.absorbing import (
    absorbing_rows,
    absorbing_tail,
    demonstrations_terminate,
    with_absorbing,
)
from imitrl.algorithms.adversarial.generator import PPOGenerator
from imitrl.algorithms.adversarial.keys import LEARNED_REWARD
from imitrl.algorithms.adversarial.transitions import (
    NEXT_ABSORBING,
    expert_transitions,
    policy_transitions,
    sample_rows,
)
from imitrl.configs.adversarial import AdversarialConfig
from imitrl.data.buffer import DemonstrationBuffer
from imitrl.learners.actor_critic import ActorCritic
from imitrl.runtime import paths
from imitrl.runtime.loop import (
    STEP_ROW_KEYS,
    Stepper,
    holds_non_finite,
    lane_count,
    play_steps,
)
from imitrl.system.device import acting
from imitrl.system.ranks import gathered, rank_and_world, rows_drawn, sharded, summed

__all__ = [
    "AdversarialResult",
    "Discriminator",
    "RoundRecord",
    "check_inputs",
    "train_adversarial",
]


class Discriminator(Protocol):
    """What the loop needs of a discriminator: a step on transitions, and a reward."""

    def update(self, expert: TensorDictBase, policy: TensorDictBase) -> dict[str, float]: ...

    def reward(self, transitions: TensorDictBase) -> torch.Tensor: ...


@dataclass
class RoundRecord:
    """One round of the loop."""

    round: int
    env_steps: int
    """environment steps so far (this round's included)"""
    discriminator: dict[str, float]
    """the last discriminator step's loss, penalty and accuracies"""
    generator: dict[str, float]
    """the round's last PPO epoch: mean ``loss_objective``, ``loss_critic`` (, entropy)"""
    learned_reward: float
    """mean learned reward of the round's transitions (the absorbing tail not included)"""
    absorbing_reward: float | None = None
    """the learned reward ``r_abs`` of the absorbing state (None: ``absorbing`` off)"""
    terminated: int = 0
    """the round's terminated steps (each adds an absorbing row on the policy side)"""
    info: dict | None = None
    """what ``on_round`` returned (e.g. an evaluation)"""


@dataclass
class AdversarialResult:
    """What :func:`train_adversarial` (and so ``gail``/``airl``) returns."""

    learner: ActorCritic
    """the trained learner (the one passed in)"""
    rounds: list[RoundRecord] = field(repr=False)
    env_steps: int = 0
    """environment steps taken by the generator (the normaliser's warm-up included)"""
    expert_queries: int = 0
    """expert actions used: the demonstration rows, none after them"""
    expert_transitions: int = 0
    """demonstration rows with a known next state (the discriminator's expert data,
    absorbing rows not counted)"""


def check_inputs(env: EnvBase, learner: ActorCritic, buffer: DemonstrationBuffer) -> None:
    """Refuse, before any work, a learner or demonstrations adversarial imitation cannot
    train on ``env`` (ValueError naming what was expected)."""
    if isinstance(learner, ActorCritic) and learner.num_states is not None:
        raise ValueError(
            f"adversarial imitation reads vector observations; this learner reads "
            f"{learner.num_states} integer states (a logits table or a one-hot MLP): one-hot "
            "the env's observations first, with a TorchRL Transform such as "
            "benchmarks/beyond_cloning.py's OneHotObservation, and build the learner on them"
        )
    if not isinstance(learner, ActorCritic) or learner.observation_shape is None:
        raise ValueError(
            "adversarial imitation trains an ActorCritic over vector observations "
            f"(build('default', env, value=True)), got {type(learner).__name__}"
        )
    if learner.value is None:
        raise ValueError(
            "adversarial imitation's PPO generator needs a value head: build the learner "
            "with value=True (build('default', env, value=True))"
        )
    if learner.pixel_shape is not None:
        raise ValueError("adversarial imitation on pixel observations is not supported")
    if not isinstance(buffer, DemonstrationBuffer) or len(buffer) == 0:
        raise ValueError("the demonstrations must be a non-empty DemonstrationBuffer")
    learner.check_env(env)


def train_adversarial(
    env: EnvBase,
    learner: ActorCritic,
    demonstrations: DemonstrationBuffer,
    discriminator: Discriminator,
    config: AdversarialConfig,
    *,
    name: str = "adversarial",
    progress: bool = False,
    logger: Logger | None = None,
    on_round: Callable[[int, ActorCritic, int], dict | None] | None = None,
) -> AdversarialResult:
    """Run the loop (module docstring) and train ``learner`` in place.

    Args:
        env: the seeded env the generator plays (``make_env``; batched or not).
        learner: the generator, a probabilistic-head ``ActorCritic``.
        demonstrations: the expert's rows (every one executed the expert's action).
        discriminator: a ``GAILDiscriminator`` or ``AIRLDiscriminator`` over ``learner``.
        config: budget and hyperparameters.
        name: the progress bar's and the logged scalars' prefix.
        progress: a progress bar over environment steps (stderr).
        logger: a TorchRL logger: discriminator and generator metrics at step = env steps.
        on_round: ``on_round(round, learner, env_steps)`` after each round; a dict it
            returns is kept as the round's ``info``.
    """
    check_inputs(env, learner, demonstrations)
    rows = demonstrations.data
    if config.absorbing is None:  # decided from the demonstrations: a goal, or survival
        config = replace(config, absorbing=demonstrations_terminate(rows))
    device = learner.device  # discriminator and PPO train there; the env stays where it is
    expert = expert_transitions(rows).to(device)
    n_expert = expert.shape[0]
    if config.absorbing:
        expert = with_absorbing(expert)
    records: list[RoundRecord] = []
    bar = tqdm(total=config.total_steps, desc=name, disable=not progress, leave=False)
    rank, world = rank_and_world()
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed * world + rank)  # each rank's own samples (ranks)
        draws = torch.Generator().manual_seed(config.seed)  # in step on every rank
        steps = _fit_normalizer(env, learner, rows, config.normalizer_warmup)
        generator = PPOGenerator(
            learner, gamma=config.gamma, gae_lambda=config.gae_lambda,
            clip_epsilon=config.clip_epsilon, entropy_coeff=config.entropy_coeff,
            epochs=config.ppo_epochs, minibatch_size=config.minibatch_size,
            max_grad_norm=config.max_grad_norm,
        )  # fmt: skip
        stepper, per_lane = _stepper(env, learner, config.rollout_steps)
        per_round = per_lane * lane_count(env) * world  # every rank's lanes
        rounds = -(-config.total_steps // per_round)  # whole rounds
        try:
            for k in range(rounds):
                with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
                    batch = play_steps(stepper, per_lane).to(device)
                steps += batch.numel() * world
                with generator.learning_rates(1 - k / rounds if config.anneal_lr else 1.0):
                    record = _round(
                        k, steps, batch, expert, discriminator, generator, config, draws
                    )
                if on_round is not None:
                    info = on_round(k, learner, steps)
                    record.info = info if isinstance(info, dict) else None
                records.append(record)
                _log(logger, name, record)
                bar.update(batch.numel() * world)
        finally:
            bar.close()
    return AdversarialResult(
        learner=learner, rounds=records, env_steps=steps,
        expert_queries=len(demonstrations), expert_transitions=n_expert,
    )  # fmt: skip


def _stepper(env: EnvBase, learner: ActorCritic, rollout_steps: int) -> tuple[Stepper, int]:
    """The stepper the rounds share (the env reset once: batches continue across rounds)
    and the steps each lane plays per round."""
    lanes = lane_count(env)
    if rollout_steps % lanes:
        raise ValueError(
            f"rollout_steps ({rollout_steps}) must be a multiple of the env's {lanes} lanes "
            "(each round steps every lane equally)"
        )
    with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        policy = acting(learner.policy, env.device)  # a learner on a GPU crosses per step
        stepper = paths.stepper(
            env, policy, record=True, row_keys=STEP_ROW_KEYS, next_observation=True
        )
        stepper.reset()
    return stepper, rollout_steps // lanes


def _fit_normalizer(env: EnvBase, learner: ActorCritic, rows: TensorDictBase, warmup: int) -> int:
    """``learner.prepare(rows)``, the normaliser fitted first to the demonstrations' and
    ``warmup`` steps of the learner's observations (module docstring) when it has one not
    yet fitted; returns the env steps taken (all lanes of a batched env)."""
    norm = learner.normalizer
    if warmup == 0 or norm is None or norm.is_fitted:
        learner.prepare(rows)
        return 0
    lanes = max(1, env.batch_size.numel())
    with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        policy = acting(learner.policy, env.device)  # a learner on a GPU crosses per step
        played = env.rollout(-(-warmup // lanes), policy, break_when_any_done=False)
    mine = played.get(keys.OBSERVATION).reshape(-1, *norm.shape).to(torch.float64)
    obs = [rows.get(keys.OBSERVATION).reshape(-1, *norm.shape).to(torch.float64), gathered(mine)]
    norm.fit(torch.cat(obs))  # every rank's steps: the same statistics on every rank
    learner.prepare(rows)  # validates the rows; the statistics stay
    return played.numel() * rank_and_world()[1]


def _round(k, steps, batch, expert, discriminator, generator, config, draws) -> RoundRecord:
    """Discriminator steps, then the learned reward, then PPO, on one round's batch."""
    n = batch.numel()
    policy = policy_transitions(batch)
    if config.absorbing:
        policy = with_absorbing(policy)  # the n rows in the batch's order, then absorbing ones
    metrics: dict[str, float] = {}
    for _ in range(config.discriminator_updates):
        metrics = discriminator.update(
            _expert_rows(expert, config.discriminator_batch, draws),
            sample_rows(policy, config.discriminator_batch, draws),  # this rank's own rows
        )
    reward = discriminator.reward(policy[:n])  # [n, 1], rows in the batch's order
    learned, r_abs = reward, None
    if config.absorbing:
        r_abs = discriminator.reward(absorbing_rows(policy, 1))  # [1, 1]
        reward = absorbing_tail(reward, policy[:n].get(NEXT_ABSORBING), r_abs, config.gamma)
    batch.set((keys.NEXT, LEARNED_REWARD), reward.reshape(*batch.shape, 1))
    ppo = generator.update(batch, draws)
    world = rank_and_world()[1]  # the record's numbers are every rank's rows
    record = RoundRecord(
        round=k, env_steps=steps, discriminator=metrics, generator=ppo,
        learned_reward=float(summed(learned.mean())) / world,  # as many rows on each
        absorbing_reward=None if r_abs is None else float(r_abs),
        terminated=int(summed(batch.get((keys.NEXT, keys.TERMINATED)).sum())),
    )  # fmt: skip
    check_finite_round(record, generator.params)
    return record


def check_finite_round(record: RoundRecord, params) -> None:
    """ValueError naming the round and what went non-finite, when a loss, the learned
    reward or a weight of the learner did (a review: a run whose every weight was NaN was
    scored, saved and reported with exit 0; the next round's rollout then blamed the env)."""
    numbers = {
        **{f"the discriminator's {k}": v for k, v in record.discriminator.items()},
        **{f"PPO's {k}": v for k, v in record.generator.items()},
        "the learned reward": record.learned_reward,
    }
    bad = [name for name, v in numbers.items() if not math.isfinite(v)]
    if not bad and holds_non_finite(params):
        bad = ["the learner's weights"]
    if bad:
        raise ValueError(
            f"round {record.round}: {bad[0]} is not finite: training diverged (a smaller "
            "learning rate, gradient penalty or entropy coefficient, or larger minibatches, "
            "keep it finite)"
        )


def _expert_rows(expert: TensorDictBase, batch: int, draws: torch.Generator) -> TensorDictBase:
    """``batch`` expert transitions drawn with replacement: on ``N`` ranks (every one
    holding the same demonstrations), this rank's share of the ``N * batch`` one process
    at ``N`` times the batch draws."""
    rank, world = rank_and_world()
    with sharded(rank * batch, world * batch):
        drawn = rows_drawn(lambda m: torch.randint(expert.shape[0], (m,), generator=draws), batch)
    return expert[drawn]


def _log(logger: Logger | None, name: str, record: RoundRecord) -> None:
    if logger is None:
        return
    values = {f"{name}/discriminator_{k}": v for k, v in record.discriminator.items()}
    values.update({f"{name}/{k}": v for k, v in record.generator.items()})
    values[f"{name}/learned_reward"] = record.learned_reward
    if record.absorbing_reward is not None:
        values[f"{name}/absorbing_reward"] = record.absorbing_reward
    for key, value in values.items():
        logger.log_scalar(key, value, step=record.env_steps)
