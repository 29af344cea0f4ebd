"""Policy heads: the TensorDictModule a learner acts with, for each kind of action.

============== =============== ============================================ ============
head           actions         policy                                       losses
============== =============== ============================================ ============
categorical    discrete        logits -> ``GreedyCategorical`` (one-hot     ``nll``
                               actions for ``OneHot`` specs)
multi          multi-discrete  logits per sub-action -> independent         ``nll``
                               categoricals
deterministic  continuous      ``tanh`` squashed into the bounds (identity  ``mse``,
                               without bounds)                              ``l1``,
                                                                            ``smooth_l1``
normal         continuous      loc, scale -> Gaussian, actions clipped to   ``nll``
                               the bounds (labels on the bounds are fine)
tanh_normal    continuous      loc, scale -> ``TanhNormal`` inside the      ``nll``
               (bounded)       bounds (labels on the bounds are refused)
normal_free    continuous      as ``normal``, the scale a learned log-std   ``nll``
                               per action dimension, the same in every
                               state (SB3's ``DiagGaussian``)
tanh_normal_   continuous      as ``tanh_normal``, the scale a learned      ``nll``
free           (bounded)       log-std per action dimension
============== =============== ============================================ ============

``normal`` and ``tanh_normal`` read their scale off the network (``NormalParamExtractor``:
a biased softplus of a second output per dimension), so a likelihood fit can shrink it
state by state and chase the labels' noise; the ``_free`` heads keep one learned log-std
per dimension (TorchRL's ``AddStateIndependentNormalScale``, initial std 1), as
Stable-Baselines3's and imitation's Gaussian policies do.

The first loss of each row is the default; the default continuous head is
``deterministic`` (MSE): it clones saturating (bang-bang) and smooth experts alike.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import torch
from tensordict.nn import (
    AddStateIndependentNormalScale,
    NormalParamExtractor,
    TensorDictModuleBase,
)
from tensordict.utils import NestedKey
from torch import nn
from torchrl.modules import ProbabilisticActor, TanhNormal

from imitrl import keys
from imitrl.policies.distributions import (
    ClippedNormal,
    GreedyCategorical,
    GreedyOneHotCategorical,
    MultiCategoricalDist,
)
from imitrl.policies.modules import Module
from imitrl.policies.specs import ActionSpace

__all__ = ["DEFAULT_HEAD", "HEADS", "HEAD_LOSSES", "Chain", "build_head", "mlp"]

HEADS = (
    "categorical", "multi", "deterministic", "normal", "tanh_normal", "normal_free",
    "tanh_normal_free",
)  # fmt: skip
HEAD_LOSSES = {
    "categorical": ("nll",),
    "multi": ("nll",),
    "deterministic": ("mse", "l1", "smooth_l1"),
    "normal": ("nll",),
    "tanh_normal": ("nll",),
    "normal_free": ("nll",),
    "tanh_normal_free": ("nll",),
}
"""the ``BehaviorCloningLoss`` types each head can be fitted with; the first is the default"""
DEFAULT_HEAD = {"discrete": "categorical", "multi_discrete": "multi", "continuous": "deterministic"}
_KIND_HEADS = {
    "discrete": ("categorical",),
    "multi_discrete": ("multi",),
    "continuous": ("deterministic", "normal", "tanh_normal", "normal_free", "tanh_normal_free"),
}


_ONE, _TWO = torch.ones(()), torch.full((), 2.0)


class Squash(nn.Module):
    """``low + (high - low) * (tanh(x) + 1) / 2``: a deterministic action inside the bounds."""

    low: torch.Tensor
    high: torch.Tensor

    def __init__(self, low: torch.Tensor, high: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("low", low.clone().float())
        self.register_buffer("high", high.clone().float())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # 0-d tensor constants: the values of ``+ 1`` and ``/ 2``, at half their cost per call
        return self.low + (self.high - self.low) * (torch.tanh(x) + _ONE) / _TWO


class OneHotInput(nn.Module):
    """Integer states ``[...]`` -> one-hot float ``[..., n]`` (MLPs over discrete observations)."""

    def __init__(self, n: int) -> None:
        super().__init__()
        self.n = int(n)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return nn.functional.one_hot(x.long(), self.n).float()


class Chain(nn.Sequential):
    """``nn.Sequential`` whose first module may take several inputs (a pixel encoder reads
    the image and the state); with one input it is ``nn.Sequential`` itself."""

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        modules = iter(self)  # not self[1:]: slicing builds a new Sequential at every call
        x = next(modules)(*inputs)
        for module in modules:
            x = module(x)
        return x


def mlp(sizes: Sequence[int], activation: type[nn.Module]) -> nn.Sequential:
    """Linear layers of ``sizes`` with ``activation`` between them (none after the last)."""
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(itertools.pairwise(sizes)):
        layers.append(nn.Linear(a, b))
        if i < len(sizes) - 2:
            layers.append(activation())
    return nn.Sequential(*layers)


def check_head(space: ActionSpace, head: str | None) -> str:
    """The head for ``space`` (its default when None); ValueError naming the valid ones."""
    allowed = _KIND_HEADS[space.kind]
    head = head or DEFAULT_HEAD[space.kind]
    if head not in allowed:
        raise ValueError(
            f"{space.kind} actions need head {' or '.join(map(repr, allowed))}, got {head!r}"
        )
    if head.startswith("tanh_normal") and space.low is None:
        raise ValueError(
            f"head {head!r} needs a bounded action spec; use 'normal' or 'deterministic'"
        )
    return head


def _probabilistic(
    trunk: nn.Module, out_keys, dist, dist_kwargs, spec, in_keys
) -> ProbabilisticActor:
    return ProbabilisticActor(
        Module(trunk, in_keys=in_keys, out_keys=out_keys),
        in_keys=out_keys,
        out_keys=[keys.ACTION],
        distribution_class=dist,
        distribution_kwargs=dist_kwargs,
        spec=spec,
    )


def build_head(
    trunk: Sequence[nn.Module],
    width: int,
    space: ActionSpace,
    head: str,
    *,
    in_keys: Sequence[NestedKey] = (keys.OBSERVATION,),
) -> TensorDictModuleBase:
    """The policy module: ``trunk`` (input layers, ending in ``width`` features) + ``head``.

    ``trunk``'s first module takes the ``in_keys`` entries as its arguments (one, the
    observation, for MLPs; the image and the state for a pixel encoder).
    """
    in_keys = list(in_keys)
    if head == "categorical":
        assert space.n is not None  # action_space gives a discrete space its n
        net = Chain(*trunk, nn.Linear(width, space.n))
        if space.one_hot:
            return _probabilistic(
                net,
                [keys.LOGITS],
                GreedyOneHotCategorical,
                {"dtype": space.dtype},
                space.spec,
                in_keys,
            )
        from torchrl.data import Categorical

        spec = space.spec or Categorical(space.n, dtype=torch.int64)
        return _probabilistic(net, [keys.LOGITS], GreedyCategorical, {}, spec, in_keys)
    if head == "multi":
        assert space.nvec is not None  # action_space gives a multi-discrete space its nvec
        net = Chain(*trunk, nn.Linear(width, sum(space.nvec)))
        multi = {"nvec": space.nvec, "dtype": space.dtype}
        return _probabilistic(net, [keys.LOGITS], MultiCategoricalDist, multi, space.spec, in_keys)
    dim = space.dim
    assert dim is not None  # the heads left are continuous ones: action_space gives dim
    if head == "deterministic":
        last: list[nn.Module] = []
        if space.low is not None:
            assert space.high is not None  # _continuous sets the bounds together
            last = [Squash(space.low, space.high)]
        net = Chain(*trunk, nn.Linear(width, dim), *last)
        return Module(net, in_keys=in_keys, out_keys=[keys.ACTION])
    if head.endswith("_free"):  # loc from the network, one learned log-std per dimension
        scale = AddStateIndependentNormalScale(dim, scale_mapping="exp", init_value=0.0)
        net = Chain(*trunk, nn.Linear(width, dim), scale)
    else:
        net = Chain(*trunk, nn.Linear(width, 2 * dim), NormalParamExtractor())
    out = [keys.LOC, keys.SCALE]
    if head.startswith("normal"):
        return _probabilistic(
            net, out, ClippedNormal, {"low": space.low, "high": space.high}, space.spec, in_keys
        )
    kwargs = {"low": space.low, "high": space.high}
    return _probabilistic(net, out, TanhNormal, kwargs, space.spec, in_keys)
