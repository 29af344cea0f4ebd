"""Conditional flow matching (rectified flow) on a :class:`~imitrl.learners.flow.policy.FlowPolicy`'s actions or chunks."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey

from imitrl import keys
from imitrl.learners.flow.policy import FlowPolicy
from imitrl.objectives.base import ImitationLoss
from imitrl.system.ranks import masked_mean, rows_drawn

__all__ = ["FlowMatchingLoss"]


class FlowMatchingLoss(ImitationLoss):
    """The conditional flow-matching loss of a :class:`FlowPolicy` (module docstring).

    Args:
        policy: the flow policy trained.
        chunked: labels are chunks ``[N, H, m]`` under ``EXPERT_CHUNK`` with the padding
            mask ``[N, H]`` under ``CHUNK_PAD`` (:func:`imitrl.data.chunks.add_chunk_labels`);
            False: actions ``[N, m]`` under ``EXPERT_ACTION``.
        seed: seed of the loss's draws (``x_0`` and ``t``).

    Keys (``set_keys``): ``observation``, ``label``, ``pad``. Returns ``loss_flow``.
    """

    @dataclass
    class _AcceptedKeys:
        observation: NestedKey = keys.OBSERVATION
        label: NestedKey = keys.EXPERT_ACTION
        pad: NestedKey | None = None

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    out_keys = ["loss_flow"]

    def __init__(self, policy: FlowPolicy, *, chunked: bool = False, seed: int = 0) -> None:
        if not isinstance(policy, FlowPolicy):
            raise ValueError(f"expected a FlowPolicy, got {type(policy).__name__}")
        super().__init__()
        self.policy = policy
        if chunked:
            from imitrl.data.chunks import CHUNK_PAD, EXPERT_CHUNK

            self.set_keys(label=EXPERT_CHUNK, pad=CHUNK_PAD)
        self.generator = torch.Generator().manual_seed(int(seed))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs = tensordict.get(self.tensor_keys.observation)
        label = tensordict.get(self.tensor_keys.label)
        n, d = label.shape[0], self.policy.low.shape[0]
        if not label.dtype.is_floating_point or label[0].numel() != d:
            raise ValueError(
                f"flow labels under {self.tensor_keys.label!r} must be float with {d} entries "
                f"per row, got {label.dtype} {tuple(label.shape)}"
            )
        x1 = self.policy.normalize(label.reshape(n, d))
        g = self.generator  # CPU draws (any device), per row: imitrl.system.ranks.rows_drawn
        x0 = rows_drawn(lambda m: torch.randn(m, d, generator=g), n).to(x1.device)
        t = rows_drawn(lambda m: torch.rand(m, 1, generator=g), n).to(x1.device)
        v = self.policy.velocity((1 - t) * x0 + t * x1, obs, t)
        err = (v - (x1 - x0)) ** 2  # [N, d]
        if self.tensor_keys.pad is None:
            loss = err.mean()
        else:  # [N, H] -> [N, H * m]: padded entries of a chunk carry no weight
            keep = (~tensordict.get(self.tensor_keys.pad)).float()
            keep = keep.repeat_interleave(d // keep.shape[-1], dim=-1)
            loss = masked_mean(err, keep)  # over the global batch (data-parallel)
        return TensorDict({"loss_flow": loss}, batch_size=[])
