"""Uniform random actions: the baseline that says whether a learner acts at all.

:class:`RandomActions` writes ``ACTION`` drawn uniformly from an action spec (every
discrete action alike; a ``Bounded`` box uniformly). Its draws come from torch's global
RNG, which an evaluation seeds from its own generator
(:func:`~imitrl.evaluation.evaluate`'s ``generator``), so the same seed gives the same
episodes. ``imitrl bc`` plays it on the learner's initial states when the learner scores
clearly below the expert, to tell a learner that has not learned to act (at random
level: fit it longer) from one whose errors compound (DAgger).
"""

from __future__ import annotations

from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import TensorSpec

from imitrl import keys

__all__ = ["RandomActions"]


class RandomActions(TensorDictModuleBase):
    """``-> ACTION``: uniform draws from ``action_spec`` (unbatched), one per lane."""

    def __init__(self, action_spec: TensorSpec) -> None:
        super().__init__()
        self.action_spec = action_spec
        self.in_keys: list = []
        self.out_keys = [keys.ACTION]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Set ``ACTION`` ``[*batch, ...]`` to a uniform draw for every lane."""
        tensordict.set(keys.ACTION, self.action_spec.rand(tensordict.batch_size))
        return tensordict
