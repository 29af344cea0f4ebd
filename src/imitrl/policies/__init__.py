"""Policies as TensorDict modules: heads and networks, experts, the DAgger mixture, chunk
execution. What trains them (a loss and an optimizer) is a learner: :mod:`imitrl.learners`."""

from imitrl.policies.distributions import GreedyCategorical
from imitrl.policies.experts import Expert, TableLookup, as_actor
from imitrl.policies.heads import HEAD_LOSSES, HEADS
from imitrl.policies.mixture import BetaMixer, behaviour_policy
from imitrl.policies.normalization import ObservationNormalizer

__all__ = [
    "HEADS",
    "HEAD_LOSSES",
    "BetaMixer",
    "Expert",
    "GreedyCategorical",
    "ObservationNormalizer",
    "TableLookup",
    "as_actor",
    "behaviour_policy",
]
