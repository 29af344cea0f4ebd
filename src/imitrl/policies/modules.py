"""Thin TensorDictModule variants that write tensor outputs directly.

tensordict 0.14.3 writes every output of a ``TensorDictModule`` through
``TensorDict.from_any``, which calls ``importlib.util.find_spec("pandas")`` on each
call (about 0.1 ms with a few entries on ``sys.path``), even when the output is a
plain tensor. On a tabular or small-MLP policy that is most of the step. :class:`Module`
and :class:`Value` set tensor outputs directly and defer to tensordict for anything
else; the override of tensordict's private writer lives in
:class:`imitrl.compat.DirectWriteMixin`.

A rollout's per-step policy call on a dict of tensors (``TensorPolicy``) is an accelerated
path of the runtime: :mod:`imitrl.runtime.fast.policy_call`, reached through
:mod:`imitrl.runtime.paths`.
"""

from __future__ import annotations

from tensordict.nn import TensorDictModule
from torchrl.modules import ValueOperator

from imitrl.compat import DirectWriteMixin

__all__ = ["Module", "Value"]


class Module(DirectWriteMixin, TensorDictModule):
    """``TensorDictModule`` writing tensor outputs directly (see the module docstring)."""


class Value(DirectWriteMixin, ValueOperator):
    """``ValueOperator`` writing tensor outputs directly (see the module docstring)."""
