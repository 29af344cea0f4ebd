"""One Minari episode's arrays, checked and turned into rows, whatever the storage.

Row ``t`` of an episode is ``(observations[t], actions[t])`` with ``("next", reward)
= rewards[t]``, ``terminated = terminations[t]``, ``truncated = truncations[t]``
(Minari records both, so they are used as they are), ``done = terminated |
truncated``; ``observations[T]`` (the final observation) goes to ``("next",
OBSERVATION)`` only with ``next_observation=True``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict

from imitrl import keys
from imitrl.datasets._common import NestedKey, check_finite, exact_cast, required_rows

__all__ = [
    "Episode",
    "EpisodeList",
    "Steps",
    "as_count",
    "check_episode",
    "check_steps",
    "episode_rows",
    "list_episodes",
]


@dataclass(frozen=True)
class Steps:
    """One episode as a storage holds it (observations and actions already checked against
    their spaces by :func:`~imitrl.datasets.minari._spaces.decode`)."""

    name: str
    """where it lies (``<file>: episode_3``, ``<dir>/3``), for messages"""
    id: int
    """Minari's episode id"""
    observations: Any
    """``[T + 1, ...]`` numpy, or a nested dict of them"""
    actions: Any
    """``[T, ...]`` numpy, or a nested dict of them"""
    rewards: np.ndarray
    """``[T]`` (or ``[T, 1]``)"""
    terminations: np.ndarray
    """``[T]`` booleans (or 0/1 integers)"""
    truncations: np.ndarray
    """``[T]`` booleans (or 0/1 integers)"""
    declared_steps: int | None
    """the episode's own ``total_steps`` record, if any"""


@dataclass(frozen=True)
class Episode:
    """One episode of ``T`` steps, as tensors (observations and actions: a tensor, or a
    dict of them for Dict/Tuple spaces)."""

    observation: Any  # observations[:T], [T, ...]
    next_observation: Any  # observations[1:T + 1], or None when not asked for
    action: Any  # [T, ...]
    reward: torch.Tensor  # [T, 1]
    terminated: torch.Tensor  # [T, 1] bool
    truncated: torch.Tensor  # [T, 1] bool
    episode: torch.Tensor  # [T] int64: the episode's id + first_episode
    step: torch.Tensor  # [T] int64: 0..T-1


def as_count(value: Any, what: str, where: str) -> int:
    """A count from metadata: a non-negative integer (numpy integers of HDF5 attributes too)."""
    if isinstance(value, bool | np.bool_) or not isinstance(value, int | np.integer) or value < 0:
        raise ValueError(f"{where}: {what} must be a non-negative integer, got {value!r}")
    return int(value)


def _length(value: Any) -> int:
    if isinstance(value, dict):
        lens = {_length(v) for v in value.values()}
        if len(lens) > 1:
            raise ValueError(f"entries of unequal length {sorted(lens)}")
        return lens.pop() if lens else 0
    return len(value)


def _per_step(values: Any, what: str, here: str) -> np.ndarray:
    """``[T]`` from ``[T]`` or ``[T, 1]`` (Minari writes ``[T]``; a 2-D copy is taken as
    one value per step only when its second size is 1)."""
    values = np.asarray(values)
    if values.ndim == 2 and values.shape[1] == 1:
        values = values[:, 0]
    if values.ndim != 1:
        raise ValueError(
            f"{here}: {what} have shape {list(values.shape)}, expected one value per step "
            "([T] or [T, 1])"
        )
    return values


def _tensors(value: Any, steps: slice) -> Any:
    if isinstance(value, dict):
        return {k: _tensors(v, steps) for k, v in value.items()}
    return torch.from_numpy(np.array(value[steps]))  # a copy: arrow's arrays are read-only


def check_episode(steps: Steps, first_episode: int, next_observation: bool) -> Episode:
    """An episode's arrays checked (lengths ``T + 1`` observations and ``T`` of everything
    else, numeric rewards without NaN or inf, boolean flags) and made tensors."""
    here = steps.name
    rewards = _per_step(steps.rewards, "rewards", here)
    if rewards.dtype.kind not in "fiu":
        raise ValueError(f"{here}: rewards hold {rewards.dtype} values, expected numbers")
    check_finite(rewards, where=f"{here}/rewards")
    flags = [
        exact_cast(_per_step(v, name, here), "bool", where=f"{here}/{name}")
        for name, v in (("terminations", steps.terminations), ("truncations", steps.truncations))
    ]
    n = len(rewards)
    try:
        n_obs, n_act = _length(steps.observations), _length(steps.actions)
    except ValueError as err:
        raise ValueError(f"{here}: observations or actions have {err}") from err
    if n_obs != n + 1 or n_act != n or len(flags[0]) != n or len(flags[1]) != n:
        raise ValueError(
            f"{here}: {n_obs} observations, {n_act} actions, {n} rewards, "
            f"{len(flags[0])} terminations, {len(flags[1])} truncations; expected "
            "T + 1 observations and T of everything else"
        )
    if steps.declared_steps is not None and steps.declared_steps != n:
        raise ValueError(f"{here}: total_steps={steps.declared_steps} but {n} rewards")
    obs = steps.observations
    return Episode(
        observation=_tensors(obs, slice(0, n)),
        next_observation=_tensors(obs, slice(1, n + 1)) if next_observation else None,
        action=_tensors(steps.actions, slice(0, n)),
        reward=torch.from_numpy(rewards.reshape(n, 1).copy()),
        terminated=torch.from_numpy(flags[0].reshape(n, 1).copy()),
        truncated=torch.from_numpy(flags[1].reshape(n, 1).copy()),
        episode=torch.full((n,), steps.id + int(first_episode), dtype=torch.int64),
        step=torch.arange(n, dtype=torch.int64),
    )


@dataclass(frozen=True)
class EpisodeList:
    """The episodes a storage holds, in id order, listed before any is read: one integer
    per episode (names are kept only where they are not ``canonical``)."""

    ids: np.ndarray
    """``[E]`` int64, ascending, each once"""
    odd_names: dict[int, str]
    """id -> the episode's name where it is not ``canonical.format(id)``"""
    canonical: str
    """the usual name of episode ``{}``: ``"episode_{}"`` (hdf5), ``"{}"`` (arrow folders)"""

    def __len__(self) -> int:
        return len(self.ids)

    def name(self, e: int) -> str:
        """The ``e``-th episode's group or folder name."""
        i = int(self.ids[e])
        return self.odd_names.get(i, self.canonical.format(i))


def list_episodes(
    found: Iterable[tuple[str, int]],
    canonical: str,
    meta: dict[str, Any],
    where: str,
    describe: Callable[[str], str],
) -> EpisodeList:
    """The ``(name, id)`` pairs a storage lists, in id order (names listed first first
    among equal ids), once each id is held once and there are as many as the metadata's
    ``total_episodes``; ``describe(name)`` names an episode in messages."""
    ids: list[int] = []
    odd: dict[int, str] = {}  # listing position -> name
    for name, i in found:
        if name != canonical.format(i):
            odd[len(ids)] = name
        ids.append(i)
    listed = np.asarray(ids, dtype=np.int64)
    order = np.argsort(listed, kind="stable")
    ordered = listed[order]
    twice = np.flatnonzero(ordered[1:] == ordered[:-1])
    if len(twice):
        a, b = (int(order[k]) for k in (twice[0], twice[0] + 1))
        first, second = (odd.get(p, canonical.format(int(listed[p]))) for p in (a, b))
        raise ValueError(
            f"{where}: episode id {int(listed[a])} is held twice ({describe(first)}, "
            f"{describe(second)})"
        )
    if meta.get("total_episodes") is not None:
        total = as_count(meta["total_episodes"], "total_episodes", where)
        if total != len(listed):
            raise ValueError(
                f"{where}: metadata declares {total} episodes, the dataset holds {len(listed)}"
            )
    return EpisodeList(ordered, {int(listed[p]): n for p, n in odd.items()}, canonical)


def check_steps(frames: int, meta: dict[str, Any], where: str) -> None:
    """The episodes hold ``frames`` steps: as many as the metadata's ``total_steps``, and
    at least one."""
    if meta.get("total_steps") is not None:
        total = as_count(meta["total_steps"], "total_steps", where)
        if total != frames:
            raise ValueError(
                f"{where}: metadata declares {total} steps, the episodes hold {frames}"
            )
    if frames == 0:
        raise ValueError(f"{where}: the dataset holds no steps")


def _cat(parts: list[Any], n: int) -> Any:
    if isinstance(parts[0], dict):
        return TensorDict({k: _cat([p[k] for p in parts], n) for k in parts[0]}, batch_size=[n])
    return torch.cat(parts)


def episode_rows(episodes: list[Episode], next_observation: bool) -> TensorDict:
    """The ``[N]`` rows of the episodes (``N > 0``), back to back, with the buffer's
    required keys."""
    frames = sum(len(ep.step) for ep in episodes)
    terminated = torch.cat([ep.terminated for ep in episodes])
    truncated = torch.cat([ep.truncated for ep in episodes])
    columns: dict[NestedKey, Any] = {
        keys.OBSERVATION: _cat([ep.observation for ep in episodes], frames),
        keys.EXPERT_ACTION: _cat([ep.action for ep in episodes], frames),
        (keys.NEXT, keys.REWARD): torch.cat([ep.reward for ep in episodes]),
        (keys.NEXT, keys.DONE): terminated | truncated,
        (keys.NEXT, keys.TERMINATED): terminated,
        (keys.NEXT, keys.TRUNCATED): truncated,
    }
    if next_observation:
        columns[(keys.NEXT, keys.OBSERVATION)] = _cat(
            [ep.next_observation for ep in episodes], frames
        )
    episode = torch.cat([ep.episode for ep in episodes])
    return required_rows(columns, episode=episode, step=torch.cat([ep.step for ep in episodes]))
