"""Experts: modules that write their label under ``EXPERT_ACTION`` for any state.

An expert is a :class:`~tensordict.nn.TensorDictModule` reading ``OBSERVATION`` and
writing ``EXPERT_ACTION``; it never writes the learner's ``ACTION``. To let an expert
drive an env, :meth:`Expert.as_actor` chains it with a copy into ``ACTION``.

Build one from a policy table (:meth:`Expert.from_table`), a Q table
(:meth:`Expert.from_q`), any batched callable ``obs -> action``
(:meth:`Expert.from_callable`), or any TensorDictModule that writes an action
(:meth:`Expert.from_policy`, e.g. a trained TorchRL actor run in deterministic mode).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type

from imitrl import keys
from imitrl.policies.modules import Module

__all__ = ["Expert", "TableLookup"]


class TableLookup(nn.Module):
    """``obs -> table[obs]`` for integer observations, with a range check."""

    def __init__(self, table: torch.Tensor) -> None:
        super().__init__()
        table = torch.as_tensor(table)
        if table.ndim < 1 or table.numel() == 0:
            raise ValueError(
                f"a policy table needs at least one state, got shape {tuple(table.shape)}"
            )
        self.register_buffer("table", table.clone())

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        if obs.dtype.is_floating_point or obs.dtype == torch.bool:
            raise ValueError(
                f"a tabular expert expects integer observations, got dtype {obs.dtype}"
            )
        n = self.table.shape[0]
        if obs.numel() and (int(obs.min()) < 0 or int(obs.max()) >= n):
            raise ValueError(f"observation outside [0, {n}) given to a tabular expert")
        return self.table[obs]


class _Call(nn.Module):
    """Wraps a plain callable so TensorDictModule can hold it."""

    def __init__(self, fn: Callable[[torch.Tensor], torch.Tensor]) -> None:
        super().__init__()
        self.fn = fn

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            return torch.as_tensor(self.fn(obs))


class _Deterministic(TensorDictModuleBase):
    """Runs a policy in deterministic mode and moves its action to ``EXPERT_ACTION``.

    The wrapped policy writes into a private copy of the input, so nothing it writes
    (its ``ACTION``, logits, ...) leaks into the caller's tensordict.
    """

    def __init__(self, policy: TensorDictModuleBase, action_key, observation_key) -> None:
        super().__init__()
        self.policy = policy
        self.action_key = action_key
        self.in_keys = [observation_key]
        self.out_keys = [keys.EXPERT_ACTION]

    def as_actor(self) -> TensorDictSequential:
        """This expert driving an env (see :meth:`Expert.as_actor`)."""
        return as_actor(self)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        scratch = tensordict.select(*self.policy.in_keys, strict=True).copy()
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            out = self.policy(scratch)
        tensordict.set(keys.EXPERT_ACTION, out.get(self.action_key))
        return tensordict


class _ExecuteExpert(TensorDictModuleBase):
    """``ACTION <- EXPERT_ACTION``, ``EXPERT_EXECUTED <- True``."""

    in_keys = [keys.EXPERT_ACTION]
    out_keys = [keys.ACTION, keys.EXPERT_EXECUTED]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get(keys.EXPERT_ACTION)
        tensordict.set(keys.ACTION, action.clone())
        tensordict.set(keys.EXPERT_EXECUTED, torch.ones(tensordict.batch_size, dtype=torch.bool))
        return tensordict


class Expert(Module):
    """A queryable expert: ``OBSERVATION -> EXPERT_ACTION``.

    Args:
        module: a callable ``obs -> action`` on batched tensors (or an ``nn.Module``).
        observation_key: the key the expert reads (default ``"observation"``).
    """

    def __init__(
        self,
        module: nn.Module | Callable[[torch.Tensor], torch.Tensor],
        *,
        observation_key=keys.OBSERVATION,
    ) -> None:
        if not isinstance(module, nn.Module):
            module = _Call(module)
        super().__init__(module, in_keys=[observation_key], out_keys=[keys.EXPERT_ACTION])

    @classmethod
    def from_table(cls, table: torch.Tensor, *, observation_key=keys.OBSERVATION) -> Expert:
        """Expert from a ``[S]`` table of actions (tabular envs)."""
        table = torch.as_tensor(table)
        if table.ndim != 1 or table.dtype.is_floating_point:
            raise ValueError(
                f"a policy table must be a 1-D integer tensor [S], got {table.dtype} {tuple(table.shape)}"
            )
        return cls(TableLookup(table.long()), observation_key=observation_key)

    @classmethod
    def from_q(cls, Q: torch.Tensor, *, observation_key=keys.OBSERVATION) -> Expert:
        """Expert acting greedily on a ``[S, A]`` Q table (ties to the lowest action)."""
        Q = torch.as_tensor(Q)
        if Q.ndim != 2:
            raise ValueError(f"Q must have shape [S, A], got {tuple(Q.shape)}")
        return cls.from_table(Q.argmax(dim=1), observation_key=observation_key)

    @classmethod
    def from_callable(
        cls, fn: Callable[[torch.Tensor], torch.Tensor], *, observation_key=keys.OBSERVATION
    ) -> Expert:
        """Expert from any batched ``obs -> action`` function (run without gradients)."""
        return cls(_Call(fn), observation_key=observation_key)

    @staticmethod
    def from_policy(
        policy: TensorDictModuleBase,
        *,
        action_key=keys.ACTION,
        observation_key=keys.OBSERVATION,
    ) -> TensorDictModuleBase:
        """Wrap a policy module (e.g. a trained TorchRL actor) as an expert.

        The policy runs in ``ExplorationType.DETERMINISTIC`` on a private copy of
        the input; its ``action_key`` output is written to ``EXPERT_ACTION``.
        """
        return _Deterministic(policy, action_key, observation_key)

    def as_actor(self) -> TensorDictSequential:
        """This expert driving an env: writes ``EXPERT_ACTION``, ``ACTION`` and ``EXPERT_EXECUTED``."""
        return as_actor(self)


def as_actor(expert: TensorDictModuleBase) -> TensorDictSequential:
    """Any expert module (writing ``EXPERT_ACTION``) made to drive an env."""
    return TensorDictSequential(expert, _ExecuteExpert())
