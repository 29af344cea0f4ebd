"""Experts: the one type that labels observations, ``OBSERVATION -> EXPERT_ACTION``.

An :class:`Expert` is a TensorDict module that reads its ``in_keys`` (the
observation, plus any latent the expert alone may see) and writes ``EXPERT_ACTION``;
it never writes the learner's ``ACTION``. The same object is what ``rollout_episodes``,
``episode_returns``, ``evaluate``, ``dagger`` and ``EnvSource`` take: handed a bare
Expert, a rollout drives the env with :meth:`Expert.as_actor` (the label copied into
``ACTION``).

Build one from a policy table (:meth:`Expert.from_table`), a Q table
(:meth:`Expert.from_q`), any batched function ``obs -> action`` on torch tensors or
numpy arrays (:meth:`Expert.from_callable`), any ``nn.Module`` of tensors
(``Expert(module)``), or any TensorDict policy that writes an action
(:meth:`Expert.from_policy`, e.g. a trained TorchRL actor run in deterministic mode).

**Action spec.** An expert that knows its env's action spec (one lane's,
``env.action_spec_unbatched``) casts every label to it when the cast is exact (float64
-> float32, ``(N,)`` -> ``(N, 1)``, ints -> int64; see
:func:`~imitrl.policies.action_check.cast_action`) and refuses it otherwise. Give the
spec at construction (``action_spec=``) or let the first rollout give the env's
(:meth:`Expert.bind`); without one, labels pass unchanged.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import Bounded, Categorical, TensorSpec
from torchrl.envs.utils import ExplorationType, set_exploration_type

from imitrl import keys
from imitrl.policies.action_check import cast_action, check_action

__all__ = ["Expert", "TableLookup", "as_actor"]


class TableLookup(nn.Module):
    """``obs -> table[obs]`` for integer observations, with a range check."""

    table: torch.Tensor

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
    """Holds a plain function (torch or numpy) so the expert can own it as a module."""

    def __init__(self, fn: Callable) -> None:
        super().__init__()
        if not callable(fn):
            raise ValueError(f"an expert needs a callable obs -> action, got {type(fn).__name__}")
        self.fn = fn

    def forward(self, *inputs: torch.Tensor) -> object:
        return self.fn(*inputs)  # may be a numpy array: Expert casts it


class _ExecuteExpert(TensorDictModuleBase):
    """``ACTION <- EXPERT_ACTION``, ``EXPERT_EXECUTED <- True``."""

    in_keys = [keys.EXPERT_ACTION]
    out_keys = [keys.ACTION, keys.EXPERT_EXECUTED]

    @staticmethod
    def execute(
        expert_action: torch.Tensor, batch_shape: Sequence[int]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(ACTION, EXPERT_EXECUTED)`` for the label ``expert_action`` of a ``batch_shape`` batch."""
        return expert_action.clone(), torch.ones(batch_shape, dtype=torch.bool)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        action, executed = self.execute(tensordict.get(keys.EXPERT_ACTION), tensordict.batch_size)
        tensordict.set(keys.ACTION, action)
        tensordict.set(keys.EXPERT_EXECUTED, executed)
        return tensordict


class Expert(TensorDictModuleBase):
    """A queryable expert: reads ``in_keys``, writes ``EXPERT_ACTION`` (no gradients).

    Args:
        module: ``module(*[td[k] for k in in_keys]) -> action`` on batched tensors (an
            ``nn.Module``, or any callable; its output may be a numpy array).
        in_keys: the keys the expert reads, in ``module``'s argument order (default
            the observation alone).
        action_spec: one lane's action spec to cast every label to (see the module
            docstring); None: cast once a rollout binds the env's (:meth:`bind`).

    Attributes:
        action_spec: the spec labels are cast to, or None.
    """

    def __init__(
        self,
        module: nn.Module | Callable,
        *,
        in_keys: Sequence[NestedKey] = (keys.OBSERVATION,),
        action_spec: TensorSpec | None = None,
        clip: bool = False,
    ) -> None:
        super().__init__()
        if not isinstance(clip, bool):
            raise ValueError(f"clip must be True or False, got {clip!r}")
        self.module = module if isinstance(module, nn.Module) else _Call(module)
        self.in_keys = list(in_keys)
        self.out_keys = [keys.EXPERT_ACTION]
        self.action_spec = None
        self.clip = clip
        if action_spec is not None:
            self.bind(action_spec)

    # ------------------------------------------------------------ builders
    @classmethod
    def from_table(
        cls,
        table: torch.Tensor,
        *,
        observation_key: NestedKey = keys.OBSERVATION,
        action_spec: TensorSpec | None = None,
    ) -> Expert:
        """Expert from a ``[S]`` table of actions (tabular envs); labels int64 ``[...]``."""
        table = torch.as_tensor(table)
        if table.ndim != 1 or table.dtype.is_floating_point:
            raise ValueError(
                f"a policy table must be a 1-D integer tensor [S], got {table.dtype} {tuple(table.shape)}"
            )
        return cls(TableLookup(table.long()), in_keys=[observation_key], action_spec=action_spec)

    @classmethod
    def from_q(
        cls,
        Q: torch.Tensor,
        *,
        observation_key: NestedKey = keys.OBSERVATION,
        action_spec: TensorSpec | None = None,
    ) -> Expert:
        """Expert acting greedily on a ``[S, A]`` Q table (ties to the lowest action)."""
        Q = torch.as_tensor(Q)
        if Q.ndim != 2:
            raise ValueError(f"Q must have shape [S, A], got {tuple(Q.shape)}")
        return cls.from_table(
            Q.argmax(dim=1), observation_key=observation_key, action_spec=action_spec
        )

    @classmethod
    def from_callable(
        cls,
        fn: Callable,
        *,
        action_spec: TensorSpec | None = None,
        observation_key: NestedKey = keys.OBSERVATION,
        clip: bool = False,
    ) -> Expert:
        """Expert from a batched function ``obs [*B, d] -> action`` (torch or numpy).

        ``fn`` receives the observation tensor (numpy functions usually accept it); it
        may return a tensor, a numpy array or a python number. Its output is cast to
        ``action_spec`` (one lane's spec; None: the env's, at the first rollout) when
        the cast is exact, and refused with a ``ValueError`` otherwise.

        ``clip``: clip every label into a ``Bounded`` spec's bounds (for experts whose
        actions the env itself clips, such as Meta-World's scripted policies); without
        it a label outside the bounds is refused where it is recorded.
        """
        return cls(_Call(fn), in_keys=[observation_key], action_spec=action_spec, clip=clip)

    @classmethod
    def from_policy(
        cls,
        policy: TensorDictModuleBase,
        *,
        action_key: NestedKey = keys.ACTION,
        action_spec: TensorSpec | None = None,
    ) -> Expert:
        """Wrap a policy module (e.g. a trained TorchRL actor) as an expert.

        The policy runs in ``ExplorationType.DETERMINISTIC`` on a private copy of its
        ``in_keys``; its ``action_key`` output becomes ``EXPERT_ACTION``, and nothing
        else it writes (its ``ACTION``, logits, ...) reaches the caller's tensordict.
        """
        if not isinstance(policy, TensorDictModuleBase):
            raise ValueError(f"from_policy needs a TensorDict module, got {type(policy).__name__}")
        return _PolicyExpert(policy, action_key=action_key, action_spec=action_spec)

    # ------------------------------------------------------------ contract
    def bind(self, action_spec: TensorSpec) -> Expert:
        """Cast labels to ``action_spec`` (one lane's) from now on; returns ``self``.

        Rollouts call it with the env's ``action_spec_unbatched``. Binding again to a
        spec of the same dtype and shape keeps the first spec.

        Raises:
            ValueError: the expert is already bound to a spec of another dtype or shape.
        """
        if not isinstance(action_spec, TensorSpec):
            raise ValueError(f"action_spec must be a TorchRL TensorSpec, got {action_spec!r}")
        if self.action_spec is None:
            self.action_spec = action_spec
        elif (self.action_spec.dtype, self.action_spec.shape) != (
            action_spec.dtype,
            action_spec.shape,
        ):
            raise ValueError(
                f"this expert labels in dtype {self.action_spec.dtype}, shape "
                f"{tuple(self.action_spec.shape)}; the env's action spec is dtype "
                f"{action_spec.dtype}, shape {tuple(action_spec.shape)}"
            )
        return self

    def label(self, tensordict: TensorDictBase) -> object:
        """The raw label of ``module`` on ``tensordict`` (before the cast)."""
        return self.module(*(tensordict.get(k) for k in self.in_keys))

    def cast_label(self, raw: object, batch_shape: Sequence[int]) -> torch.Tensor:
        """A raw label of a ``batch_shape`` batch as the ``EXPERT_ACTION`` tensor: cast to
        ``action_spec`` when bound (see the module docstring), else only made a tensor."""
        if self.action_spec is not None:
            label = cast_action(raw, self.action_spec, batch_shape=batch_shape)
            if isinstance(self.action_spec, Categorical):  # no env takes another action
                # (a hostile review: label 5 of 2 actions was gymnasium's AssertionError)
                check_action(
                    label, self.action_spec, batch_shape=batch_shape, in_range=True,
                    name="the expert's label",
                )  # fmt: skip
            if self.clip and isinstance(self.action_spec, Bounded):
                low, high = self.action_spec.space.low, self.action_spec.space.high
                label = torch.minimum(torch.maximum(label, low.to(label)), high.to(label))
            return label
        return raw if isinstance(raw, torch.Tensor) else torch.as_tensor(raw)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        with torch.no_grad():
            raw = self.label(tensordict)
        tensordict.set(keys.EXPERT_ACTION, self.cast_label(raw, tensordict.batch_size))
        return tensordict

    def as_actor(self) -> TensorDictSequential:
        """This expert driving an env: writes ``EXPERT_ACTION``, ``ACTION`` and ``EXPERT_EXECUTED``."""
        return as_actor(self)


class _PolicyExpert(Expert):
    """An Expert whose label is a TensorDict policy's action in deterministic mode."""

    def __init__(
        self,
        policy: TensorDictModuleBase,
        *,
        action_key: NestedKey,
        action_spec: TensorSpec | None,
    ) -> None:
        super().__init__(policy, in_keys=policy.in_keys, action_spec=action_spec)
        self.action_key = action_key

    def label(self, tensordict: TensorDictBase) -> torch.Tensor:
        scratch = tensordict.select(*self.in_keys, strict=True).copy()
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            return self.module(scratch).get(self.action_key)


def as_actor(expert: Expert) -> TensorDictSequential:
    """``expert`` made to drive an env (``expert.as_actor()``; kept for older code)."""
    return TensorDictSequential(expert, _ExecuteExpert())
