"""Behaviour cloning as a TorchRL ``LossModule``, with optional per-row weights.

``loss_type`` is chosen by argument, never guessed from a dtype:

=========== =================================== ====================================
loss_type   per-row loss ``l_i``                heads
=========== =================================== ====================================
nll         ``-log pi(a*_i | s_i)``             categorical (= cross-entropy),
                                                tanh_normal
mse         ``mean_j (mu(s_i)_j - a*_ij)^2``    deterministic
l1          ``mean_j |mu(s_i)_j - a*_ij|``      deterministic
smooth_l1   Huber(1) averaged over dims         deterministic
=========== =================================== ====================================

The objective is ``loss_bc = mean_i w_i l_i`` with ``w_i = 1`` unless a weight key
is set; weights are read as data (detached): with ``loss_type="nll"`` and weights
equal to advantages this is the advantage-weighted log-likelihood of
:func:`imitrl.algorithms.policy_step`.

Why not ``torchrl.objectives.BCLoss``: in torchrl 0.14.1 it routes integer labels of
a ``Categorical`` actor to a cross-entropy on the *sampled action* as if it were
logits, and one ``action`` key names both the label and the prediction, so an
expert label and a learner's action cannot live under different keys.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey

from imitrl import keys
from imitrl.objectives.base import ImitationLoss
from imitrl.runtime import paths

__all__ = ["LOSS_TYPES", "BehaviorCloningLoss"]

LOSS_TYPES = ("nll", "mse", "l1", "smooth_l1")
_NO_LABEL = torch.iinfo(torch.int64).min
"""``ignore_index`` of the cross-entropy: a value no label takes"""
_REGRESSION = {
    "mse": F.mse_loss,
    "l1": F.l1_loss,
    "smooth_l1": F.smooth_l1_loss,
}


class BehaviorCloningLoss(ImitationLoss):
    """``mean_i w_i * l(pi(.|s_i), a*_i)`` for a policy module.

    Args:
        actor: the policy: a ``ProbabilisticActor`` (for ``nll``) or a module writing
            its action (for the regression losses).
        loss_type: one of :data:`LOSS_TYPES`.
        weighted: read per-row weights from the ``weight`` key (detached).
        report_accuracy: also return ``accuracy`` (greedy action equals the label) for
            categorical actors (an argmax over the batch every call).
        bound_margin: NLL of a bounded (tanh-normal) policy: labels are clamped to
            ``bound_margin`` of the half-range inside the action bounds, where the
            density is finite (a label exactly at a bound has log-density -inf, clamped
            by TorchRL to a constant with no useful gradient).

    Keys (``set_keys`` to remap): ``observation`` is read by the actor; ``label``
    (default ``"expert_action"``) is the target; ``prediction`` (default
    ``"action"``) is where a deterministic actor writes; ``weight`` (default
    ``"weight"``).

    Returns ``loss_bc`` (to minimise) and a detached metric: ``nll`` or the regression
    error (unweighted mean), plus ``accuracy`` if asked for.
    """

    @dataclass
    class _AcceptedKeys:
        label: NestedKey = keys.EXPERT_ACTION
        prediction: NestedKey = keys.ACTION
        weight: NestedKey = keys.WEIGHT

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    out_keys = ["loss_bc"]
    supports_weights = True

    def __init__(
        self,
        actor: TensorDictModule,
        *,
        loss_type: str = "nll",
        weighted: bool = False,
        report_accuracy: bool = False,
        bound_margin: float = 1e-3,
    ) -> None:
        if not 0.0 <= bound_margin < 0.5:
            raise ValueError(f"bound_margin must be in [0, 0.5), got {bound_margin}")
        if loss_type not in LOSS_TYPES:
            raise ValueError(f"loss_type must be one of {LOSS_TYPES}, got {loss_type!r}")
        super().__init__()
        self.actor = actor
        self.loss_type = loss_type
        self.weighted = weighted
        self.report_accuracy = report_accuracy
        self.bound_margin = float(bound_margin)
        # plain attributes, not registered: these modules already belong to the actor
        logits_modules = _categorical_param_modules(actor) if loss_type == "nll" else None
        object.__setattr__(self, "_logits_modules", logits_modules)
        # the loss's fast form (the seam's): the networks on the batch's tensors
        chain = paths.loss_chain(logits_modules if loss_type == "nll" else [actor])
        object.__setattr__(self, "_chain", chain)

    @contextlib.contextmanager
    def fitting(self) -> Iterator[None]:
        """Within: :meth:`row_losses` calls its networks without ``nn.Module.__call__``
        per layer where the seam's fast paths run (built on entry; the same operations,
        so the same bits and gradients; hooks registered inside are not seen)."""
        if self._chain is None or not paths.fast_enabled("loss_chain"):
            yield
            return
        with self._chain.direct():
            yield

    def read_keys(self) -> list[NestedKey]:
        extra = [self.tensor_keys.label] + ([self.tensor_keys.weight] if self.weighted else [])
        return [*self.actor.in_keys, *extra]

    @property
    def num_actions(self) -> int | None:
        """Number of discrete actions, read from the actor's spec (None if unknown)."""
        spec = getattr(self.actor, "spec", None)
        try:
            action_spec = spec[keys.ACTION] if spec is not None else None
        except KeyError:
            return None
        space = getattr(action_spec, "space", None)
        n = getattr(space, "n", None)
        return None if n is None else int(n)

    def check_labels(self, tensordict: TensorDictBase) -> None:
        """Raise ``ValueError`` unless the labels fit the loss (called once per fit).

        Finite values; for a categorical actor integer labels with one entry per row,
        in ``[0, num_actions)``; for the regression losses the prediction's shape.
        """
        super().check_labels(tensordict)
        key = self.tensor_keys.label
        label = tensordict.get(key)
        dist_class = _distribution_class(self.actor)
        if dist_class is not None and dist_class.__name__ == "GreedyOneHotCategorical":
            return _check_one_hot(label, self.num_actions, key, tensordict.shape[0])
        if dist_class is not None and dist_class.__name__ == "MultiCategoricalDist":
            nvec = self.actor.spec[keys.ACTION].nvec
            return _check_multi(label, nvec.reshape(-1), key, tensordict.shape[0])
        if self._logits_modules is None and not (
            self.loss_type == "nll" and not label.dtype.is_floating_point
        ):
            return
        if label.dtype.is_floating_point or label.dtype == torch.bool:
            raise ValueError(
                f"categorical labels under {key!r} must be integers, got {label.dtype}"
            )
        if label.ndim != tensordict.batch_dims:
            raise ValueError(
                f"categorical labels under {key!r} need one integer per row, shape "
                f"{tuple(tensordict.batch_size)}, got {tuple(label.shape)}"
            )
        n = self.num_actions
        lo, hi = int(label.min()), int(label.max())
        if lo < 0 or (n is not None and hi >= n):
            bad = lo if lo < 0 else hi
            raise ValueError(f"label {bad} under {key!r} is outside [0, {n})")

    def per_row(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, TensorDictBase]:
        """Per-row losses ``[N]`` and the actor's output tensordict (a shallow copy)."""
        td = tensordict.select(*self.actor.in_keys, strict=True)  # a new dict: writes stay local
        label = tensordict.get(self.tensor_keys.label)
        if self._logits_modules is not None:
            # Categorical fast path: run the actor's parameter modules and take
            # log_softmax(logits)[label] directly (equal to dist.log_prob(label)) instead
            # of building a distribution object every step.
            if label.dtype.is_floating_point:
                raise ValueError(
                    f"categorical labels under {self.tensor_keys.label!r} must be integers, got {label.dtype}"
                )
            return self._categorical_nll(self._logits(td), label), td
        if self.loss_type == "nll":
            dist = self.actor.get_dist(td)
            if isinstance(dist, torch.distributions.Categorical):
                if label.dtype.is_floating_point:
                    raise ValueError(
                        f"categorical labels under {self.tensor_keys.label!r} must be integers, got {label.dtype}"
                    )
                # Same value as F.cross_entropy(logits, label); reuse the normalised logits.
                logp = dist.logits.gather(-1, label.long().unsqueeze(-1)).squeeze(-1)
                td.set(keys.LOGITS, dist.logits)
            else:
                low, high = getattr(dist, "low", None), getattr(dist, "high", None)
                if low is not None and high is not None and self.bound_margin > 0:
                    # A bounded (tanh) density is singular at its bounds, where experts
                    # often act (saturated torques): move labels a hair inside.
                    pad = self.bound_margin * (high - low) / 2
                    label = torch.maximum(torch.minimum(label, high - pad), low + pad)
                logp = dist.log_prob(label)
            return -logp, td
        out = self.actor(td)
        return self._regression(out.get(self.tensor_keys.prediction), label), out

    def row_losses(self, tensordict: TensorDictBase) -> torch.Tensor:
        """The per-row losses ``[N]`` of :meth:`per_row`, without its output tensordict.

        The fast form (:func:`imitrl.runtime.paths.loss_chain`): when the actor's modules
        are plain one-input, one-output TensorDictModules (the logits of a categorical
        actor, a deterministic actor), their networks are called on the row's tensors
        directly: no TensorDict is built, and the digits are those of :meth:`per_row`,
        the reference (what runs otherwise, and inside ``paths.reference()``).
        """
        chain = self._chain if paths.fast_enabled("loss_chain") else None
        if chain is None:
            return self.per_row(tensordict)[0]
        label = tensordict.get(self.tensor_keys.label)
        if self._logits_modules is not None:
            if label.dtype.is_floating_point:
                raise ValueError(
                    f"categorical labels under {self.tensor_keys.label!r} must be integers, got {label.dtype}"
                )
            return self._categorical_nll(chain.run(tensordict, keys.LOGITS), label)
        if chain.out_key != self.tensor_keys.prediction:  # keys remapped: the actor's own path
            return self.per_row(tensordict)[0]
        return self._regression(chain.run(tensordict, chain.out_key), label)

    def _categorical_nll(self, logits: torch.Tensor, label: torch.Tensor) -> torch.Tensor:
        """``-log softmax(logits)[label]`` per row, ``logits [..., A]``, ``label [...]``.

        ``F.cross_entropy(reduction="none")`` is ``log_softmax`` then ``nll_loss``, whose
        entry ``-logp[label]`` and gradient ``-g`` at ``label`` are exactly those of
        ``-log_softmax(logits).gather(label)``, in two autograd nodes instead of four.
        No label is ignored (``nll_loss`` ignores -100 by default): out of range, it raises.
        """
        if label.shape != logits.shape[:-1]:
            raise ValueError(
                f"categorical labels under {self.tensor_keys.label!r} need shape "
                f"{tuple(logits.shape[:-1])}, got {tuple(label.shape)}"
            )
        if logits.ndim == 2:
            return F.cross_entropy(logits, label.long(), reduction="none", ignore_index=_NO_LABEL)
        flat = F.cross_entropy(
            logits.reshape(-1, logits.shape[-1]),
            label.reshape(-1).long(),
            reduction="none",
            ignore_index=_NO_LABEL,
        )
        return flat.reshape(label.shape)

    def _regression(self, pred: torch.Tensor, label: torch.Tensor) -> torch.Tensor:
        """The regression error per row, averaged over the action dimensions."""
        if pred.shape != label.shape:
            raise ValueError(
                f"prediction {tuple(pred.shape)} and label {tuple(label.shape)} shapes differ "
                f"(label key {self.tensor_keys.label!r})"
            )
        err = _REGRESSION[self.loss_type](pred, label.to(pred.dtype), reduction="none")
        return err.reshape(err.shape[0], -1).mean(-1)

    def _logits(self, td: TensorDictBase) -> torch.Tensor:
        """Run the logits modules on ``td`` (their own calls)."""
        for module in self._logits_modules:
            td = module(td)
        return td.get(keys.LOGITS)

    def reduce(self, losses: torch.Tensor, tensordict: TensorDictBase) -> torch.Tensor:
        """``mean_i w_i l_i`` (weights read as data) or ``mean_i l_i``."""
        if not self.weighted:
            return losses.mean()
        w = tensordict.get(self.tensor_keys.weight).detach().to(losses.dtype)
        if w.shape != losses.shape:
            raise ValueError(
                f"weights {tuple(w.shape)} must have one entry per row {tuple(losses.shape)}"
            )
        return (w * losses).mean()

    def objective(
        self, tensordict: TensorDictBase, weights: torch.Tensor | None = None
    ) -> torch.Tensor:
        """The scalar ``loss_bc`` alone (what a training loop differentiates).

        ``weights`` (``[N]``, data) replaces the weight key: ``mean_i w_i l_i``.
        """
        losses = self.row_losses(tensordict)
        if weights is None:
            return self.reduce(losses, tensordict)
        if weights.shape != losses.shape:
            raise ValueError(
                f"weights {tuple(weights.shape)} must have one entry per row {tuple(losses.shape)}"
            )
        return (weights.detach().to(losses.dtype) * losses).mean()

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        losses, out = self.per_row(tensordict)
        loss = self.reduce(losses, tensordict)
        metrics = {"loss_bc": loss, self.loss_type: losses.detach().mean()}
        if self.report_accuracy and keys.LOGITS in out.keys():
            label = tensordict.get(self.tensor_keys.label)
            metrics["accuracy"] = (out.get(keys.LOGITS).argmax(-1) == label).float().mean().detach()
        return TensorDict(metrics, batch_size=[])


def _distribution_class(actor: TensorDictModule) -> type | None:
    """The distribution class of a ``ProbabilisticActor`` (None for other actors)."""
    from tensordict.nn import ProbabilisticTensorDictModule, ProbabilisticTensorDictSequential

    if not isinstance(actor, ProbabilisticTensorDictSequential):
        return None
    last = list(actor.module)[-1]
    return last.distribution_class if isinstance(last, ProbabilisticTensorDictModule) else None


def _check_one_hot(label: torch.Tensor, n: int | None, key, rows: int) -> None:
    """One-hot labels ``[N, n]``: entries 0 or 1, exactly one 1 per row."""
    if label.shape != (rows, n):
        raise ValueError(
            f"one-hot labels under {key!r} need shape ({rows}, {n}), got {tuple(label.shape)}"
        )
    values = label.double()
    if not ((values == 0) | (values == 1)).all() or not (values.sum(-1) == 1).all():
        raise ValueError(f"one-hot labels under {key!r} need exactly one 1 per row, the rest 0")


def _check_multi(label: torch.Tensor, nvec: torch.Tensor, key, rows: int) -> None:
    """Multi-discrete labels ``[N, k]``: integers, column ``i`` in ``[0, nvec[i])``."""
    if label.dtype.is_floating_point or label.dtype == torch.bool:
        raise ValueError(f"multi-discrete labels under {key!r} must be integers, got {label.dtype}")
    if label.shape != (rows, nvec.numel()):
        raise ValueError(
            f"multi-discrete labels under {key!r} need shape ({rows}, {nvec.numel()}), got {tuple(label.shape)}"
        )
    bad = (label < 0) | (label >= nvec.to(label.device))
    if bad.any():
        raise ValueError(f"multi-discrete labels under {key!r} must lie in [0, {nvec.tolist()})")


def _categorical_param_modules(actor: TensorDictModule) -> list[TensorDictModule] | None:
    """The modules computing ``LOGITS`` of a categorical ``ProbabilisticActor``, else None."""
    from tensordict.nn import ProbabilisticTensorDictModule, ProbabilisticTensorDictSequential

    if not isinstance(actor, ProbabilisticTensorDictSequential):
        return None
    *params, last = list(actor.module)
    if not isinstance(last, ProbabilisticTensorDictModule) or not params:
        return None
    dist_class = getattr(last, "distribution_class", None)
    if not (
        isinstance(dist_class, type) and issubclass(dist_class, torch.distributions.Categorical)
    ):
        return None
    if list(last.in_keys) != [keys.LOGITS] or keys.LOGITS not in params[-1].out_keys:
        return None
    return params
