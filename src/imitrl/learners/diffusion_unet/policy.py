"""Diffusion Policy (Chi et al. 2023) as its paper and LeRobot's reproduction build it.

A policy that denoises a whole action sequence at once, conditioned on the recent
observations; the registry's ``diffusion_unet`` entry (:mod:`imitrl.learners.catalogue`)
executes it with a receding horizon. The pieces, each in its own module:

* the noise-prediction network: a 1-D temporal U-Net with FiLM conditioning and a
  sinusoidal step embedding (:class:`~imitrl.learners.diffusion_unet.unet1d.ConditionalUnet1D`);
* the observation horizon ``T_o``: the network reads the last ``T_o`` observations of the
  episode (``observation_history``, :mod:`imitrl.data.history`), normalised and
  flattened into FiLM's conditioning vector; with a camera (``pixel_shape``), each step's
  image is encoded by a ResNet-18 with GroupNorm and a spatial softmax, trained on random
  crops (:mod:`imitrl.learners.diffusion_unet.rgb_encoder`), and its features join the state's; rows carry the history
  (:meth:`~imitrl.learners.Learner.training_rows`), and the acting policy builds it
  from what each lane has seen since its reset
  (:class:`~imitrl.policies.chunking.ChunkedPolicy` ``history=``);
* the prediction horizon ``T_p`` (16) and action horizon ``T_a`` (8): the network predicts
  ``T_p`` actions from the current step on, of which the policy executes ``T_a`` before
  it plans again;
* DDPM training with ``K`` = 100 steps of the ``squaredcos_cap_v2`` schedule, epsilon
  prediction, samples clipped to ``[-1, 1]``; DDIM (or DDPM) inference
  (:class:`~imitrl.learners.diffusion_unet.noise_schedule.NoiseSchedule`);
* AdamW (lr 1e-4, weight decay 1e-6, betas 0.95/0.999), cosine schedule after a 500-step
  warm-up, EMA of the weights (power 0.75) that the policy acts with
  (:class:`~imitrl.policies.ema.EMA`).

Actions are diffused in ``[-1, 1]``: the label is mapped from the action spec's bounds
(the paper maps by the data's range; a spec's bounds are known before any data and are
what the executed action is clipped to). Where a label chunk runs past its episode's
end, or past the first step a DAgger round's learner drove (:mod:`imitrl.data.chunks`),
its padded entries are left out of the loss (``mask_padding``, LeRobot's
``do_mask_loss_for_padding``): a relabelled row's chunk holds one expert label, and the
repeated padding is no action the expert planned.

Where this differs from the paper, and why:

* the predicted window starts at the current step (``t .. t + T_p - 1``, as every chunked
  learner here is labelled, :mod:`imitrl.data.chunks`); the paper's starts ``T_o - 1``
  steps earlier and executes from index ``T_o - 1``. The executed actions are the same;
  the paper's network also predicts the ``T_o - 1`` actions already taken;
* observations are normalised by mean and standard deviation (the library's
  :class:`~imitrl.policies.normalization.ObservationNormalizer`), actions by the spec's
  bounds; the paper min-max normalises both from the data;
* padded label entries are masked (above);
* DDIM in 10 steps by default (``sampler``).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import InteractionType, TensorDictModuleBase
from tensordict.nn.probabilistic import interaction_type
from tensordict.utils import NestedKey
from torchrl.data import Bounded

from imitrl import keys
from imitrl.data.history import OBS_HISTORY, history_key
from imitrl.learners.diffusion_unet.config import UnetDiffusionConfig
from imitrl.learners.diffusion_unet.noise_schedule import NoiseSchedule
from imitrl.learners.diffusion_unet.rgb_encoder import RgbEncoder
from imitrl.learners.diffusion_unet.unet1d import ConditionalUnet1D
from imitrl.policies.normalization import ObservationNormalizer

__all__ = ["UnetDiffusionPolicy"]


class UnetDiffusionPolicy(TensorDictModuleBase):
    """``observation_history [*B, T_o, d] -> ACTION [*B, T_p * m]``: a sampled action
    sequence inside the bounds of ``action_spec`` (flat, as a chunked policy reads it).

    Args:
        observation_dim: ``d``.
        action_spec: ``Bounded`` ``[m]``.
        config: the hyperparameters.
        seed: initialisation seed; samples draw from torch's global RNG, which an
            evaluation seeds (``evaluate(generator=)``), as every sampled policy's do.

    ``RANDOM`` exploration samples (a fresh latent per query, as the paper acts);
    ``DETERMINISTIC`` starts from the zero latent: with DDIM (deterministic updates)
    repeatable but not a sample; DDPM still adds its per-step noise.
    """

    def __init__(
        self,
        observation_dim: int,
        action_spec: Bounded,
        config: UnetDiffusionConfig,
        *,
        seed: int,
        pixel_shape: tuple[int, int, int] | None = None,
        pixel_key: NestedKey = keys.PIXELS,
    ) -> None:
        super().__init__()
        if not isinstance(action_spec, Bounded) or len(action_spec.shape) != 1:
            raise ValueError(
                f"Diffusion Policy needs a Bounded action spec [m], got {action_spec!r}"
            )
        self.config = config
        self.action_dim, self.observation_dim = int(action_spec.shape[0]), int(observation_dim)
        self.pixel_key = None if pixel_shape is None else pixel_key
        self.in_keys, self.out_keys = [OBS_HISTORY], [keys.ACTION]
        if self.pixel_key is not None:
            self.in_keys.append(history_key(pixel_key))
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(int(seed))
            self.rgb = None
            if pixel_shape is not None:
                h, w, c = pixel_shape
                crop = config.crop_shape or (round(h * 76 / 84), round(w * 76 / 84))
                self.rgb = RgbEncoder((h, w, c), crop, config.keypoints)
            per_step = self.observation_dim + (0 if self.rgb is None else self.rgb.features)
            self.unet = ConditionalUnet1D(
                self.action_dim,
                config.obs_horizon * per_step,
                down_dims=config.down_dims,
                kernel_size=config.kernel_size,
                n_groups=config.n_groups,
                step_embed_dim=config.step_embed_dim,
            )
        self.normalizer = (
            ObservationNormalizer((self.observation_dim,)) if config.normalize else None
        )
        self.schedule = NoiseSchedule(
            config.train_steps, config.schedule, clip_sample=config.clip_sample
        )
        self.register_buffer("low", action_spec.space.low.float().clone())
        self.register_buffer("high", action_spec.space.high.float().clone())

    def get_extra_state(self) -> torch.Tensor:
        """Nothing (an empty tensor): acting draws from torch's global RNG, which an
        evaluation or a rollout seeds from its own generator (as every sampled policy's
        draws), so ``imitrl eval`` replays a run's evaluation. Kept so that checkpoints
        which saved the sampler's own generator (imitrl up to 2f3db47) still load."""
        return torch.empty(0, dtype=torch.uint8)

    def set_extra_state(self, state: torch.Tensor) -> None:
        """Ignore the saved state (:meth:`get_extra_state`)."""

    def condition(
        self, td: TensorDictBase, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """FiLM's observation features ``[B, T_o * (d + F)]`` from ``td``'s histories: per
        step the normalised state and (cameras) the image features, random crops drawn
        from ``generator`` when given (training), centre crops otherwise."""
        n = self.config.obs_horizon
        history = td.get(OBS_HISTORY)
        if history.shape[-2:] != (n, self.observation_dim):
            raise ValueError(
                f"{OBS_HISTORY!r} must be [..., {n}, {self.observation_dim}] (the last "
                f"{n} observations), got {tuple(history.shape)}"
            )
        h = history.reshape(-1, n, self.observation_dim).float()
        if self.normalizer is not None:
            h = self.normalizer(h)
        if self.rgb is not None:
            images = td.get(history_key(self.pixel_key))  # [*B, T_o, H, W, C] uint8
            flat = images.reshape(-1, *images.shape[-3:])
            features = self.rgb(flat, generator, per_row=n).reshape(h.shape[0], n, -1)
            h = torch.cat([h, features], dim=-1)
        return h.flatten(-2)

    def to_unit(self, action: torch.Tensor) -> torch.Tensor:
        """Bounds -> ``[-1, 1]``."""
        return 2 * (action.float() - self.low) / (self.high - self.low) - 1

    @torch.no_grad()
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        batch = tensordict.get(OBS_HISTORY).shape[:-2]
        cond = self.condition(tensordict)
        shape = (cond.shape[0], self.config.horizon, self.action_dim)
        if interaction_type() == InteractionType.DETERMINISTIC:
            x = torch.zeros(shape, device=cond.device)
        else:
            x = torch.randn(shape).to(cond.device)  # the global RNG: module docstring
        x = self.schedule.sample(
            lambda xk, k: self.unet(xk, k, cond),
            x,
            sampler=self.config.sampler,
            sample_steps=self.config.sample_steps,
        )
        action = self.low + (self.high - self.low) * (x.clamp(-1.0, 1.0) + 1) / 2
        tensordict.set(keys.ACTION, action.reshape(*batch, -1))
        return tensordict
