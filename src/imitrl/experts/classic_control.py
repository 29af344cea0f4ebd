"""Queryable experts for gymnasium's classic-control tasks, as TensorDict modules.

Each expert is a batched function of the observation (no simulator access), so
DAgger can ask it about any state the learner visits.
"""

from __future__ import annotations

import torch

from imitrl import keys
from imitrl.policies.experts import Expert

__all__ = ["CARTPOLE_GAINS", "cartpole_expert"]

CARTPOLE_GAINS = (0.5, 1.0, 10.0, 2.0)
"""state-feedback gains on (x, x_dot, theta, theta_dot): push right when K . obs > 0"""


def cartpole_expert(*, observation_key=keys.OBSERVATION, gains=CARTPOLE_GAINS) -> Expert:
    """CartPole-v1: linear state feedback, ``a = 1[K . obs > 0]`` (500/500 from any reset).

    Observations ``[..., 4]`` float; writes int64 ``EXPERT_ACTION`` ``[...]``.
    """
    K = torch.tensor(gains, dtype=torch.float32)

    def act(obs: torch.Tensor) -> torch.Tensor:
        if obs.shape[-1:] != (4,):
            raise ValueError(f"CartPole observations have 4 entries, got shape {tuple(obs.shape)}")
        return ((obs.to(torch.float32) * K).sum(-1) > 0).long()

    return Expert.from_callable(act, observation_key=observation_key)
