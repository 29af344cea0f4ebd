"""Action distributions whose deterministic action is spelled out.

TorchRL's ``ProbabilisticActor`` under ``ExplorationType.DETERMINISTIC`` takes
``dist.deterministic_sample``. For a categorical policy that must be the argmax of
the raw logits with ties to the lowest index (a zero-initialised tabular policy
picks action 0 on states it never saw), not a re-derived argmax of normalised
probabilities, which can merge logits that differ by less than a float's spacing.
"""

from __future__ import annotations

import torch
from torch import distributions as D

__all__ = ["GreedyCategorical"]


class GreedyCategorical(D.Categorical):
    """Categorical over the last dimension of ``logits``; greedy = ``logits.argmax(-1)``."""

    def __init__(self, logits: torch.Tensor, validate_args: bool | None = False) -> None:
        self._raw_logits = logits
        super().__init__(logits=logits, validate_args=validate_args)

    @property
    def deterministic_sample(self) -> torch.Tensor:
        # torch.argmax returns the first maximal index: ties go to the lowest action.
        return self._raw_logits.argmax(dim=-1)

    @property
    def mode(self) -> torch.Tensor:
        return self.deterministic_sample
