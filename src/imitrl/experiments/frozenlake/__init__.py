"""The section's FrozenLake study: `imitrl frozenlake`."""

from imitrl.experiments.frozenlake.config import PROTOCOLS, StudyConfig
from imitrl.experiments.frozenlake.study import run_study

__all__ = ["PROTOCOLS", "StudyConfig", "run_study"]
