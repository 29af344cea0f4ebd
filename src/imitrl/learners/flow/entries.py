"""The registry's flow-matching learners: ``flow`` (one action, :data:`FLOW_STEPS` Euler
steps) and ``flow_chunk`` (masked chunks, :data:`FLOW_CHUNK_STEPS` steps, the noise held
per episode)."""

from __future__ import annotations

import torch
from torchrl.data import Bounded
from torchrl.envs.utils import ExplorationType

from imitrl.learners.chunks import RECEDING_HELD, chunk_task, chunked_learner
from imitrl.learners.flow.loss import FlowMatchingLoss
from imitrl.learners.flow.policy import FlowPolicy
from imitrl.learners.learner import Learner
from imitrl.learners.registry import LearnerConfig
from imitrl.learners.task import TaskSpec

__all__ = ["FLOW_CHUNK_STEPS", "FLOW_STEPS", "flow", "flow_chunk", "flow_policy"]

FLOW_STEPS = 8
"""Euler steps of ``flow``"""
FLOW_CHUNK_STEPS = 16
"""Euler steps of ``flow_chunk`` (``flow`` takes ``FLOW_STEPS``): with its noise held
per episode, 16 steps succeeded 0.96 on the two-way task against 0.93 at 8 (6 seeds x 500
episodes; 32 and 64 steps: 0.96-0.97); without holding, 8 -> 32 steps moved 0.90 -> 0.92"""


def flow_policy(
    observation_dim: int | None,
    action: Bounded,
    config: LearnerConfig,
    *,
    num_steps: int = FLOW_STEPS,
) -> FlowPolicy:
    """The registry's flow policy over ``action`` (a task's spec, or a tiled chunk spec),
    sampled with ``num_steps`` Euler steps."""
    if observation_dim is None:
        raise ValueError("a flow policy needs vector observations")
    return FlowPolicy(
        observation_dim,
        action,
        hidden=config.width,
        num_steps=num_steps,
        normalize=config.normalize,
        seed=config.seed,
    )


def flow(task: TaskSpec, config: LearnerConfig) -> Learner:
    """``flow``: rectified flow over one action, sampled."""
    policy = flow_policy(task.observation_dim, task.action, config)
    assert config.lr is not None  # registry.make resolved it
    return Learner(
        policy,
        FlowMatchingLoss(policy, seed=config.seed),
        torch.optim.Adam(policy.parameters(), lr=config.lr),
        exploration=ExplorationType.RANDOM,
        normalizer=policy.normalizer,
    )


def flow_chunk(task: TaskSpec, config: LearnerConfig) -> Learner:
    """``flow_chunk``: rectified flow over masked chunks, executed on a receding horizon
    with the noise held per episode."""
    policy = flow_policy(
        task.observation_dim, chunk_task(task).action, config, num_steps=FLOW_CHUNK_STEPS
    )
    loss = FlowMatchingLoss(policy, chunked=True, seed=config.seed)
    assert config.lr is not None  # registry.make resolved it
    opt = torch.optim.Adam(policy.parameters(), lr=config.lr)
    return chunked_learner(
        task,
        policy,
        loss,
        opt,
        RECEDING_HELD,
        exploration=ExplorationType.RANDOM,
        normalizer=policy.normalizer,
    )
