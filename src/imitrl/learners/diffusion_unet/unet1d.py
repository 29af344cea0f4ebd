"""Diffusion Policy's noise-prediction network: a 1-D temporal U-Net conditioned by FiLM.

Chi et al. (2023), "Diffusion Policy: Visuomotor Policy Learning via Action Diffusion",
Sec. 3.2 and their ``ConditionalUnet1D``; LeRobot's ``DiffusionConditionalUnet1d`` is the
same network. The input is a noisy action sequence ``[B, T, m]``, treated as ``m``
channels over ``T`` time steps; the output is the predicted noise of the same shape.

* **Convolutions over time.** Each block is ``Conv1d -> GroupNorm -> Mish``; a
  :class:`ConditionalResidualBlock1D` stacks two with a residual path. The encoder halves
  the time axis between levels (strided convolution), the decoder doubles it back
  (transposed convolution) after concatenating the encoder's features of the same length
  (skip connections), so ``T`` must be divisible by ``2 ** (levels - 1)``. As in the
  paper's code, the features of the finest encoder level are not concatenated back.
* **FiLM conditioning** (Perez et al. 2018). The diffusion step ``k`` (a sinusoidal
  embedding through a small MLP) and the observation features (``global_cond``: the
  flattened observation history, or an image encoder's features) form one vector; each
  residual block maps it to a per-channel scale and bias applied after its first
  convolution: ``h <- scale(c) * h + bias(c)``.
* Widths: ``down_dims`` per level (the paper's state configs 256-512-1024; LeRobot's
  default 512-1024-2048), ``kernel_size`` 5, ``n_groups`` 8, step embedding 256.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import cast

import torch
from torch import nn

__all__ = [
    "ConditionalResidualBlock1D",
    "ConditionalUnet1D",
    "Conv1dBlock",
    "SinusoidalStepEmbedding",
]


class SinusoidalStepEmbedding(nn.Module):
    """``k [B] -> [B, dim]``: ``sin(k w_i), cos(k w_i)`` with ``w_i = 10000 ** (-i / (dim/2 - 1))``
    (the transformer's position encoding, as Diffusion Policy embeds the step)."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        if dim < 4 or dim % 2:
            raise ValueError(f"the step embedding needs an even dim >= 4, got {dim}")
        self.dim = int(dim)

    def forward(self, k: torch.Tensor) -> torch.Tensor:
        half = self.dim // 2
        scale = math.log(10000) / (half - 1)
        freqs = torch.exp(torch.arange(half, device=k.device, dtype=torch.float32) * -scale)
        args = k.float()[:, None] * freqs[None, :]
        return torch.cat([args.sin(), args.cos()], dim=-1)


class Conv1dBlock(nn.Module):
    """``Conv1d (same length) -> GroupNorm -> Mish`` over ``[B, C, T]``."""

    def __init__(
        self, in_channels: int, out_channels: int, kernel_size: int, n_groups: int
    ) -> None:
        super().__init__()
        self.block = nn.Sequential(
            nn.Conv1d(in_channels, out_channels, kernel_size, padding=kernel_size // 2),
            nn.GroupNorm(n_groups, out_channels),
            nn.Mish(),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.block(x)


class ConditionalResidualBlock1D(nn.Module):
    """Two :class:`Conv1dBlock` with FiLM between them and a residual path (module docstring).

    ``forward(x [B, C_in, T], cond [B, D]) -> [B, C_out, T]``.
    """

    def __init__(
        self, in_channels: int, out_channels: int, cond_dim: int, kernel_size: int, n_groups: int
    ) -> None:
        super().__init__()
        self.blocks = nn.ModuleList(
            [
                Conv1dBlock(in_channels, out_channels, kernel_size, n_groups),
                Conv1dBlock(out_channels, out_channels, kernel_size, n_groups),
            ]
        )
        # FiLM: a scale and a bias per channel from the conditioning vector
        self.cond_encoder = nn.Sequential(nn.Mish(), nn.Linear(cond_dim, 2 * out_channels))
        self.out_channels = int(out_channels)
        self.residual = (
            nn.Conv1d(in_channels, out_channels, 1)
            if in_channels != out_channels
            else nn.Identity()
        )

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        out = self.blocks[0](x)
        film = self.cond_encoder(cond).reshape(cond.shape[0], 2, self.out_channels, 1)
        out = film[:, 0] * out + film[:, 1]
        out = self.blocks[1](out)
        return out + self.residual(x)


class ConditionalUnet1D(nn.Module):
    """``eps_theta(x_k [B, T, m], k [B], global_cond [B, G]) -> [B, T, m]`` (module docstring).

    Args:
        action_dim: ``m``, channels of the action sequence.
        global_cond_dim: ``G``, length of the observation features.
        down_dims: channels of each level (its length is the number of levels).
        kernel_size: temporal kernel of every convolution (odd).
        n_groups: GroupNorm groups (each level's channels must be divisible by it).
        step_embed_dim: size of the diffusion-step embedding.
    """

    def __init__(
        self,
        action_dim: int,
        global_cond_dim: int,
        *,
        down_dims: Sequence[int] = (256, 512, 1024),
        kernel_size: int = 5,
        n_groups: int = 8,
        step_embed_dim: int = 256,
    ) -> None:
        super().__init__()
        dims = [int(d) for d in down_dims]
        if not dims or any(d % n_groups for d in dims):
            raise ValueError(f"down_dims {dims} must be non-empty multiples of n_groups={n_groups}")
        if kernel_size % 2 != 1:
            raise ValueError(
                f"kernel_size must be odd (same-length convolutions), got {kernel_size}"
            )
        self.levels = len(dims)
        self.step_encoder = nn.Sequential(
            SinusoidalStepEmbedding(step_embed_dim),
            nn.Linear(step_embed_dim, 4 * step_embed_dim),
            nn.Mish(),
            nn.Linear(4 * step_embed_dim, step_embed_dim),
        )
        cond = step_embed_dim + int(global_cond_dim)

        def block(a: int, b: int) -> ConditionalResidualBlock1D:
            return ConditionalResidualBlock1D(a, b, cond, kernel_size, n_groups)

        pairs = list(zip([int(action_dim), *dims[:-1]], dims))
        self.down = nn.ModuleList()
        for i, (a, b) in enumerate(pairs):
            last = i == len(pairs) - 1
            halve = nn.Identity() if last else nn.Conv1d(b, b, 3, stride=2, padding=1)
            self.down.append(nn.ModuleList([block(a, b), block(b, b), halve]))
        self.mid = nn.ModuleList([block(dims[-1], dims[-1]), block(dims[-1], dims[-1])])
        # every decoder level doubles the time axis back (the encoder halved it levels - 1
        # times); the finest level's skip features are left unused, as in the paper's code
        self.up = nn.ModuleList()
        for a, b in reversed(pairs[1:]):
            double = nn.ConvTranspose1d(a, a, 4, stride=2, padding=1)
            self.up.append(nn.ModuleList([block(2 * b, a), block(a, a), double]))
        self.final = nn.Sequential(
            Conv1dBlock(dims[0], dims[0], kernel_size, n_groups), nn.Conv1d(dims[0], action_dim, 1)
        )

    def forward(self, x: torch.Tensor, k: torch.Tensor, global_cond: torch.Tensor) -> torch.Tensor:
        T = x.shape[-2]
        if T % (2 ** (self.levels - 1)):
            raise ValueError(
                f"the action horizon {T} must be divisible by 2 ** (levels - 1) = "
                f"{2 ** (self.levels - 1)} (the U-Net halves it between levels)"
            )
        if k.ndim == 0:
            k = k.expand(x.shape[0])
        cond = torch.cat([self.step_encoder(k), global_cond.to(x.dtype)], dim=-1)
        h = x.transpose(-1, -2)  # [B, m, T]
        skips = []
        # torch's ModuleList is not generic: each level is a ModuleList (block, block, resample)
        for first, second, halve in cast("Iterable[nn.ModuleList]", self.down):
            h = second(first(h, cond), cond)
            skips.append(h)
            h = halve(h)
        for block in self.mid:
            h = block(h, cond)
        for first, second, double in cast("Iterable[nn.ModuleList]", self.up):
            h = torch.cat([h, skips.pop()], dim=1)
            h = double(second(first(h, cond), cond))
        return self.final(h).transpose(-1, -2)
