"""The keys adversarial imitation adds to :mod:`imitrl.keys` (named once, here).

===================== =====================================================================
``ACTION_FEATURES``   float ``[..., k]`` action the discriminator reads: one-hot for discrete
                      actions (GAILLoss interpolates actions for its gradient penalty, so
                      they must be float), the action itself for continuous ones
``POLICY``            group of the policy's side of a discriminator batch (GAILLoss's
                      "collector" observations and actions live under it)
``DISCRIMINATOR_LOGIT`` float ``[..., 1]`` logit of ``D(s, a)`` = P(expert)
``EXPERT_PROBABILITY`` float ``[..., 1]`` ``D = sigmoid(logit)``, what GAILLoss's BCE reads
``LEARNED_REWARD``    float ``[..., 1]`` under ``"next"``: the discriminator's reward that the
                      generator's PPO/GAE reads (the env's ``("next", "reward")`` is kept
                      beside it, untouched)
===================== =====================================================================
"""

from __future__ import annotations

ACTION_FEATURES = "action_features"
POLICY = "policy"
DISCRIMINATOR_LOGIT = "discriminator_logit"
EXPERT_PROBABILITY = "expert_probability"
LEARNED_REWARD = "learned_reward"

__all__ = [
    "ACTION_FEATURES",
    "DISCRIMINATOR_LOGIT",
    "EXPERT_PROBABILITY",
    "LEARNED_REWARD",
    "POLICY",
]
