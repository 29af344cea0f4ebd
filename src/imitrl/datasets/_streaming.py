"""The two passes of a streamed load into a buffer: nothing half-loaded.

A streamed load (LeRobot's :mod:`~imitrl.datasets.lerobot._stream`, Minari's
:mod:`~imitrl.datasets.minari._stream`) reads its rows a piece at a time and reads them
twice. :func:`check_pieces` runs the buffer's own checks
(:func:`~imitrl.data.validation.check_rows`) on every piece with the schema and episode ids
the buffer would have after the pieces before it, and writes nothing; only then does
:func:`extend_pieces` add the same pieces. A bad piece anywhere, the last one included,
leaves the buffer as it was. One piece is resident at a time: the allocators' unused
memory is handed back after each (:func:`~imitrl.datasets._arrow.release_unused_memory`).
"""

from __future__ import annotations

from collections.abc import Iterable

from tensordict import TensorDict, TensorDictBase

from imitrl import keys
from imitrl.data.buffer import DemonstrationBuffer
from imitrl.data.validation import check_rows
from imitrl.datasets._arrow import release_unused_memory

__all__ = ["check_pieces", "extend_pieces"]


def check_pieces(buffer: DemonstrationBuffer, pieces: Iterable[TensorDict], where: object) -> int:
    """Pass 1: every piece checked as ``buffer.extend`` would check it after the pieces
    before it; nothing written. Returns the number of rows; a misfit raises ``ValueError``
    naming ``where``."""
    schema, next_episode = buffer.schema, buffer.next_episode
    total = 0
    for rows in pieces:
        try:
            schema = check_rows(
                rows,
                schema=schema,
                next_episode=next_episode,
                action_spec=buffer.action_spec,
                num_states=buffer.num_states,
            )
        except ValueError as err:
            raise ValueError(f"{where}: the rows do not fit the buffer: {err}") from None
        next_episode = max(next_episode, int(rows.get(keys.EPISODE).max()) + 1)
        total += rows.shape[0]
        del rows
        release_unused_memory()
    return total


def extend_pieces(buffer: DemonstrationBuffer, pieces: Iterable[TensorDict]) -> TensorDictBase:
    """Pass 2: the pieces (already checked by :func:`check_pieces`) added to ``buffer``;
    returns the rows added (a view of the buffer)."""
    before = len(buffer)
    for rows in pieces:
        buffer.extend(rows)
        del rows
        release_unused_memory()
    return buffer.data[before:]
