"""Diffusion Policy (Chi et al. 2023) in one folder: every hyperparameter
(:mod:`~imitrl.learners.diffusion_unet.config`), the temporal U-Net
(:mod:`~imitrl.learners.diffusion_unet.unet1d`), the camera encoder
(:mod:`~imitrl.learners.diffusion_unet.rgb_encoder`), the noise schedule
(:mod:`~imitrl.learners.diffusion_unet.noise_schedule`), the policy and how it acts
(:mod:`~imitrl.learners.diffusion_unet.policy`), its loss
(:mod:`~imitrl.learners.diffusion_unet.loss`) and its registry entry and builder
(:mod:`~imitrl.learners.diffusion_unet.entries`)."""

from imitrl.learners.diffusion_unet.config import UnetDiffusionConfig, fit_recipe
from imitrl.learners.diffusion_unet.entries import DIFFUSION_UNET, diffusion_unet_learner
from imitrl.learners.diffusion_unet.loss import UnetDiffusionLoss
from imitrl.learners.diffusion_unet.policy import UnetDiffusionPolicy

__all__ = [
    "DIFFUSION_UNET",
    "UnetDiffusionConfig",
    "UnetDiffusionLoss",
    "UnetDiffusionPolicy",
    "diffusion_unet_learner",
    "fit_recipe",
]
