"""The minimal iterative policy (MIP) of Pan et al. (2025): the policy and its loss
(:mod:`~imitrl.learners.mip.policy`) and the registry's ``mip`` and ``mip_chunk`` entries
(:mod:`~imitrl.learners.mip.entries`)."""

from imitrl.learners.mip.policy import MIPLoss, MIPPolicy

__all__ = ["MIPLoss", "MIPPolicy"]
