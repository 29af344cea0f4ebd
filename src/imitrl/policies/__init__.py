"""Policies as TensorDict modules: the learner contract, ActorCritic, experts, the DAgger mixture."""

from imitrl.policies.actor_critic import HEAD_LOSSES, HEADS, ActorCritic
from imitrl.policies.distributions import GreedyCategorical
from imitrl.policies.experts import Expert, TableLookup, as_actor
from imitrl.policies.learner import Learner
from imitrl.policies.mixture import BetaMixer, behaviour_policy
from imitrl.policies.normalization import ObservationNormalizer

__all__ = [
    "HEADS",
    "HEAD_LOSSES",
    "ActorCritic",
    "BetaMixer",
    "Expert",
    "GreedyCategorical",
    "Learner",
    "ObservationNormalizer",
    "TableLookup",
    "as_actor",
    "behaviour_policy",
]
