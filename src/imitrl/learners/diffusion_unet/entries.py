"""The registry's ``diffusion_unet``: Diffusion Policy (Chi et al. 2023) at CPU widths, and
its builder at any widths (:func:`diffusion_unet_learner`: the paper's are
``UnetDiffusionConfig()``)."""

from __future__ import annotations

from dataclasses import replace

import torch
from torchrl.data import Bounded
from torchrl.envs.utils import ExplorationType

from imitrl import keys
from imitrl.learners.diffusion_unet.config import UnetDiffusionConfig
from imitrl.learners.diffusion_unet.loss import UnetDiffusionLoss
from imitrl.learners.diffusion_unet.policy import UnetDiffusionPolicy
from imitrl.learners.learner import Learner
from imitrl.learners.registry import LearnerConfig
from imitrl.learners.task import TaskSpec
from imitrl.policies.chunking import ChunkedPolicy, ChunkExecution
from imitrl.policies.ema import EMA

__all__ = ["DIFFUSION_UNET", "diffusion_unet", "diffusion_unet_learner", "unet_summary"]


DIFFUSION_UNET = UnetDiffusionConfig.cpu()
"""``diffusion_unet``: Diffusion Policy at CPU widths (:meth:`UnetDiffusionConfig.cpu`).
The paper's widths and learning rate (66M parameters, for a GPU) are
``diffusion_unet_learner(task, config, UnetDiffusionConfig())``; they are not a registry
entry because everything that runs every entry (the loss benchmark, the tests) would
train them on the CPU."""


def diffusion_unet_learner(
    task: TaskSpec,
    config: LearnerConfig,
    unet: UnetDiffusionConfig,
    *,
    pixel_shape: tuple[int, int, int] | None = None,
    pixel_key=keys.PIXELS,
) -> Learner:
    """Diffusion Policy (:mod:`imitrl.learners.diffusion_unet`) for ``task``: the U-Net
    over ``unet.horizon`` actions, conditioned on the last ``unet.obs_horizon``
    observations, executing ``unet.action_steps`` per query, trained by AdamW and acting
    with the EMA of its weights. ``config`` gives the seed and ``normalize`` (the widths
    and the learning rate are ``unet``'s, the paper's recipe).

    ``pixel_shape`` ``(H, W, C)``: a camera under ``pixel_key`` (uint8 images) beside the
    state, encoded by :class:`~imitrl.learners.diffusion_unet.rgb_encoder.RgbEncoder`; its history
    is carried and fed like the state's.
    """
    if task.observation_dim is None:
        raise ValueError("Diffusion Policy needs vector observations")
    unet = replace(unet, normalize=config.normalize)
    network = UnetDiffusionPolicy(
        task.observation_dim,
        task.action,
        unet,
        seed=config.seed,
        pixel_shape=pixel_shape,
        pixel_key=pixel_key,
    )
    seen = (keys.OBSERVATION,) if pixel_shape is None else (keys.OBSERVATION, pixel_key)
    execution = ChunkExecution(unet.horizon, execute=unet.action_steps)
    assert isinstance(task.action, Bounded)  # UnetDiffusionPolicy refused any other action
    m = int(task.action.shape[0])
    policy = ChunkedPolicy(network, m, execution, history=unet.obs_horizon, history_keys=seen)
    opt = torch.optim.AdamW(
        network.parameters(), lr=unet.lr, betas=unet.betas, weight_decay=unet.weight_decay
    )
    ema = EMA(policy, power=unet.ema_power, max_decay=unet.ema_max_decay) if unet.ema else None
    learner = Learner(
        policy,
        UnetDiffusionLoss(network, seed=config.seed),
        opt,
        exploration=ExplorationType.RANDOM,
        normalizer=network.normalizer,
        ema=ema,
        horizon=unet.horizon,
        history=unet.obs_horizon,
        history_keys=seen,
    )
    return learner.placed(config.device)


def unet_summary(unet: UnetDiffusionConfig) -> str:
    dims = "-".join(map(str, unet.down_dims))
    return (
        f"Diffusion Policy: U-Net {dims}, T_o={unet.obs_horizon}, T_p={unet.horizon}, "
        f"executes {unet.action_steps}; DDPM K={unet.train_steps} {unet.schedule}, "
        f"{unet.sampler.upper()} {unet.sample_steps} steps; AdamW lr {unet.lr:g}, EMA"
    )


def diffusion_unet(task: TaskSpec, config: LearnerConfig) -> Learner:
    """``diffusion_unet``: :func:`diffusion_unet_learner` at ``config.options`` (None:
    :data:`DIFFUSION_UNET`, the CPU widths), reading the env's camera beside the state
    when the env has one (``task.pixels``)."""
    unet = DIFFUSION_UNET if config.options is None else config.options
    if not isinstance(unet, UnetDiffusionConfig):
        raise ValueError(f"diffusion_unet's options are a UnetDiffusionConfig, got {unet!r}")
    camera = task.pixels
    if camera is None:
        return diffusion_unet_learner(task, config, unet)
    (h, w, c), key = camera  # an image [H, W, C]
    return diffusion_unet_learner(task, config, unet, pixel_shape=(h, w, c), pixel_key=key)
