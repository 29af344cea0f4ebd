"""Diffusion Policy's camera encoder: ResNet-18 with GroupNorm, a spatial softmax, random crops.

Chi et al. (2023, Sec. 3.3 and their ``get_resnet``/``replace_bn_with_gn``; LeRobot's
``DiffusionRgbEncoder``) encode each camera with its own ResNet-18 trained from scratch:

* the torchvision ResNet-18 trunk (a 7x7/2 convolution, a 3x3/2 max pool, four stages of
  two basic residual blocks with 64, 128, 256, 512 channels; the average pool and the
  classifier removed), every BatchNorm replaced by a GroupNorm of ``channels // 16``
  groups (a batch statistic would mix the samples of a small, correlated batch and
  differ between training and acting);
* a spatial softmax head (Levine et al. 2016): a 1x1 convolution to ``K`` keypoint maps,
  a softmax over each map's pixels, and the expected ``(x, y)`` of each in ``[-1, 1]``:
  ``2K`` numbers that say *where* things are, then a linear layer and a ReLU;
* random crops in training (each sample its own offset, as the paper's
  ``CropRandomizer``), the centre crop when acting.

Written out here (60 lines) rather than taken from torchvision: the paper uses only the
architecture, trained from scratch, and the layer layout below is torchvision's
``resnet18`` (the parameter count is checked against it in the tests: 11,176,512 without
the classifier). Images arrive as the library stores them, uint8 ``[B, H, W, C]``, and
are scaled to ``[0, 1]``.
"""

from __future__ import annotations

import torch
from torch import nn

from imitrl.system.ranks import rows_drawn

__all__ = ["ResNet18GN", "RgbEncoder", "SpatialSoftmax", "crop"]


def _gn(channels: int) -> nn.GroupNorm:
    return nn.GroupNorm(channels // 16, channels)


class _BasicBlock(nn.Module):
    """torchvision's ``BasicBlock`` with GroupNorm: two 3x3 convolutions and a residual."""

    def __init__(self, cin: int, cout: int, stride: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.bn1 = _gn(cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.bn2 = _gn(cout)
        self.downsample = None
        if stride != 1 or cin != cout:
            self.downsample = nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), _gn(cout))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = torch.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return torch.relu(out + (x if self.downsample is None else self.downsample(x)))


class ResNet18GN(nn.Sequential):
    """The ResNet-18 trunk with GroupNorm: ``[B, C, H, W] -> [B, 512, ceil(H/32), ceil(W/32)]``."""

    def __init__(self, in_channels: int = 3) -> None:
        layers: list[nn.Module] = [
            nn.Conv2d(in_channels, 64, 7, 2, 3, bias=False),
            _gn(64),
            nn.ReLU(),
            nn.MaxPool2d(3, 2, 1),
        ]
        cin = 64
        for cout, stride in ((64, 1), (128, 2), (256, 2), (512, 2)):
            layers.append(nn.Sequential(_BasicBlock(cin, cout, stride), _BasicBlock(cout, cout, 1)))
            cin = cout
        super().__init__(*layers)


class SpatialSoftmax(nn.Module):
    """``[B, C, H, W] -> [B, 2K]``: the expected ``(x, y)`` in ``[-1, 1]`` of ``K`` softmax
    keypoint maps (a 1x1 convolution makes them from the ``C`` features)."""

    grid: torch.Tensor  # [HW, 2], a buffer

    def __init__(self, channels: int, height: int, width: int, keypoints: int = 32) -> None:
        super().__init__()
        self.keypoints = nn.Conv2d(channels, keypoints, 1)
        ys, xs = torch.meshgrid(
            torch.linspace(-1.0, 1.0, height), torch.linspace(-1.0, 1.0, width), indexing="ij"
        )
        self.register_buffer("grid", torch.stack([xs.reshape(-1), ys.reshape(-1)], -1))  # [HW, 2]

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        maps = self.keypoints(features).flatten(2)  # [B, K, HW]
        attention = torch.softmax(maps, dim=-1)
        return (attention @ self.grid).flatten(1)  # [B, K, 2] -> [B, 2K]


def crop(
    images: torch.Tensor,
    size: tuple[int, int],
    generator: torch.Generator | None,
    per_row: int = 1,
):
    """``[B, C, H, W]`` cropped to ``size``: each sample at its own offset drawn from
    ``generator``, or all at the centre when ``generator`` is None. ``per_row``: images
    per batch row (a row's observation history), consecutive: the offsets are per-row
    draws (:func:`~imitrl.system.ranks.rows_drawn`: a data-parallel rank keeps its rows')."""
    h, w = images.shape[-2:]
    ch, cw = size
    if (ch, cw) == (h, w):
        return images
    if generator is None:
        top, left = (h - ch) // 2, (w - cw) // 2
        return images[..., top : top + ch, left : left + cw]
    n = images.shape[0]

    def offsets(high: int) -> torch.Tensor:
        def draw(m: int) -> torch.Tensor:
            return torch.randint(0, high, (m * per_row,), generator=generator).reshape(m, -1)

        return rows_drawn(draw, n // per_row).reshape(-1)

    tops, lefts = offsets(h - ch + 1), offsets(w - cw + 1)
    rows = (tops[:, None] + torch.arange(ch)).to(images.device)  # [B, ch]
    cols = (lefts[:, None] + torch.arange(cw)).to(images.device)  # [B, cw]
    b = torch.arange(n, device=images.device)[:, None, None]
    out = images.permute(0, 2, 3, 1)[b, rows[:, :, None], cols[:, None, :]]  # [B, ch, cw, C]
    return out.permute(0, 3, 1, 2)


class RgbEncoder(nn.Module):
    """uint8 ``[B, H, W, C]`` -> features ``[B, 2K]`` (module docstring).

    Args:
        image_shape: ``(H, W, C)``.
        crop_shape: ``(h, w)`` of the crops (the paper: 76x76 of 84x84; LeRobot 84 of 96);
            None: no crop.
        keypoints: ``K`` of the spatial softmax.
    """

    def __init__(
        self,
        image_shape: tuple[int, int, int],
        crop_shape: tuple[int, int] | None = None,
        keypoints: int = 32,
    ) -> None:
        super().__init__()
        h, w, c = (int(s) for s in image_shape)
        self.image_shape = (h, w, c)
        ch, cw = (h, w) if crop_shape is None else (int(s) for s in crop_shape)
        self.crop_shape = (ch, cw)
        if not (0 < self.crop_shape[0] <= h and 0 < self.crop_shape[1] <= w):
            raise ValueError(f"crop_shape {self.crop_shape} must fit the image {(h, w)}")
        self.backbone = ResNet18GN(c)
        with torch.no_grad():  # the trunk's output size at the crop's size
            fh, fw = self.backbone(torch.zeros(1, c, *self.crop_shape)).shape[-2:]
        if fh * fw < 2:
            raise ValueError(
                f"crops of {self.crop_shape} leave the ResNet a 1x1 feature map, where a "
                "spatial softmax cannot tell positions apart: use images (crops) of at "
                "least 33 pixels on a side"
            )
        self.pool = SpatialSoftmax(512, fh, fw, keypoints)
        self.out = nn.Linear(2 * keypoints, 2 * keypoints)
        self.features = 2 * keypoints

    def forward(
        self, images: torch.Tensor, generator: torch.Generator | None = None, per_row: int = 1
    ):
        """Features of ``images``; random crops drawn from ``generator`` when given
        (training), the centre crop otherwise (acting); ``per_row`` images per batch row
        (:func:`crop`)."""
        if tuple(images.shape[-3:]) != self.image_shape:
            raise ValueError(
                f"the camera encoder was built for images {self.image_shape} (H, W, C), "
                f"got {tuple(images.shape[-3:])}"
            )
        x = images.movedim(-1, -3).float() / 255.0
        x = crop(x, self.crop_shape, generator, per_row)
        return torch.relu(self.out(self.pool(self.backbone(x))))
