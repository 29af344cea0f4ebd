"""The reference forms of the seam's two loss pieces: TorchRL's loss modules as they are.

:func:`imitrl.runtime.paths.ppo_loss` and :func:`~imitrl.runtime.paths.gail_loss` return
an object of one interface on either path, so an algorithm calls it without asking which
path runs. These are the reference objects: ``ClipPPOLoss`` called on a minibatch's rows,
``GAILLoss`` called on its batch. The accelerated ones
(:class:`~imitrl.runtime.fast.ppo_step.TensorPPO`,
:class:`~imitrl.runtime.fast.gail_step.TensorGAILLoss`) compute the same bits on the
batch's tensors and have the same methods.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.objectives import LossModule

__all__ = ["GAILReference", "PPOReference"]


class PPOReference:
    """``ClipPPOLoss`` on a minibatch's rows: :meth:`prepare` a flat batch once per epoch,
    then :meth:`on_rows` per minibatch."""

    accelerated = False
    """the reference path (the accelerated object says True)"""

    def __init__(self, loss: LossModule) -> None:
        self.loss = loss

    def prepare(self, flat: TensorDictBase) -> TensorDictBase:
        """What :meth:`on_rows` indexes: the flat batch itself."""
        return flat

    def on_rows(self, prepared: TensorDictBase, rows: torch.Tensor) -> dict[str, torch.Tensor]:
        """The loss module's ``loss_*`` entries on ``prepared[rows]``."""
        out = self.loss(prepared[rows])
        return {k: v for k, v in out.items() if k.startswith("loss_")}


class GAILReference:
    """``GAILLoss`` on its batch, and the discriminator module on each side's pairs."""

    accelerated = False
    """the reference path (the accelerated object says True)"""

    def __init__(self, loss: LossModule, module: TensorDictModuleBase) -> None:
        self.loss, self.module = loss, module

    def loss_and_penalty(
        self, batch: TensorDictBase, sides: tuple[TensorDictBase, TensorDictBase]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``GAILLoss(batch)``'s loss (penalty included) and its gradient penalty (0 if none)."""
        out = self.loss(batch)
        return out.get("loss"), out.get("gp_loss", torch.zeros(()))

    def logits(
        self, sides: tuple[TensorDictBase, TensorDictBase], key: NestedKey
    ) -> list[torch.Tensor]:
        """The discriminator's output ``key`` on each side's pairs."""
        return [self.module(side).get(key) for side in sides]
