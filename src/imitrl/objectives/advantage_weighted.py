"""Advantage-weighted behaviour cloning as a loss module: ``-mean_i A(s_i, a*_i) log pi(a*_i | s_i)``.

The objective of :func:`imitrl.algorithms.policy_step` with the weights computed
from the row by a task-supplied advantage function instead of passed in, so it
trains through the same interface as every other loss (rows of ``OBSERVATION`` and
the expert's label in, ``loss_bc`` out). The weights are data: computed without
gradients and detached, exactly as ``policy_step`` treats its ``advantage``.

On slippery FrozenLake the exact advantage of the expert's action over a uniformly
random choice, ``A(s, a) = Q*(s, a) - mean_b Q*(s, b)``, weights each state by how
much the choice of action matters there.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule

from imitrl import keys
from imitrl.objectives.base import InnerBCLoss
from imitrl.objectives.bc import BehaviorCloningLoss

__all__ = ["Advantage", "AdvantageWeightedLoss"]

Advantage = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
"""``A(observation [N, ...], action [N, ...]) -> [N]`` weights"""


class AdvantageWeightedLoss(InnerBCLoss):
    """``-mean_i A(s_i, a_i) log pi(a_i | s_i)`` with ``A`` computed from each row.

    Args:
        actor: a probabilistic actor (categorical or tanh-normal).
        advantage: ``(observation, label) -> [N]`` finite weights.

    Keys: ``label`` (``"expert_action"``) as :class:`BehaviorCloningLoss`; the weight
    is written to ``"weight"`` on a copy of the batch. Returns ``loss_bc``, ``nll``
    (unweighted) and ``mean_weight``.
    """

    out_keys = ["loss_bc"]

    def __init__(self, actor: TensorDictModule, advantage: Advantage) -> None:
        if not callable(advantage):
            raise ValueError(f"advantage must be callable, got {type(advantage).__name__}")
        super().__init__()
        self.bc = BehaviorCloningLoss(actor, loss_type="nll", weighted=True)
        self.advantage = advantage

    def read_keys(self) -> list:
        return [k for k in self.bc.in_keys if k != self.bc.tensor_keys.weight]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        label_key = self.bc.tensor_keys.label
        obs, label = tensordict.get(keys.OBSERVATION), tensordict.get(label_key)
        with torch.no_grad():
            weight = torch.as_tensor(self.advantage(obs, label)).detach().to(torch.float32)
        if weight.shape != (tensordict.shape[0],):
            raise ValueError(
                f"advantage must return one weight per row, shape ({tensordict.shape[0]},), got {tuple(weight.shape)}"
            )
        if not torch.isfinite(weight).all():
            raise ValueError("advantage returned NaN or inf")
        td = tensordict.select(*self.bc.actor.in_keys, label_key).copy()
        td.set(self.bc.tensor_keys.weight, weight)
        out = self.bc(td)
        out.set("mean_weight", weight.mean())
        return out
