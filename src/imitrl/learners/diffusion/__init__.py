"""The MLP diffusion baseline: TorchRL's ``DiffusionActor`` and ``DiffusionBCLoss`` kept to
imitrl's contracts (:mod:`~imitrl.learners.diffusion.policy`,
:mod:`~imitrl.learners.diffusion.loss`) and the registry's ``diffusion*`` entries
(:mod:`~imitrl.learners.diffusion.entries`)."""

from imitrl.learners.diffusion.loss import DiffusionBehaviorCloningLoss
from imitrl.learners.diffusion.policy import DiffusionPolicy

__all__ = ["DiffusionBehaviorCloningLoss", "DiffusionPolicy"]
