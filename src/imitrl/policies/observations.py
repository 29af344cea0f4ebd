"""The array boundary of a learner of states or vectors: what a caller hands ``act`` & co.

:func:`read_observations` turns a tensor, numpy array, Python number or list into the
tensor the policy reads, validated against the learner's observation space, and says
what kind of input it was, so the learner answers in kind (tensors in, tensors out;
numpy or scalars in, numpy or Python values out). Pixel learners read through
:meth:`imitrl.policies.pixel_learner.PixelInputs.read` instead.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

__all__ = ["read_observations"]


def read_observations(
    obs: Any, *, num_states: int | None, shape: tuple[int, ...] | None
) -> tuple[torch.Tensor, str]:
    """``(tensor, kind)`` of observations for a learner of ``num_states`` integer states
    (int64 ``[*B]`` in range) or of vectors of trailing ``shape`` (finite float32
    ``[*B, *shape]``); ``kind`` is ``"tensor"``, ``"numpy"`` or ``"scalar"``."""
    if isinstance(obs, torch.Tensor):
        kind, t = "tensor", obs
    elif isinstance(obs, np.ndarray):
        kind, t = "numpy", torch.from_numpy(obs)
    elif isinstance(obs, (int, float, np.integer, np.floating, list, tuple)):
        kind, t = ("scalar" if np.ndim(obs) == 0 else "numpy"), torch.as_tensor(np.asarray(obs))
    else:
        raise ValueError(
            f"observations must be a tensor, numpy array or number, got {type(obs).__name__}"
        )
    if num_states is not None:
        if t.dtype.is_floating_point or t.dtype == torch.bool:
            raise ValueError(f"this policy expects integer state observations, got dtype {t.dtype}")
        t = t.long()
        if t.numel() and (int(t.min()) < 0 or int(t.max()) >= num_states):
            raise ValueError(f"state observation outside [0, {num_states})")
        return t, kind
    assert shape is not None  # a learner reads integer states or vectors of a shape
    if t.shape[-1:] != shape[-1:]:
        raise ValueError(
            f"this policy expects observations of trailing shape {shape}, "
            f"got shape {tuple(t.shape)}"
        )
    t = t.to(torch.float32)
    if not torch.isfinite(t).all():
        raise ValueError("NaN or inf in observations given to the policy")
    return t, kind
