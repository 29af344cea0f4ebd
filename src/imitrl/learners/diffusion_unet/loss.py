"""Diffusion Policy's loss: the masked epsilon-prediction MSE of a :class:`~imitrl.learners.diffusion_unet.policy.UnetDiffusionPolicy` over its action chunk."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey

from imitrl import keys
from imitrl.data.chunks import CHUNK_PAD, EXPERT_CHUNK
from imitrl.data.history import OBS_HISTORY, history_key
from imitrl.learners.diffusion_unet.policy import UnetDiffusionPolicy
from imitrl.objectives.base import ImitationLoss
from imitrl.rng import SavedGenerator
from imitrl.system.ranks import masked_mean, rows_drawn

__all__ = ["UnetDiffusionLoss"]


class UnetDiffusionLoss(SavedGenerator, ImitationLoss):
    """Epsilon prediction on the expert's label chunks: ``E ||eps - eps_theta(x_k, k, obs)||^2``.

    Args:
        policy: the :class:`UnetDiffusionPolicy` being trained.
        seed: seed of the loss's draws (steps ``k`` and noise ``eps``).

    Keys (``set_keys``): ``observation`` (read only to fit the normaliser), ``history``
    (``"observation_history"``), ``label`` (``EXPERT_CHUNK``, float ``[N, T_p, m]``),
    ``pad`` (``CHUNK_PAD``). Returns ``loss_diffusion``.
    """

    @dataclass
    class _AcceptedKeys:
        observation: NestedKey = keys.OBSERVATION
        history: NestedKey = OBS_HISTORY
        label: NestedKey = EXPERT_CHUNK
        pad: NestedKey = CHUNK_PAD

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    out_keys = ["loss_diffusion"]

    def __init__(self, policy: UnetDiffusionPolicy, *, seed: int = 0) -> None:
        if not isinstance(policy, UnetDiffusionPolicy):
            raise ValueError(f"expected a UnetDiffusionPolicy, got {type(policy).__name__}")
        super().__init__()
        self.policy = policy
        self.generator = torch.Generator().manual_seed(int(seed))

    def read_keys(self) -> list[NestedKey]:
        t = self.tensor_keys
        cameras = [] if self.policy.pixel_key is None else [history_key(self.policy.pixel_key)]
        return [t.observation, t.history, *cameras, t.label, t.pad]

    def check_labels(self, rows: TensorDictBase) -> None:
        super().check_labels(rows)
        label, p = rows.get(self.label_key), self.policy
        want = (p.config.horizon, p.action_dim)
        if not label.dtype.is_floating_point or tuple(label.shape[1:]) != want:
            raise ValueError(
                f"Diffusion Policy labels under {self.label_key!r} must be float [N, "
                f"{want[0]}, {want[1]}] (add_chunk_labels(rows, {want[0]})), got "
                f"{label.dtype} {tuple(label.shape)}"
            )

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        p = self.policy
        x0 = p.to_unit(tensordict.get(self.tensor_keys.label))
        td = tensordict
        if self.tensor_keys.history != OBS_HISTORY:
            td = tensordict.copy().set(OBS_HISTORY, tensordict.get(self.tensor_keys.history))
        cond = p.condition(td, self.generator)  # random crops in training
        n = x0.shape[0]
        g, steps, shape = self.generator, p.config.train_steps, tuple(x0.shape[1:])
        # per-row draws: a data-parallel rank keeps its rows' (imitrl.system.ranks.rows_drawn)
        k = rows_drawn(lambda m: torch.randint(0, steps, (m,), generator=g), n).to(x0.device)
        eps = rows_drawn(lambda m: torch.randn((m, *shape), generator=g), n).to(x0.device)
        err = (p.unet(p.schedule.add_noise(x0, eps, k), k, cond) - eps).pow(2)
        if p.config.mask_padding:
            keep = ~tensordict.get(self.tensor_keys.pad).to(err.device).bool()  # [N, T_p]
            weight = keep.unsqueeze(-1).to(err.dtype).expand_as(err)
            loss = masked_mean(err, weight)  # over the global batch (data-parallel)
        else:
            loss = err.mean()
        return TensorDict({"loss_diffusion": loss}, batch_size=[])
