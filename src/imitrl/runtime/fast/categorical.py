"""A categorical policy's draw and log-probability without building its distribution.

Accelerated internals of :mod:`imitrl.runtime.paths` (import them from there, nowhere else).

Building ``GreedyCategorical(logits)`` (torch's ``Categorical``: the logits normalised,
the shapes worked out, a lazy ``probs``) costs more than what a rollout's draw or a PPO
step's log-probability computes from it on 8 lanes or 256 rows. These functions run the
distribution's own operations on the same tensors, in its order:

* ``Categorical.__init__``: ``logits - logits.logsumexp(-1, keepdim=True)``;
* ``sample()``: ``torch.multinomial`` of ``softmax(logits)`` (its ``probs``) flattened to
  two dimensions, one draw with replacement, transposed and reshaped to the batch: the
  same RNG draw;
* ``log_prob(a)``: the normalised logits gathered at ``a``, broadcast as it broadcasts.

The same bits and draws as the distribution (``tests/runtime/fast/test_ppo_step.py``; the rollout's
draw also through ``tests/runtime/test_paths.py``'s replay of every head). :func:`replays`
says which distributions this covers: exactly ``GreedyCategorical`` over ``logits``
(which never validates its arguments).
"""

from __future__ import annotations

import torch
from torch.nn import functional as F

from imitrl.policies.distributions import GreedyCategorical

__all__ = ["log_prob", "replays", "sample"]


def replays(dist_class, names: list[str], dist_kwargs: dict) -> bool:
    """Whether these functions compute this distribution's draws and log-probabilities."""
    return dist_class is GreedyCategorical and names == ["logits"] and not dist_kwargs


def _normalised(logits: torch.Tensor) -> torch.Tensor:
    return logits - logits.logsumexp(dim=-1, keepdim=True)


def sample(logits: torch.Tensor) -> torch.Tensor:
    """``GreedyCategorical(logits).sample()``."""
    probs = F.softmax(_normalised(logits), dim=-1)
    draws = torch.multinomial(probs.reshape(-1, logits.shape[-1]), 1, True).T
    return draws.reshape(logits.shape[:-1])


def log_prob(logits: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """``GreedyCategorical(logits).log_prob(action)``."""
    value, log_pmf = torch.broadcast_tensors(action.long().unsqueeze(-1), _normalised(logits))
    return log_pmf.gather(-1, value[..., :1]).squeeze(-1)
