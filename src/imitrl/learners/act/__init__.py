"""ACT (Zhao et al. 2023): TorchRL's ``ACTModel`` and ``ACTLoss`` kept to imitrl's contracts
(:mod:`~imitrl.learners.act.policy`, :mod:`~imitrl.learners.act.loss`) and the registry's
``act`` entry (:mod:`~imitrl.learners.act.entries`)."""

from imitrl.learners.act.loss import ACTChunkLoss
from imitrl.learners.act.policy import ACTPolicy

__all__ = ["ACTChunkLoss", "ACTPolicy"]
