"""Imitation objectives as TorchRL loss modules."""

from imitrl.objectives.bc import LOSS_TYPES, BehaviorCloningLoss
from imitrl.objectives.weighted import policy_step

__all__ = ["LOSS_TYPES", "BehaviorCloningLoss", "policy_step"]
