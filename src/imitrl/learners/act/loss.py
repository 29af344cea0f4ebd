"""ACT's loss: TorchRL's ``ACTLoss`` (L1 reconstruction + beta KL) on an :class:`~imitrl.learners.act.policy.ACTPolicy`'s chunk labels, on its own seeded generator."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torchrl.objectives import ACTLoss

from imitrl import keys
from imitrl.compat import act_latent_noise
from imitrl.data.chunks import EXPERT_CHUNK
from imitrl.learners.act.policy import ACTPolicy
from imitrl.objectives.base import ImitationLoss
from imitrl.rng import SavedGenerator, rng_from
from imitrl.system.ranks import rows_drawn

__all__ = ["ACTChunkLoss"]


class ACTChunkLoss(SavedGenerator, ImitationLoss):
    """TorchRL's ``ACTLoss`` on the chunk labels of an :class:`ACTPolicy` (module docstring).

    Args:
        policy: the ACT policy trained.
        kl_weight: ``beta`` (the paper's 10).
        seed: seed of the latent's reparameterisation draws.

    Keys (``set_keys``): ``observation``, ``label`` (``EXPERT_CHUNK``, float ``[N, H, m]``
    inside the bounds). Returns ``loss_act`` and the detached ``l1`` and ``kl`` terms.
    """

    @dataclass
    class _AcceptedKeys:
        observation: NestedKey = keys.OBSERVATION
        label: NestedKey = EXPERT_CHUNK

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    out_keys = ["loss_act", "l1", "kl"]

    def __init__(self, policy: ACTPolicy, *, kl_weight: float = 10.0, seed: int = 0) -> None:
        if not isinstance(policy, ACTPolicy):
            raise ValueError(f"expected an ACTPolicy, got {type(policy).__name__}")
        super().__init__()
        self.policy = policy
        actor = TensorDictModule(
            policy.network,
            in_keys=["observation", "action_chunk"],
            out_keys=["action_pred", "mu", "log_var"],
        )
        self.inner = ACTLoss(actor, kl_weight=kl_weight)
        self.inner.set_keys(action_chunk="action_chunk")
        self.generator = torch.Generator().manual_seed(int(seed))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        label = tensordict.get(self.tensor_keys.label)
        p = self.policy
        if not label.dtype.is_floating_point or tuple(label.shape[1:]) != (p.horizon, p.action_dim):
            raise ValueError(
                f"ACT labels under {self.tensor_keys.label!r} must be float [N, {p.horizon}, "
                f"{p.action_dim}], got {label.dtype} {tuple(label.shape)}"
            )
        td = TensorDict(
            {
                "observation": tensordict.get(self.tensor_keys.observation),
                "action_chunk": p.normalize(label),
            },
            batch_size=label.shape[:1],
        )
        g, latent = self.generator, p.network.model.latent_dim
        # the CVAE latent's noise, per row: what randn_like drew from the generator's state
        # before, and a data-parallel rank's rows of it (imitrl.system.ranks.rows_drawn)
        noise = rows_drawn(lambda m: torch.randn(m, latent, generator=g), label.shape[0])
        with rng_from(self.generator), act_latent_noise(noise):
            out = self.inner(td)
        return TensorDict(
            {"loss_act": out["loss_act"], "l1": out["loss_reconstruction"], "kl": out["loss_kl"]},
            batch_size=[],
        )
