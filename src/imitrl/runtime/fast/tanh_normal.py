"""A tanh-normal actor's action without building its distribution.

Accelerated internals of :mod:`imitrl.runtime.paths` (import them from there, nowhere else).

Acting through TorchRL's ``TanhNormal`` costs about 80 us to build the distribution (a
``Normal``, an ``Independent``, a composed tanh-and-affine transform, bound checks) and
about 45-65 us to push a sample or the mean through its transforms, against about 70 us
for the 64x64 network that computes ``loc`` and ``scale`` at a batch of 8 (a sampled
policy call, network included: 205-210 us through the distribution, 100-115 us here,
load 0.7). An action is
two or three elementwise operations; :class:`TanhNormalAction` runs the ones the
distribution runs, in its order, on the same tensors:

* ``deterministic_sample``: the transforms of the base ``Normal``'s mean, ``loc``;
* ``rsample``: the transforms of ``loc + eps * scale``, ``eps`` drawn by the call
  ``Normal.rsample`` makes (:func:`imitrl.compat.standard_normal`, the global RNG);
* the transforms: TorchRL's safe tanh (:func:`imitrl.compat.safe_tanh`), then, unless
  the bounds are -1 and 1, ``AffineTransform``'s ``loc + scale * y`` with ``loc = (high +
  low) / 2`` and ``scale = (high - low) / 2``.

The same bits and the same RNG draws as the distribution
(``tests/test_fast_path.py::test_policy_replay_equals_the_tensordict_call`` compares the
replayed actor with its own forward under every exploration type, for every head);
:func:`replays` says which distributions this covers: exactly ``TanhNormal`` built from
``loc`` and ``scale`` with at most ``low`` and ``high`` (its defaults otherwise:
``tanh_loc`` off, the safe tanh on).
"""

from __future__ import annotations

import torch
from torchrl.modules import TanhNormal

from imitrl.compat import safe_tanh, standard_normal

__all__ = ["TanhNormalAction", "replays"]


def replays(dist_class, names: list[str], dist_kwargs: dict) -> bool:
    """Whether :class:`TanhNormalAction` computes this distribution's actions."""
    return (
        dist_class is TanhNormal
        and names == ["loc", "scale"]
        and set(dist_kwargs) <= {"low", "high"}
        and all(isinstance(v, torch.Tensor) for v in dist_kwargs.values())
    )


class TanhNormalAction:
    """``TanhNormal(loc, scale, low=low, high=high)``'s ``rsample()`` (``draw``) or
    ``deterministic_sample`` (module docstring). The bounds' affine map is worked out
    once, as the distribution would at every construction: the same tensors."""

    def __init__(self, low: torch.Tensor | None, high: torch.Tensor | None) -> None:
        low = torch.as_tensor(-1.0) if low is None else low
        high = torch.as_tensor(1.0) if high is None else high
        trivial = not ((high != 1.0).any() or (low != -1.0).any())  # TanhNormal's test
        self.affine = None if trivial else ((high + low) / 2, (high - low) / 2)

    def __call__(self, loc: torch.Tensor, scale: torch.Tensor, *, draw: bool) -> torch.Tensor:
        loc, scale = torch.broadcast_tensors(loc, scale)  # Normal's broadcast_all
        x = loc + standard_normal(loc.shape, loc) * scale if draw else loc
        y = safe_tanh(x)
        if self.affine is not None:
            shift, half = (t.to(loc.device) for t in self.affine)
            y = shift + half * y
        return y
