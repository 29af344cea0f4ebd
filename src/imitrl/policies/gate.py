"""A gated expert: it takes over where a rule says the learner is about to go wrong.

HG-DAgger (Kelly et al., ICRA 2019) and ThriftyDAgger (Hoque et al., CoRL 2021) let a
supervisor watch the learner drive and take control only when it judges the learner
unsafe; those corrections are what LeRobot's DAgger rollouts record with
``intervention=True``. ``ExpertGate`` is that supervisor in simulation: in the behaviour
policy ``TensorDictSequential(expert, learner, gate)`` (the place of DAgger's
:class:`~imitrl.policies.mixture.BetaMixer`), per lane and step, ``rule(expert_action,
learner_action)`` says whether the expert intervenes; the executed action is the
expert's where it does, the learner's elsewhere, and ``EXPERT_EXECUTED`` records the
intervention. The rule is a parameter: :class:`ActionDistance` (the default: intervene
where the learner's action is farther than ``threshold`` from the expert's, Euclidean
over the action's dimensions; for discrete actions, where they differ) or any callable
of the same signature (a novelty or risk estimate).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from imitrl import keys

__all__ = ["ActionDistance", "ExpertGate"]


@dataclass(frozen=True)
class ActionDistance:
    """Intervene where ``|learner - expert| > threshold`` (Euclidean over the action's
    dimensions); discrete actions: where they differ."""

    threshold: float

    def __post_init__(self) -> None:
        if not self.threshold >= 0:  # nan too; inf: never intervene
            raise ValueError(f"threshold must be >= 0, got {self.threshold}")

    def __call__(
        self, expert: torch.Tensor, learner: torch.Tensor, batch: torch.Size
    ) -> torch.Tensor:
        if not expert.is_floating_point():
            differ = expert != learner
            return differ.reshape(*batch, -1).any(-1) if differ.dim() > len(batch) else differ
        gap = (learner - expert).double().reshape(*batch, -1).norm(dim=-1)
        # a NaN or inf proposal is as far as can be: the expert takes over (NaN > t is
        # False, and a review saw the NaN executed, with no intervention recorded)
        return (gap > self.threshold) | ~torch.isfinite(gap)


class ExpertGate(TensorDictModuleBase):
    """Per lane, execute ``EXPERT_ACTION`` where ``rule`` fires, else the learner's
    ``ACTION`` (module docstring); writes ``LEARNER_ACTION`` and ``EXPERT_EXECUTED``.

    Args:
        rule: ``rule(expert, learner, batch_size) -> bool [*batch]``; a float ``t`` means
            ``ActionDistance(t)``.
    """

    in_keys = [keys.ACTION, keys.EXPERT_ACTION]
    out_keys = [keys.ACTION, keys.LEARNER_ACTION, keys.EXPERT_EXECUTED]

    def __init__(self, rule: Callable[..., torch.Tensor] | float) -> None:
        super().__init__()
        self.rule = ActionDistance(float(rule)) if isinstance(rule, int | float) else rule
        if not callable(self.rule):
            raise ValueError(f"rule must be a threshold or a callable, got {rule!r}")

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        expert = tensordict.get(keys.EXPERT_ACTION)
        learner = tensordict.get(keys.ACTION, None)
        if learner is None:
            raise ValueError(
                f"ExpertGate needs the learner's proposal under {keys.ACTION!r}: put the learner "
                "before the gate"
            )
        batch = tensordict.batch_size
        take = self.rule(expert, learner, batch).reshape(batch).bool()
        mask = take.reshape((*batch, *([1] * (expert.ndim - len(batch)))))
        tensordict.set(keys.LEARNER_ACTION, learner)
        tensordict.set(keys.ACTION, torch.where(mask, expert, learner))
        tensordict.set(keys.EXPERT_EXECUTED, take)
        return tensordict

    def __repr__(self) -> str:
        return f"ExpertGate({self.rule!r})"
