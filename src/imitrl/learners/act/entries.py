"""The registry's ``act``: ACT (TorchRL's ``ACTModel`` and ``ACTLoss``, sized for CPU) on
chunks of ``H``, temporal ensembling, its own batch :data:`ACT_BATCH` and rate
:data:`ACT_LR`."""

from __future__ import annotations

import torch
from torchrl.envs.utils import ExplorationType

from imitrl.learners.act.loss import ACTChunkLoss
from imitrl.learners.act.policy import ACTPolicy
from imitrl.learners.chunks import CHUNK_HORIZON, ENSEMBLE, chunked_learner
from imitrl.learners.learner import Learner
from imitrl.learners.registry import LearnerConfig
from imitrl.learners.task import TaskSpec

__all__ = ["ACT_BATCH", "ACT_LR", "act"]

ACT_BATCH = 128
"""ACT's minibatch in a benchmark protocol: smaller than the MLPs' (its paper trains on
8); a transformer step at 256 rows costs about ten MLP steps on two cores"""
ACT_LR = 3e-3
"""ACT's Adam learning rate (its own recipe, not ``LearnerConfig.lr``: the transformer
diverged on some seeds at the MLPs' 1e-2 on the two-way task)"""


def act(task: TaskSpec, config: LearnerConfig) -> Learner:
    """``act``: the CVAE over chunks, acting with ``z = 0`` and temporal ensembling."""
    if task.observation_dim is None:
        raise ValueError("ACT needs vector observations")
    policy = ACTPolicy(
        task.observation_dim,
        task.action,
        horizon=CHUNK_HORIZON,
        normalize=config.normalize,
        seed=config.seed,
    )
    loss = ACTChunkLoss(policy, seed=config.seed)
    opt = torch.optim.Adam(policy.parameters(), lr=ACT_LR)
    det = ExplorationType.DETERMINISTIC
    return chunked_learner(
        task, policy, loss, opt, ENSEMBLE, exploration=det, normalizer=policy.normalizer
    )
