"""`DemonstrationBuffer`: demonstrations in a TorchRL replay buffer that only grows.

One row per visited state. Required keys (see :mod:`imitrl.keys`):

===================== ============ ===================================================
key                   dtype        meaning
===================== ============ ===================================================
``OBSERVATION``       any          what the policy saw
``EXPERT_ACTION``     any          the expert's label there (the training target)
``ACTION``            = label      the action executed in the env
``EXPERT_EXECUTED``   bool         whether the executed action was the expert's
``EPISODE``           int64        episode id, unique in the buffer
``ROUND``             int64        DAgger round that collected the row (0 = demos)
``STEP``              int64        time index inside the episode
===================== ============ ===================================================

Rows may carry more keys (``("next", "reward")``, done flags, a task index, ...);
the first ``extend`` fixes the schema (key set, dtypes, trailing shapes) and every
later ``extend`` must match it exactly.

Why not a bare ``ReplayBuffer(LazyTensorStorage(n))``: that storage wraps around
and silently overwrites the oldest rows when full, and fills keys missing from a
later ``extend`` with zeros. DAgger's guarantee rests on aggregation (every round's
data kept), so this buffer grows its storage instead of wrapping, and validates the
schema, dtypes, episode ids and finiteness on every ``extend``.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.checkpoint import Checkpoint
from torchrl.data import Bounded, Categorical, ReplayBuffer, TensorSpec
from torchrl.data.replay_buffers import LazyTensorStorage, SamplerWithoutReplacement

from imitrl import keys
from imitrl.compat import set_writer_cursor, writer_cursor

__all__ = ["REQUIRED_KEYS", "DemonstrationBuffer", "GrowingTensorStorage"]

REQUIRED_KEYS = (
    keys.OBSERVATION,
    keys.EXPERT_ACTION,
    keys.ACTION,
    keys.EXPERT_EXECUTED,
    keys.EPISODE,
    keys.ROUND,
    keys.STEP,
)
_INT_KEYS = (keys.EPISODE, keys.ROUND, keys.STEP)


class GrowingTensorStorage(LazyTensorStorage):
    """A ``LazyTensorStorage`` that doubles its capacity instead of wrapping around.

    Call :meth:`reserve` before writing ``n`` rows (``DemonstrationBuffer.extend``
    does); it reallocates the underlying tensordict and copies the rows kept so far.
    """

    def reserve(self, n: int) -> bool:
        """Make room for ``n`` more rows; returns True if the storage grew."""
        need = len(self) + int(n)
        if need <= self.max_size:
            return False
        new_size = max(2 * self.max_size, need)
        if self.initialized:
            old = self._storage
            grown = torch.empty_like(old[:1].expand(new_size, *old.shape[1:]))
            grown[: len(self)] = old[: len(self)]
            self._storage = grown
        self.max_size = new_size
        return True


def _schema(rows: TensorDictBase) -> dict[str, tuple[str, tuple[int, ...]]]:
    out = {}
    for key in rows.keys(include_nested=True, leaves_only=True):
        value = rows.get(key)
        name = key if isinstance(key, str) else ".".join(key)
        out[name] = (str(value.dtype).replace("torch.", ""), tuple(value.shape[1:]))
    return out


class DemonstrationBuffer:
    """A growing, schema-checked demonstration buffer on a TorchRL ``ReplayBuffer``.

    Args:
        action_spec: if given, every ``EXPERT_ACTION`` and ``ACTION`` is checked against
            it (range of a ``Categorical``, bounds of a ``Bounded``).
        num_states: if given, integer observations are checked to lie in ``[0, num_states)``.
        capacity: initial storage rows (grows by doubling).
        batch_size: default minibatch size of :meth:`sample`.
        generator: random source of sampling (seed it for reproducible minibatches).

    Attributes:
        rb: the underlying ``torchrl.data.ReplayBuffer`` (sampling without replacement:
            ``for batch in buffer.rb`` is one epoch over the current rows).
    """

    def __init__(
        self,
        *,
        action_spec: TensorSpec | None = None,
        num_states: int | None = None,
        capacity: int = 1024,
        batch_size: int | None = None,
        generator: torch.Generator | None = None,
    ) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be positive, got {capacity}")
        self.action_spec = action_spec
        self.num_states = num_states
        self.storage = GrowingTensorStorage(int(capacity))
        self.rb = ReplayBuffer(
            storage=self.storage,
            sampler=SamplerWithoutReplacement(drop_last=False, shuffle=True),
            batch_size=batch_size,
            generator=generator,
        )
        self.schema: dict[str, tuple[str, tuple[int, ...]]] | None = None
        self.next_episode = 0

    # ------------------------------------------------------------------ size
    def __len__(self) -> int:
        return len(self.storage)

    @property
    def num_episodes(self) -> int:
        return int(self.data[keys.EPISODE].unique().numel()) if len(self) else 0

    @property
    def data(self) -> TensorDictBase:
        """All rows, in insertion order (a view on the storage)."""
        if len(self) == 0:
            raise ValueError(
                "the demonstration buffer is empty: collect or load demonstrations first"
            )
        return self.storage[: len(self)]

    # ----------------------------------------------------------------- write
    def extend(self, rows: TensorDictBase) -> torch.Tensor:
        """Append rows (a TensorDict with one batch dimension); returns their indices.

        Raises:
            ValueError: empty rows, a missing or extra key, a dtype or trailing-shape
                change, an episode id already used, NaN/inf values, actions outside
                ``action_spec``, observations outside ``[0, num_states)``.
        """
        self._validate(rows)
        n = rows.shape[0]
        before = len(self)
        grew = self.storage.reserve(n)
        if grew or writer_cursor(self.rb) != before:
            # After a reallocation the round-robin writer must continue at the end,
            # not at its wrapped cursor (torchrl's writer computes cursor % max_size).
            set_writer_cursor(self.rb, before)
        index = self.rb.extend(rows)
        if len(self) != before + n:  # guard: nothing may have been overwritten
            raise RuntimeError(f"buffer write lost rows: had {before}, wrote {n}, now {len(self)}")
        self.next_episode = max(self.next_episode, int(rows[keys.EPISODE].max()) + 1)
        return index

    def _validate(self, rows: TensorDictBase) -> None:
        if not isinstance(rows, TensorDictBase):
            raise ValueError(f"extend expects a TensorDict of rows, got {type(rows).__name__}")
        if rows.batch_dims != 1:
            raise ValueError(
                f"rows must have exactly one batch dimension, got batch_size {tuple(rows.batch_size)}"
            )
        if rows.shape[0] == 0:
            raise ValueError("cannot extend the demonstration buffer with zero rows")
        missing = [k for k in REQUIRED_KEYS if k not in rows.keys()]
        if missing:
            raise ValueError(
                f"rows are missing required keys {missing}; required: {list(REQUIRED_KEYS)}"
            )
        schema = _schema(rows)
        if self.schema is None:
            for k in _INT_KEYS:
                if rows.get(k).dtype != torch.int64 or rows.get(k).ndim != 1:
                    raise ValueError(
                        f"{k!r} must be an int64 vector [N], got {rows.get(k).dtype} {tuple(rows.get(k).shape)}"
                    )
            if rows.get(keys.EXPERT_EXECUTED).dtype != torch.bool:
                raise ValueError(
                    f"{keys.EXPERT_EXECUTED!r} must be bool, got {rows.get(keys.EXPERT_EXECUTED).dtype}"
                )
            if schema[keys.ACTION] != schema[keys.EXPERT_ACTION]:
                raise ValueError(
                    f"{keys.ACTION!r} {schema[keys.ACTION]} and {keys.EXPERT_ACTION!r} "
                    f"{schema[keys.EXPERT_ACTION]} must share dtype and shape"
                )
        else:
            if schema != self.schema:
                raise ValueError(
                    "rows do not match the buffer's schema: " + _schema_diff(self.schema, schema)
                )
        for key in rows.keys(include_nested=True, leaves_only=True):
            value = rows.get(key)
            if value.dtype.is_floating_point and not torch.isfinite(value).all():
                raise ValueError(f"rows contain NaN or inf under {key!r}")
        episodes = rows.get(keys.EPISODE)
        starts = int((episodes[1:] != episodes[:-1]).sum()) + 1
        if starts != int(episodes.unique().numel()):
            raise ValueError(
                f"each episode's rows must be contiguous: {keys.EPISODE!r} ids reappear after another episode"
            )
        if int(episodes.min()) < self.next_episode:
            raise ValueError(
                f"episode id {int(episodes.min())} is already used in this buffer; "
                f"new episodes must start at buffer.next_episode = {self.next_episode}"
            )
        if (rows.get(keys.ROUND) < 0).any() or (rows.get(keys.STEP) < 0).any():
            raise ValueError(f"{keys.ROUND!r} and {keys.STEP!r} must be non-negative")
        if self.action_spec is not None:
            for k in (keys.EXPERT_ACTION, keys.ACTION):
                _check_action(rows.get(k), self.action_spec, k)
        if self.num_states is not None:
            obs = rows.get(keys.OBSERVATION)
            if (
                obs.dtype.is_floating_point
                or int(obs.min()) < 0
                or int(obs.max()) >= self.num_states
            ):
                raise ValueError(f"observations must be integer states in [0, {self.num_states})")
        if self.schema is None:
            self.schema = schema

    # ------------------------------------------------------------------ read
    def sample(self, batch_size: int | None = None) -> TensorDictBase:
        """A minibatch without replacement (epochs over the current rows)."""
        if len(self) == 0:
            raise ValueError("cannot sample from an empty demonstration buffer")
        return self.rb.sample(batch_size)

    def rounds(self) -> Iterable[int]:
        """The DAgger rounds present in the buffer, sorted (0 = demonstrations)."""
        return sorted(set(self.data[keys.ROUND].tolist()))

    # -------------------------------------------------------------- save/load
    def save(
        self,
        path: str | Path,
        *,
        learner: torch.nn.Module | None = None,
        state: dict[str, Any] | None = None,
    ) -> Path:
        """Save the rows, optionally a learner (weights and optimizers) and a JSON round state.

        One ``torchrl.checkpoint.Checkpoint`` directory: the replay buffer (its own
        dumps format), the buffer's schema and capacity, ``learner``'s state dict and,
        when it has them, its ``opt_pi`` / ``opt_v`` optimizers, and ``state``
        (e.g. ``{"round": 3, "beta": 0.5}``).
        """
        if len(self) == 0:
            raise ValueError("refusing to save an empty demonstration buffer")
        components: dict[str, Any] = {
            "buffer": self.rb,
            "buffer_meta": {
                "format": _FORMAT,
                "rows": len(self),
                "capacity": self.storage.max_size,
                "schema": {k: [v[0], list(v[1])] for k, v in (self.schema or {}).items()},
                "next_episode": self.next_episode,
                "num_states": self.num_states,
            },
            "state": dict(state or {}),
        }
        if learner is not None:
            components.update(_learner_components(learner))
        return Checkpoint(**components).save(Path(path))

    @classmethod
    def load(
        cls,
        path: str | Path,
        *,
        learner: torch.nn.Module | None = None,
        action_spec: TensorSpec | None = None,
        generator: torch.Generator | None = None,
        batch_size: int | None = None,
    ) -> tuple[DemonstrationBuffer, dict[str, Any]]:
        """Read a checkpoint written by :meth:`save`; returns ``(buffer, state)``.

        Pass ``learner`` (built as before saving) to restore its weights and optimizers.
        """
        path = Path(path)
        if not Checkpoint.is_checkpoint(path):
            raise ValueError(
                f"{path} is not a saved DemonstrationBuffer (no torchrl checkpoint manifest)"
            )
        try:
            values = (
                Checkpoint(buffer_meta={}, state={})
                .load(path, components=["buffer_meta", "state"])
                .values
            )
        except Exception as err:  # torchrl raises CheckpointError and assorted IO errors
            raise ValueError(f"{path}: cannot read the checkpoint's metadata ({err})") from err
        meta, state = values["buffer_meta"], values["state"]
        if meta.get("format") != _FORMAT:
            raise ValueError(f"{path}: unknown buffer format {meta.get('format')!r}")
        buf = cls(
            action_spec=action_spec,
            num_states=meta.get("num_states"),
            capacity=int(meta["capacity"]),
            batch_size=batch_size,
            generator=generator,
        )
        components: dict[str, Any] = {"buffer": buf.rb}
        if learner is not None:
            components.update(_learner_components(learner))
        try:
            Checkpoint(**components).load(path, components=list(components))
        except Exception as err:
            raise ValueError(f"{path}: cannot load {sorted(components)} ({err})") from err
        if len(buf) != int(meta["rows"]):
            raise ValueError(
                f"{path}: expected {meta['rows']} rows, the stored buffer holds {len(buf)}"
            )
        buf.schema = {k: (v[0], tuple(v[1])) for k, v in meta["schema"].items()}
        if _schema(buf.data) != buf.schema:
            raise ValueError(f"{path}: stored rows do not match the recorded schema")
        buf.next_episode = int(meta["next_episode"])
        return buf, state


_FORMAT = "imitrl.DemonstrationBuffer/2"


def _learner_components(learner: torch.nn.Module) -> dict[str, Any]:
    """The learner's weights and, for an imitrl ``Learner``, every optimizer it declares."""
    from imitrl.policies.learner import Learner  # policies import the buffer's users, not it

    out: dict[str, Any] = {"learner": learner}
    if isinstance(learner, Learner):
        out.update(learner.optimizers())
    return out


def _schema_diff(old: dict, new: dict) -> str:
    parts = []
    for k in sorted(set(old) - set(new)):
        parts.append(f"missing key {k!r}")
    for k in sorted(set(new) - set(old)):
        parts.append(f"unexpected key {k!r}")
    for k in sorted(set(old) & set(new)):
        if old[k] != new[k]:
            parts.append(
                f"{k!r} is {new[k][0]} {list(new[k][1])}, expected {old[k][0]} {list(old[k][1])}"
            )
    return "; ".join(parts)


def _check_action(action: torch.Tensor, spec: TensorSpec, key: str) -> None:
    # the labels must carry the spec's own dtype: a learner acts in it, and an expert
    # label of another dtype would only fail later, when the two are mixed in DAgger
    if action.dtype != spec.dtype:
        raise ValueError(f"{key!r} has dtype {action.dtype}, the action spec expects {spec.dtype}")
    if isinstance(spec, Categorical):
        n = spec.space.n
        # rows carry the unbatched action shape: the spec's own, or its shape without
        # the leading env-batch dimension of a batched env's spec
        allowed = {tuple(spec.shape), tuple(spec.shape[1:])}
        if tuple(action.shape[1:]) not in allowed:
            raise ValueError(
                f"{key!r} rows have shape {tuple(action.shape[1:])}, expected one of {sorted(allowed)} "
                "for this discrete action spec"
            )
        if int(action.min()) < 0 or int(action.max()) >= n:
            bad = int(action.min()) if int(action.min()) < 0 else int(action.max())
            raise ValueError(f"{key!r} holds action {bad}, outside [0, {n})")
    elif isinstance(spec, Bounded):
        d = spec.shape[-1]
        if action.ndim < 2 or action.shape[-1] != d:
            raise ValueError(f"{key!r} has shape {tuple(action.shape[1:])}, expected (..., {d})")
        # a batched env's spec repeats the bounds per lane: rows hold one lane's action
        low, high = spec.space.low.reshape(-1, d), spec.space.high.reshape(-1, d)
        if not bool((low == low[0]).all() and (high == high[0]).all()):
            raise ValueError(
                "the action spec's lanes have different bounds: pass one lane's spec "
                "(env.action_spec_unbatched) to the buffer"
            )
        low, high = low[0], high[0]
        if (action < low).any() or (action > high).any():
            raise ValueError(
                f"{key!r} holds actions outside the bounds [{low.tolist()}, {high.tolist()}]"
            )
    elif not spec.is_in(action):  # TorchRL specs check a leading batch of rows at once
        raise ValueError(f"{key!r} holds actions outside {spec}")
