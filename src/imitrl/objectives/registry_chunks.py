"""The chunked entries of the loss registry: every continuous loss, predicting H actions.

Each ``*_chunk`` learner predicts the expert's next ``CHUNK_HORIZON`` actions at once
(a network over the tiled action spec ``[H * m]``) and acts through a
:class:`~imitrl.policies.chunking.ChunkedPolicy`. Its rows need chunk labels
(``add_chunk_labels(rows, H)``) and its envs ``is_init`` (``chunk_env(env)``); its
:class:`~imitrl.objectives.registry.LossEntry` says so with ``horizon``.

====================== ===================================== =========================
name                   policy and loss                       execution
====================== ===================================== =========================
mse_chunk              deterministic, masked MSE             receding horizon (k of H)
l1_chunk               deterministic, masked L1              receding horizon
l1_chunk_ensemble      deterministic, masked L1 (ACT's)      temporal ensembling, m
gaussian_nll_chunk     tanh-normal NLL (free std), flat chunk receding horizon
diffusion_chunk        DDPM over the flat chunk              receding horizon
diffusion_ddim_chunk   the same, sampled by DDIM             receding horizon
flow_chunk             flow matching, masked, 16 Euler       receding horizon, noise
                       steps                                 held per episode
act                    ACT: TorchRL's ACTModel (CVAE,        temporal ensembling, m
                       transformer, sized for CPU), ACTLoss
diffusion_unet         Diffusion Policy (Chi et al. 2023):   receding horizon, 8 of 16
                       temporal U-Net with FiLM, the last 2
                       observations, DDPM K=100 cosine
                       schedule, DDIM 10 steps, AdamW,
                       warm-up + cosine lr, EMA weights;
                       masked epsilon loss
====================== ===================================== =========================

``diffusion_chunk`` and ``diffusion_ddim_chunk`` (and the one-step ``diffusion``,
``diffusion_ddim`` of the registry) are the **MLP baselines**: TorchRL's
``DiffusionActor`` with an MLP score network on the current observation, a linear
schedule over 50 steps, Adam, no EMA. ``diffusion_unet`` is Diffusion Policy as its
paper builds it (:mod:`imitrl.objectives.diffusion_unet`), at CPU widths; the paper's
widths are ``diffusion_unet_learner(task, config, UnetDiffusionConfig())``.

Temporal ensembling averages chunks predicted at different steps; a sampling policy's
chunks may come from different modes, whose average no demonstrator took, so only a
deterministic head ensembles here (as ACT ensembles its CVAE's mean, ``z = 0``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import torch
from torchrl.envs.utils import ExplorationType

from imitrl import keys
from imitrl.objectives.act import ACTChunkLoss, ACTPolicy
from imitrl.objectives.bc import BehaviorCloningLoss
from imitrl.objectives.chunked import FLAT_CHUNK, ChunkRegressionLoss, FlatChunkLoss
from imitrl.objectives.diffusion import DiffusionBehaviorCloningLoss
from imitrl.objectives.diffusion_unet import (
    UnetDiffusionConfig,
    UnetDiffusionLoss,
    UnetDiffusionPolicy,
    fit_recipe,
)
from imitrl.objectives.flow import FlowMatchingLoss
from imitrl.objectives.registry import (
    Learner,
    LearnerConfig,
    TaskSpec,
    diffusion_policy,
    flow_policy,
    mlp,
    register,
)
from imitrl.policies.chunking import ChunkedPolicy, ChunkExecution, tile_spec
from imitrl.policies.ema import EMA

__all__ = [
    "CHUNK_EXECUTE",
    "CHUNK_HORIZON",
    "DIFFUSION_UNET",
    "ENSEMBLE_M",
    "FLOW_CHUNK_STEPS",
    "diffusion_unet_learner",
]

# H and k, measured on the two-way task (flow_chunk, BC, 200 held-out episodes per
# setting, seeds 0-1): k = 2-4 is best; k = 1 lets a sampling policy switch modes
# (0.77 against 0.94 on one seed); k = H = 8 executes a bad chunk to its end (0.86-0.93);
# H = 4 did about as well as H = 8, H = 16 worse (0.85-0.90). Euler steps (8, 16, 32)
# changed success by less than the seed-to-seed spread; what mattered was the labels seen
# in training (benchmarks/README.md).
CHUNK_HORIZON = 8
"""``H``: actions predicted per query"""
CHUNK_EXECUTE = 4
"""``k``: actions executed per query (receding horizon) before replanning"""
ENSEMBLE_M = 0.01
"""``m`` of ACT's temporal-ensembling weights ``exp(-m i)`` (the paper's value)"""
ACT_BATCH = 128
"""ACT's minibatch in a benchmark protocol: smaller than the MLPs' (its paper trains on
8); a transformer step at 256 rows costs about ten MLP steps on two cores"""
ACT_LR = 3e-3
"""ACT's Adam learning rate (its own recipe, not ``LearnerConfig.lr``: the transformer
diverged on some seeds at the MLPs' 1e-2 on the two-way task)"""
FLOW_CHUNK_STEPS = 16
"""Euler steps of ``flow_chunk`` (``flow`` takes ``FLOW_STEPS``): with its noise held
per episode, 16 steps succeeded 0.96 on the two-way task against 0.93 at 8 (6 seeds x 500
episodes; 32 and 64 steps: 0.96-0.97); without holding, 8 -> 32 steps moved 0.90 -> 0.92"""
RECEDING = ChunkExecution(CHUNK_HORIZON, execute=CHUNK_EXECUTE)
RECEDING_HELD = ChunkExecution(CHUNK_HORIZON, execute=CHUNK_EXECUTE, hold_noise=True)
"""the receding horizon of ``flow_chunk``: one noise draw per episode (a flow's map from
noise to chunk is deterministic, so an episode keeps the mode its draw chose)"""
ENSEMBLE = ChunkExecution(CHUNK_HORIZON, ensemble=ENSEMBLE_M)


def _spec(task: TaskSpec) -> TaskSpec:
    """The task with its action tiled to a flat chunk ``[H * m]``."""
    return TaskSpec(
        action=tile_spec(task.action, CHUNK_HORIZON), observation_dim=task.observation_dim
    )


def _learner(task, network, loss, opt, execution, *, exploration, normalizer=None) -> Learner:
    m = int(task.action.shape[0])
    policy = ChunkedPolicy(network, m, execution)
    return Learner(
        policy,
        loss,
        opt,
        exploration=exploration,
        normalizer=normalizer,
        horizon=execution.horizon,
    )


def _regression(loss_type: str, execution: ChunkExecution) -> Callable:
    def build(task: TaskSpec, config: LearnerConfig) -> Learner:
        ac = mlp(_spec(task), config, head="deterministic")
        loss = ChunkRegressionLoss(ac.policy, horizon=CHUNK_HORIZON, loss_type=loss_type)
        det = ExplorationType.DETERMINISTIC
        return _learner(
            task, ac.policy, loss, ac.opt_pi, execution, exploration=det, normalizer=ac.normalizer
        )

    return build


_H, _K = CHUNK_HORIZON, CHUNK_EXECUTE
register(
    "mse_chunk",
    actions="continuous",
    summary=f"MSE on chunks of {_H}, executes {_K} then replans",
    horizon=_H,
)(_regression("mse", RECEDING))
register(
    "l1_chunk",
    actions="continuous",
    summary=f"L1 on chunks of {_H}, executes {_K} then replans",
    horizon=_H,
)(_regression("l1", RECEDING))
register(
    "l1_chunk_ensemble",
    actions="continuous",
    summary=f"L1 on chunks of {_H}, ACT's temporal ensembling (m={ENSEMBLE_M})",
    horizon=_H,
)(_regression("l1", ENSEMBLE))


@register(
    "gaussian_nll_chunk",
    actions="continuous",
    summary=f"tanh-normal NLL of chunks of {_H} (unmasked), a learned state-independent "
    "log-std, acts with the mean",
    horizon=_H,
)
def _gaussian_nll_chunk(task: TaskSpec, config: LearnerConfig) -> Learner:
    """The head as ``gaussian_nll``'s (one learned log-std per dimension): on the loss
    benchmark's continuous tasks (5 seeds) its BC / DAgger mean normalised score rose from
    0.16 / 0.03 with the state-dependent scale to 0.31 / 0.35 (corridor fell, 0.50 ->
    0.08 as BC; Pendulum and the two-way task rose)."""
    ac = mlp(_spec(task), config, head="tanh_normal_free")
    inner = BehaviorCloningLoss(ac.policy, loss_type="nll")
    inner.set_keys(label=FLAT_CHUNK)
    loss = FlatChunkLoss(inner, dim=_H * int(task.action.shape[0]))
    det = ExplorationType.DETERMINISTIC
    return _learner(
        task, ac.policy, loss, ac.opt_pi, RECEDING, exploration=det, normalizer=ac.normalizer
    )


def _diffusion_chunk(sampler: str) -> Callable:
    def build(task: TaskSpec, config: LearnerConfig) -> Learner:
        policy = diffusion_policy(task.observation_dim, _spec(task).action, config, sampler=sampler)
        inner = DiffusionBehaviorCloningLoss(policy, seed=config.seed)
        inner.set_keys(label=FLAT_CHUNK)
        loss = FlatChunkLoss(inner, dim=_H * int(task.action.shape[0]))
        opt = torch.optim.Adam(policy.parameters(), lr=config.lr)
        return _learner(task, policy, loss, opt, RECEDING, exploration=ExplorationType.RANDOM)

    return build


register(
    "diffusion_chunk",
    actions="continuous",
    summary=f"diffusion (DDPM) on chunks of {_H} (unmasked), executes {_K}",
    horizon=_H,
)(_diffusion_chunk("ddpm"))
register(
    "diffusion_ddim_chunk",
    actions="continuous",
    summary=f"diffusion on chunks of {_H}, sampled by DDIM, executes {_K}",
    horizon=_H,
)(_diffusion_chunk("ddim"))


@register(
    "flow_chunk",
    actions="continuous",
    summary=f"flow matching on chunks of {_H} (masked, {FLOW_CHUNK_STEPS} Euler steps), "
    f"executes {_K}, noise held per episode",
    horizon=_H,
)
def _flow_chunk(task: TaskSpec, config: LearnerConfig) -> Learner:
    policy = flow_policy(
        task.observation_dim, _spec(task).action, config, num_steps=FLOW_CHUNK_STEPS
    )
    loss = FlowMatchingLoss(policy, chunked=True, seed=config.seed)
    opt = torch.optim.Adam(policy.parameters(), lr=config.lr)
    return _learner(
        task,
        policy,
        loss,
        opt,
        RECEDING_HELD,
        exploration=ExplorationType.RANDOM,
        normalizer=policy.normalizer,
    )


@register(
    "act",
    actions="continuous",
    summary=f"ACT (TorchRL ACTModel/ACTLoss, d=32, 1+1 layers) on chunks of {_H}, "
    f"temporal ensembling (m={ENSEMBLE_M}); its own batch {ACT_BATCH} and lr {ACT_LR}",
    horizon=_H,
    batch_size=ACT_BATCH,
    own_lr=ACT_LR,
)
def _act(task: TaskSpec, config: LearnerConfig) -> Learner:
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
    return _learner(
        task, policy, loss, opt, ENSEMBLE, exploration=det, normalizer=policy.normalizer
    )


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
    """Diffusion Policy (:mod:`imitrl.objectives.diffusion_unet`) for ``task``: the U-Net
    over ``unet.horizon`` actions, conditioned on the last ``unet.obs_horizon``
    observations, executing ``unet.action_steps`` per query, trained by AdamW and acting
    with the EMA of its weights. ``config`` gives the seed and ``normalize`` (the widths
    and the learning rate are ``unet``'s, the paper's recipe).

    ``pixel_shape`` ``(H, W, C)``: a camera under ``pixel_key`` (uint8 images) beside the
    state, encoded by :class:`~imitrl.policies.resnet_encoder.RgbEncoder`; its history
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


def _unet_summary(unet: UnetDiffusionConfig) -> str:
    dims = "-".join(map(str, unet.down_dims))
    return (
        f"Diffusion Policy: U-Net {dims}, T_o={unet.obs_horizon}, T_p={unet.horizon}, "
        f"executes {unet.action_steps}; DDPM K={unet.train_steps} {unet.schedule}, "
        f"{unet.sampler.upper()} {unet.sample_steps} steps; AdamW lr {unet.lr:g}, EMA"
    )


register(
    "diffusion_unet",
    actions="continuous",
    summary=_unet_summary(DIFFUSION_UNET),
    horizon=DIFFUSION_UNET.horizon,
    history=DIFFUSION_UNET.obs_horizon,
    recipe=fit_recipe(DIFFUSION_UNET),
    own_lr=DIFFUSION_UNET.lr,
)(lambda task, config: diffusion_unet_learner(task, config, DIFFUSION_UNET))
