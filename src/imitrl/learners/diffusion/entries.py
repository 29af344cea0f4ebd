"""The registry's MLP diffusion baselines: ``diffusion``, ``diffusion_ddim`` and their
chunked forms (TorchRL's ``DiffusionActor`` with an MLP score network on the current
observation, a linear schedule over :data:`DIFFUSION_STEPS` steps, Adam, no EMA).
Diffusion Policy as its paper builds it is :mod:`imitrl.learners.diffusion_unet`."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torchrl.data import Bounded
from torchrl.envs.utils import ExplorationType

from imitrl.learners.chunks import CHUNK_HORIZON, RECEDING, chunk_task, chunked_learner
from imitrl.learners.diffusion.loss import DiffusionBehaviorCloningLoss
from imitrl.learners.diffusion.policy import DiffusionPolicy
from imitrl.learners.learner import Learner
from imitrl.learners.registry import LearnerConfig
from imitrl.learners.task import TaskSpec
from imitrl.objectives.chunked import FLAT_CHUNK, FlatChunkLoss

__all__ = ["DDIM_STEPS", "DIFFUSION_STEPS", "diffusion", "diffusion_chunk", "diffusion_policy"]

DIFFUSION_STEPS = 50
"""denoising steps of ``diffusion`` (each action costs this many network calls)"""
DDIM_STEPS = 8
"""DDIM sampling steps of ``diffusion_ddim`` (of the ``DIFFUSION_STEPS`` it trains on)"""

Build = Callable[[TaskSpec, LearnerConfig], Learner]


def diffusion_policy(
    observation_dim: int | None, action: Bounded, config: LearnerConfig, *, sampler: str
) -> DiffusionPolicy:
    """The registry's diffusion policy over ``action`` (a task's spec, or a tiled chunk spec)."""
    if observation_dim is None:
        raise ValueError("a diffusion policy needs vector observations")
    return DiffusionPolicy(
        observation_dim,
        action,
        hidden=config.width,
        num_steps=DIFFUSION_STEPS,
        seed=config.seed,
        sampler=sampler,
        sample_steps=DDIM_STEPS,
    )


def diffusion(sampler: str) -> Build:
    """``diffusion`` (``sampler="ddpm"``) and ``diffusion_ddim``: one action per query."""

    def build(task: TaskSpec, config: LearnerConfig) -> Learner:
        policy = diffusion_policy(task.observation_dim, task.action, config, sampler=sampler)
        assert config.lr is not None  # registry.make resolved it
        return Learner(
            policy,
            DiffusionBehaviorCloningLoss(policy, seed=config.seed),
            torch.optim.Adam(policy.parameters(), lr=config.lr),
            exploration=ExplorationType.RANDOM,
        )

    return build


def diffusion_chunk(sampler: str) -> Build:
    """``diffusion_chunk`` and ``diffusion_ddim_chunk``: the flat chunk, unmasked."""

    def build(task: TaskSpec, config: LearnerConfig) -> Learner:
        action = chunk_task(task).action
        policy = diffusion_policy(task.observation_dim, action, config, sampler=sampler)
        inner = DiffusionBehaviorCloningLoss(policy, seed=config.seed)
        inner.set_keys(label=FLAT_CHUNK)
        assert isinstance(task.action, Bounded)  # a continuous entry's task: a Bounded [m] spec
        loss = FlatChunkLoss(inner, dim=CHUNK_HORIZON * int(task.action.shape[0]))
        assert config.lr is not None  # registry.make resolved it
        opt = torch.optim.Adam(policy.parameters(), lr=config.lr)
        return chunked_learner(
            task, policy, loss, opt, RECEDING, exploration=ExplorationType.RANDOM
        )

    return build
