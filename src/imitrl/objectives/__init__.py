"""Imitation objectives as TorchRL loss modules, and the registry that names them.

``imitrl.objectives.registry`` (imported on first use: it builds learners, which
import these losses) names every objective.
"""

from imitrl.objectives.advantage_weighted import AdvantageWeightedLoss
from imitrl.objectives.base import ImitationLoss, SummedLoss, sum_losses
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
    "ImitationLoss",
    "RegularizedBCLoss",
    "SummedLoss",
    "policy_step",
    "registry",
    "sum_losses",
]


def __getattr__(name: str):
    if name == "registry":
        import importlib

        return importlib.import_module("imitrl.objectives.registry")
    raise AttributeError(f"module 'imitrl.objectives' has no attribute {name!r}")
