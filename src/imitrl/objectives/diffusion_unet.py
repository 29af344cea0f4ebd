"""Diffusion Policy (Chi et al. 2023) as its paper and LeRobot's reproduction build it.

A policy that denoises a whole action sequence at once, conditioned on the recent
observations; the registry's ``diffusion_unet`` entry (:mod:`imitrl.objectives.registry_chunks`)
executes it with a receding horizon. The pieces, each in its own module:

* the noise-prediction network: a 1-D temporal U-Net with FiLM conditioning and a
  sinusoidal step embedding (:class:`~imitrl.policies.unet1d.ConditionalUnet1D`);
* the observation horizon ``T_o``: the network reads the last ``T_o`` observations of the
  episode (``observation_history``, :mod:`imitrl.data.history`), normalised and
  flattened into FiLM's conditioning vector; with a camera (``pixel_shape``), each step's
  image is encoded by a ResNet-18 with GroupNorm and a spatial softmax, trained on random
  crops (:mod:`imitrl.policies.resnet_encoder`), and its features join the state's; rows carry the history
  (:meth:`~imitrl.policies.Learner.training_rows`), and the acting policy builds it
  from what each lane has seen since its reset
  (:class:`~imitrl.policies.chunking.ChunkedPolicy` ``history=``);
* the prediction horizon ``T_p`` (16) and action horizon ``T_a`` (8): the network predicts
  ``T_p`` actions from the current step on, of which the policy executes ``T_a`` before
  it plans again;
* DDPM training with ``K`` = 100 steps of the ``squaredcos_cap_v2`` schedule, epsilon
  prediction, samples clipped to ``[-1, 1]``; DDIM (or DDPM) inference
  (:class:`~imitrl.objectives.noise_schedule.NoiseSchedule`);
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

from dataclasses import dataclass, replace

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import InteractionType, TensorDictModuleBase
from tensordict.nn.probabilistic import interaction_type
from tensordict.utils import NestedKey
from torchrl.data import Bounded

from imitrl import keys
from imitrl.data.chunks import CHUNK_PAD, EXPERT_CHUNK
from imitrl.data.history import OBS_HISTORY, history_key
from imitrl.objectives.base import ImitationLoss
from imitrl.objectives.noise_schedule import NoiseSchedule
from imitrl.policies.normalization import ObservationNormalizer
from imitrl.policies.resnet_encoder import RgbEncoder
from imitrl.policies.unet1d import ConditionalUnet1D

__all__ = ["UnetDiffusionConfig", "UnetDiffusionLoss", "UnetDiffusionPolicy"]


@dataclass(frozen=True)
class UnetDiffusionConfig:
    """Every hyperparameter of Diffusion Policy; the defaults are the paper's (its
    state-based configs and LeRobot's ``DiffusionConfig``). :meth:`cpu` gives the same
    architecture at the widths a 2-core CPU trains in minutes."""

    obs_horizon: int = 2
    """``T_o``: observations the network is conditioned on (the current one last)"""
    horizon: int = 16
    """``T_p``: actions predicted per query (divisible by 2 ** (levels - 1))"""
    action_steps: int = 8
    """``T_a``: actions executed per query before planning again (receding horizon)"""
    down_dims: tuple[int, ...] = (256, 512, 1024)
    """channels of the U-Net's levels (the paper's state configs; LeRobot 512-1024-2048)"""
    kernel_size: int = 5
    """temporal kernel of every convolution"""
    n_groups: int = 8
    """GroupNorm groups"""
    step_embed_dim: int = 256
    """size of the sinusoidal diffusion-step embedding (the paper's state configs; its
    image configs and LeRobot use 128)"""
    train_steps: int = 100
    """``K``: diffusion steps of training"""
    schedule: str = "squaredcos_cap_v2"
    """the noise schedule (:data:`~imitrl.objectives.noise_schedule.SCHEDULES`)"""
    clip_sample: bool = True
    """clip the predicted clean sample to ``[-1, 1]`` at every reverse step"""
    sampler: str = "ddim"
    """``"ddim"`` (``sample_steps`` deterministic steps) or ``"ddpm"`` (all ``K``). The
    paper samples its simulated tasks by DDPM in 100 steps and its real robot by DDIM in
    10 (LeRobot: DDPM); DDIM is the default here, a tenth of the network calls"""
    sample_steps: int = 10
    """DDIM steps at inference (the paper's real-world setting)"""
    lr: float = 1e-4
    """AdamW learning rate"""
    weight_decay: float = 1e-6
    """AdamW weight decay"""
    betas: tuple[float, float] = (0.95, 0.999)
    """AdamW betas"""
    warmup_steps: int = 500
    """linear warm-up of the learning rate, then cosine decay, in every fit (capped at a
    tenth of a fit's steps: :func:`fit_recipe`)"""
    ema: bool = True
    """act with an exponential moving average of the weights"""
    ema_power: float = 0.75
    """the EMA decay's warm-up power (:class:`~imitrl.policies.ema.EMA`)"""
    ema_max_decay: float = 0.9999
    """the EMA decay's cap"""
    mask_padding: bool = True
    """leave padded chunk entries out of the loss, averaging over the kept ones (module
    docstring; the paper trains on the padding, LeRobot's ``do_mask_loss_for_padding``
    is off by default and averages over every entry)"""
    normalize: bool = True
    """normalise observations by the demonstrations' mean and standard deviation"""
    crop_shape: tuple[int, int] | None = None
    """cameras: ``(h, w)`` of the random training crops (centre crop when acting); None:
    the paper's proportion, 76 of every 84 pixels"""
    keypoints: int = 32
    """cameras: keypoints of each camera's spatial softmax (features ``2 * keypoints``)"""

    def __post_init__(self) -> None:
        for name in ("obs_horizon", "horizon", "action_steps", "train_steps", "sample_steps"):
            value = getattr(self, name)
            if isinstance(value, bool) or int(value) != value or value < 1:
                raise ValueError(f"UnetDiffusionConfig.{name} must be a positive integer")
        if self.action_steps > self.horizon:
            raise ValueError(
                f"action_steps ({self.action_steps}) cannot exceed horizon ({self.horizon})"
            )
        if self.horizon % (2 ** (len(self.down_dims) - 1)):
            raise ValueError(
                f"horizon {self.horizon} must be divisible by 2 ** (levels - 1) = "
                f"{2 ** (len(self.down_dims) - 1)} for down_dims {self.down_dims}"
            )
        if self.sampler not in ("ddim", "ddpm"):
            raise ValueError(f"sampler must be 'ddim' or 'ddpm', got {self.sampler!r}")
        if self.sample_steps > self.train_steps:
            raise ValueError("sample_steps cannot exceed train_steps")

    @classmethod
    def cpu(cls, **overrides) -> UnetDiffusionConfig:
        """The paper's architecture at CPU widths: down dims 32-64-128 and a 64-d step
        embedding (1.2M parameters against the paper's 66M; a training step at batch 128
        takes about 0.1 s on one thread against 10 s), and a learning rate for fits of
        hundreds of steps rather than the paper's hundreds of thousands."""
        base = {"down_dims": (32, 64, 128), "step_embed_dim": 64, "lr": 1e-3}
        return cls(**{**base, **overrides})


def fit_recipe(config: UnetDiffusionConfig):
    """``BCConfig -> BCConfig``: the paper's schedule on a fit of any length (cosine,
    warm-up ``min(warmup_steps, num_steps // 10)``)."""

    def recipe(bc):
        warmup = min(config.warmup_steps, bc.num_steps // 10)
        return replace(bc, lr_schedule="cosine", warmup_steps=warmup)

    return recipe


class UnetDiffusionPolicy(TensorDictModuleBase):
    """``observation_history [*B, T_o, d] -> ACTION [*B, T_p * m]``: a sampled action
    sequence inside the bounds of ``action_spec`` (flat, as a chunked policy reads it).

    Args:
        observation_dim: ``d``.
        action_spec: ``Bounded`` ``[m]``.
        config: the hyperparameters.
        seed: initialisation seed; samples draw from a generator seeded ``seed + 1``.

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
                h, w, _ = pixel_shape
                crop = config.crop_shape or (round(h * 76 / 84), round(w * 76 / 84))
                self.rgb = RgbEncoder(tuple(pixel_shape), crop, config.keypoints)
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
        self.generator = torch.Generator().manual_seed(int(seed) + 1)

    def get_extra_state(self) -> torch.Tensor:
        """The sampling generator's state: saved with the weights, so a resumed run
        draws the samples the uninterrupted one would have."""
        return self.generator.get_state()

    def set_extra_state(self, state: torch.Tensor) -> None:
        self.generator.set_state(state.cpu())  # (a map_location may have moved it)

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
            features = self.rgb(flat, generator).reshape(h.shape[0], n, -1)
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
            x = torch.randn(shape, generator=self.generator).to(cond.device)
        x = self.schedule.sample(
            lambda xk, k: self.unet(xk, k, cond),
            x,
            sampler=self.config.sampler,
            sample_steps=self.config.sample_steps,
            generator=self.generator,
        )
        action = self.low + (self.high - self.low) * (x.clamp(-1.0, 1.0) + 1) / 2
        tensordict.set(keys.ACTION, action.reshape(*batch, -1))
        return tensordict


class UnetDiffusionLoss(ImitationLoss):
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

    def get_extra_state(self) -> torch.Tensor:
        """The generator of the steps and noise: saved with the learner (a resumed fit
        draws what the uninterrupted one would have)."""
        return self.generator.get_state()

    def set_extra_state(self, state: torch.Tensor) -> None:
        self.generator.set_state(state.cpu())  # (a map_location may have moved it)

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
        k = torch.randint(0, p.config.train_steps, (n,), generator=self.generator).to(x0.device)
        eps = torch.randn(x0.shape, generator=self.generator).to(x0.device)
        err = (p.unet(p.schedule.add_noise(x0, eps, k), k, cond) - eps).pow(2)
        if p.config.mask_padding:
            keep = ~tensordict.get(self.tensor_keys.pad).to(err.device).bool()  # [N, T_p]
            weight = keep.unsqueeze(-1).to(err.dtype).expand_as(err)
            loss = (err * weight).sum() / weight.sum().clamp_min(1.0)
        else:
            loss = err.mean()
        return TensorDict({"loss_diffusion": loss}, batch_size=[])
