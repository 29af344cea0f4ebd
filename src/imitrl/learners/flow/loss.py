"""Conditional flow matching (rectified flow) on a :class:`~imitrl.learners.flow.policy.FlowPolicy`'s actions or chunks."""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase

from imitrl.learners.action_loss import NormalizedActionLoss
from imitrl.learners.flow.policy import FlowPolicy
from imitrl.system.ranks import rows_drawn

__all__ = ["FlowMatchingLoss"]


class FlowMatchingLoss(NormalizedActionLoss):
    """The conditional flow-matching loss of a :class:`FlowPolicy` (module docstring).

    Args:
        policy: the flow policy trained.
        chunked: labels are chunks ``[N, H, m]`` under ``EXPERT_CHUNK`` with the padding
            mask ``[N, H]`` under ``CHUNK_PAD`` (:func:`imitrl.data.chunks.add_chunk_labels`);
            False: actions ``[N, m]`` under ``EXPERT_ACTION``.
        seed: seed of the loss's draws (``x_0`` and ``t``).

    Keys (``set_keys``): ``observation``, ``label``, ``pad``. Returns ``loss_flow``.
    """

    out_keys = ["loss_flow"]
    what = "flow labels"

    def __init__(self, policy: FlowPolicy, *, chunked: bool = False, seed: int = 0) -> None:
        if not isinstance(policy, FlowPolicy):
            raise ValueError(f"expected a FlowPolicy, got {type(policy).__name__}")
        super().__init__(policy, chunked=chunked, seed=seed)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs = tensordict.get(self.tensor_keys.observation)
        x1 = self.labels(tensordict)
        n, d = x1.shape
        g = self.generator  # CPU draws (any device), per row: imitrl.system.ranks.rows_drawn
        x0 = rows_drawn(lambda m: torch.randn(m, d, generator=g), n).to(x1.device)
        t = rows_drawn(lambda m: torch.rand(m, 1, generator=g), n).to(x1.device)
        v = self.policy.velocity((1 - t) * x0 + t * x1, obs, t)
        err = (v - (x1 - x0)) ** 2  # [N, d]
        return TensorDict({"loss_flow": self.mean_error(err, tensordict)}, batch_size=[])
