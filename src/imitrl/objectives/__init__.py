"""Imitation objectives as TorchRL loss modules over any policy: behaviour cloning's
likelihood and regression losses, their weighted and regularized forms, chunk losses.

A policy family's own loss (Diffusion Policy's, ACT's, flow matching's) lives in its
folder under :mod:`imitrl.learners`; the loss registry
(:mod:`imitrl.learners.registry`) names every objective.
"""

from imitrl.objectives.advantage_weighted import AdvantageWeightedLoss
from imitrl.objectives.base import ImitationLoss, SummedLoss, sum_losses
from imitrl.objectives.bc import LOSS_TYPES, BehaviorCloningLoss
from imitrl.objectives.regularized import RegularizedBCLoss

__all__ = [
    "LOSS_TYPES",
    "AdvantageWeightedLoss",
    "BehaviorCloningLoss",
    "ImitationLoss",
    "RegularizedBCLoss",
    "SummedLoss",
    "sum_losses",
]
