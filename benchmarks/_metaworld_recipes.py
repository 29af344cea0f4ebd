"""Loss entries of the Meta-World benchmarks' own: Diffusion Policy at the horizons its
published Meta-World numbers were trained with.

``diffusion_unet_mw``: the registry's ``diffusion_unet`` (CPU widths, its AdamW, EMA,
warm-up and cosine decay, DDIM in 10 steps) predicting ``T_p = 4`` actions from ``T_o = 2``
observations and executing ``T_a = 3`` of them before it plans again: the horizons of the
Meta-World configs of the 3D Diffusion Policy paper (arXiv 2403.03954, its ``dp3.yaml``:
``horizon 4, n_obs_steps 2, n_action_steps 3``), whose Diffusion Policy baseline is the
published MT10 anchor of ``metaworld_mt10.py``. The registry's default (``T_p = 16``,
``T_a = 8``) is the paper's own for its robomimic and Push-T tasks.

Imported by the workers of a run (``execute(..., modules=(__name__,))``); importing it
twice in one process registers the entry once.
"""

from __future__ import annotations

from dataclasses import replace

from imitrl.learners import registry
from imitrl.learners.diffusion_unet.config import fit_recipe
from imitrl.learners.diffusion_unet.entries import (
    DIFFUSION_UNET,
    diffusion_unet_learner,
    unet_summary,
)

DIFFUSION_UNET_MW = replace(DIFFUSION_UNET, horizon=4, action_steps=3)
"""``diffusion_unet``'s configuration at DP3's Meta-World horizons"""
NAME = "diffusion_unet_mw"


def _diffusion_unet_mw(task, config):
    return diffusion_unet_learner(task, config, DIFFUSION_UNET_MW)


if NAME not in registry.names():
    registry.register(
        NAME,
        actions="continuous",
        summary=unet_summary(DIFFUSION_UNET_MW) + " (DP3's Meta-World horizons)",
        horizon=DIFFUSION_UNET_MW.horizon,
        history=DIFFUSION_UNET_MW.obs_horizon,
        recipe=fit_recipe(DIFFUSION_UNET_MW),
        own_lr=DIFFUSION_UNET_MW.lr,
        hidden=False,
    )(_diffusion_unet_mw)
