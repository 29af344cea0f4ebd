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
schema, dtypes, episode ids and finiteness on every ``extend``. The replay buffer and
its storage are private: ``extend`` is the only way rows get in, so no public path
wraps or drops rows.

Checkpoints (:meth:`DemonstrationBuffer.save` / :meth:`~DemonstrationBuffer.load`)
store the rows, not the storage's capacity: one raw file per key, with a manifest of
every file's size and SHA-256 (:mod:`imitrl.data.checkpoint`), written atomically and
verified before anything is read.
"""

from __future__ import annotations

import io
import json
import sys
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.data import Bounded, Categorical, ReplayBuffer, TensorSpec
from torchrl.data.replay_buffers import LazyTensorStorage, SamplerWithoutReplacement

from imitrl import keys
from imitrl.compat import grow_tensor_storage, set_writer_cursor, writer_cursor
from imitrl.data.checkpoint import (
    MANIFEST,
    decode_rows,
    encode_rows,
    learner_components,
    read_checkpoint,
    restore_learner,
    state_json,
    write_checkpoint,
)

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
    does); it reallocates the underlying tensordict and copies the rows kept so far
    (through :func:`imitrl.compat.grow_tensor_storage`: torchrl has no public way).
    """

    def reserve(self, n: int) -> bool:
        """Make room for ``n`` more rows; returns True if the storage grew."""
        need = len(self) + int(n)
        if need <= self.max_size:
            return False
        grow_tensor_storage(self, max(2 * self.max_size, need))
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

    The ``torchrl.data.ReplayBuffer`` inside (sampling without replacement: successive
    :meth:`sample` calls run epochs over the current rows) and its storage are private:
    written to directly, a TorchRL storage wraps around and overwrites the oldest rows.
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
        self._storage = GrowingTensorStorage(int(capacity))
        self._rb = ReplayBuffer(
            storage=self._storage,
            sampler=SamplerWithoutReplacement(drop_last=False, shuffle=True),
            batch_size=batch_size,
            generator=generator,
        )
        self.schema: dict[str, tuple[str, tuple[int, ...]]] | None = None
        self.next_episode = 0

    # ------------------------------------------------------------------ size
    def __len__(self) -> int:
        return len(self._storage)

    @property
    def capacity(self) -> int:
        """Rows the storage holds before it next grows (it doubles; never wraps)."""
        return int(self._storage.max_size)

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
        return self._storage[: len(self)]

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
        grew = self._storage.reserve(n)
        if grew or writer_cursor(self._rb) != before:
            # After a reallocation the round-robin writer must continue at the end,
            # not at its wrapped cursor (torchrl's writer computes cursor % max_size).
            set_writer_cursor(self._rb, before)
        index = self._rb.extend(rows)
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
            if value.dtype.is_floating_point and value.numel() and not _finite(value):
                raise ValueError(f"rows contain NaN or inf under {key!r}")
        episodes = rows.get(keys.EPISODE)
        starts = int((episodes[1:] != episodes[:-1]).sum()) + 1
        # non-decreasing ids are contiguous blocks; only other orders need the sort
        ordered = bool((episodes[1:] >= episodes[:-1]).all())
        if not ordered and starts != int(episodes.unique().numel()):
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
        return self._rb.sample(batch_size)

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
        """Save the rows, optionally a learner (weights and optimizers) and a JSON state.

        ``path`` becomes a directory (see :mod:`imitrl.data.checkpoint`)::

            manifest.json        format, rows, next_episode, num_states, byte order, the
                                 columns (key, dtype, trailing shape, file), the learner's
                                 files, and every file's size and SHA-256
            column_000.bin ...   one per key: that key's rows only, raw, C order
            learner.pt           ``learner.state_dict()`` (when ``learner`` is given)
            opt_pi.pt ...        each optimizer ``learner.optimizers()`` declares
            state.json           ``state`` (e.g. ``{"round": 3, "beta": 0.5}``)

        The write is atomic: ``path`` afterwards holds this checkpoint or, after a crash
        or ``kill -9``, the previous one, whole. An existing ``path`` is replaced only if
        it is empty or a checkpoint of this format. Returns the absolute path.

        Raises:
            ValueError: the buffer is empty; ``state`` is not plain JSON; ``path`` holds
                something other than a buffer checkpoint (left untouched).
        """
        if len(self) == 0:
            raise ValueError("refusing to save an empty demonstration buffer")
        files: dict[str, bytes | memoryview] = {"state.json": state_json(state).encode()}
        column_files, columns = encode_rows(self.data)
        files.update(column_files)
        learner_files = None
        if learner is not None:
            learner_files = {}
            for component, obj in learner_components(learner).items():
                name = f"{component}.pt"
                if name in files:
                    raise ValueError(f"learner component {component!r} clashes with {name}")
                stream = io.BytesIO()
                torch.save(obj.state_dict(), stream)
                files[name], learner_files[component] = stream.getvalue(), name
        content = {
            "rows": len(self),
            "next_episode": self.next_episode,
            "num_states": self.num_states,
            "byteorder": sys.byteorder,
            "columns": columns,
            "learner": learner_files,
            "state": "state.json",
        }
        return write_checkpoint(path, files, content, fmt=_FORMAT)

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

        Every file is checked against the manifest (presence, size, SHA-256, no
        unlisted file) before any is read; the rows then pass the same checks as
        :meth:`extend` (and ``action_spec``, when given). Pass ``learner`` (built as
        before saving) to restore its weights and optimizers: it is changed only if
        everything loads. Nothing is written to ``path``.

        Raises:
            ValueError: naming the file: not a checkpoint, a file missing, truncated,
                appended to, altered or unlisted, an edited manifest, rows that fail the
                buffer's checks, a ``learner`` that does not match the saved one.
        """
        path = Path(path)
        content, files = read_checkpoint(path, fmt=_FORMAT)
        try:
            rows = decode_rows(content, files)
            num_states, next_episode = content["num_states"], content["next_episode"]
            if not (num_states is None or type(num_states) is int) or type(next_episode) is not int:
                raise ValueError("num_states and next_episode must be integers")
            state = json.loads(bytes(files[content["state"]].numpy()))
        except (KeyError, TypeError, ValueError) as err:
            raise ValueError(f"{path / MANIFEST}: malformed content ({err})") from None
        buf = cls(
            action_spec=action_spec,
            num_states=num_states,
            capacity=rows.shape[0],
            batch_size=batch_size,
            generator=generator,
        )
        try:
            buf.extend(rows)
        except ValueError as err:
            raise ValueError(f"{path}: the stored rows fail the buffer's checks: {err}") from None
        if next_episode < buf.next_episode:
            raise ValueError(
                f"{path / MANIFEST}: next_episode {next_episode} is below the stored episode ids"
            )
        buf.next_episode = next_episode
        if learner is not None:
            restore_learner(learner, content.get("learner"), files, path)
        return buf, state


def _finite(value: torch.Tensor) -> bool:
    """No NaN or inf in a non-empty float tensor (min and max propagate NaN: one pass,
    no [N, ...] bool temporary; 20x faster than ``isfinite(value).all()`` on 4e7 floats)."""
    low, high = torch.aminmax(value)
    return bool(torch.isfinite(low)) and bool(torch.isfinite(high))


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


_FORMAT = "imitrl.DemonstrationBuffer/3"
