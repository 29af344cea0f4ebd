"""What a pixel learner reads, and its networks: the pixel half of ``ActorCritic.pixels``.

A pixel learner reads a uint8 image ``[*batch, H, W, C]`` under its *pixel key* and,
optionally, the state ``OBSERVATION`` ``[*batch, d]`` beside it. The pixel key is
``keys.PIXELS`` (``"pixels"``, TorchRL's convention) by default, or any nested key such
as ``("pixels", "top")``: a dataset with several cameras keeps one nested key per
camera, and a learner reads the one it is built for.

* :class:`PixelInputs` names what the learner reads (key, image shape, state shape)
  and validates it at every boundary: the arrays a caller acts on, the rows a fit
  trains on (rows of images alone, with no ``OBSERVATION``, are fine when the state
  is not read), and the env a rollout steps.
* :func:`pixel_networks` builds the policy and the value, each
  ``PixelEncoder -> MLP -> head`` (:mod:`imitrl.policies.encoders`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey, unravel_key
from torch import nn
from torchrl.data import Composite, TensorSpec
from torchrl.envs import EnvBase

from imitrl import keys
from imitrl.policies.encoders import PixelEncoder, check_pixels, pixel_shape
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
    "PixelInputs",
    "PixelNetworks",
    "check_pixel_key",
    "pixel_networks",
    "spec_pixel_inputs",
]


def check_pixel_key(key: Any) -> NestedKey:
    """``key`` as a TensorDict key (``"pixels"`` or ``("pixels", "top")``), or ``ValueError``."""
    parts = key if isinstance(key, tuple) else (key,)
    if not parts or not all(isinstance(p, str) and p for p in parts):
        raise ValueError(
            f"pixel_key must be a non-empty string or a tuple of them (a nested key such as "
            f"('pixels', 'top')), got {key!r}"
        )
    return unravel_key(key)


def _lookup(obs: TensorDictBase | Mapping | Composite, key: NestedKey) -> Any:
    """``obs[key]`` of a TensorDict, a Composite spec, a dict keyed by ``key`` or a dict of
    dicts; None if absent (also when a prefix of ``key`` is a leaf, not a node)."""
    if isinstance(obs, Mapping) and key in obs:
        return obs[key]
    node: Any = obs
    for part in key if isinstance(key, tuple) else (key,):
        if not isinstance(node, (Mapping, TensorDictBase, Composite)) or part not in node.keys():
            return None
        node = node[part]
    return node


def _tensor(x: Any, name: NestedKey) -> tuple[torch.Tensor, bool]:
    """``(tensor, was_tensor)`` of a tensor or numpy array."""
    if isinstance(x, torch.Tensor):
        return x, True
    if isinstance(x, np.ndarray):
        return torch.from_numpy(x), False
    raise ValueError(f"{name!r} must be a tensor or a numpy array, got {type(x).__name__}")


@dataclass(frozen=True)
class PixelInputs:
    """What a pixel learner reads: uint8 images under ``key``, and the state when asked."""

    key: NestedKey
    """the image's key (``keys.PIXELS`` or a nested camera key)"""
    shape: tuple[int, int, int]
    """``(H, W, C)`` of one (frame-stacked) image"""
    state_shape: tuple[int, ...] | None
    """trailing shape of ``OBSERVATION`` read beside the image, or None (image alone)"""

    def __post_init__(self) -> None:
        key = check_pixel_key(self.key)
        object.__setattr__(self, "key", key)
        object.__setattr__(self, "shape", pixel_shape(self.shape))
        head = key[0] if isinstance(key, tuple) else key
        if self.state_shape is not None and head == keys.OBSERVATION:
            raise ValueError(
                f"pixel_key {key!r} lies under {keys.OBSERVATION!r}, where this learner "
                "reads the state: give the image its own key"
            )

    @property
    def in_keys(self) -> list[NestedKey]:
        """The policy's and value's ``in_keys``: the image, then the state if read."""
        return [self.key] if self.state_shape is None else [self.key, keys.OBSERVATION]

    def describe(self) -> str:
        """``"uint8 'pixels' [84, 84, 3] and 'observation' [4]"``, for error messages."""
        out = f"uint8 {self.key!r} {list(self.shape)}"
        if self.state_shape is not None:
            out += f" and {keys.OBSERVATION!r} {list(self.state_shape)}"
        return out

    def read(self, obs: Any) -> tuple[TensorDict, str]:
        """What the learner reads, validated, as a TensorDict of ``in_keys``, and the kind
        of the input (``"tensor"`` or ``"numpy"``).

        ``obs`` is a TensorDict or dict holding the image under ``key`` (a dict may
        nest it, ``{"pixels": {"top": x}}``, or key it by the tuple) and ``OBSERVATION``
        when the state is read; or, for a learner of the image alone, the image itself.
        """
        if not isinstance(obs, (TensorDictBase, Mapping)):
            if self.state_shape is not None:
                raise ValueError(
                    f"this learner reads {self.describe()}: pass a dict or TensorDict of both"
                )
            obs = {self.key: obs}
        found = _lookup(obs, self.key)
        if found is None:
            raise ValueError(
                f"this learner reads {self.describe()}; the observations lack {self.key!r} "
                f"(keys {list(obs.keys())})"
            )
        pixels, is_tensor = _tensor(found, self.key)
        check_pixels(pixels, self.shape)
        batch = pixels.shape[:-3]
        out = TensorDict({}, batch_size=batch)
        out.set(self.key, pixels)
        if self.state_shape is not None:
            out.set(keys.OBSERVATION, self._state(_lookup(obs, keys.OBSERVATION), batch))
        return out, "tensor" if is_tensor else "numpy"

    def _state(self, found: Any, batch: torch.Size) -> torch.Tensor:
        if found is None:
            raise ValueError(f"this learner reads the state {keys.OBSERVATION!r} beside the pixels")
        shape = self.state_shape
        assert shape is not None  # read reads the state only when the learner has one
        state, _ = _tensor(found, keys.OBSERVATION)
        if tuple(state.shape) != (*batch, *shape):
            raise ValueError(
                f"the state must be [..., {', '.join(map(str, shape))}] with the "
                f"pixels' batch {tuple(batch)}, got {tuple(state.shape)}"
            )
        state = state.to(torch.float32)
        if not torch.isfinite(state).all():
            raise ValueError("NaN or inf in the state given to the policy")
        return state

    def check_env(self, env: EnvBase, actions: ActionSpace | None) -> None:
        """Raise ``ValueError``, naming both, unless ``env`` gives what the learner reads
        (uint8 images under ``key`` of ``shape``, the state when read) and takes its
        ``actions`` (when known)."""
        spec = env.observation_spec_unbatched
        pixels = _lookup(spec, self.key)
        if pixels is None:
            raise ValueError(
                f"the learner reads {self.describe()}; the env has no {self.key!r} observation "
                f"(keys {list(spec.keys(include_nested=True))}; make_env(..., pixels=(H, W)) "
                "renders one)"
            )
        if pixels.dtype != torch.uint8 or tuple(pixels.shape) != self.shape:
            raise ValueError(
                f"the learner reads {self.describe()}; the env gives {self.key!r} "
                f"{pixels.dtype} {list(pixels.shape)}"
            )
        if self.state_shape is not None:
            obs = _lookup(spec, keys.OBSERVATION)
            if obs is None or tuple(obs.shape) != tuple(self.state_shape):
                theirs = "none" if obs is None else list(obs.shape)
                raise ValueError(
                    f"the learner reads {self.describe()}; the env's {keys.OBSERVATION!r} is "
                    f"{theirs}"
                )
        if actions is not None:
            check_same_actions(actions, action_space(env.action_spec_unbatched))


def spec_pixel_inputs(
    spec: Composite, pixel_key: NestedKey | None, *, state: bool
) -> tuple[TensorSpec, TensorSpec | None, NestedKey]:
    """``(image spec, state spec or None, pixel key)`` of a pixel learner of an env whose
    (unbatched) observation spec is ``spec``: the image under ``pixel_key`` (None:
    ``keys.PIXELS``), the state ``OBSERVATION`` when ``state``; ``ValueError`` naming the
    env's keys when one is missing."""
    key = check_pixel_key(keys.PIXELS if pixel_key is None else pixel_key)
    if _lookup(spec, key) is None or (state and keys.OBSERVATION not in spec.keys()):
        wanted = [key, keys.OBSERVATION] if state else [key]
        raise ValueError(
            f"a pixel learner of this env reads {wanted}; the env's observations are "
            f"{list(spec.keys(include_nested=True, leaves_only=True))}"
        )
    return spec[key], spec[keys.OBSERVATION] if state else None, key


@dataclass(frozen=True)
class PixelNetworks:
    """What :func:`pixel_networks` builds for ``ActorCritic.pixels``."""

    policy: TensorDictModuleBase
    value: Value | None
    """None unless asked for (``value=True``)"""
    normalizer: ObservationNormalizer | None
    head: str
    space: ActionSpace
    inputs: PixelInputs
    """what both networks read (``inputs.shape`` is ``(H, W, C * frames)``)"""


def pixel_networks(
    pixels: Sequence[int] | TensorSpec,
    action: int | TensorSpec,
    *,
    pixel_key: NestedKey,
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
    value: bool = False,
) -> PixelNetworks:
    """The policy and value of a pixel learner (arguments: ``ActorCritic.pixels``).

    Each network is ``PixelEncoder -> MLP(hidden) -> head``, with its own encoder; the
    state normaliser (when the state is read and ``normalize``) is shared by both.
    """
    if int(frames) != frames or frames < 1:
        raise ValueError(f"frames must be a positive integer, got {frames!r}")
    height, width, c = pixel_shape(pixels)
    obs = None if state is None else observation_space(state)
    if obs is not None and obs.kind != "vector":
        raise ValueError("a pixel learner reads a vector state [d] beside its images")
    state_shape = None if obs is None else obs.shape  # a vector space always has its shape
    inputs = PixelInputs(pixel_key, (height, width, c * int(frames)), state_shape)
    space = action_space(action)
    head = check_head(space, head)
    normalizer = (
        ObservationNormalizer(state_shape) if state_shape is not None and normalize else None
    )
    state_in = None if state_shape is None else (normalizer or nn.Identity(), state_shape[0])

    def trunk() -> tuple[list[nn.Module], int]:
        encoder = PixelEncoder(
            inputs.shape,
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
        policy = build_head(layers, width, space, head, in_keys=inputs.in_keys)
        critic = None
        if value:  # drawn after the policy: the policy is the same with or without it
            layers, width = trunk()
            critic = Value(Chain(*layers, nn.Linear(width, 1)), in_keys=inputs.in_keys)
    return PixelNetworks(policy, critic, normalizer, head, space, inputs)
