"""The built-in entries of the loss registry, registered here in one table, in order.

Each family folder (:mod:`~imitrl.learners.actor_critic`, :mod:`~imitrl.learners.diffusion`,
:mod:`~imitrl.learners.flow`, :mod:`~imitrl.learners.act`,
:mod:`~imitrl.learners.diffusion_unet`) holds its policy, its loss and the builder of
each of its entries; this module names them, says what each is, and what its rows and
fit need (``horizon``, ``history``, ``batch_size``, ``recipe``, ``own_lr``:
:class:`~imitrl.learners.registry.LossEntry`). The order is the registry's
(:func:`~imitrl.learners.registry.names`): one-step entries first, then the chunked ones.
"""

from __future__ import annotations

from typing import TypedDict

from imitrl.learners.act.entries import ACT_BATCH, ACT_LR, act
from imitrl.learners.actor_critic.entries import (
    ENTROPY_COEF,
    L2_COEF,
    ForEnvOptions,
    advantage_weighted,
    chunk_regression,
    cross_entropy,
    cross_entropy_entropy,
    for_env,
    gaussian_nll,
    gaussian_nll_chunk,
    mse_l2,
    regression,
)
from imitrl.learners.chunks import CHUNK_EXECUTE, CHUNK_HORIZON, ENSEMBLE, ENSEMBLE_M, RECEDING
from imitrl.learners.diffusion.entries import (
    DDIM_STEPS,
    DIFFUSION_STEPS,
    diffusion,
    diffusion_chunk,
)
from imitrl.learners.diffusion_unet.config import fit_recipe
from imitrl.learners.diffusion_unet.entries import DIFFUSION_UNET, diffusion_unet, unet_summary
from imitrl.learners.flow.entries import FLOW_CHUNK_STEPS, FLOW_STEPS, flow, flow_chunk
from imitrl.learners.mip.entries import mip, mip_chunk
from imitrl.learners.mip.policy import T_STAR
from imitrl.learners.registry import register

__all__: list[str] = []

_H, _K = CHUNK_HORIZON, CHUNK_EXECUTE
_C, _D = "continuous", "discrete"


class _Flags(TypedDict):
    """``register``'s keyword flags shared by several entries."""

    value: bool


# ------------------------------------------------------------------ one action a step
_AC: _Flags = {"value": True}  # ActorCritic: a value head when a job asks for one
register("cross_entropy", actions=_D, summary="cross-entropy (categorical NLL)", **_AC)(
    cross_entropy
)
register(
    "cross_entropy_entropy",
    actions=_D,
    summary=f"cross-entropy - {ENTROPY_COEF} x policy entropy",
    **_AC,
)(cross_entropy_entropy)
register(
    "advantage_weighted",
    actions=_D,
    summary="advantage-weighted cross-entropy (policy_step's objective)",
    requires=("advantage",),
    **_AC,
)(advantage_weighted)
register(
    "gaussian_nll",
    actions=_C,
    summary="tanh-normal NLL with a learned state-independent log-std, acts with tanh(mean)",
    **_AC,
)(gaussian_nll)
register("mse", actions=_C, summary="mean squared error", **_AC)(regression("mse"))
register("l1", actions=_C, summary="mean absolute error", **_AC)(regression("l1"))
register("smooth_l1", actions=_C, summary="Huber loss (delta 1)", **_AC)(regression("smooth_l1"))
register("mse_l2", actions=_C, summary=f"MSE + {L2_COEF} x squared L2 norm of weights", **_AC)(
    mse_l2
)
register(
    "diffusion",
    actions=_C,
    summary=f"diffusion policy (DDPM, {DIFFUSION_STEPS} steps), samples its actions",
)(diffusion("ddpm"))
register(
    "diffusion_ddim",
    actions=_C,
    summary=f"diffusion trained as DDPM ({DIFFUSION_STEPS} steps), sampled by DDIM in {DDIM_STEPS}",
)(diffusion("ddim"))
register(
    "flow",
    actions=_C,
    summary=f"flow matching (rectified flow), {FLOW_STEPS} Euler steps, samples its actions",
)(flow)

register(
    "mip",
    actions=_C,
    summary=f"minimal iterative policy (Pan et al. 2025): 2 regression steps, t*={T_STAR}, "
    "noise in training only",
)(mip)

# ------------------------------------------------------------------ chunks of H actions
register(
    "mse_chunk",
    actions=_C,
    summary=f"MSE on chunks of {_H}, executes {_K} then replans",
    horizon=_H,
)(chunk_regression("mse", RECEDING))
register(
    "l1_chunk",
    actions=_C,
    summary=f"L1 on chunks of {_H}, executes {_K} then replans",
    horizon=_H,
)(chunk_regression("l1", RECEDING))
register(
    "l1_chunk_ensemble",
    actions=_C,
    summary=f"L1 on chunks of {_H}, ACT's temporal ensembling (m={ENSEMBLE_M})",
    horizon=_H,
)(chunk_regression("l1", ENSEMBLE))
register(
    "gaussian_nll_chunk",
    actions=_C,
    summary=f"tanh-normal NLL of chunks of {_H} (unmasked), a learned state-independent "
    "log-std, acts with the mean",
    horizon=_H,
)(gaussian_nll_chunk)
register(
    "diffusion_chunk",
    actions=_C,
    summary=f"diffusion (DDPM) on chunks of {_H} (unmasked), executes {_K}",
    horizon=_H,
)(diffusion_chunk("ddpm"))
register(
    "diffusion_ddim_chunk",
    actions=_C,
    summary=f"diffusion on chunks of {_H}, sampled by DDIM, executes {_K}",
    horizon=_H,
)(diffusion_chunk("ddim"))
register(
    "flow_chunk",
    actions=_C,
    summary=f"flow matching on chunks of {_H} (masked, {FLOW_CHUNK_STEPS} Euler steps), "
    f"executes {_K}, noise held per episode",
    horizon=_H,
)(flow_chunk)
register(
    "mip_chunk",
    actions=_C,
    summary=f"minimal iterative policy on chunks of {_H} (masked), executes {_K}",
    horizon=_H,
)(mip_chunk)
register(
    "act",
    actions=_C,
    summary=f"ACT (TorchRL ACTModel/ACTLoss, d=32, 1+1 layers) on chunks of {_H}, "
    f"temporal ensembling (m={ENSEMBLE_M}); its own batch {ACT_BATCH} and lr {ACT_LR}",
    horizon=_H,
    batch_size=ACT_BATCH,
    own_lr=ACT_LR,
    hidden=False,
)(act)
register(
    "diffusion_unet",
    actions=_C,
    summary=unet_summary(DIFFUSION_UNET),
    horizon=DIFFUSION_UNET.horizon,
    history=DIFFUSION_UNET.obs_horizon,
    recipe=fit_recipe(DIFFUSION_UNET),
    own_lr=DIFFUSION_UNET.lr,
    options=DIFFUSION_UNET,
    hidden=False,
    pixels=True,
)(diffusion_unet)

# ------------------------------------------------------------------ any env
register(
    "for_env",
    actions="any",
    summary="the network the env's specs call for: a CNN on images, an MLP (one-hot on "
    "integer states); any action spec, its head's default loss",
    options=ForEnvOptions(),
    value=True,
    tables=False,
)(for_env)
