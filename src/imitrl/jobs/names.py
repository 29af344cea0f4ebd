"""Names the command line lists, without importing torch: experts, losses, loggers.

``imitrl bc --help`` prints these lists; importing the loss registry or the experts to
read them would import torch and TorchRL (seconds). ``tests/jobs/test_names_imports.py`` checks
that each table here equals what the registry and :data:`imitrl.jobs.resolve.EXPERTS`
build, so a loss or expert added there and not here fails a test.
"""

from __future__ import annotations

__all__ = ["EXPERT_ENVS", "EXPERT_KINDS", "LOGGERS", "LOSSES", "TABULAR_ENVS", "VALUE_ITERATION"]

EXPERT_KINDS = ("builder", "callable")
"""what the ``function`` of ``--expert module:function`` is (:mod:`imitrl.jobs.resolve`)"""

LOGGERS = ("csv", "tensorboard", "wandb")
"""where a run's curves are logged (``--logger``)"""

EXPERT_ENVS: dict[str, str] = {
    "cartpole": "CartPole-v1",
    "mountaincar": "MountainCar-v0",
    "acrobot": "Acrobot-v1",
    "pendulum": "Pendulum-v1",
    "inverted_pendulum": "InvertedPendulum-v5",
    "inverted_double_pendulum": "InvertedDoublePendulum-v5",
}
"""built-in expert name -> the gymnasium id it acts in (``--expert auto`` picks by it)"""

VALUE_ITERATION = "value_iteration"
"""``--expert value_iteration``: the optimal policy of a toy-text env's own model
(:func:`imitrl.experts.value_iteration_expert`), for any env publishing one"""

TABULAR_ENVS = (
    "FrozenLake-v1",
    "FrozenLake8x8-v1",
    "CliffWalking-v1",
    "CliffWalkingSlippery-v1",
    "Taxi-v4",
)
"""the gymnasium ids ``--expert auto`` gives :data:`VALUE_ITERATION` (each publishes its
model as ``unwrapped.P``)"""

LOSSES: tuple[tuple[str, str, str], ...] = (
    ("cross_entropy", "discrete", "cross-entropy (categorical NLL)"),
    ("cross_entropy_entropy", "discrete", "cross-entropy - 0.01 x policy entropy"),
    (
        "advantage_weighted",
        "discrete",
        "advantage-weighted cross-entropy (policy_step's objective)",
    ),
    (
        "gaussian_nll",
        "continuous",
        "tanh-normal NLL with a learned state-independent log-std, acts with tanh(mean)",
    ),
    ("mse", "continuous", "mean squared error"),
    ("l1", "continuous", "mean absolute error"),
    ("smooth_l1", "continuous", "Huber loss (delta 1)"),
    ("mse_l2", "continuous", "MSE + 0.0001 x squared L2 norm of weights"),
    ("diffusion", "continuous", "diffusion policy (DDPM, 50 steps), samples its actions"),
    ("diffusion_ddim", "continuous", "diffusion trained as DDPM (50 steps), sampled by DDIM in 8"),
    ("flow", "continuous", "flow matching (rectified flow), 8 Euler steps, samples its actions"),
    (
        "mip",
        "continuous",
        "minimal iterative policy (Pan et al. 2025): 2 regression steps, t*=0.9, noise in training only",
    ),
    ("mse_chunk", "continuous", "MSE on chunks of 8, executes 4 then replans"),
    ("l1_chunk", "continuous", "L1 on chunks of 8, executes 4 then replans"),
    ("l1_chunk_ensemble", "continuous", "L1 on chunks of 8, ACT's temporal ensembling (m=0.01)"),
    (
        "gaussian_nll_chunk",
        "continuous",
        "tanh-normal NLL of chunks of 8 (unmasked), a learned state-independent log-std, "
        "acts with the mean",
    ),
    ("diffusion_chunk", "continuous", "diffusion (DDPM) on chunks of 8 (unmasked), executes 4"),
    ("diffusion_ddim_chunk", "continuous", "diffusion on chunks of 8, sampled by DDIM, executes 4"),
    (
        "flow_chunk",
        "continuous",
        "flow matching on chunks of 8 (masked, 16 Euler steps), executes 4, noise held per episode",
    ),
    ("mip_chunk", "continuous", "minimal iterative policy on chunks of 8 (masked), executes 4"),
    (
        "act",
        "continuous",
        "ACT (TorchRL ACTModel/ACTLoss, d=32, 1+1 layers) on chunks of 8, temporal ensembling (m=0.01); its own batch 128 and lr 0.003",
    ),
    (
        "diffusion_unet",
        "continuous",
        "Diffusion Policy: U-Net 32-64-128, T_o=2, T_p=16, executes 8; DDPM K=100 squaredcos_cap_v2, DDIM 10 steps; AdamW lr 0.001, EMA",
    ),
    (
        "for_env",
        "any",
        "the network the env's specs call for: a CNN on images, an MLP (one-hot on integer "
        "states); any action spec, its head's default loss",
    ),
)
"""(name, actions, summary) of every loss of :mod:`imitrl.learners.registry`"""
