"""What a learner needs to know of an env's spaces, read from TorchRL specs.

``observation_space(x)`` and ``action_space(x)`` accept what a user has at hand: a
TorchRL spec of any kind TorchRL builds for gymnasium spaces (``Categorical``,
``OneHot``, ``Bounded``, ``Unbounded``, ``MultiCategorical``), or a plain number
(observation width / number of actions), and return a small frozen description.
Batched specs are refused with a pointer to the unbatched one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torchrl.data import (
    Bounded,
    Categorical,
    MultiCategorical,
    MultiOneHot,
    OneHot,
    TensorSpec,
    Unbounded,
)

__all__ = [
    "ActionSpace",
    "ObservationSpace",
    "action_space",
    "check_same_actions",
    "describe_actions",
    "observation_space",
]


@dataclass(frozen=True)
class ObservationSpace:
    """``kind`` ``"states"`` (integers ``0 .. n-1``) or ``"vector"`` (float ``[..., *shape]``)."""

    kind: str
    num_states: int | None = None
    shape: tuple[int, ...] | None = None


@dataclass(frozen=True, eq=False)
class ActionSpace:
    """One of ``"discrete"`` (``n`` actions; ``one_hot`` labels of ``dtype``),
    ``"multi_discrete"`` (``nvec``), ``"continuous"`` (``dim``; bounds or None)."""

    kind: str
    n: int | None = None
    one_hot: bool = False
    dtype: torch.dtype = torch.int64
    nvec: tuple[int, ...] | None = None
    dim: int | None = None
    low: torch.Tensor | None = None
    high: torch.Tensor | None = None
    spec: TensorSpec | None = None


def _is_int(x) -> bool:
    return isinstance(x, (int, np.integer)) and not isinstance(x, bool)


def observation_space(obs: int | TensorSpec) -> ObservationSpace:
    """Vector observations ``[d]`` from a width or a ``Bounded``/``Unbounded`` spec;
    integer states from a ``Categorical`` spec (its ``n``)."""
    if _is_int(obs):
        if obs < 1:
            raise ValueError(f"observation width must be >= 1, got {obs}")
        return ObservationSpace("vector", shape=(int(obs),))
    if isinstance(obs, Categorical):
        if len(obs.shape):
            raise ValueError(
                f"a Categorical observation spec must be a scalar state, got shape {tuple(obs.shape)}"
            )
        return ObservationSpace("states", num_states=int(obs.space.n))
    if isinstance(obs, (Bounded, Unbounded)) and obs.dtype.is_floating_point:
        if len(obs.shape) != 1:
            raise ValueError(
                f"MLP learners read vector observations [d]; got an observation spec of shape "
                f"{tuple(obs.shape)} (for a batched env pass the unbatched spec, "
                "env.observation_spec_unbatched['observation'])"
            )
        return ObservationSpace("vector", shape=(int(obs.shape[0]),))
    raise ValueError(
        "observation must be a width or a Categorical, Bounded or Unbounded float spec, "
        f"got {obs!r}"
    )


def _continuous(spec: Bounded | Unbounded) -> ActionSpace:
    if len(spec.shape) != 1 or not spec.dtype.is_floating_point:
        raise ValueError(
            f"a continuous action spec must be float with shape [action_dim], got "
            f"{spec.dtype} {tuple(spec.shape)} (for a batched env pass env.action_spec_unbatched)"
        )
    low = high = None
    if isinstance(spec, Bounded):
        low, high = spec.space.low.float().clone(), spec.space.high.float().clone()
        if not (torch.isfinite(low).all() and torch.isfinite(high).all() and (low < high).all()):
            raise ValueError(f"action bounds must be finite with low < high, got {low}, {high}")
    return ActionSpace(
        "continuous", dim=int(spec.shape[0]), low=low, high=high, dtype=spec.dtype, spec=spec
    )


def action_space(action: int | TensorSpec) -> ActionSpace:
    """The action space of a number of actions or of a TorchRL action spec (unbatched)."""
    if _is_int(action):
        if action < 1:
            raise ValueError(f"need at least one action, got {action}")
        return ActionSpace("discrete", n=int(action))
    if isinstance(action, MultiOneHot):  # a OneHot subclass with no single n
        raise ValueError(
            "MultiOneHot actions (a gymnasium MultiDiscrete space, one-hot encoded) are not "
            "supported: wrap the env with categorical_action_encoding=True (MultiCategorical)"
        )
    if isinstance(action, OneHot):
        if len(action.shape) != 1:
            raise ValueError(
                f"a OneHot action spec must have shape [n], got {tuple(action.shape)} "
                "(for a batched env pass env.action_spec_unbatched)"
            )
        return ActionSpace(
            "discrete", n=int(action.space.n), one_hot=True, dtype=action.dtype, spec=action
        )
    if isinstance(action, MultiCategorical):
        nvec = tuple(int(n) for n in action.nvec.reshape(-1).tolist())
        if len(action.shape) != 1:
            raise ValueError(
                f"a MultiCategorical action spec must have shape [k], got {tuple(action.shape)}"
            )
        return ActionSpace("multi_discrete", nvec=nvec, dtype=action.dtype, spec=action)
    if isinstance(action, Categorical):
        if len(action.shape):
            raise ValueError(
                f"a Categorical action spec must be a scalar action, got shape {tuple(action.shape)} "
                "(for a batched env pass env.action_spec_unbatched)"
            )
        return ActionSpace("discrete", n=int(action.space.n), dtype=action.dtype, spec=action)
    if isinstance(action, (Bounded, Unbounded)) and action.dtype.is_floating_point:
        return _continuous(action)
    raise ValueError(
        "action must be a number of actions or a Categorical, OneHot, MultiCategorical, "
        f"Bounded or Unbounded spec, got {action!r}"
    )


def describe_actions(space: ActionSpace) -> str:
    """The action space in words (for error messages naming a learner and an env)."""
    if space.kind == "discrete":
        return f"{space.n} discrete actions" + (" (one-hot)" if space.one_hot else "")
    if space.kind == "multi_discrete":
        assert space.nvec is not None  # action_space gives a multi-discrete space its nvec
        return f"multi-discrete actions {list(space.nvec)}"
    bounds = ""
    if space.low is not None:
        assert space.high is not None  # _continuous sets the bounds together
        bounds = f" in [{space.low.tolist()}, {space.high.tolist()}]"
    return f"continuous actions of size {space.dim}{bounds}"


def check_same_actions(mine: ActionSpace, env: ActionSpace) -> None:
    """ValueError naming both unless the learner's actions are the env's."""
    same = (mine.kind, mine.n, mine.nvec, mine.dim) == (env.kind, env.n, env.nvec, env.dim)
    same = same and (mine.kind != "discrete" or mine.one_hot == env.one_hot)
    if same and mine.low is not None and env.low is not None:
        assert mine.high is not None and env.high is not None  # _continuous sets both bounds
        same = torch.equal(mine.low, env.low) and torch.equal(mine.high, env.high)
    if not same:
        raise ValueError(
            f"the learner writes {describe_actions(mine)}; the env takes {describe_actions(env)}"
        )
