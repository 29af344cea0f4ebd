"""GAIL's discriminator loss on tensors: ``GAILLoss``'s arithmetic, without its TensorDicts.

Accelerated internals of :mod:`imitrl.runtime.paths` (import them from there, nowhere else).

A ``GAILLoss`` call on the discriminator's small network costs about a millisecond of
bookkeeping around a forward that computes in a fifth of that: the batch cloned, a
TensorDict of the concatenated pairs built, the network's parameters swapped in and out
of the module (``to_module``), labels made on the device. :class:`TensorGAILLoss`
computes what ``GAILLoss.forward`` computes without a gradient penalty (the penalty draws
its interpolation weights from the RNG: the loss module keeps it) and with the ``"mean"``
reduction, on the same tensors with the same operations in the same order: the expert's
and the policy's features concatenated, the network's probability split back, ``BCELoss``
against ones and zeros, summed and averaged (``tests/algorithms/adversarial/test_loop_lanes.py`` trains
GAIL on both paths and compares every weight).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch.nn import functional as F
from torchrl.objectives import GAILLoss

from imitrl.compat import forward_hooked, loss_mask_keys, plain_module

__all__ = ["TensorGAILLoss"]


class TensorGAILLoss:
    """``GAILLoss(batch)["loss"]`` from the four feature tensors (module docstring)."""

    accelerated = True
    """the accelerated path (:class:`~imitrl.runtime.losses.GAILReference` says False)"""

    def __init__(self, loss: GAILLoss) -> None:
        self.net = loss.discriminator_network.module
        self.in_keys = list(loss.discriminator_network.in_keys)
        self.out_keys = list(loss.discriminator_network.out_keys)
        self.out = self.out_keys.index(loss.tensor_keys.discriminator_pred)
        self.loss = loss

    @classmethod
    def of(cls, loss: GAILLoss, batch: TensorDictBase | None = None) -> TensorGAILLoss | None:
        """A :class:`TensorGAILLoss` of ``loss``, or None where it would compute anything
        else (a gradient penalty, another reduction, a loss mask in ``batch``, a network
        that is not a plain two-input module)."""
        net = loss.discriminator_network
        if type(loss) is not GAILLoss or loss.use_grad_penalty or loss.reduction != "mean":
            return None
        if (
            not isinstance(net, TensorDictModule)
            or type(net).forward is not TensorDictModule.forward
            or not plain_module(net)
            or len(net.in_keys) != 2
            or forward_hooked(net, net.module)
        ):
            return None  # a network whose call is not its module on the two features
        k = loss.tensor_keys
        if list(net.in_keys) != [k.expert_observation, k.expert_action]:
            return None
        if batch is not None and any(m in batch.keys(True) for m in loss_mask_keys(loss)):
            return None
        return cls(loss)

    def loss_and_penalty(
        self, batch: TensorDictBase, sides: tuple[TensorDictBase, TensorDictBase]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`__call__` on ``sides``' (expert's, policy's) features, and a zero
        penalty (a penalised loss is never replayed)."""
        (eo, ea), (po, pa) = ([side.get(k) for k in self.in_keys] for side in sides)
        return self(eo, ea, po, pa), torch.zeros(())

    def logits(
        self, sides: tuple[TensorDictBase, TensorDictBase], key: NestedKey
    ) -> list[torch.Tensor]:
        """The network's output ``key`` on each side's features (the module's call on the
        same tensors)."""
        out = self.out_keys.index(key)
        return [self.net(*(side.get(k) for k in self.in_keys))[out] for side in sides]

    def __call__(
        self,
        expert_obs: torch.Tensor,
        expert_act: torch.Tensor,
        policy_obs: torch.Tensor,
        policy_act: torch.Tensor,
    ) -> torch.Tensor:
        n = expert_obs.shape[0]
        obs = torch.cat([expert_obs, policy_obs], dim=0)
        act = torch.cat([expert_act, policy_act], dim=0)
        pred = self.net(obs, act)[self.out]
        fake = torch.zeros((n, 1), dtype=torch.float32).to(pred.device)
        real = torch.ones((n, 1), dtype=torch.float32).to(pred.device)
        expert_pred, policy_pred = torch.split(pred, [n, n], dim=0)
        expert_loss = F.binary_cross_entropy(expert_pred, real, reduction="none")
        policy_loss = F.binary_cross_entropy(policy_pred, fake, reduction="none")
        return (expert_loss + policy_loss).mean()
