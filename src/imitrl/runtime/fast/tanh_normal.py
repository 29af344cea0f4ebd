"""A tanh-normal actor's action without building its distribution.

Accelerated internals of :mod:`imitrl.runtime.paths` (import them from there, nowhere else).

Acting through TorchRL's ``TanhNormal`` costs about 80 us to build the distribution (a
``Normal``, an ``Independent``, a composed tanh-and-affine transform, bound checks) and
about 45-65 us to push a sample or the mean through its transforms, against about 70 us
for the 64x64 network that computes ``loc`` and ``scale`` at a batch of 8 (a sampled
policy call, network included: 270 us through the distribution, 180 us here). An action is
two or three elementwise operations; :func:`tanh_normal_action` runs the ones the
distribution runs, in its order, on the same tensors:

* ``deterministic_sample``: the transforms of the base ``Normal``'s mean, ``loc``;
* ``rsample``: the transforms of ``loc + eps * scale``, ``eps`` drawn by the call
  ``Normal.rsample`` makes (:func:`imitrl.compat.standard_normal`, the global RNG);
* the transforms: TorchRL's safe tanh (:func:`imitrl.compat.safe_tanh`), then, unless
  the bounds are -1 and 1, ``AffineTransform``'s ``loc + scale * y`` with ``loc = (high +
  low) / 2`` and ``scale = (high - low) / 2``.

The same bits and the same RNG draws as the distribution
(``tests/test_fast_path.py::test_policy_replay_equals_the_tensordict_call`` compares the
replayed actor with its own forward under every exploration type, for every head).
:func:`replays` says which distributions this covers: exactly ``TanhNormal`` built from
``loc`` and ``scale`` with at most ``low`` and ``high`` (its defaults otherwise:
``tanh_loc`` off, the safe tanh on).
"""

from __future__ import annotations

import torch
from torchrl.modules import TanhNormal

from imitrl.compat import safe_tanh, standard_normal

__all__ = ["replays", "tanh_normal_action"]


def replays(dist_class, names: list[str], dist_kwargs: dict) -> bool:
    """Whether :func:`tanh_normal_action` computes this distribution's actions."""
    return (
        dist_class is TanhNormal
        and names == ["loc", "scale"]
        and set(dist_kwargs) <= {"low", "high"}
        and all(isinstance(v, torch.Tensor) for v in dist_kwargs.values())
    )


def tanh_normal_action(
    loc: torch.Tensor,
    scale: torch.Tensor,
    low: torch.Tensor | None,
    high: torch.Tensor | None,
    *,
    draw: bool,
) -> torch.Tensor:
    """``TanhNormal(loc, scale, low=low, high=high)``'s ``rsample()`` (``draw``) or
    ``deterministic_sample`` (module docstring)."""
    low = torch.as_tensor(-1.0, device=loc.device) if low is None else low.to(loc.device)
    high = torch.as_tensor(1.0, device=loc.device) if high is None else high.to(loc.device)
    loc, scale = torch.broadcast_tensors(loc, scale)  # Normal's broadcast_all
    x = loc + standard_normal(loc.shape, loc) * scale if draw else loc
    y = safe_tanh(x)
    if (high != 1.0).any() or (low != -1.0).any():  # TanhNormal's non-trivial bounds
        y = (high + low) / 2 + (high - low) / 2 * y
    return y
