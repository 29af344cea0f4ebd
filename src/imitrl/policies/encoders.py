"""Pixel learners: a CNN encoder in front of every head, reading ``PIXELS`` (and the state).

Images are stored as they come from TorchRL's renderers and LeRobot datasets: uint8
``[*batch, H, W, C]`` under ``keys.PIXELS`` (``C = 3 * frames`` when frames are stacked
on the channel axis, e.g. by ``CatFrames(N=frames, dim=-1, in_keys=["pixels"])``). The
learner alone turns them into what a CNN takes, inside its network::

    x = pixels.float() / 255                    # [*B, H, W, C] uint8 -> float in [0, 1]
    x = x.movedim(-1, -3)                       # [*B, C, H, W]
    f = ConvNet(x)                              # [*B, F] (torchrl.modules.ConvNet, flattened)
    f = cat([f, normalizer(observation)], -1)   # only when the learner reads the state too

so the buffer, the expert and the env keep the raw uint8 image (4x smaller than float).
``ActorCritic.pixels`` puts an MLP and any head of :mod:`imitrl.policies.heads` after ``f``.

Default convolutions (``kernels=None``): three layers of ``channels`` with the DQN
("Nature") kernels ``(8, 4, 3)`` / strides ``(4, 2, 1)`` when the image is at least
36 pixels on its short side (84x84 -> 7x7); otherwise kernel 3, stride 2, padding 1 per
layer (32x32 -> 4x4), which keeps small images from shrinking to nothing.

Several cameras (nested ``("pixels", name)`` keys) are not supported yet: one image key.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torchrl.data import TensorSpec
from torchrl.envs import EnvBase
from torchrl.modules import ConvNet

from imitrl import keys
from imitrl.policies.heads import Chain, build_head, check_head, mlp
from imitrl.policies.modules import Value
from imitrl.policies.normalization import ObservationNormalizer
from imitrl.policies.specs import (
    ActionSpace,
    action_space,
    check_same_actions,
    observation_space,
)

__all__ = [
    "PixelEncoder",
    "PixelNetworks",
    "check_pixel_env",
    "check_pixels",
    "conv_layout",
    "pixel_inputs",
    "pixel_networks",
    "pixel_shape",
]

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
    return shape  # type: ignore[return-value]


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
        channels: Sequence[int] = (32, 64, 64),
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


def _tensor(x: Any, name: str) -> tuple[torch.Tensor, bool]:
    """``(tensor, was_tensor)`` of a tensor or numpy array."""
    if isinstance(x, torch.Tensor):
        return x, True
    if isinstance(x, np.ndarray):
        return torch.from_numpy(x), False
    raise ValueError(f"{name} must be a tensor or a numpy array, got {type(x).__name__}")


def pixel_inputs(
    obs: Any, shape: tuple[int, int, int], state_shape: tuple[int, ...] | None
) -> tuple[dict, str]:
    """What a pixel learner reads, validated: ``({PIXELS: .., [OBSERVATION: ..]}, kind)``.

    ``obs`` is a TensorDict or dict holding ``PIXELS`` (and ``OBSERVATION`` when the
    learner reads the state), or, for a learner of pixels alone, the image itself.
    ``kind`` is ``"tensor"`` when the inputs were tensors, else ``"numpy"``.
    """
    if not isinstance(obs, (TensorDictBase, Mapping)):
        if state_shape is not None:
            raise ValueError(
                f"this learner reads {keys.PIXELS!r} and {keys.OBSERVATION!r}: pass a dict or "
                "TensorDict with both"
            )
        obs = {keys.PIXELS: obs}
    if keys.PIXELS not in obs.keys():
        raise ValueError(f"the observations lack {keys.PIXELS!r} (keys {list(obs.keys())})")
    pixels, is_tensor = _tensor(obs[keys.PIXELS], keys.PIXELS)
    check_pixels(pixels, shape)
    out = {keys.PIXELS: pixels}
    if state_shape is not None:
        if keys.OBSERVATION not in obs.keys():
            raise ValueError(f"this learner reads the state {keys.OBSERVATION!r} beside the pixels")
        state, _ = _tensor(obs[keys.OBSERVATION], keys.OBSERVATION)
        if tuple(state.shape) != (*pixels.shape[:-3], *state_shape):
            raise ValueError(
                f"the state must be [..., {', '.join(map(str, state_shape))}] with the pixels' "
                f"batch {tuple(pixels.shape[:-3])}, got {tuple(state.shape)}"
            )
        state = state.to(torch.float32)
        if not torch.isfinite(state).all():
            raise ValueError("NaN or inf in the state given to the policy")
        out[keys.OBSERVATION] = state
    return out, "tensor" if is_tensor else "numpy"


@dataclass(frozen=True)
class PixelNetworks:
    """What :func:`pixel_networks` builds for ``ActorCritic.pixels``."""

    policy: TensorDictModuleBase
    value: Value
    normalizer: ObservationNormalizer | None
    head: str
    space: ActionSpace
    shape: tuple[int, int, int]
    """``(H, W, C * frames)`` the learner reads"""
    state_shape: tuple[int] | None


def pixel_networks(
    pixels: Sequence[int] | TensorSpec,
    action: int | TensorSpec,
    *,
    state: int | TensorSpec | None,
    frames: int,
    head: str | None,
    channels: Sequence[int],
    kernels: Sequence[int] | None,
    strides: Sequence[int] | None,
    hidden: Sequence[int],
    activation: type[nn.Module],
    seed: int,
    normalize: bool,
) -> PixelNetworks:
    """The policy and value of a pixel learner (arguments: ``ActorCritic.pixels``).

    Each network is ``PixelEncoder -> MLP(hidden) -> head``, with its own encoder; the
    state normaliser (when the state is read and ``normalize``) is shared by both.
    """
    if int(frames) != frames or frames < 1:
        raise ValueError(f"frames must be a positive integer, got {frames!r}")
    height, width, c = pixel_shape(pixels)
    shape = (height, width, c * int(frames))
    obs = None if state is None else observation_space(state)
    if obs is not None and obs.kind != "vector":
        raise ValueError("a pixel learner reads a vector state [d] beside its images")
    space = action_space(action)
    head = check_head(space, head)
    in_keys = [keys.PIXELS] if obs is None else [keys.PIXELS, keys.OBSERVATION]
    normalizer = ObservationNormalizer(obs.shape) if obs is not None and normalize else None
    state_in = None if obs is None else (normalizer or nn.Identity(), obs.shape[0])

    def trunk() -> tuple[list[nn.Module], int]:
        encoder = PixelEncoder(
            shape,
            channels=channels,
            kernels=kernels,
            strides=strides,
            activation=activation,
            state=state_in,
        )
        sizes = [encoder.out_features, *[int(h) for h in hidden]]
        layers = [encoder, *mlp(sizes, activation), activation()] if hidden else [encoder]
        return layers, sizes[-1]

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        layers, width = trunk()
        policy = build_head(layers, width, space, head, in_keys=in_keys)
        layers, width = trunk()
        value = Value(Chain(*layers, nn.Linear(width, 1)), in_keys=in_keys)
    state_shape = None if obs is None else obs.shape
    return PixelNetworks(policy, value, normalizer, head, space, shape, state_shape)


def check_pixel_env(
    env: EnvBase,
    shape: tuple[int, int, int],
    state_shape: tuple[int, ...] | None,
    actions: ActionSpace | None,
) -> None:
    """Raise ``ValueError``, naming both, unless ``env`` gives the images (and state) a pixel
    learner reads, uint8 ``PIXELS`` of ``shape`` (and ``OBSERVATION`` ``[*state_shape]``),
    and takes its ``actions`` (when known)."""
    spec = env.observation_spec_unbatched
    mine = f"uint8 {keys.PIXELS!r} {list(shape)}"
    if state_shape is not None:
        mine += f" and {keys.OBSERVATION!r} {list(state_shape)}"
    pixels = spec.get(keys.PIXELS, None)
    if pixels is None:
        raise ValueError(
            f"the learner reads {mine}; the env has no {keys.PIXELS!r} observation "
            f"(keys {list(spec.keys())}; make_env(..., pixels=(H, W)) renders one)"
        )
    if pixels.dtype != torch.uint8 or tuple(pixels.shape) != shape:
        raise ValueError(
            f"the learner reads {mine}; the env gives {keys.PIXELS!r} {pixels.dtype} "
            f"{list(pixels.shape)}"
        )
    if state_shape is not None:
        obs = spec.get(keys.OBSERVATION, None)
        if obs is None or tuple(obs.shape) != tuple(state_shape):
            theirs = "none" if obs is None else list(obs.shape)
            raise ValueError(
                f"the learner reads {mine}; the env's {keys.OBSERVATION!r} is {theirs}"
            )
    if actions is not None:
        check_same_actions(actions, action_space(env.action_spec_unbatched))
