"""Imitation algorithms: behaviour cloning, DAgger, and the section's ``policy_step``."""

from imitrl.algorithms.bc import BCResult, fit_bc
from imitrl.algorithms.dagger import (
    Constant,
    DAggerConfig,
    DAggerResult,
    EnvSource,
    EpisodeSource,
    Exponential,
    Linear,
    RoundRecord,
    dagger,
)
from imitrl.algorithms.policy_step import policy_step
from imitrl.configs.bc import BCConfig

__all__ = [
    "BCConfig",
    "BCResult",
    "Constant",
    "DAggerConfig",
    "DAggerResult",
    "EnvSource",
    "EpisodeSource",
    "Exponential",
    "Linear",
    "RoundRecord",
    "dagger",
    "fit_bc",
    "policy_step",
]
