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
``loop``                     collect -> discriminate -> reinforce, and its results
(the configs)                ``imitrl.configs.adversarial`` (no torch: the CLI extends them)
``gail`` / ``airl``          the two algorithms: a config and one function each
============================ ===============================================================
"""

from imitrl.algorithms.adversarial.airl import airl
from imitrl.algorithms.adversarial.airl_discriminator import (
    AIRLDiscriminator,
    airl_reward,
    shaped_f,
)
from imitrl.algorithms.adversarial.gail import gail
from imitrl.algorithms.adversarial.gail_discriminator import GAILDiscriminator, gail_reward
from imitrl.algorithms.adversarial.loop import (
    AdversarialResult,
    RoundRecord,
    train_adversarial,
)
from imitrl.configs.adversarial import (
    ADVERSARIAL_LR,
    AdversarialConfig,
    AIRLConfig,
    GAILConfig,
)

__all__ = [
    "ADVERSARIAL_LR",
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
