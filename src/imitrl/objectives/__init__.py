"""Imitation objectives as TorchRL loss modules, and the registry that names them."""

from imitrl.objectives import registry
from imitrl.objectives.advantage_weighted import AdvantageWeightedLoss
from imitrl.objectives.bc import LOSS_TYPES, BehaviorCloningLoss
from imitrl.objectives.diffusion import DiffusionBehaviorCloningLoss, DiffusionPolicy
from imitrl.objectives.regularized import RegularizedBCLoss
from imitrl.objectives.weighted import policy_step

__all__ = [
    "LOSS_TYPES",
    "AdvantageWeightedLoss",
    "BehaviorCloningLoss",
    "DiffusionBehaviorCloningLoss",
    "DiffusionPolicy",
    "RegularizedBCLoss",
    "policy_step",
    "registry",
]
