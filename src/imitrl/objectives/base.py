"""The contract every imitation loss keeps, so that ``fit_bc`` never guesses.

An :class:`ImitationLoss` is a TorchRL ``LossModule`` (TensorDict in, ``loss_*``
entries out, summed to train) that also declares, as plain methods:

* ``label_key``: where it reads the expert's label;
* ``in_keys``: every key of a row it reads (observations, label, extras);
* ``check_labels(rows)``: validates every row a fit can draw, once per fit;
* ``objective(batch, weights=None)``: the scalar to differentiate; ``weights`` is a
  ``[N]`` tensor of per-row weights (data, not differentiated) or None, and is only
  ever passed when ``supports_weights`` is True.

:class:`SummedLoss` makes any other TorchRL ``LossModule`` keep the contract: its
objective is the sum of its ``loss_*`` outputs.
"""

from __future__ import annotations

import contextlib
from typing import ClassVar

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.objectives import LossModule

from imitrl import keys

__all__ = ["ImitationLoss", "InnerBCLoss", "SummedLoss", "sum_losses"]


def sum_losses(out: TensorDictBase) -> torch.Tensor:
    """The sum of the ``loss_*`` entries of a loss module's output (TorchRL's convention)."""
    terms = [v for k, v in out.items() if isinstance(k, str) and k.startswith("loss_")]
    if not terms:
        raise ValueError(f"the loss returned no loss_* entry (keys {list(out.keys())})")
    return sum(terms)


class ImitationLoss(LossModule):
    """Base class of imitrl's losses (see the module docstring for the contract)."""

    supports_weights: ClassVar[bool] = False
    """whether :meth:`objective` accepts per-row weights (pair deduplication needs it)"""

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass  # no value estimator: these losses read labels, not returns

    @property
    def label_key(self) -> NestedKey:
        """The key of the expert's label in a row."""
        return self.tensor_keys.label

    @property
    def in_keys(self) -> list[NestedKey]:
        """Every key of a row the loss reads: always derived (:meth:`read_keys`), so that
        ``set_keys`` is reflected at once."""
        return self.read_keys()

    @in_keys.setter
    def in_keys(self, values) -> None:
        pass  # TorchRL's LossModule assigns in_keys; imitrl's are derived, never stored

    def read_keys(self) -> list[NestedKey]:
        """The keys of ``in_keys``; by default ``tensor_keys``' observation, label and pad
        (where the loss has one and it is set)."""
        pad = getattr(self.tensor_keys, "pad", None)
        return [
            self.tensor_keys.observation,
            self.tensor_keys.label,
            *([] if pad is None else [pad]),
        ]

    def check_labels(self, rows: TensorDictBase) -> None:
        """Raise ``ValueError`` unless the labels of ``rows`` are present and finite."""
        key = self.label_key
        if key not in rows.keys(include_nested=True):
            raise ValueError(f"rows lack the label key {key!r}")
        label = rows.get(key)
        if label.dtype.is_floating_point and not torch.isfinite(label).all():
            raise ValueError(f"labels under {key!r} contain NaN or inf")

    def fitting(self) -> contextlib.AbstractContextManager:
        """A context a fit's steps run in (``fit_bc``): here nothing; a loss may run its
        networks without ``nn.Module.__call__`` per layer inside it (``BehaviorCloningLoss``:
        :func:`imitrl.runtime.paths.loss_chain`)."""
        return contextlib.nullcontext()

    def objective(self, batch: TensorDictBase, weights: torch.Tensor | None = None) -> torch.Tensor:
        """The scalar a training step differentiates: the sum of the ``loss_*`` outputs."""
        if weights is not None:
            raise ValueError(f"{type(self).__name__} does not take per-row weights")
        return sum_losses(self(batch))


class SummedLoss(ImitationLoss):
    """Any TorchRL ``LossModule`` made an :class:`ImitationLoss`.

    Args:
        loss: the wrapped loss; it reads ``label_key`` and returns ``loss_*`` entries.
        label_key: where it reads the expert's label (default ``"expert_action"``).
    """

    def __init__(self, loss: LossModule, *, label_key: NestedKey = keys.EXPERT_ACTION) -> None:
        if not isinstance(loss, LossModule):
            raise ValueError(f"expected a torchrl LossModule, got {type(loss).__name__}")
        if label_key not in loss.in_keys:
            raise ValueError(
                f"the loss reads {list(loss.in_keys)}, not the label key {label_key!r}: "
                "remap it with set_keys or pass label_key="
            )
        super().__init__()
        self.inner = loss
        self._label_key = label_key

    @property
    def label_key(self) -> NestedKey:
        return self._label_key

    def read_keys(self) -> list[NestedKey]:
        return list(self.inner.in_keys)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self.inner(tensordict)


class InnerBCLoss(ImitationLoss):
    """A loss built around an inner ``BehaviorCloningLoss`` ``self.bc`` (set by the
    subclass): keys, label checks and ``set_keys`` are the inner loss's."""

    bc: ImitationLoss

    def read_keys(self) -> list[NestedKey]:
        return list(self.bc.in_keys)

    @property
    def label_key(self) -> NestedKey:
        return self.bc.label_key

    def check_labels(self, rows: TensorDictBase) -> None:
        """The inner loss's label checks."""
        self.bc.check_labels(rows)

    def set_keys(self, **kwargs) -> None:
        """Remap keys of the inner loss (``label``, ``prediction``)."""
        self.bc.set_keys(**kwargs)
