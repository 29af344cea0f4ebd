"""A loss's fast form: a chain of plain TensorDictModules run on a batch's tensors.

Accelerated internals of :mod:`imitrl.runtime.paths` (import them from there, nowhere else).

A fit differentiates its loss once per step. When the actor's modules are plain
one-input, one-output ``TensorDictModule``\\ s (the logits of a categorical actor, a
deterministic actor), :class:`TensorChain` calls their networks on the batch's tensors:
no TensorDict is built per step, and inside :meth:`TensorChain.direct` the networks run
through :func:`~imitrl.runtime.fast.policy_call.direct_call` (no ``nn.Module.__call__``
per layer). The same operations on the same tensors: the digits and gradients of the
actor's own call (``tests/runtime/test_paths.py``).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from typing import cast

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import nn

from imitrl.policies.modules import Module
from imitrl.runtime.fast.policy_call import direct_call

__all__ = ["TensorChain"]

_PLAIN_MODULES = (TensorDictModule, Module)
_Step = tuple[Callable[..., torch.Tensor], NestedKey, NestedKey]
"""one step of a chain: its network, the key it reads, the key it writes"""


def _is_plain(module: nn.Module) -> bool:
    """A TensorDictModule (or imitrl's ``Module``) of one input and one output key: its
    forward writes ``module.module(td[in_key])`` to ``out_key``."""
    if type(module) not in _PLAIN_MODULES:
        return False
    plain = cast(TensorDictModule, module)
    return len(plain.in_keys) == 1 and len(plain.out_keys) == 1


class TensorChain:
    """``(network, in_key, out_key)`` steps, each reading the row or an earlier output."""

    def __init__(self, steps: tuple[_Step, ...]) -> None:
        self._steps = steps

    @classmethod
    def of(cls, modules: list[nn.Module] | None) -> TensorChain | None:
        """The chain of ``modules`` when every one is plain (:func:`_is_plain`), else None."""
        if not modules or not all(_is_plain(m) for m in modules):
            return None
        plain = [cast(TensorDictModule, m) for m in modules]
        return cls(tuple((m.module, m.in_keys[0], m.out_keys[0]) for m in plain))

    @property
    def out_key(self) -> NestedKey:
        """the key the last module writes"""
        return self._steps[-1][2]

    def run(self, tensordict: TensorDictBase, out_key: NestedKey) -> torch.Tensor:
        """Run the chain on ``tensordict``'s tensors; the tensor written to ``out_key``."""
        values: dict = {}
        for network, in_key, key in self._steps:
            values[key] = network(values[in_key] if in_key in values else tensordict.get(in_key))
        return values[out_key]

    @contextlib.contextmanager
    def direct(self) -> Iterator[None]:
        """Within: the networks are called through ``direct_call`` (built on entry; hooks
        registered inside the context are not seen)."""
        steps = self._steps
        self._steps = tuple((direct_call(cast(nn.Module, n)), i, o) for n, i, o in steps)
        try:
            yield
        finally:
            self._steps = steps
