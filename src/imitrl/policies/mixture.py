"""The DAgger behaviour policy: execute the expert's action with probability beta.

``behaviour = TensorDictSequential(expert, learner, BetaMixer(beta))``: the expert
writes ``EXPERT_ACTION``, the learner writes its proposal under ``ACTION``, and the
mixer flips one coin per lane, keeps the learner's proposal as ``LEARNER_ACTION``,
overwrites ``ACTION`` with the executed action and records ``EXPERT_EXECUTED``. Every
visited state thus carries the expert's label whichever action was executed.

``beta`` lives in a registered buffer so that multi-process collectors can receive a
new value through ``update_policy_weights_()``; set it (``mixer.beta = b``) before
the round's batch is requested.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential

from imitrl import keys

__all__ = ["BetaMixer", "behaviour_policy"]


class BetaMixer(TensorDictModuleBase):
    """Per lane, execute ``EXPERT_ACTION`` with probability ``beta``, else ``ACTION``.

    Args:
        beta: probability of executing the expert's action, in ``[0, 1]``.
        generator: source of the coin flips (one uniform per lane per call).
    """

    in_keys = [keys.ACTION, keys.EXPERT_ACTION]
    out_keys = [keys.ACTION, keys.LEARNER_ACTION, keys.EXPERT_EXECUTED]

    def __init__(self, beta: float = 0.0, *, generator: torch.Generator | None = None) -> None:
        super().__init__()
        self.register_buffer("_beta", torch.zeros((), dtype=torch.float64))
        self.beta = beta
        self.generator = generator

    @property
    def beta(self) -> float:
        return float(self._beta)

    @beta.setter
    def beta(self, value: float) -> None:
        value = float(value)
        if not 0.0 <= value <= 1.0:
            raise ValueError(f"beta must be in [0, 1], got {value}")
        self._beta.fill_(value)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        learner, action, coin = self.mix(
            tensordict.get(keys.EXPERT_ACTION),
            tensordict.get(keys.ACTION, None),
            tensordict.batch_size,
        )
        tensordict.set(keys.LEARNER_ACTION, learner)
        tensordict.set(keys.ACTION, action)
        tensordict.set(keys.EXPERT_EXECUTED, coin)
        return tensordict

    def mix(
        self, expert: torch.Tensor, learner: torch.Tensor | None, batch: torch.Size
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One coin per lane of ``batch``: ``(LEARNER_ACTION, ACTION, EXPERT_EXECUTED)``
        from the expert's label and the learner's proposal (None without a learner)."""
        beta = self.beta
        if learner is None:
            if beta < 1.0:
                raise ValueError(
                    f"BetaMixer with beta={beta} needs the learner's proposal under {keys.ACTION!r}; "
                    "put the learner before the mixer"
                )
            learner = expert
        if learner.dtype != expert.dtype or learner.shape != expert.shape:
            raise ValueError(
                f"expert and learner actions must agree in dtype and shape: expert {expert.dtype} "
                f"{tuple(expert.shape)}, learner {learner.dtype} {tuple(learner.shape)}"
            )
        if beta >= 1.0:  # every coin executes the expert: torch.where would return its values
            return learner, expert, torch.ones(batch, dtype=torch.bool)
        if beta <= 0.0:  # ... or the learner's
            return learner, learner, torch.zeros(batch, dtype=torch.bool)
        coin = torch.rand(batch, generator=self.generator, dtype=torch.float64) < beta
        # a tuple, not unpacked: an unbatched env has batch_size () and reshape() needs a shape
        mask = coin.reshape((*batch, *([1] * (expert.ndim - len(batch)))))
        return learner, torch.where(mask, expert, learner), coin


def behaviour_policy(
    expert: TensorDictModuleBase,
    learner: TensorDictModuleBase | None,
    mixer: BetaMixer,
) -> TensorDictSequential:
    """``TensorDictSequential(expert, learner, mixer)``; no learner means pure expert (beta must be 1)."""
    if learner is None:
        if mixer.beta < 1.0:
            raise ValueError("without a learner the behaviour policy is the expert: beta must be 1")
        return TensorDictSequential(expert, mixer)
    return TensorDictSequential(expert, learner, mixer)
