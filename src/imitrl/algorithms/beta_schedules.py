"""DAgger's beta schedules: round -> the probability of executing the expert's action.

Tiny frozen dataclasses, so a run's checkpoint records them by value (Ross et al. 2011 use
``beta_1 = 1`` and ``beta_i = p^{i-1}``: :class:`Exponential`; the section's miniature uses
``beta = 0``: ``Constant(0.0)``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

__all__ = ["BetaSchedule", "Constant", "Exponential", "Linear"]

BetaSchedule = Callable[[int], float]


@dataclass(frozen=True)
class Constant:
    """``beta_i = beta`` for every relabel round."""

    beta: float = 0.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.beta <= 1.0:
            raise ValueError(f"Constant beta must be in [0, 1], got {self.beta}")

    def __call__(self, round_index: int) -> float:
        return self.beta


@dataclass(frozen=True)
class Linear:
    """``beta_i = max(0, 1 - i / rounds)``: from all-expert to all-learner over ``rounds``."""

    rounds: int

    def __post_init__(self) -> None:
        if int(self.rounds) != self.rounds or self.rounds < 1:
            raise ValueError(f"Linear rounds must be a positive integer, got {self.rounds!r}")

    def __call__(self, round_index: int) -> float:
        return max(0.0, 1.0 - round_index / self.rounds)


@dataclass(frozen=True)
class Exponential:
    """``beta_i = p ** (i - 1)`` for ``i >= 1`` (Ross et al. 2011): round 1 is all expert."""

    p: float = 0.5

    def __post_init__(self) -> None:
        if not 0.0 <= self.p <= 1.0:
            raise ValueError(f"Exponential p must be in [0, 1], got {self.p}")

    def __call__(self, round_index: int) -> float:
        return self.p ** max(0, round_index - 1)
