"""AIRL (Fu, Luo & Levine 2018): PPO on ``f(s, a, s') - log pi(a|s)``, the logit of a
discriminator ``D = exp(f) / (exp(f) + pi(a|s))`` whose ``f = g(s) + gamma h(s') - h(s)``
separates a state-only reward ``g`` from a shaping potential ``h``.

``airl(env, learner, demonstrations, AIRLConfig(...))`` trains ``learner`` in place; the
discriminator is :class:`~imitrl.algorithms.adversarial.airl_discriminator.AIRLDiscriminator`
(its ``network.g`` is the recovered reward), the loop and generator are
:mod:`~imitrl.algorithms.adversarial.loop`'s, with ``f``'s discount = the generator's
``gamma``.
"""

from __future__ import annotations

from collections.abc import Callable

from torchrl.envs import EnvBase
from torchrl.record.loggers import Logger

from imitrl.algorithms.adversarial.airl_discriminator import AIRLDiscriminator
from imitrl.algorithms.adversarial.loop import (
    AdversarialResult,
    check_inputs,
    train_adversarial,
)
from imitrl.configs.adversarial import AIRLConfig
from imitrl.data.buffer import DemonstrationBuffer
from imitrl.learners.actor_critic import ActorCritic

__all__ = ["AIRLConfig", "airl"]


def airl(
    env: EnvBase,
    learner: ActorCritic,
    demonstrations: DemonstrationBuffer,
    config: AIRLConfig = AIRLConfig(),
    *,
    progress: bool = False,
    logger: Logger | None = None,
    on_round: Callable[[int, ActorCritic, int], dict | None] | None = None,
) -> tuple[AdversarialResult, AIRLDiscriminator]:
    """Train ``learner`` by AIRL (arguments as in
    :func:`~imitrl.algorithms.adversarial.loop.train_adversarial`); returns the result and
    the discriminator (``discriminator.network.g``: the recovered state-only reward)."""
    if not isinstance(config, AIRLConfig):
        raise ValueError(f"airl takes an AIRLConfig, got {type(config).__name__}")
    if not isinstance(learner, ActorCritic):
        raise ValueError(f"airl trains an ActorCritic, got {type(learner).__name__}")
    check_inputs(env, learner, demonstrations)  # before the discriminator reads the learner
    discriminator = AIRLDiscriminator(
        learner,
        gamma=config.gamma,
        hidden=config.discriminator_hidden,
        lr=config.discriminator_lr,
        grad_penalty=config.grad_penalty,
        seed=config.seed,
        entropy_weight=config.entropy_weight,
    )
    result = train_adversarial(
        env, learner, demonstrations, discriminator, config,
        name="airl", progress=progress, logger=logger, on_round=on_round,
    )  # fmt: skip
    return result, discriminator
