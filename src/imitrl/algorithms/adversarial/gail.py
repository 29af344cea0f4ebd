"""GAIL (Ho & Ermon 2016): PPO on the reward ``-log(1 - D(s, a))`` of a discriminator that
tells the expert's (observation, action) pairs from the policy's.

``gail(env, learner, demonstrations, GAILConfig(...))`` trains ``learner`` in place: the
discriminator is :class:`~imitrl.algorithms.adversarial.gail_discriminator.GAILDiscriminator`
(TorchRL's ``GAILLoss``, gradient penalty ``config.grad_penalty``), the loop and the
generator are :mod:`~imitrl.algorithms.adversarial.loop`'s.

Example (CartPole from one demonstration episode)::

    env = make_env("CartPole-v1", seed=0)
    buffer = DemonstrationBuffer(action_spec=env.action_spec_unbatched)
    buffer.extend(rollout_episodes(env, cartpole_expert(), 1))
    learner = build("default", env, lr=ADVERSARIAL_LR, value=True)  # a value head for PPO
    result = gail(env, learner, buffer, GAILConfig(total_steps=50_000))
    evaluate(env, learner, 20, seed=1)
"""

from __future__ import annotations

from collections.abc import Callable

from torchrl.envs import EnvBase
from torchrl.record.loggers import Logger

from imitrl.algorithms.adversarial.gail_discriminator import GAILDiscriminator
from imitrl.algorithms.adversarial.loop import (
    AdversarialResult,
    check_inputs,
    train_adversarial,
)
from imitrl.configs.adversarial import GAILConfig
from imitrl.data.buffer import DemonstrationBuffer
from imitrl.learners.actor_critic import ActorCritic

__all__ = ["GAILConfig", "gail"]


def gail(
    env: EnvBase,
    learner: ActorCritic,
    demonstrations: DemonstrationBuffer,
    config: GAILConfig = GAILConfig(),
    *,
    progress: bool = False,
    logger: Logger | None = None,
    on_round: Callable[[int, ActorCritic, int], dict | None] | None = None,
) -> AdversarialResult:
    """Train ``learner`` by GAIL on ``env`` from ``demonstrations`` (arguments as in
    :func:`~imitrl.algorithms.adversarial.loop.train_adversarial`)."""
    if not isinstance(config, GAILConfig):
        raise ValueError(f"gail takes a GAILConfig, got {type(config).__name__}")
    if not isinstance(learner, ActorCritic):
        raise ValueError(f"gail trains an ActorCritic, got {type(learner).__name__}")
    check_inputs(env, learner, demonstrations)  # before the discriminator reads the learner
    discriminator = GAILDiscriminator(
        learner,
        hidden=config.discriminator_hidden,
        lr=config.discriminator_lr,
        grad_penalty=config.grad_penalty,
        seed=config.seed,
    )
    return train_adversarial(
        env, learner, demonstrations, discriminator, config,
        name="gail", progress=progress, logger=logger, on_round=on_round,
    )  # fmt: skip
