"""Tabular policies as tensors: the deterministic table ``pi[s]`` or rows ``pi[s, a]``.

Every exact routine accepts either form; :func:`policy_probs` turns both into
probability rows after checking them.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from imitrl.tabular.mdp import TabularMDP
from imitrl.tabular.validation import ROW_TOL

__all__ = ["kernel_under", "policy_probs", "reward_under"]


def policy_probs(pi: Any, num_states: int, num_actions: int) -> torch.Tensor:
    """``[S, A]`` float64 action probabilities of a tabular policy.

    Args:
        pi: ``[S]`` integer actions (deterministic) or ``[S, A]`` probabilities.

    Raises:
        ValueError: wrong shape or dtype, an action outside ``[0, A)``, negative or
            non-finite probabilities, rows not summing to 1.
    """
    t = torch.as_tensor(np.asarray(pi) if not isinstance(pi, torch.Tensor) else pi)
    if t.shape == (num_states,):
        if t.dtype.is_floating_point or t.dtype == torch.bool:
            raise ValueError(
                f"a deterministic policy table must hold integer actions, got dtype {t.dtype}"
            )
        if (t < 0).any() or (t >= num_actions).any():
            bad = int(torch.nonzero((t < 0) | (t >= num_actions))[0])
            raise ValueError(
                f"policy table action {int(t[bad])} at state {bad} is outside [0, {num_actions})"
            )
        return torch.nn.functional.one_hot(t.long(), num_actions).to(torch.float64)
    if t.shape == (num_states, num_actions):
        t = t.to(torch.float64)
        if not torch.isfinite(t).all() or (t < 0).any():
            raise ValueError("policy probabilities must be finite and non-negative")
        dev = (t.sum(-1) - 1).abs()
        if (dev > ROW_TOL).any():
            s = int(torch.argmax(dev))
            raise ValueError(
                f"policy probabilities at state {s} sum to {float(t[s].sum()):.12g}, not 1"
            )
        return t
    raise ValueError(
        f"a tabular policy must have shape [{num_states}] (actions) or "
        f"[{num_states}, {num_actions}] (probabilities), got {tuple(t.shape)}"
    )


def kernel_under(mdp: TabularMDP, pi: Any) -> torch.Tensor:
    """``P_pi[s, s'] = sum_a pi(a|s) P[s, a, s']``, shape ``[S, S]``."""
    probs = policy_probs(pi, mdp.num_states, mdp.num_actions)
    return torch.einsum("sa,sat->st", probs, mdp.P)


def reward_under(mdp: TabularMDP, pi: Any) -> torch.Tensor:
    """``r_pi[s] = sum_a pi(a|s) r[s, a]``, shape ``[S]``."""
    probs = policy_probs(pi, mdp.num_states, mdp.num_actions)
    return (probs * mdp.r).sum(-1)
