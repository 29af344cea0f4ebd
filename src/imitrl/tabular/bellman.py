"""The Bellman backup on dense arrays, below :class:`TabularMDP` in the import order.

``TabularMDP.backup`` and :mod:`imitrl.tabular.dp` both call it, so the MDP never
imports the dynamic-programming module that imports it.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

__all__ = ["backup_arrays", "backup_dense"]


def backup_arrays(r: np.ndarray, gamma_P: np.ndarray, V: np.ndarray) -> np.ndarray:
    """``Q = r + (gamma P) @ V``: ``r`` ``[S, A]``, ``gamma_P`` ``[S, A, S]``, ``V`` ``[S]`` -> ``[S, A]``."""
    # numpy, and (gamma P) @ V in that order: the float64 rounding of the textbook
    # reference ``r + gamma * P @ V``. Q values that tie mathematically (mirror-image
    # moves on a symmetric map) then tie, or fail to, exactly as they do there, so the
    # greedy policy (ties to the lowest action) is the same policy on every map.
    return r + gamma_P @ V


def backup_dense(P: torch.Tensor, r: torch.Tensor, gamma: float, V: Any) -> torch.Tensor:
    """Bellman backup ``Q[s, a] = r[s, a] + gamma * sum_s' P[s, a, s'] V[s']``.

    Args:
        P: ``[S, A, S]`` float64 kernel.
        r: ``[S, A]`` float64 expected reward.
        gamma: discount.
        V: ``[S]`` state values.

    Returns:
        ``[S, A]`` float64 action values.
    """
    num_states = int(P.shape[0])
    V = torch.as_tensor(V, dtype=torch.float64)
    if V.shape != (num_states,):
        raise ValueError(f"V must have shape [{num_states}], got {tuple(V.shape)}")
    return torch.from_numpy(backup_arrays(r.numpy(), gamma * P.numpy(), V.numpy()))
