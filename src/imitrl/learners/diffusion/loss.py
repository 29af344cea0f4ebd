"""The MLP diffusion baseline's loss: TorchRL's ``DiffusionBCLoss`` (epsilon prediction) on a :class:`~imitrl.learners.diffusion.policy.DiffusionPolicy`, on its own seeded generator."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.objectives import DiffusionBCLoss

from imitrl import keys
from imitrl.learners.diffusion.policy import NORMALIZED, DiffusionPolicy
from imitrl.objectives.base import ImitationLoss
from imitrl.rng import SavedGenerator, rng_from

__all__ = ["DiffusionBehaviorCloningLoss"]


class DiffusionBehaviorCloningLoss(SavedGenerator, ImitationLoss):
    """TorchRL's ``DiffusionBCLoss`` on the expert's label, mapped to ``[-1, 1]``.

    Args:
        policy: the :class:`DiffusionPolicy` being trained.
        seed: seed of the loss's draws (diffusion steps ``t`` and noise ``eps``).

    Keys (``set_keys``): ``observation`` (``"observation"``), ``label``
    (``"expert_action"``, float ``[N, m]`` inside the bounds). Returns
    ``loss_diffusion_bc`` (epsilon-prediction MSE).
    """

    @dataclass
    class _AcceptedKeys:
        observation: NestedKey = keys.OBSERVATION
        label: NestedKey = keys.EXPERT_ACTION

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    out_keys = ["loss_diffusion_bc"]

    def __init__(self, policy: DiffusionPolicy, *, seed: int = 0) -> None:
        if not isinstance(policy, DiffusionPolicy):
            raise ValueError(f"expected a DiffusionPolicy, got {type(policy).__name__}")
        super().__init__()
        self.policy = policy
        self.inner = DiffusionBCLoss(policy.actor)
        self.inner.set_keys(action=NORMALIZED, observation=keys.OBSERVATION)
        self.generator = torch.Generator().manual_seed(int(seed))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        label = tensordict.get(self.tensor_keys.label)
        obs = tensordict.get(self.tensor_keys.observation)
        if not label.dtype.is_floating_point or label.shape[-1:] != self.policy.low.shape:
            raise ValueError(
                f"diffusion labels under {self.tensor_keys.label!r} must be float [N, {self.policy.low.shape[0]}], "
                f"got {label.dtype} {tuple(label.shape)}"
            )
        td = TensorDict(
            {keys.OBSERVATION: obs, NORMALIZED: self.policy.normalize(label)},
            batch_size=tensordict.batch_size,
        )
        with rng_from(self.generator):
            out = self.inner(td)
        return TensorDict({"loss_diffusion_bc": out["loss_diffusion_bc"]}, batch_size=[])
