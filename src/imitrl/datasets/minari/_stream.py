"""A Minari dataset streamed into a buffer, episode by episode
(``load_minari(..., into=buffer)``).

Episodes are read one at a time (one HDF5 group's datasets, or one arrow / parquet
folder), checked exactly as :func:`load_minari` checks them, and gathered into pieces of
about :data:`PIECE_ROWS` steps (whole episodes, at least one) that become rows.

Nothing half-loaded (:mod:`imitrl.datasets._streaming`): the episodes are read twice. The
first pass runs every check, the dataset's records (``total_steps``; ids held once and
``total_episodes`` are checked when the episodes are listed) and the buffer's own; only
then does the second pass extend the buffer, piece by piece. A damaged episode anywhere,
the last one included, leaves the buffer as it was. Resident memory: one piece and one
integer per episode (its id), whatever the dataset's length.

The second pass reads the files the first one opened (the source keeps them open,
:mod:`._source`), so a dataset replaced meanwhile cannot change it. Only past the
descriptors a source may hold does it open an episode again by name; should that find the
dataset replaced, the load stops with a RuntimeError saying how many rows the buffer took
(never retried: the buffer already holds them).
"""

from __future__ import annotations

from collections.abc import Iterator

from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase

from imitrl.data.buffer import DemonstrationBuffer
from imitrl.datasets._common import conform_to_env
from imitrl.datasets._streaming import check_pieces, extend_pieces
from imitrl.datasets.minari._episodes import Episode, check_episode, check_steps, episode_rows
from imitrl.datasets.minari._source import EpisodeSource

__all__ = ["PIECE_ROWS", "stream_into"]

PIECE_ROWS = 1 << 17
"""steps gathered into one piece of rows, checked and added to the buffer at once (whole
episodes, at least one)"""


def _pieces(
    src: EpisodeSource,
    first_episode: int,
    next_observation: bool,
    env: EnvBase | None,
    names: dict[str, str],
    notes: list[str],
) -> Iterator[TensorDict]:
    """The rows of the episodes, a piece at a time, in id order (fitted to ``env``); a
    piece's episodes with no step give no rows. One pass over ``src``."""
    src.new_pass()
    piece: list[Episode] = []
    steps = 0
    for e in range(len(src)):
        episode = check_episode(src.read(e), first_episode, next_observation)
        piece.append(episode)
        steps += len(episode.step)
        if steps >= PIECE_ROWS or e == len(src) - 1:
            if steps:
                rows = episode_rows(piece, next_observation)
                if env is not None:
                    found: list[str] = []
                    rows = conform_to_env(rows, env, where=src.where, notes=found, names=names)
                    notes.extend(n for n in found if n not in notes)
                yield rows
            piece, steps = [], 0


def stream_into(
    buffer: DemonstrationBuffer,
    src: EpisodeSource,
    *,
    first_episode: int,
    next_observation: bool,
    env: EnvBase | None,
    names: dict[str, str],
) -> tuple[TensorDictBase, list[str]]:
    """Check every episode and piece (the dataset's records and the buffer's checks
    included), then extend ``buffer`` with them; returns the rows added (a view of the
    buffer) and the notes of :func:`conform_to_env`."""
    notes: list[str] = []
    frames = check_pieces(
        buffer, _pieces(src, first_episode, next_observation, env, names, notes), src.where
    )
    check_steps(frames, src.meta, src.where)
    before = len(buffer)
    try:
        view = extend_pieces(buffer, _pieces(src, first_episode, next_observation, env, names, []))
    except ValueError as err:  # it passed every check a moment ago: the files changed
        raise RuntimeError(
            f"{src.where}: changed while it was loaded into the buffer, after its check "
            f"({err}); the buffer took {len(buffer) - before} of its rows. Load it again "
            "into a fresh buffer"
        ) from err
    return view, notes
