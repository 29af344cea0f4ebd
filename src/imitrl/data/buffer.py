"""`DemonstrationBuffer`: demonstrations in a TorchRL replay buffer that only grows.

One row per visited state. Keys (see :mod:`imitrl.keys`):

===================== ============ ===================================================
key                   dtype        meaning
===================== ============ ===================================================
``OBSERVATION``       any          what the policy saw: the state (*)
``PIXELS``            uint8        camera image ``[H, W, C]``, or one per camera
                                   under ``("pixels", name)`` (*)
``EXPERT_ACTION``     any          the expert's label there (the training target)
``ACTION``            = label      the action executed in the env
``EXPERT_EXECUTED``   bool         whether the executed action was the expert's
``EPISODE``           int64        episode id, unique in the buffer
``ROUND``             int64        DAgger round that collected the row (0 = demos)
``STEP``              int64        time index inside the episode
===================== ============ ===================================================

(*) every row has at least one of the two (:data:`OBSERVATION_KEYS`): a dataset whose
only observation is a camera gives rows with ``PIXELS`` and no ``OBSERVATION``.

Rows may carry more keys (``("next", "reward")``, done flags, a task index, ...);
the first ``extend`` fixes the schema (key set, dtypes, trailing shapes) and every
later ``extend`` must match it exactly (:func:`imitrl.data.validation.check_rows`).

Why not a bare ``ReplayBuffer(LazyTensorStorage(n))``: that storage wraps around
and silently overwrites the oldest rows when full, and fills keys missing from a
later ``extend`` with zeros. DAgger's guarantee rests on aggregation (every round's
data kept), so this buffer grows its storage instead of wrapping, and validates the
schema, dtypes, episode ids and finiteness on every ``extend``. The replay buffer and
its storage are private: ``extend`` is the only way rows get in, so no public path
wraps or drops rows.

In memory (default) or on disk (``path=...``: TorchRL's ``LazyMemmapStorage`` in that
directory, :mod:`imitrl.data.disk`): the same checks and API; on disk, ``data`` is a
view on the memory-mapped files (nothing is copied into the process), ``sample`` draws
its epochs from a :class:`~imitrl.data.permutation.LazyPermutation` (no ``[N]`` index in
memory), and a directory holding data is refused unless ``resume=True``.

Checkpoints (:meth:`DemonstrationBuffer.save` / :meth:`~DemonstrationBuffer.load`)
store the rows, not the storage's capacity: one raw file per key, with a manifest of
every file's size and SHA-256 (:mod:`imitrl.data.checkpoint`), written atomically and
verified before anything is read.
"""

from __future__ import annotations

import io
import shutil
import sys
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.data import ReplayBuffer, TensorSpec
from torchrl.data.replay_buffers import LazyTensorStorage, SamplerWithoutReplacement

from imitrl import keys
from imitrl.compat import (
    forget_rows_after,
    grow_tensor_storage,
    quiet_torchrl_info,
    set_writer_cursor,
    writer_cursor,
)
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
from imitrl.data.disk import DiskLayout, GrowingMemmapStorage, drop_uncommitted, release_pages
from imitrl.data.permutation import LazyPermutation
from imitrl.data.validation import (
    OBSERVATION_KEYS,
    REQUIRED_KEYS,
    check_actions,
    check_rows,
    check_stored_episodes,
    check_stored_schema,
    episode_runs,
)
from imitrl.fs.reading import parse_json

__all__ = ["OBSERVATION_KEYS", "REQUIRED_KEYS", "DemonstrationBuffer", "GrowingTensorStorage"]

CHUNK_BYTES = 64 << 20
"""rows a disk buffer reads at once in a pass over all its rows (``load``, ``rounds``)"""


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


class DemonstrationBuffer:
    """A growing, schema-checked demonstration buffer on a TorchRL ``ReplayBuffer``.

    Args:
        action_spec: if given, every ``EXPERT_ACTION`` and ``ACTION`` is checked against
            it (range of a ``Categorical``, bounds of a ``Bounded``).
        num_states: if given, integer observations are checked to lie in ``[0, num_states)``.
        capacity: initial storage rows (grows by doubling).
        batch_size: default minibatch size of :meth:`sample`.
        generator: random source of sampling (seed it for reproducible minibatches).
        path: keep the rows on disk in this directory (absent or empty) instead of in
            memory (:mod:`imitrl.data.disk`).
        resume: with ``path``: continue the disk buffer stored there (its rows, schema
            and episode ids; ``num_states`` must match the stored one).

    The ``torchrl.data.ReplayBuffer`` inside (sampling without replacement: successive
    :meth:`sample` calls run epochs over the current rows) and its storage are private:
    written to directly, a TorchRL storage wraps around and overwrites the oldest rows.

    Raises:
        ValueError: ``capacity < 1``; ``path`` holds files and ``resume`` is False, or
            holds no disk buffer and ``resume`` is True, or is in use by another buffer.
    """

    def __init__(
        self,
        *,
        action_spec: TensorSpec | None = None,
        num_states: int | None = None,
        capacity: int = 1024,
        batch_size: int | None = None,
        generator: torch.Generator | None = None,
        path: str | Path | None = None,
        resume: bool = False,
    ) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be positive, got {capacity}")
        if resume and path is None:
            raise ValueError("resume=True needs the path of a disk buffer")
        self.action_spec = action_spec
        self.num_states = num_states
        self.schema: dict[str, tuple[str, tuple[int, ...]]] | None = None
        self.next_episode = 0
        self._num_episodes = 0
        self._layout = None if path is None else DiskLayout(path, resume=resume)
        if self._layout is None:
            self._storage = GrowingTensorStorage(int(capacity))
        else:
            self._storage = GrowingMemmapStorage(self._layout.scratch_dir, int(capacity))
        self._rb = ReplayBuffer(
            storage=self._storage,
            sampler=SamplerWithoutReplacement(drop_last=False, shuffle=True),
            generator=generator,  # no batch_size: sample passes one (TorchRL warned when a
        )  # call's differed from the constructor's, which sample's own argument allows)
        self._generator, self._batch_size = generator, batch_size
        self._permutation: LazyPermutation | None = None  # a disk buffer's sampling order
        if self._layout is not None:
            if resume:
                stored = self._layout.stored
                assert stored is not None  # DiskLayout(resume=True) read it
                self._resume(stored)
            self._commit()

    def _resume(self, stored: dict[str, Any]) -> None:
        assert self._layout is not None  # only a disk buffer resumes
        if self.num_states is not None and stored["num_states"] != self.num_states:
            raise ValueError(
                f"{self._layout.path}: stored num_states {stored['num_states']}, given {self.num_states}"
            )
        self.num_states = stored["num_states"]
        if stored["columns"]:
            self._storage.map(stored["capacity"], stored["columns"], stored["rows"])
        else:  # a first write killed before its commit left files that hold no row
            drop_uncommitted(self._layout.scratch_dir)
        set_writer_cursor(self._rb, stored["rows"])
        check_stored_schema(stored["schema"], stored["columns"], where=self._layout.path)
        self.schema = stored["schema"]
        self.next_episode, self._num_episodes = stored["next_episode"], stored["num_episodes"]
        if stored["rows"]:  # resume trusts no count the directory holds
            check_stored_episodes(self.data.get(keys.EPISODE), stored, where=self._layout.path)
        if stored["rows"] and self.action_spec is not None:  # as load checks them (a
            # hostile review: a resume with a tighter spec kept rows outside it)
            for chunk in self.chunks(keys.EXPERT_ACTION, keys.ACTION):
                try:
                    check_actions(chunk, self.action_spec)
                except ValueError as err:
                    raise ValueError(f"{self._layout.path}: stored rows: {err}") from None

    def _commit(self) -> None:
        """Record a disk buffer's rows and state (after the rows are written)."""
        assert self._layout is not None  # called for a disk buffer only
        self._layout.write(
            {
                "rows": len(self),
                "capacity": self.capacity,
                "next_episode": self.next_episode,
                "num_episodes": self._num_episodes,
                "num_states": self.num_states,
                "schema": self.schema,
                "columns": self._storage.columns(self._layout.path),
            }
        )

    # ------------------------------------------------------------------ size
    def __len__(self) -> int:
        return len(self._storage)

    @property
    def capacity(self) -> int:
        """Rows the storage holds before it next grows (it doubles; never wraps)."""
        return int(self._storage.max_size)

    @property
    def path(self) -> Path | None:
        """The directory of a disk buffer; None for one in memory."""
        return None if self._layout is None else self._layout.path

    @property
    def num_episodes(self) -> int:
        """Distinct episode ids (each episode's rows are contiguous: counted on extend)."""
        return self._num_episodes

    @property
    def data(self) -> TensorDictBase:
        """All rows, in insertion order (a view on the storage; on disk, on the mapped
        files: reading it pages rows in, nothing is copied up front)."""
        if len(self) == 0:
            raise ValueError(
                "the demonstration buffer is empty: collect or load demonstrations first"
            )
        return self._storage[: len(self)]

    def chunks(self, *select: Any) -> Iterator[TensorDictBase]:
        """The rows (only the keys ``select``, or all) in consecutive slices of about
        ``CHUNK_BYTES``: a pass over every row that holds one slice at a time (on disk,
        the pages a pass maps are let go every ``REMAP_BYTES``)."""
        view = lambda: self.data if not select else self.data.select(*select)  # noqa: E731
        rows = view()
        step = max(1, CHUNK_BYTES // max(1, _row_bytes(rows)))
        for start in range(0, len(self), step):
            part = rows[start : start + step]
            yield part
            if self._layout is not None and self._storage.note_bytes(
                part.shape[0] * _row_bytes(self.data)
            ):
                del part
                rows = view()  # views on the new mapping: the old one's pages go

    def rows_at(self, index: torch.Tensor, *select: Any) -> TensorDictBase:
        """The rows at ``index`` (only the keys ``select``, or all), read from the storage
        (on disk: only those rows, and the pages such reads map are let go regularly)."""
        batch = self._storage.get(index)
        if self._layout is not None:
            self._storage.note_reads(batch.shape[0])
        return batch.select(*select) if select else batch

    # ----------------------------------------------------------------- write
    def extend(self, rows: TensorDictBase) -> torch.Tensor:
        """Append rows (a TensorDict with one batch dimension); returns their indices.

        Raises:
            ValueError: empty rows, a missing or extra key, no ``OBSERVATION`` nor
                ``PIXELS``, a dtype or trailing-shape change, an episode id already used,
                NaN/inf values, actions outside ``action_spec``, observations outside
                ``[0, num_states)``.
        """
        return self._extend(rows, check_episodes=True)

    def _extend(self, rows: TensorDictBase, *, check_episodes: bool) -> torch.Tensor:
        schema = check_rows(
            rows,
            schema=self.schema,
            next_episode=self.next_episode if check_episodes else None,
            action_spec=self.action_spec,
            num_states=self.num_states,
        )
        start = len(self)
        try:
            index = self._write_all(rows)
        except BaseException:  # a write that failed part-way (or a Ctrl-C) counts nothing
            forget_rows_after(self._rb, start)
            raise
        episodes = rows.get(keys.EPISODE)
        self.schema = schema
        self.next_episode = max(self.next_episode, int(episodes.max()) + 1)
        self._num_episodes += int((episodes[1:] != episodes[:-1]).sum()) + 1
        if self._layout is not None:
            self._commit()
        return index

    def _write_all(self, rows: TensorDictBase) -> torch.Tensor:
        """Write checked rows, on disk a chunk at a time; their indices."""
        n = rows.shape[0]
        if self._layout is None:
            index = self._write(rows)
        else:
            # on disk, CHUNK_BYTES of rows per write: the storage maps its files again
            # every REMAP_BYTES written, so the pages one large extend writes (rows
            # decoded into a memory-mapped file, say) do not all stay in this process's
            # resident set; the rows are counted only after all of them are written
            step = max(1, CHUNK_BYTES // max(1, _row_bytes(rows)))
            parts = []
            for s in range(0, n, step):
                part = rows[s : s + step]
                parts.append(self._write(part))
                release_pages(part)  # a memory-mapped source's pages, once copied
            index = torch.cat(parts)
        return index

    def _write(self, rows: TensorDictBase) -> torch.Tensor:
        """Write checked rows into the storage (growing it first); their indices."""
        n, before = rows.shape[0], len(self)
        grew = self._storage.reserve(n)
        if grew or writer_cursor(self._rb) != before:
            # After a reallocation the round-robin writer must continue at the end,
            # not at its wrapped cursor (torchrl's writer computes cursor % max_size).
            set_writer_cursor(self._rb, before)
        if self._storage.initialized:
            index = self._rb.extend(rows)
        else:
            with quiet_torchrl_info():  # its first write logs on stdout
                index = self._rb.extend(rows)
        if len(self) != before + n:  # guard: nothing may have been overwritten
            raise RuntimeError(f"buffer write lost rows: had {before}, wrote {n}, now {len(self)}")
        return index

    # ------------------------------------------------------------------ read
    def sample(self, batch_size: int | None = None) -> TensorDictBase:
        """A minibatch without replacement (epochs over the current rows; the last
        batch of an epoch may be smaller)."""
        if len(self) == 0:
            raise ValueError("cannot sample from an empty demonstration buffer")
        batch_size = self._batch_size if batch_size is None else batch_size
        if batch_size is None or batch_size < 1:  # both kinds of buffer alike
            raise ValueError(f"sample needs a positive batch_size, got {batch_size}")
        if self._layout is None:
            return self._rb.sample(batch_size)
        perm = self._permutation
        if perm is None or perm.n != len(self) or perm.remaining == 0:
            perm = self._permutation = LazyPermutation(len(self), self._generator)
        batch = self._storage.get(perm.take(batch_size))
        self._storage.note_reads(batch.shape[0])  # bounds the pages mapped by sampling
        return batch

    def rounds(self) -> Iterable[int]:
        """The DAgger rounds present in the buffer, sorted (0 = demonstrations)."""
        found: set[int] = set()
        for part in self.chunks(keys.ROUND):
            found.update(part.get(keys.ROUND).unique().tolist())
        return sorted(found)

    # -------------------------------------------------------------- save/load
    def save(
        self,
        path: str | Path,
        *,
        learner: torch.nn.Module | None = None,
        state: dict[str, Any] | None = None,
        overwrite: bool = False,
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

        The write is atomic and exclusive: ``path`` afterwards holds this checkpoint or,
        after a crash or ``kill -9``, the previous one, whole; while one process saves to
        ``path`` every other saver of it is refused. An existing, non-empty ``path`` is
        replaced only with ``overwrite=True``, and only if it is a checkpoint of this
        format, so of several processes saving to one new path exactly one succeeds and
        the others are told why. Returns the absolute path.

        Raises:
            ValueError: the buffer is empty; ``state`` is not plain JSON; ``path`` exists
                (without ``overwrite``) or holds something other than a buffer checkpoint
                (left untouched); another process is saving to it.
            imitrl.fs.DiskFullError: the disk filled up (``path`` keeps what it held).
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
        return write_checkpoint(path, files, content, fmt=_FORMAT, overwrite=overwrite)

    @classmethod
    def load(
        cls,
        path: str | Path,
        *,
        learner: torch.nn.Module | None = None,
        action_spec: TensorSpec | None = None,
        generator: torch.Generator | None = None,
        batch_size: int | None = None,
        into: str | Path | None = None,
    ) -> tuple[DemonstrationBuffer, dict[str, Any]]:
        """Read a checkpoint written by :meth:`save`; returns ``(buffer, state)``.

        Every file is checked against the manifest (presence, size, SHA-256, no
        unlisted file) before any is read; the rows then pass the same checks as
        :meth:`extend` (and ``action_spec``, when given). Pass ``learner`` (built as
        before saving) to restore its weights and optimizers: it is changed only if
        everything loads. Nothing is written to ``path``.

        ``into``: load into a new disk buffer in that directory (absent or empty),
        streaming: the column files are hashed in a streaming pass, then memory-mapped
        and copied ``CHUNK_BYTES`` of rows at a time (resident memory does not grow with
        the rows; a file changed between its hash and its copy goes unnoticed). If the
        rows fail a check, the partial disk buffer is removed.

        Raises:
            ValueError: naming the file: not a checkpoint, a file missing, truncated,
                appended to, altered or unlisted, an edited manifest, rows that fail the
                buffer's checks, a ``learner`` that does not match the saved one; an
                occupied ``into``.
        """
        path = Path(path)
        content, files = read_checkpoint(path, fmt=_FORMAT, map_bytes=None if into is None else 1)
        try:
            rows = decode_rows(content, files)
            num_states, next_episode = content["num_states"], content["next_episode"]
            if not (num_states is None or type(num_states) is int) or type(next_episode) is not int:
                raise ValueError("num_states and next_episode must be integers")
            where = str(path / str(content["state"]))
            state = parse_json(bytes(files[content["state"]].numpy()), where=where)
        except (KeyError, TypeError, ValueError) as err:
            raise ValueError(f"{path / MANIFEST}: malformed content ({err})") from None
        buf = cls(
            action_spec=action_spec,
            num_states=num_states,
            capacity=rows.shape[0],
            batch_size=batch_size,
            generator=generator,
            path=into,
        )
        try:
            if into is None:
                buf.extend(rows)
            else:
                buf._extend_streaming(rows)
        except ValueError as err:
            removed = (
                "" if into is None else f" (the partial disk buffer {buf._discard()} was removed)"
            )
            raise ValueError(
                f"{path}: the stored rows fail the buffer's checks: {err}{removed}"
            ) from None
        if next_episode < buf.next_episode:
            raise ValueError(
                f"{path / MANIFEST}: next_episode {next_episode} is below the stored episode ids"
            )
        buf.next_episode = next_episode
        if learner is not None:
            restore_learner(learner, content.get("learner"), files, path)
        if into is not None:
            buf._commit()
        return buf, state

    def _extend_streaming(self, rows: TensorDictBase) -> None:
        """Extend an empty buffer with ``rows`` ``CHUNK_BYTES`` at a time: the episode ids
        are checked over all rows first (an episode may span two chunks)."""
        step = max(1, CHUNK_BYTES // max(1, _row_bytes(rows)))
        count, _ = episode_runs(rows.get(keys.EPISODE), step, self.next_episode)
        for start in range(0, rows.shape[0], step):
            self._extend(rows[start : start + step], check_episodes=False)
        self._num_episodes = count
        self._commit()

    def _discard(self) -> Path:
        """Remove a disk buffer's directory (one this object created; see ``load``)."""
        assert self._layout is not None  # called for a disk buffer only
        where = self._layout.path
        self._layout.close()
        shutil.rmtree(where)
        return where


def _row_bytes(rows: TensorDictBase) -> int:
    return sum(v[0].nbytes for v in rows.values(include_nested=True, leaves_only=True))


_FORMAT = "imitrl.DemonstrationBuffer/3"
