"""DDPM noise schedules, the forward noising, and the DDPM and DDIM reverse updates.

The arithmetic Diffusion Policy uses (Chi et al. 2023, through ``diffusers``' DDPM and
DDIM schedulers; LeRobot's reproduction the same), written out so that each update can
be checked by hand (``tests/learners/diffusion_unet/test_unet1d.py``):

* **Schedules.** ``squaredcos_cap_v2`` (Nichol & Dhariwal 2021): ``abar(s) = cos(((s +
  0.008) / 1.008) pi / 2) ** 2`` and ``beta_k = min(1 - abar((k + 1) / K) / abar(k / K),
  0.999)``; ``linear``: ``beta_k`` evenly from ``beta_start`` to ``beta_end``.
  ``alphas_cumprod[k] = prod_{j <= k} (1 - beta_j)``.
* **Forward.** ``x_k = sqrt(abar_k) x_0 + sqrt(1 - abar_k) eps``; the network predicts ``eps``.
* **DDPM step** (``variance_type="fixed_small"``): ``x0_hat = (x_k - sqrt(1 - abar_k) eps) /
  sqrt(abar_k)``, clipped to ``[-1, 1]``; the posterior mean ``sqrt(abar_prev) beta_k' /
  (1 - abar_k) x0_hat + sqrt(alpha_k') (1 - abar_prev) / (1 - abar_k) x_k`` with ``alpha_k'
  = abar_k / abar_prev``, ``beta_k' = 1 - alpha_k'``; plus ``sqrt((1 - abar_prev) / (1 -
  abar_k) beta_k') z`` for ``k > 0``.
* **DDIM step** (eta = 0, Song et al. 2021): ``x_prev = sqrt(abar_prev) x0_hat + sqrt(1 -
  abar_prev) eps`` on the timesteps ``k_i = i * (K // S)``, ``i = S-1 .. 0``, with
  ``abar`` before the first step taken as 1 (``set_alpha_to_one``).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

__all__ = ["SCHEDULES", "NoiseSchedule"]

SCHEDULES = ("squaredcos_cap_v2", "linear")


def _squaredcos_betas(num_steps: int, max_beta: float = 0.999) -> torch.Tensor:
    def abar(s: float) -> float:
        return math.cos((s + 0.008) / 1.008 * math.pi / 2) ** 2

    betas = [
        min(1 - abar((k + 1) / num_steps) / abar(k / num_steps), max_beta) for k in range(num_steps)
    ]
    return torch.tensor(betas, dtype=torch.float32)


class NoiseSchedule:
    """A DDPM schedule of ``num_steps`` steps and its reverse updates (module docstring).

    Args:
        num_steps: ``K``, the training steps (the paper's 100).
        kind: one of :data:`SCHEDULES`.
        beta_start, beta_end: the ``linear`` schedule's ends.
        clip_sample: clip ``x0_hat`` to ``[-1, 1]`` in every update (actions live there).
    """

    def __init__(
        self,
        num_steps: int = 100,
        kind: str = "squaredcos_cap_v2",
        *,
        beta_start: float = 1e-4,
        beta_end: float = 0.02,
        clip_sample: bool = True,
    ) -> None:
        if int(num_steps) != num_steps or num_steps < 1:
            raise ValueError(f"num_steps must be a positive integer, got {num_steps!r}")
        if kind not in SCHEDULES:
            raise ValueError(f"kind must be one of {SCHEDULES}, got {kind!r}")
        self.num_steps, self.kind, self.clip_sample = int(num_steps), kind, bool(clip_sample)
        if kind == "linear":
            self.betas = torch.linspace(beta_start, beta_end, self.num_steps, dtype=torch.float32)
        else:
            self.betas = _squaredcos_betas(self.num_steps)
        self.alphas_cumprod = torch.cumprod(1.0 - self.betas, dim=0)

    # ------------------------------------------------------------------ forward
    def add_noise(self, x0: torch.Tensor, eps: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
        """``sqrt(abar_k) x0 + sqrt(1 - abar_k) eps`` with ``k [B]`` per leading row."""
        abar = self.alphas_cumprod.to(x0.device)[k].reshape(-1, *([1] * (x0.ndim - 1)))
        return abar.sqrt() * x0 + (1 - abar).sqrt() * eps

    # ------------------------------------------------------------------ reverse
    def _abar(self, k: int, device) -> torch.Tensor:
        if k < 0:
            return torch.tensor(1.0, device=device)
        return self.alphas_cumprod[k].to(device)

    def _x0(self, x: torch.Tensor, eps: torch.Tensor, abar: torch.Tensor) -> torch.Tensor:
        x0 = (x - (1 - abar).sqrt() * eps) / abar.sqrt()
        return x0.clamp(-1.0, 1.0) if self.clip_sample else x0

    def ddpm_step(
        self, eps: torch.Tensor, k: int, x: torch.Tensor, noise: torch.Tensor | None
    ) -> torch.Tensor:
        """``x_{k-1}`` from ``x_k`` and the predicted ``eps`` (``noise``: ``z``, used for ``k > 0``)."""
        abar, abar_prev = self._abar(k, x.device), self._abar(k - 1, x.device)
        alpha, beta = abar / abar_prev, 1 - abar / abar_prev
        x0 = self._x0(x, eps, abar)
        mean = (abar_prev.sqrt() * beta / (1 - abar)) * x0 + (
            alpha.sqrt() * (1 - abar_prev) / (1 - abar)
        ) * x
        if k == 0:
            return mean
        assert noise is not None  # the caller draws z for every k > 0
        variance = ((1 - abar_prev) / (1 - abar) * beta).clamp_min(1e-20)
        return mean + variance.sqrt() * noise

    def ddim_timesteps(self, sample_steps: int) -> list[int]:
        """``k_i = i * (K // S)`` for ``i = S-1 .. 0`` (diffusers' ``"leading"`` spacing)."""
        if int(sample_steps) != sample_steps or not 1 <= sample_steps <= self.num_steps:
            raise ValueError(f"sample_steps must be in [1, {self.num_steps}], got {sample_steps!r}")
        ratio = self.num_steps // int(sample_steps)
        return [i * ratio for i in reversed(range(int(sample_steps)))]

    def ddim_step(self, eps: torch.Tensor, k: int, prev: int, x: torch.Tensor) -> torch.Tensor:
        """``x_prev`` from ``x_k`` by DDIM (eta = 0); ``prev < 0``: the last step."""
        abar, abar_prev = self._abar(k, x.device), self._abar(prev, x.device)
        return abar_prev.sqrt() * self._x0(x, eps, abar) + (1 - abar_prev).sqrt() * eps

    def sample(
        self,
        eps_model: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
        x: torch.Tensor,
        *,
        sampler: str = "ddim",
        sample_steps: int = 10,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Denoise the latent ``x`` ``[B, ...]`` with ``eps_model(x_k, k [B])``.

        ``sampler``: ``"ddpm"`` (every one of the ``K`` steps, fresh noise from
        ``generator`` at each) or ``"ddim"`` (``sample_steps`` deterministic steps).
        """
        batch = x.shape[0]
        if sampler == "ddpm":
            for k in reversed(range(self.num_steps)):
                eps = eps_model(x, torch.full((batch,), k, device=x.device, dtype=torch.long))
                z = None
                if k > 0:
                    z = torch.randn(x.shape, generator=generator, dtype=x.dtype).to(x.device)
                x = self.ddpm_step(eps, k, x, z)
            return x
        if sampler != "ddim":
            raise ValueError(f"sampler must be 'ddpm' or 'ddim', got {sampler!r}")
        steps = self.ddim_timesteps(sample_steps)
        ratio = self.num_steps // int(sample_steps)
        for k in steps:
            eps = eps_model(x, torch.full((batch,), k, device=x.device, dtype=torch.long))
            x = self.ddim_step(eps, k, k - ratio, x)
        return x
