"""Adversarial imitation on neural policies through TorchRL: GAIL and AIRL.

============================ ===============================================================
module                       holds
============================ ===============================================================
``keys``                     the keys this package adds (action features, learned reward)
``transitions``              ``(s, a, s', terminated)`` from demonstrations and rollouts
``absorbing``                DAC's absorbing state: terminated episodes vs the living bias
``gail_discriminator``       ``D(s, a)`` on TorchRL's ``GAILLoss``; reward ``-log(1 - D)``
``airl_discriminator``       ``D = sigmoid(f - log pi)``, ``f = g(s) + gamma h(s') - h(s)``
``generator``                PPO (``ClipPPOLoss`` + ``GAE``) on the learner, and why PPO
``loop``                     collect -> discriminate -> reinforce; config and results
``gail`` / ``airl``          the two algorithms: a config and one function each
============================ ===============================================================
"""

from imitrl.algorithms.adversarial.airl import AIRLConfig, airl
from imitrl.algorithms.adversarial.airl_discriminator import (
    AIRLDiscriminator,
    airl_reward,
    shaped_f,
)
from imitrl.algorithms.adversarial.gail import GAILConfig, gail
from imitrl.algorithms.adversarial.gail_discriminator import GAILDiscriminator, gail_reward
from imitrl.algorithms.adversarial.loop import (
    AdversarialConfig,
    AdversarialResult,
    RoundRecord,
    train_adversarial,
)

__all__ = [
    "AIRLConfig",
    "AIRLDiscriminator",
    "AdversarialConfig",
    "AdversarialResult",
    "GAILConfig",
    "GAILDiscriminator",
    "RoundRecord",
    "airl",
    "airl_reward",
    "gail",
    "gail_reward",
    "shaped_f",
    "train_adversarial",
]
