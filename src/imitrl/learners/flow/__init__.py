"""Flow matching (rectified flow): the policy (:mod:`~imitrl.learners.flow.policy`), its
loss (:mod:`~imitrl.learners.flow.loss`) and the registry's ``flow`` and ``flow_chunk``
entries (:mod:`~imitrl.learners.flow.entries`)."""

from imitrl.learners.flow.loss import FlowMatchingLoss
from imitrl.learners.flow.policy import FlowPolicy

__all__ = ["FlowMatchingLoss", "FlowPolicy"]
