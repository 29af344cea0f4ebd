"""What the flow-matching and MIP losses share: labels read as one action or a masked
chunk, mapped to the policy's ``[-1, 1]``, and per-entry errors averaged over what is not
padding.

A policy over a bounded action (or the tiled spec of a chunk, ``[H * m]``) that has
``normalize(action) -> [-1, 1]`` and the bounds ``low``/``high`` is trained on labels
``[N, d]`` under ``EXPERT_ACTION``, or, ``chunked``, on chunks ``[N, H, m]`` under
``EXPERT_CHUNK`` with the mask ``[N, H]`` under ``CHUNK_PAD``
(:func:`imitrl.data.chunks.add_chunk_labels`): a padded entry's error carries no weight,
and the mean is over the global batch on data-parallel ranks
(:func:`~imitrl.system.ranks.masked_mean`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey

from imitrl import keys
from imitrl.objectives.base import ImitationLoss
from imitrl.rng import SavedGenerator
from imitrl.system.ranks import masked_mean

__all__ = ["NormalizedActionLoss"]


class NormalizedActionLoss(SavedGenerator, ImitationLoss):
    """Base of a loss over a policy's normalised actions or chunks (module docstring).

    Args:
        policy: the policy trained (``normalize``, ``low``, ``high``).
        chunked: chunk labels with their padding mask; False: one action per row.
        seed: seed of the loss's own draws (``self.generator``).

    Keys (``set_keys``): ``observation``, ``label``, ``pad``.
    """

    @dataclass
    class _AcceptedKeys:
        observation: NestedKey = keys.OBSERVATION
        label: NestedKey = keys.EXPERT_ACTION
        pad: NestedKey | None = None

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    what = "the labels"
    """how a message names the labels (``"flow labels"``)"""

    def __init__(self, policy, *, chunked: bool = False, seed: int = 0) -> None:
        super().__init__()
        self.policy = policy
        if chunked:
            from imitrl.data.chunks import CHUNK_PAD, EXPERT_CHUNK

            self.set_keys(label=EXPERT_CHUNK, pad=CHUNK_PAD)
        self.generator = torch.Generator().manual_seed(int(seed))

    def labels(self, tensordict: TensorDictBase) -> torch.Tensor:
        """The rows' labels ``[N, d]`` in ``[-1, 1]`` (ValueError naming the key unless
        they are float with ``d`` entries per row)."""
        label = tensordict.get(self.tensor_keys.label)
        n, d = label.shape[0], self.policy.low.shape[0]
        if not label.dtype.is_floating_point or label[0].numel() != d:
            raise ValueError(
                f"{self.what} under {self.tensor_keys.label!r} must be float with {d} entries "
                f"per row, got {label.dtype} {tuple(label.shape)}"
            )
        return self.policy.normalize(label.reshape(n, d))

    def mean_error(self, err: torch.Tensor, tensordict: TensorDictBase) -> torch.Tensor:
        """The mean of per-entry errors ``[N, d]``; chunked, over the entries that are not
        padding (``[N, H]`` -> ``[N, H * m]``)."""
        if self.tensor_keys.pad is None:
            return err.mean()
        keep = (~tensordict.get(self.tensor_keys.pad)).float()
        keep = keep.repeat_interleave(err.shape[-1] // keep.shape[-1], dim=-1)
        return masked_mean(err, keep)  # over the global batch (data-parallel)
