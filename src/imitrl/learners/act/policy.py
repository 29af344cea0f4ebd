"""ACT (Zhao et al. 2023, "Action Chunking with Transformers"): TorchRL's ``ACTModel`` and ``ACTLoss``.

The model is a CVAE over action chunks: in training an encoder maps ``(observation,
chunk)`` to a style latent ``z ~ q(z | o, a)``, and a DETR-style transformer decoder
reconstructs the chunk from ``(observation, z)``; at inference ``z = 0`` (the prior's
mean), so the policy is deterministic. The loss (``ACTLoss``) is

    L = mean |a_pred - a_chunk|  +  beta * KL(q(z | o, a) || N(0, I)),   beta = 10 (the paper's).

TorchRL 0.14.1 has both (``torchrl.modules.models.ACTModel``,
``torchrl.objectives.ACTLoss``); this module wraps them so that they keep imitrl's
contracts, and says what it changes:

* **sized for CPU**: the paper's model (d = 512, 4 encoder and 7 decoder layers, 8
  heads, 32-dimensional latent) is far beyond a benchmark cell on two cores;
  :class:`ACTPolicy` defaults to ``d = 32``, one encoder and one decoder layer, 2 heads,
  a feed-forward width of 64, an 8-dimensional latent and no dropout (the toy tasks are
  small; dropout would also need train/eval switching). Even so a training step costs
  several times an MLP's of the same task (attention over ``H + 2`` tokens);
* observations are normalised inside the network (fitted by ``Learner.prepare``), and
  chunks live in ``[-1, 1]`` (the action bounds mapped there), as ACT normalises both;
  the predicted chunk is clipped to ``[-1, 1]`` and mapped back to the bounds;
* labels: the chunk ``EXPERT_CHUNK`` ``[N, H, m]`` of :func:`imitrl.data.chunks.add_chunk_labels`.
  ``ACTLoss`` has no padding mask (the paper's code masks padded entries): past an
  episode's end the label repeats its last action (``ActionChunkTransform``'s padding),
  so the model is taught to hold it;
* the latent's reparameterisation draws from the global RNG inside ``ACTModel``; the
  loss runs it on its own seeded generator (same seed, same digits);
* ``ACTLoss`` returns its detached terms as ``loss_reconstruction`` and ``loss_kl``,
  which a sum of ``loss_*`` entries would count twice; they are reported as ``l1`` and
  ``kl`` here.

Execution: ACT queries every step and averages the chunks predicted for the current
step with weights ``exp(-m i)`` (temporal ensembling,
:class:`~imitrl.policies.chunking.ChunkedPolicy` with ``ensemble=m``).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torchrl.data import Bounded
from torchrl.modules.models import ACTModel

from imitrl import keys
from imitrl.policies.normalization import ObservationNormalizer

__all__ = ["ACTPolicy"]


class _Network(nn.Module):
    """``(observation [N, o], chunk [N, H, m] in [-1, 1] or None) -> (pred, mu, log_var)``."""

    def __init__(self, model: ACTModel, normalizer: ObservationNormalizer | None) -> None:
        super().__init__()
        self.model = model
        self.normalizer = normalizer

    def forward(self, observation: torch.Tensor, action_chunk: torch.Tensor | None = None):
        obs = observation.float()
        if self.normalizer is not None:
            obs = self.normalizer(obs)
        return self.model(obs, action_chunk)


class ACTPolicy(TensorDictModuleBase):
    """``OBSERVATION -> ACTION`` ``[*B, H * m]``: ACT's chunk at ``z = 0``, in the bounds.

    Args:
        observation_dim: length of the observation vector ``[..., o]``.
        action_spec: ``Bounded`` spec ``[m]`` of one action.
        horizon: ``H``, actions per chunk.
        hidden_dim, heads, encoder_layers, decoder_layers, latent_dim, feedforward:
            the transformer's size (``ACTModel``'s arguments; module docstring).
        normalize: normalise observations inside the network.
        seed: initialisation seed.
    """

    def __init__(
        self,
        observation_dim: int,
        action_spec: Bounded,
        *,
        horizon: int,
        hidden_dim: int = 32,
        heads: int = 2,
        encoder_layers: int = 1,
        decoder_layers: int = 1,
        latent_dim: int = 8,
        feedforward: int = 64,
        normalize: bool = True,
        seed: int = 0,
    ) -> None:
        super().__init__()
        if not isinstance(action_spec, Bounded) or len(action_spec.shape) != 1:
            raise ValueError(f"ACT needs a Bounded action spec [m], got {action_spec!r}")
        if int(horizon) != horizon or horizon < 1:
            raise ValueError(f"horizon must be a positive integer, got {horizon!r}")
        self.horizon, self.action_dim = int(horizon), int(action_spec.shape[0])
        self.in_keys, self.out_keys = [keys.OBSERVATION], [keys.ACTION]
        normalizer = ObservationNormalizer((int(observation_dim),)) if normalize else None
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            model = ACTModel(
                obs_dim=int(observation_dim),
                action_dim=self.action_dim,
                chunk_size=self.horizon,
                hidden_dim=hidden_dim,
                nheads=heads,
                num_encoder_layers=encoder_layers,
                num_decoder_layers=decoder_layers,
                latent_dim=latent_dim,
                dropout=0.0,
                dim_feedforward=feedforward,
            )
        self.network = _Network(model, normalizer)
        self.register_buffer("low", action_spec.space.low.float().clone())
        self.register_buffer("high", action_spec.space.high.float().clone())

    @property
    def normalizer(self) -> ObservationNormalizer | None:
        return self.network.normalizer

    def normalize(self, action: torch.Tensor) -> torch.Tensor:
        """Bounds -> ``[-1, 1]`` (``action`` ``[..., m]``)."""
        return 2 * (action.float() - self.low) / (self.high - self.low) - 1

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs = tensordict.get(keys.OBSERVATION)
        batch = obs.shape[:-1]
        pred, _, _ = self.network(obs.reshape(-1, obs.shape[-1]))  # z = 0: the prior's mean
        x = pred.clamp(-1.0, 1.0)
        action = self.low + (self.high - self.low) * (x + 1) / 2  # [N, H, m]
        tensordict.set(keys.ACTION, action.reshape(*batch, self.horizon * self.action_dim))
        return tensordict
