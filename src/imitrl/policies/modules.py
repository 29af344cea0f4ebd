"""Thin TensorDictModule variants that skip tensordict's per-call output probing.

tensordict 0.14.3 writes every output of a ``TensorDictModule`` through
``TensorDict.from_any``, which calls ``importlib.util.find_spec("pandas")`` on each
call (about 0.1 ms with a few entries on ``sys.path``), even when the output is a
plain tensor. On a tabular or small-MLP policy that is most of the step. These
subclasses set tensor outputs directly and defer to tensordict for anything else.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torchrl.modules import ValueOperator

__all__ = ["Module", "Value"]


class _DirectWrite:
    def _write_to_tensordict(self, tensordict, tensors, tensordict_out=None, out_keys=None):
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
                if key != "_":
                    tensordict.set(key, value)
            return tensordict
        return super()._write_to_tensordict(tensordict, tensors, tensordict_out, out_keys)


class Module(_DirectWrite, TensorDictModule):
    """``TensorDictModule`` writing tensor outputs directly (see the module docstring)."""


class Value(_DirectWrite, ValueOperator):
    """``ValueOperator`` writing tensor outputs directly (see the module docstring)."""
