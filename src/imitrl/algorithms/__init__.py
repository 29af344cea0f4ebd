"""Imitation algorithms: behaviour cloning and DAgger."""

from imitrl.algorithms.bc import BCConfig, BCResult, fit_bc
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
]
