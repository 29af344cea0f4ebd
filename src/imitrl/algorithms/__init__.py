"""Imitation algorithms: behaviour cloning and DAgger."""

from imitrl.algorithms.bc import BCConfig, FitResult, fit_bc
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

__all__ = [
    "BCConfig",
    "Constant",
    "DAggerConfig",
    "DAggerResult",
    "EnvSource",
    "EpisodeSource",
    "Exponential",
    "FitResult",
    "Linear",
    "RoundRecord",
    "dagger",
    "fit_bc",
]
