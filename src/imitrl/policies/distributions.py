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

__all__ = ["ClippedNormal", "GreedyCategorical", "GreedyOneHotCategorical", "MultiCategoricalDist"]

_Shape = torch.Size | list[int] | tuple[int, ...]  # a sample shape, as torch's Distribution takes


class GreedyCategorical(D.Categorical):
    """Categorical over the last dimension of ``logits``; greedy = ``logits.argmax(-1)``."""

    def __init__(self, logits: torch.Tensor, validate_args: bool | None = False) -> None:
        self._raw_logits = logits
        super().__init__(logits=logits, validate_args=validate_args)

    @staticmethod
    def greedy(logits: torch.Tensor) -> torch.Tensor:
        """The greedy action of ``logits`` without building the distribution (rollouts'
        per-step call, ``TensorPolicy`` in :mod:`imitrl.runtime.fast.policy_call`)."""
        # torch.argmax returns the first maximal index: ties go to the lowest action.
        return logits.argmax(dim=-1)

    @property
    def deterministic_sample(self) -> torch.Tensor:
        return self.greedy(self._raw_logits)

    @property
    def mode(self) -> torch.Tensor:
        return self.deterministic_sample


class GreedyOneHotCategorical(D.OneHotCategorical):
    """One-hot categorical (for ``OneHot`` action specs); samples in the spec's ``dtype``.

    ``log_prob`` takes one-hot labels of any dtype; greedy = one-hot of ``logits.argmax(-1)``.
    """

    def __init__(
        self,
        logits: torch.Tensor,
        dtype: torch.dtype = torch.int64,
        validate_args: bool | None = False,
    ) -> None:
        self._raw_logits, self._dtype = logits, dtype
        super().__init__(logits=logits, validate_args=validate_args)

    def sample(self, sample_shape: _Shape = ()) -> torch.Tensor:
        return super().sample(sample_shape).to(self._dtype)

    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        return super().log_prob(value.to(self.logits.dtype))

    @property
    def deterministic_sample(self) -> torch.Tensor:
        idx = self._raw_logits.argmax(dim=-1)
        return torch.nn.functional.one_hot(idx, self._raw_logits.shape[-1]).to(self._dtype)

    @property
    def mode(self) -> torch.Tensor:
        return self.deterministic_sample


class MultiCategoricalDist(D.Distribution):
    """Independent categoricals over ``nvec`` sub-actions; logits ``[..., sum(nvec)]``.

    Actions are ``[..., k]`` integers; ``log_prob`` sums the sub-actions' log-probabilities.
    """

    arg_constraints: dict = {}

    def __init__(
        self,
        logits: torch.Tensor,
        nvec: tuple[int, ...],
        dtype: torch.dtype = torch.int64,
        validate_args: bool | None = False,
    ) -> None:
        self.nvec, self._dtype = tuple(nvec), dtype
        self.parts = [GreedyCategorical(x) for x in logits.split(self.nvec, dim=-1)]
        super().__init__(batch_shape=logits.shape[:-1], validate_args=validate_args)

    def sample(self, sample_shape: _Shape = ()) -> torch.Tensor:
        return torch.stack([p.sample(sample_shape) for p in self.parts], -1).to(self._dtype)

    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        value = value.long()
        return sum(p.log_prob(value[..., i]) for i, p in enumerate(self.parts))

    def entropy(self) -> torch.Tensor:
        return sum(p.entropy() for p in self.parts)

    @property
    def deterministic_sample(self) -> torch.Tensor:
        return torch.stack([p.deterministic_sample for p in self.parts], -1).to(self._dtype)

    @property
    def mode(self) -> torch.Tensor:
        return self.deterministic_sample


class ClippedNormal(D.Independent):
    """A diagonal Gaussian whose actions are clipped into ``[low, high]``.

    The density is the unclipped Gaussian's (finite everywhere), so labels exactly on
    the bounds, as a saturating expert gives, have a finite negative log-likelihood:
    the mean learns to sit at (or past) the bound and the executed action is clipped,
    as Stable-Baselines3 policies act. Greedy = ``clip(loc)``.
    """

    def __init__(
        self,
        loc: torch.Tensor,
        scale: torch.Tensor,
        low: torch.Tensor | None = None,
        high: torch.Tensor | None = None,
        validate_args: bool | None = False,
    ) -> None:
        self.clip_low, self.clip_high = low, high
        super().__init__(D.Normal(loc, scale), 1, validate_args=validate_args)

    def _clip(self, x: torch.Tensor) -> torch.Tensor:
        if self.clip_low is None:
            return x
        assert self.clip_high is not None  # the bounds come together (an ActionSpace's)
        return torch.maximum(torch.minimum(x, self.clip_high), self.clip_low)

    def sample(self, sample_shape: _Shape = ()) -> torch.Tensor:
        return self._clip(super().sample(sample_shape))

    def rsample(self, sample_shape: _Shape = ()) -> torch.Tensor:
        return self._clip(super().rsample(sample_shape))

    @property
    def deterministic_sample(self) -> torch.Tensor:
        return self._clip(self.base_dist.loc)

    @property
    def mode(self) -> torch.Tensor:
        return self.deterministic_sample
