"""Every use of a private attribute of TorchRL or tensordict, in one module.

imitrl reaches past the public API of TorchRL/tensordict only here, each time for a
reason written next to it, and ``tests/test_compat.py`` checks that the public path
gives the same digits. Written against tensordict 0.14.3 and torchrl 0.14.1 (the
pins in ``pyproject.toml``): on an upgrade, read this file and run that test first.

=================================== ==========================================================
private attribute                   used by
=================================== ==========================================================
``TensorDictModule._write_to_       :class:`DirectWriteMixin` (``imitrl.policies.modules``)
tensordict`` (overridden)
``RoundRobinWriter._cursor``        :func:`writer_cursor`, :func:`set_writer_cursor`
                                    (``imitrl.data.buffer.DemonstrationBuffer.extend``)
=================================== ==========================================================
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import ReplayBuffer

__all__ = ["DirectWriteMixin", "set_writer_cursor", "writer_cursor"]


class DirectWriteMixin:
    """Mixin for ``TensorDictModule`` subclasses: tensor outputs are set directly.

    Why: tensordict 0.14.3 writes every output of a ``TensorDictModule`` in its
    private ``_write_to_tensordict`` through ``TensorDict.from_any``, which calls
    ``importlib.util.find_spec("pandas")`` on each call (about 0.1 ms with a few
    entries on ``sys.path``), even when the output is a plain tensor. On a tabular or
    small-MLP policy that is most of the step, and tensordict has no public switch to
    skip it. This override handles the common case (write in place into a
    ``TensorDictBase``, every output a tensor) with ``TensorDictBase.set``, which
    stores the same tensor object ``from_any`` returns for a tensor, and defers to
    tensordict for everything else (``inplace`` False or ``"empty"``, an explicit
    ``tensordict_out``, non-tensor outputs).

    Put it first in the bases: ``class Module(DirectWriteMixin, TensorDictModule)``.
    """

    def _write_to_tensordict(
        self,
        tensordict: TensorDictBase,
        tensors: Sequence[torch.Tensor],
        tensordict_out: TensorDictBase | None = None,
        out_keys: Iterable[NestedKey] | None = None,
    ) -> TensorDictBase:
        if (
            tensordict_out is None
            and self.inplace is True
            and isinstance(tensordict, TensorDictBase)
            and all(isinstance(t, torch.Tensor) for t in tensors)
        ):
            out_keys = self.out_keys_source if out_keys is None else out_keys
            if len(tensors) != len(out_keys):
                raise RuntimeError(f"{len(tensors)} outputs for out_keys {out_keys}")
            for key, value in zip(out_keys, tensors):
                if key != "_":  # tensordict's placeholder for an output to drop
                    tensordict.set(key, value)
            return tensordict
        return super()._write_to_tensordict(tensordict, tensors, tensordict_out, out_keys)


def writer_cursor(rb: ReplayBuffer) -> int:
    """The row where ``rb``'s round-robin writer puts its next ``extend``.

    Why: torchrl has no public getter. ``RoundRobinWriter._cursor`` is
    ``len(rb) % max_size`` as long as the storage never wraps; the public
    ``rb.writer.state_dict()["_cursor"]`` holds the same number but builds a dict.
    """
    return int(rb.writer._cursor)


def set_writer_cursor(rb: ReplayBuffer, value: int) -> None:
    """Make ``rb``'s round-robin writer put its next ``extend`` at row ``value``.

    Why: a storage that grows (``imitrl.data.buffer.GrowingTensorStorage``) must
    continue writing at its end, but the writer computes its cursor modulo the
    capacity it had at the last write: after exactly filling a capacity of ``n`` it
    points at row 0 and would overwrite the oldest rows. torchrl has no public
    setter; ``rb.writer.load_state_dict({"_cursor": value})`` does the same through
    the same private name, spelled as a state-dict key.
    """
    rb.writer._cursor = int(value)
