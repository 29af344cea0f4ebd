"""The CNN encoder of pixel learners: uint8 images (and the state) -> features.

Images are stored as they come from TorchRL's renderers and LeRobot datasets: uint8
``[*batch, H, W, C]`` under a pixel key (``keys.PIXELS`` or a nested camera key, see
:mod:`imitrl.policies.pixel_learner`; ``C = 3 * frames`` when frames are stacked
on the channel axis, e.g. by ``CatFrames(N=frames, dim=-1, in_keys=["pixels"])``). The
learner alone turns them into what a CNN takes, inside its network::

    x = pixels.float() / 255                    # [*B, H, W, C] uint8 -> float in [0, 1]
    x = x.movedim(-1, -3)                       # [*B, C, H, W]
    f = ConvNet(x)                              # [*B, F] (torchrl.modules.ConvNet, flattened)
    f = cat([f, normalizer(observation)], -1)   # only when the learner reads the state too

so the buffer, the expert and the env keep the raw uint8 image (4x smaller than float).
``ActorCritic.pixels`` puts an MLP and any head of :mod:`imitrl.policies.heads` after ``f``
(:func:`imitrl.policies.pixel_learner.pixel_networks`).

Default convolutions (``kernels=None``): three layers of ``channels`` with the DQN
("Nature") kernels ``(8, 4, 3)`` / strides ``(4, 2, 1)`` when the image is at least
36 pixels on its short side (84x84 -> 7x7); otherwise kernel 3, stride 2, padding 1 per
layer (32x32 -> 4x4), which keeps small images from shrinking to nothing.

A learner reads one camera; with several (nested ``("pixels", name)`` keys) it is built
for one of them (``pixel_key``).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn
from torchrl.data import TensorSpec
from torchrl.modules import ConvNet

from imitrl import keys

__all__ = ["PixelEncoder", "check_pixels", "conv_layout", "pixel_shape"]

_NATURE_MIN_SIDE = 36  # 8/4 -> 2/1 -> 1 needs 36 px: (36 - 8) // 4 + 1 = 8, (8 - 4) // 2 + 1 = 3


def pixel_shape(pixels: Sequence[int] | TensorSpec) -> tuple[int, int, int]:
    """``(H, W, C)`` of one image from a shape or the env's (unbatched) uint8 pixel spec."""
    if isinstance(pixels, TensorSpec):
        if pixels.dtype != torch.uint8:
            raise ValueError(
                f"pixel learners read uint8 images [H, W, C]; the pixel spec is {pixels.dtype} "
                "(store images as uint8 HWC, as TorchRL's PixelRenderTransform and LeRobot do)"
            )
        pixels = tuple(pixels.shape)
    shape = tuple(int(s) for s in pixels)
    if len(shape) != 3 or min(shape) < 1:
        raise ValueError(
            f"a pixel shape is (H, W, C) with positive sizes, got {shape} (for a batched env "
            "pass env.observation_spec_unbatched['pixels'])"
        )
    return shape


def conv_layout(
    shape: tuple[int, int, int],
    channels: Sequence[int],
    kernels: Sequence[int] | None,
    strides: Sequence[int] | None,
    paddings: Sequence[int] | None = None,
) -> tuple[list[int], list[int], list[int]]:
    """``(kernels, strides, paddings)`` of the conv layers (defaults: module docstring)."""
    n = len(channels)
    if n < 1 or min(channels) < 1:
        raise ValueError(f"channels must be one or more positive widths, got {tuple(channels)}")
    nature = n == 3 and min(shape[:2]) >= _NATURE_MIN_SIDE
    if kernels is None:
        kernels = [8, 4, 3] if nature else [3] * n
    if strides is None:
        strides = [4, 2, 1] if nature else [2] * n
    if paddings is None:
        paddings = [0] * n if nature else [k // 2 for k in kernels]
    out = [list(map(int, kernels)), list(map(int, strides)), list(map(int, paddings))]
    if any(len(x) != n for x in out):
        raise ValueError(
            f"kernels {out[0]}, strides {out[1]} and paddings {out[2]} need one entry per "
            f"conv layer ({n}, from channels)"
        )
    return out[0], out[1], out[2]


def check_pixels(pixels: torch.Tensor, shape: tuple[int, int, int]) -> None:
    """Raise ``ValueError`` unless ``pixels`` is uint8 ``[*batch, *shape]``."""
    if not isinstance(pixels, torch.Tensor):
        raise ValueError(f"pixels must be a tensor, got {type(pixels).__name__}")
    if pixels.dtype != torch.uint8 or tuple(pixels.shape[-3:]) != shape:
        raise ValueError(
            f"this learner reads uint8 pixels [..., {', '.join(map(str, shape))}], got "
            f"{pixels.dtype} {tuple(pixels.shape)}"
        )


class PixelEncoder(nn.Module):
    """uint8 ``[*B, H, W, C]`` (+ state ``[*B, d]``) -> float features ``[*B, out_features]``.

    Args:
        shape: ``(H, W, C)`` of the images it reads.
        channels: output channels of each conv layer.
        kernels, strides, paddings: per layer (None: see the module docstring).
        activation: after every conv layer.
        state: the normaliser (or ``nn.Identity``) of a state ``[d]`` read beside the
            image, with its width ``d``; None: the image alone.
    """

    def __init__(
        self,
        shape: tuple[int, int, int],
        *,
        channels: Sequence[int],
        kernels: Sequence[int] | None = None,
        strides: Sequence[int] | None = None,
        paddings: Sequence[int] | None = None,
        activation: type[nn.Module] = nn.ReLU,
        state: tuple[nn.Module, int] | None = None,
    ) -> None:
        super().__init__()
        self.shape = pixel_shape(shape)
        k, s, p = conv_layout(self.shape, channels, kernels, strides, paddings)
        height, width, c = self.shape
        self.conv = ConvNet(
            in_features=c,
            num_cells=list(channels),
            kernel_sizes=k,
            strides=s,
            paddings=p,
            activation_class=activation,
        )
        try:
            with torch.no_grad():
                conv_width = self.conv(torch.zeros(1, c, height, width)).shape[-1]
        except RuntimeError as err:
            raise ValueError(
                f"images of {height}x{width} are too small for kernels {k}, strides {s}, "
                f"paddings {p} ({err})"
            ) from None
        self.state = None if state is None else state[0]
        self.state_width = 0 if state is None else int(state[1])
        self.out_features = int(conv_width) + self.state_width

    def forward(self, pixels: torch.Tensor, state: torch.Tensor | None = None) -> torch.Tensor:
        check_pixels(pixels, self.shape)
        x = pixels.to(torch.float32).div(255.0).movedim(-1, -3)  # [*B, C, H, W] in [0, 1]
        features = self.conv(x)
        if self.state is None:
            return features
        if state is None:
            raise ValueError(f"this encoder reads the state {keys.OBSERVATION!r} beside the pixels")
        return torch.cat([features, self.state(state.to(torch.float32))], dim=-1)

    def extra_repr(self) -> str:
        return f"shape={self.shape}, state_width={self.state_width}, out={self.out_features}"
