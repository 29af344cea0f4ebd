"""The keys adversarial imitation adds to :mod:`imitrl.keys` (named once, here).

===================== =====================================================================
``ACTION_FEATURES``   float ``[..., k]`` action the discriminator reads: one-hot for discrete
                      actions (GAILLoss interpolates actions for its gradient penalty, so
                      they must be float), the action itself for continuous ones; zeros
                      at the absorbing state
``STATE_FEATURES``    float ``[..., d + 1]`` state the discriminators read: the normalised
                      observation and a last entry 0, or ``[0, ..., 0, 1]`` at the
                      absorbing state (:mod:`~imitrl.algorithms.adversarial.absorbing`)
``ABSORBING``         bool ``[..., 1]`` on a transition: its state is the absorbing state
                      (its observation and action are placeholders, zeros); under
                      ``"next"``: its next state is (the episode terminated there)
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
STATE_FEATURES = "state_features"
ABSORBING = "absorbing"
POLICY = "policy"
DISCRIMINATOR_LOGIT = "discriminator_logit"
EXPERT_PROBABILITY = "expert_probability"
LEARNED_REWARD = "learned_reward"

__all__ = [
    "ABSORBING",
    "ACTION_FEATURES",
    "DISCRIMINATOR_LOGIT",
    "EXPERT_PROBABILITY",
    "LEARNED_REWARD",
    "POLICY",
    "STATE_FEATURES",
]
