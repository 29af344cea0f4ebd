"""Diffusion Policy's hyperparameters, every one in one frozen dataclass with the paper's values (:class:`UnetDiffusionConfig`), and its fit schedule (:func:`fit_recipe`)."""

from __future__ import annotations

from dataclasses import dataclass, replace

__all__ = ["UnetDiffusionConfig", "fit_recipe"]


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
    """the noise schedule (:data:`~imitrl.learners.diffusion_unet.noise_schedule.SCHEDULES`)"""
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
