"""GAIL's and AIRL's hyperparameters, each declared once, with its limits and its default
(:class:`AdversarialConfig`, :class:`GAILConfig`, :class:`AIRLConfig`).

This module imports no torch: the command line's ``imitrl gail`` and ``imitrl airl``
configs extend these classes (:mod:`imitrl.jobs.configs`), so that every training flag is
the library's own field, its docstring the flag's help, its limits the flag's range.
"""

from __future__ import annotations

from dataclasses import dataclass

from imitrl.limits import (
    MAX_BATCH,
    MAX_ENV_STEPS,
    MAX_ROLLOUT_STEPS,
    MAX_SEED,
    MAX_UPDATES,
    bounded,
    check_bounds,
    widths,
)

__all__ = [
    "ADVERSARIAL_LR",
    "DISCRIMINATOR_HIDDEN",
    "AIRLConfig",
    "AdversarialConfig",
    "GAILConfig",
]

ADVERSARIAL_LR = 3e-4
"""Adam's rate of GAIL's and AIRL's networks: the discriminator's
(:attr:`AdversarialConfig.discriminator_lr`) and, as the command line builds it, the
generator's (the learner's policy and value: ``imitrl gail --lr``), as in imitation's and
Stable-Baselines3's PPO"""
DISCRIMINATOR_HIDDEN = (64, 64)
"""hidden layers of the discriminator's networks (GAIL's ``D``, AIRL's ``g`` and ``h``)"""


@dataclass(frozen=True)
class AdversarialConfig:
    """What GAIL and AIRL share: budget, generator (PPO + GAE), discriminator schedule.

    The generator's learning rate is the learner's own (its ``opt_pi`` / ``opt_v``, set
    when it is built), scaled round by round when ``anneal_lr``."""

    total_steps: int = bounded(102_400, 1, MAX_ENV_STEPS)
    """environment steps of the whole run (50 rounds of 2048; rounded up to whole rounds)"""
    rollout_steps: int = bounded(2048, 1, MAX_ROLLOUT_STEPS)
    """environment steps collected per round, all lanes together (a multiple of them)"""
    ppo_epochs: int = bounded(10, 1, MAX_UPDATES)
    """PPO passes over each round's batch"""
    minibatch_size: int = bounded(256, 1, MAX_BATCH)
    """rows per PPO gradient step"""
    discriminator_updates: int = bounded(10, 0, MAX_UPDATES)
    """discriminator Adam steps per round"""
    discriminator_batch: int = bounded(256, 1, MAX_BATCH)
    """expert (and as many policy) transitions per discriminator step"""
    discriminator_lr: float = bounded(ADVERSARIAL_LR, 0, integer=False, low_open=True)
    """Adam learning rate of the discriminator"""
    discriminator_hidden: tuple[int, ...] = widths(DISCRIMINATOR_HIDDEN)
    """hidden layer sizes of the discriminator's networks"""
    grad_penalty: float = bounded(0.0, 0, integer=False)
    """weight of the discriminator's gradient penalty (GAILLoss's gp_lambda); 0 = none"""
    gamma: float = bounded(0.99, 0, 1, integer=False)
    """discount of GAE (and of AIRL's shaping, and of the absorbing state's value)"""
    gae_lambda: float = bounded(0.95, 0, 1, integer=False)
    """GAE's lambda"""
    clip_epsilon: float = bounded(0.2, 0, integer=False, low_open=True)
    """PPO's ratio clip"""
    entropy_coeff: float = bounded(0.0, 0, integer=False)
    """weight of PPO's entropy bonus"""
    max_grad_norm: float = bounded(0.5, 0, integer=False, low_open=True)
    """gradient-norm clip of each PPO step"""
    anneal_lr: bool = False
    """the generator's learning rates fall linearly over the rounds: round ``k`` of ``K``
    (``k`` from 0) steps at ``1 - k / K`` times the learner's own, the first at the
    learner's rate, the last at ``1 / K`` of it (CleanRL's PPO schedule); the
    discriminator's rate stays constant, and the learner's optimizers keep their own
    rates after the run. False: constant"""
    absorbing: bool | None = None
    """absorbing-state handling (DAC) of terminated episodes; None (default): on when a
    demonstration episode ends by termination (a goal: Acrobot, FrozenLake), off when every
    one is truncated (the expert survives: CartPole, Pendulum), where GAIL's reward
    ``-log(1 - D) > 0`` pays for living (:mod:`~imitrl.algorithms.adversarial.absorbing`:
    why, and what it measured: Acrobot, seed 0, one demonstration, GAIL ends at -82 with
    absorbing states, the expert's -80, and at -226 without)"""
    normalizer_warmup: int = bounded(0, 0, MAX_ROLLOUT_STEPS)
    """environment steps of the untrained learner whose observations join the
    demonstrations' in the normaliser's statistics (counted as env steps); 0: the
    demonstrations' alone. Ignored when the normaliser is already fitted or absent"""
    seed: int = bounded(0, 0, MAX_SEED)
    """seeds the policy's samples, the discriminator's initialisation and every minibatch"""

    def __post_init__(self) -> None:
        check_bounds(self, name=str)  # every field in its range, named as a field
        if self.absorbing and self.gamma >= 1.0:
            raise ValueError(
                "absorbing states need gamma < 1 (the absorbing state's value is "
                "r_abs / (1 - gamma)); set absorbing=False (--no-absorbing) for gamma = 1"
            )


@dataclass(frozen=True)
class GAILConfig(AdversarialConfig):
    """GAIL: every field of :class:`AdversarialConfig` (budget, PPO, discriminator)."""


@dataclass(frozen=True)
class AIRLConfig(AdversarialConfig):
    """AIRL: every field of :class:`AdversarialConfig`; ``gamma`` also discounts ``h(s')``."""

    entropy_weight: float = bounded(1.0, 0, integer=False)
    """weight ``w`` of ``-log pi`` in the generator's reward ``f - w log pi``: 1 is the
    paper's ``log D - log(1 - D)`` (a soft-RL generator at temperature 1); 0 trains the
    generator on ``f`` alone. The discriminator's logit is ``f - log pi`` either way.
    Measured (``benchmarks/beyond_cloning.py``, 5 seeds): on Pendulum, which never
    terminates, w = 0 ends at -152 to -156 where w = 1 ends at -275 to -836; on tasks that
    end on failure the term is the generator's living bonus, and at w = 0 CartPole and
    InvertedPendulum collapse to 9- and 2-step episodes"""
