"""Losses over action chunks: a network predicts ``H`` actions, flat ``[N, H * m]``.

The labels are the expert's next ``H`` actions and their padding mask,
``EXPERT_CHUNK`` ``[N, H, m]`` and ``CHUNK_PAD`` ``[N, H]``
(:func:`imitrl.data.chunks.add_chunk_labels`). Two ways to train on them:

* :class:`ChunkRegressionLoss` (``mse``, ``l1``, ``smooth_l1``): the per-entry error of
  the predicted chunk, averaged over the entries that are not padding;
* :class:`FlatChunkLoss`: any loss over the flat action (a tanh-normal NLL, TorchRL's
  diffusion loss) reads the flattened chunk as its label. These losses have no mask:
  the padded entries hold the episode's last label (``ActionChunkTransform``'s
  padding), so the learner is also taught to hold that action past the end.

:class:`~imitrl.learners.flow.FlowMatchingLoss` takes chunks itself, with the mask.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey

from imitrl import keys
from imitrl.data.chunks import CHUNK_PAD, EXPERT_CHUNK
from imitrl.objectives.base import ImitationLoss, sum_losses
from imitrl.system.ranks import masked_mean

__all__ = ["FLAT_CHUNK", "ChunkRegressionLoss", "FlatChunkLoss"]

FLAT_CHUNK = "expert_action_chunk_flat"
"""``[N, H * m]`` the chunk label flattened, where a :class:`FlatChunkLoss`'s inner loss reads it"""

_ERRORS = {"mse": F.mse_loss, "l1": F.l1_loss, "smooth_l1": F.smooth_l1_loss}


def _chunk(tensordict: TensorDictBase, d: int) -> torch.Tensor:
    label = tensordict.get(EXPERT_CHUNK)
    if not label.dtype.is_floating_point or label[0].numel() != d:
        raise ValueError(
            f"chunk labels under {EXPERT_CHUNK!r} must be float [N, H, m] with H * m = {d}, "
            f"got {label.dtype} {tuple(label.shape)}"
        )
    return label.reshape(label.shape[0], d)


class ChunkRegressionLoss(ImitationLoss):
    """``sum_{i,h,j} keep[i,h] err(pred[i,h,j], a*[i,h,j]) / sum_{i,h,j} keep[i,h]``.

    Args:
        network: writes the flat chunk under ``ACTION`` ``[N, H * m]``.
        horizon: ``H``.
        loss_type: ``mse``, ``l1`` or ``smooth_l1`` (Huber, delta 1).

    Reads ``EXPERT_CHUNK`` and ``CHUNK_PAD`` (``keep = ~pad``). Returns ``loss_chunk``
    and the detached error over every entry, padding included, under ``loss_type``.
    """

    def __init__(self, network: TensorDictModuleBase, *, horizon: int, loss_type: str) -> None:
        if loss_type not in _ERRORS:
            raise ValueError(f"loss_type must be one of {tuple(_ERRORS)}, got {loss_type!r}")
        super().__init__()
        self.network = network
        self.horizon = int(horizon)
        self.loss_type = loss_type

    @property
    def label_key(self) -> NestedKey:
        return EXPERT_CHUNK

    def read_keys(self) -> list[NestedKey]:
        return [*self.network.in_keys, EXPERT_CHUNK, CHUNK_PAD]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        pred = self.network(tensordict.select(*self.network.in_keys)).get(keys.ACTION)
        label = _chunk(tensordict, pred.shape[-1])
        err = _ERRORS[self.loss_type](pred, label.to(pred.dtype), reduction="none")
        keep = (~tensordict.get(CHUNK_PAD)).to(err.dtype)
        keep = keep.repeat_interleave(err.shape[-1] // self.horizon, dim=-1)
        loss = masked_mean(err, keep)  # over the global batch (data-parallel)
        return TensorDict({"loss_chunk": loss, self.loss_type: err.detach().mean()}, [])


class FlatChunkLoss(ImitationLoss):
    """Any loss whose label key is :data:`FLAT_CHUNK`, fed the flattened ``EXPERT_CHUNK``.

    Args:
        inner: the loss over the flat action ``[N, H * m]``, its label key set to
            ``FLAT_CHUNK`` (``set_keys(label=FLAT_CHUNK)``).
        dim: ``H * m``.
    """

    def __init__(self, inner: ImitationLoss, *, dim: int) -> None:
        if inner.label_key != FLAT_CHUNK:
            raise ValueError(
                f"the inner loss must read its label under {FLAT_CHUNK!r}, not {inner.label_key!r}"
            )
        super().__init__()
        self.inner = inner
        self.dim = int(dim)

    @property
    def label_key(self) -> NestedKey:
        return EXPERT_CHUNK

    def read_keys(self) -> list[NestedKey]:
        return [*(k for k in self.inner.in_keys if k != FLAT_CHUNK), EXPERT_CHUNK]

    def _flat(self, tensordict: TensorDictBase) -> TensorDictBase:
        td = tensordict.select(*(k for k in self.inner.in_keys if k != FLAT_CHUNK))
        td.set(FLAT_CHUNK, _chunk(tensordict, self.dim))
        return td

    def check_labels(self, rows: TensorDictBase) -> None:
        super().check_labels(rows)
        self.inner.check_labels(self._flat(rows))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self.inner(self._flat(tensordict))

    def objective(self, batch: TensorDictBase, weights: torch.Tensor | None = None) -> torch.Tensor:
        if weights is not None:
            raise ValueError("FlatChunkLoss does not take per-row weights")
        return sum_losses(self(batch))
