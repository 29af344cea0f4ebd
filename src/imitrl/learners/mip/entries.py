"""The registry's MIP learners: ``mip`` (one action) and ``mip_chunk`` (masked chunks
of :data:`~imitrl.learners.chunks.CHUNK_HORIZON`, executed on a receding horizon)."""

from __future__ import annotations

import torch
from torchrl.envs.utils import ExplorationType

from imitrl.learners.chunks import RECEDING, chunk_task, chunked_learner
from imitrl.learners.learner import Learner
from imitrl.learners.mip.policy import MIPLoss, MIPPolicy
from imitrl.learners.registry import LearnerConfig
from imitrl.learners.task import TaskSpec

__all__ = ["mip", "mip_chunk"]


def _policy(task: TaskSpec, action, config: LearnerConfig) -> MIPPolicy:
    if task.observation_dim is None:
        raise ValueError("a MIP policy needs vector observations")
    return MIPPolicy(task.observation_dim, action, hidden=config.width,
                     normalize=config.normalize, seed=config.seed)  # fmt: skip


def mip(task: TaskSpec, config: LearnerConfig) -> Learner:
    """``mip``: the minimal iterative policy over one action (deterministic)."""
    policy = _policy(task, task.action, config)
    assert config.lr is not None  # registry.make resolved it
    return Learner(
        policy,
        MIPLoss(policy, seed=config.seed),
        torch.optim.Adam(policy.parameters(), lr=config.lr),
        exploration=ExplorationType.DETERMINISTIC,
        normalizer=policy.normalizer,
    )


def mip_chunk(task: TaskSpec, config: LearnerConfig) -> Learner:
    """``mip_chunk``: MIP over masked chunks, executed on a receding horizon."""
    policy = _policy(task, chunk_task(task).action, config)
    assert config.lr is not None  # registry.make resolved it
    opt = torch.optim.Adam(policy.parameters(), lr=config.lr)
    return chunked_learner(
        task, policy, MIPLoss(policy, chunked=True, seed=config.seed), opt, RECEDING,
        exploration=ExplorationType.DETERMINISTIC, normalizer=policy.normalizer,
    )  # fmt: skip
