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
(``tests/runtime/test_paths.py::test_policy_replay_equals_the_tensordict_call`` compares the
replayed actor with its own forward under every exploration type, for every head);
:func:`replays` says which distributions this covers: exactly ``TanhNormal`` built from
``loc`` and ``scale`` with at most ``low`` and ``high`` (its defaults otherwise:
``tanh_loc`` off, the safe tanh on).
"""

from __future__ import annotations

import math

import torch
from torch import distributions as D
from torch.nn import functional as F
from torchrl.modules import TanhNormal

from imitrl.compat import (
    safe_atanh,
    safe_tanh,
    standard_normal,
    sum_rightmost,
    validates_args,
)

__all__ = ["TanhNormalAction", "TanhNormalLogProb", "replays"]

_LOG_SQRT_2PI = math.log(math.sqrt(2 * math.pi))
"""``Normal.log_prob``'s constant, computed as it computes it"""
_LOG_2 = math.log(2.0)
"""``TanhTransform.log_abs_det_jacobian``'s constant"""


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


class TanhNormalLogProb:
    """``TanhNormal(loc, scale, low=low, high=high).log_prob(action)`` on a minibatch's
    tensors, without building the distribution: on Pendulum's batch of 256, 89 us a call
    against 332 us for ``TanhNormal(...).log_prob`` (one thread, load 0.2; the
    construction, the transforms' objects and ``Function.apply`` around an arithmetic of
    about twenty tensor calls).

    ``TransformedDistribution.log_prob`` inverts the transforms and sums their
    log-Jacobians on the action, then adds the base ``Independent(Normal)``'s log-density
    of the pre-image. :meth:`__call__` runs the same operations on the same tensors, in
    the same order:

    * the pre-image: ``AffineTransform``'s inverse ``(y - loc) / scale`` with ``loc =
      (high + low) / 2``, ``scale = (high - low) / 2`` (skipped where the bounds are -1 and
      1, as ``TanhNormal`` skips the affine part), then TorchRL's safe atanh (clamped one
      resolution inside +-1, :func:`imitrl.compat.safe_atanh`);
    * the log-Jacobian: ``TanhTransform``'s ``2 (log 2 - x - softplus(-2 x))`` plus the
      affine part's ``log |scale|`` (``ComposeTransform`` adds its parts' terms), summed
      over the action's dimension and subtracted from 0;
    * ``Normal.log_prob``: ``-((x - loc) ** 2) / (2 var) - log(scale) - log(sqrt(2 pi))``
      summed over the action's dimension (``Independent``), added to the above.

    Every operation is computed on the minibatch's own tensors, as the distribution
    computes it: a transcendental function's vectorised and scalar loops may round the
    same input differently, so an element's bits can depend on its position in the
    tensor, and only the same layout gives the same bits. :meth:`of` checks the
    arithmetic against the distribution's own transform objects on a probe of actions
    (the bounds included) and declines where they differ (another TorchRL's
    transforms); ``tests/runtime/fast/test_ppo_step.py`` compares values and gradients with the
    distribution's, row counts with a scalar tail included.
    """

    def __init__(self, low: torch.Tensor | None, high: torch.Tensor | None) -> None:
        self.affine = TanhNormalAction(low, high).affine
        self._on: dict[torch.device, tuple[torch.Tensor, ...]] = {}

    def _bounds(self, device: torch.device) -> tuple[torch.Tensor, ...]:
        """``(loc, scale, log |scale|)`` of the affine part on ``device``: moved there, as
        ``TanhNormal`` moves its bounds to ``loc``'s device, and the log taken there, as
        ``AffineTransform.log_abs_det_jacobian`` takes it."""
        if device not in self._on:
            assert self.affine is not None  # called where the bounds are not trivial
            shift, half = (t.to(device) for t in self.affine)
            self._on[device] = (shift, half, torch.abs(half).log())
        return self._on[device]

    @classmethod
    def of(cls, dist_class, names: list[str], dist_kwargs: dict) -> TanhNormalLogProb | None:
        """A :class:`TanhNormalLogProb` of the distribution, or None where it does not
        replay it (not :func:`replays`, argument validation on, transforms that compute
        otherwise)."""
        if not replays(dist_class, names, dist_kwargs):
            return None
        low, high = dist_kwargs.get("low"), dist_kwargs.get("high")
        out = cls(low, high)
        lo = torch.as_tensor(-1.0) if low is None else low
        hi = torch.as_tensor(1.0) if high is None else high
        u = torch.linspace(0.0, 1.0, 37, device=lo.device)[:, None]  # a scalar tail on every width
        action = lo + (hi - lo) * u.expand(37, *torch.broadcast_shapes(lo.shape, hi.shape))
        probe = dist_class(torch.zeros_like(action), torch.ones_like(action), **dist_kwargs)
        base = probe.base_dist
        if (
            validates_args(probe)
            or len(probe.transforms) != 1
            or type(base) is not D.Independent
            or type(base.base_dist) is not D.Normal
            or base.reinterpreted_batch_ndims != 1
            or len(probe.event_shape) != 1
        ):
            return None
        (transform,) = probe.transforms  # TransformedDistribution.log_prob, event_dim 1
        x = transform.inv(action)
        shift = 0.0 - sum_rightmost(transform.log_abs_det_jacobian(x, action), 1)
        mine = out.action_terms(action)
        return out if torch.equal(mine[0], x) and torch.equal(mine[1], shift) else None

    def action_terms(self, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The pre-image of ``action`` and the log-Jacobian part of the log-probability."""
        if self.affine is None:
            x = safe_atanh(action)
            jacobian = 2.0 * (_LOG_2 - x - F.softplus(-2.0 * x))
        else:
            shift, half, log_half = self._bounds(action.device)
            x = safe_atanh((action - shift) / half)
            jacobian = 2.0 * (_LOG_2 - x - F.softplus(-2.0 * x)) + log_half.expand(x.shape)
        return x, 0.0 - sum_rightmost(jacobian, 1)

    def __call__(
        self, loc: torch.Tensor, scale: torch.Tensor, action: torch.Tensor
    ) -> torch.Tensor:
        pre, shift = self.action_terms(action)
        loc, scale = torch.broadcast_tensors(loc, scale)  # Normal's broadcast_all
        var = scale**2  # Normal.log_prob
        log_prob = -((pre - loc) ** 2) / (2 * var) - scale.log() - _LOG_SQRT_2PI
        return shift + sum_rightmost(log_prob, 1)  # Independent's sum over the action
