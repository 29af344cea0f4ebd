"""Minari datasets read straight from their files, offline, without the ``minari`` package.

Both storage formats of Minari 0.5 are read: ``hdf5`` (``data/main_data.hdf5``, one
group per episode: :mod:`._hdf5`) and ``arrow`` / ``parquet`` (one folder per episode:
:mod:`._arrow`); ``data/metadata.json`` names the format (``data_format``) and the
spaces. Every array is checked against its space before it is converted
(:mod:`._spaces`: no cast that changes a value, Discrete actions in range, no NaN or
inf) and every episode against its own records (:mod:`._episodes`: lengths, boolean
flags, one value of reward per step, unique ids). :mod:`._source` lists the episodes and
reads them one at a time, whatever the storage; :mod:`._stream` streams them into a
buffer (``load_minari(..., into=buffer)``); :mod:`._write` writes rows back as an
``hdf5`` dataset (:func:`save_minari`, checked by :mod:`._write_spaces`).

A downloaded dataset is hostile until checked: the ``data`` folder is pinned by a
descriptor and every file opened once inside it (:func:`~imitrl.fs.reading.read_whole`:
no link out, no FIFO, a load that meets a replacement in progress runs again on the new
dataset), every size a file declares is checked against the bytes it holds before it is
allocated, what the whole load declares beyond them against one floor (:mod:`._bounds`),
and JSON too deeply nested is refused by name. Why not TorchRL's
``MinariExperienceReplay``: in torchrl 0.14.1 it returns all-zero data for a local
dataset (see TORCHRL_NOTES.md).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from torchrl.envs import EnvBase

from imitrl import keys
from imitrl.data.buffer import DemonstrationBuffer
from imitrl.datasets._common import LoadedDemonstrations, conform_to_env, warn_skipped
from imitrl.datasets.minari._episodes import check_episode, check_steps, episode_rows
from imitrl.datasets.minari._hdf5 import MAIN_FILE
from imitrl.datasets.minari._source import METADATA_FILE, open_episodes
from imitrl.datasets.minari._stream import stream_into
from imitrl.datasets.minari._write import save_minari
from imitrl.fs.contained import links_stay_inside
from imitrl.fs.reading import OpenedFolder, read_whole

__all__ = ["load_minari", "resolve_minari_root", "save_minari"]


def resolve_minari_root(path_or_id: str | Path) -> Path:
    """The ``data`` directory of a Minari dataset: a path (the dataset or its ``data``
    folder), or a dataset id under ``$MINARI_DATASETS_PATH`` (default ``~/.minari/datasets``).

    Raises:
        ValueError: nothing holding ``main_data.hdf5`` or ``metadata.json`` found (the
            message lists where it looked); a symbolic link in the dataset points outside it.
    """
    path = Path(path_or_id)
    candidates = [path, path / "data"]
    if not path.is_absolute() and not path.exists():
        base = Path(os.environ.get("MINARI_DATASETS_PATH", Path.home() / ".minari" / "datasets"))
        candidates += [base / path / "data"]
    for c in candidates:
        # any entry by these names (what it is, is checked when it is opened: a FIFO or a
        # link out is refused by name then)
        if os.path.lexists(c / MAIN_FILE) or os.path.lexists(c / METADATA_FILE):
            # every file it reads lies inside the dataset (a link out is refused)
            links_stay_inside(c, what="dataset")
            return c
    raise ValueError(
        f"no Minari dataset at {path_or_id!r} (looked for {MAIN_FILE} or {METADATA_FILE} in "
        f"{[str(c) for c in candidates]}); this loader never downloads"
    )


_LOADED = {
    "observations": keys.OBSERVATION,
    "actions": f"{keys.EXPERT_ACTION} (and {keys.ACTION})",
    "rewards": "next.reward",
    "terminations": "next.terminated",
    "truncations": "next.truncated",
}
"""Minari dataset -> the buffer key it is loaded into (``LoadedDemonstrations.loaded``)"""

_SOURCES = {
    keys.OBSERVATION: "observations",
    keys.ACTION: "actions",
    keys.EXPERT_ACTION: "actions",
    "next.reward": "rewards",
    "next.done": "terminations | truncations",
    "next.terminated": "terminations",
    "next.truncated": "truncations",
}
"""buffer key name -> the Minari dataset it comes from, for :func:`conform_to_env`'s messages"""


def load_minari(
    path_or_id: str | Path,
    *,
    env: EnvBase | None = None,
    first_episode: int = 0,
    next_observation: bool = False,
    into: DemonstrationBuffer | None = None,
) -> LoadedDemonstrations:
    """Read a local Minari dataset (hdf5, arrow or parquet storage) into demonstration rows.

    Args:
        path_or_id: the dataset directory, its ``data`` folder, or a dataset id under
            ``$MINARI_DATASETS_PATH`` (see :func:`resolve_minari_root`).
        env: if given, observation/action shapes must match its specs (else ValueError);
            dtypes are cast within a kind (float64 rewards -> the env's float32) or from
            integer to floating when every value is exact (Taxi's int64 rewards -> float32),
            reward and done flags take its shapes. Pass it whenever the rows are to share a
            buffer with the env's own rollouts.
        first_episode: added to Minari's episode ids (use ``buffer.next_episode``).
        next_observation: also keep ``observations[t + 1]`` as ``("next", OBSERVATION)``.
        into: stream the dataset into this buffer (in memory or on disk,
            ``DemonstrationBuffer(path=...)``) episode by episode (:mod:`._stream`):
            resident memory does not grow with the dataset's length. Every check runs over
            the whole dataset before the buffer is extended (the dataset is read twice),
            so a damaged episode anywhere leaves the buffer as it was. ``rows`` is then a
            view of the rows added to the buffer, the same rows the load into memory gives.

    Returns:
        :class:`LoadedDemonstrations`: ``OBSERVATION`` (a tensor, or a nested TensorDict for
        Dict/Tuple spaces; Tuple entries are named ``_index_<i>`` as in the hdf5 file),
        ``EXPERT_ACTION`` = ``ACTION``, ``("next", reward|done|terminated|truncated)`` as
        ``[N, 1]`` (TorchRL's layout; Minari's own terminations and truncations, as
        recorded), round 0, ``EXPERT_EXECUTED`` True. Per-step ``infos`` are not loaded
        (listed in ``skipped`` with a warning).

    Raises:
        ValueError: no dataset; an unreadable or truncated file; metadata missing a space
            or holding a malformed one; values their space cannot hold unchanged (float
            data in an integer Box, float or out-of-range Discrete actions, flags other
            than booleans or 0/1), NaN or inf; an episode whose arrays have inconsistent
            lengths or shapes, or rewards of more than one value per step; an episode id
            held twice; episode counts or step totals that contradict the metadata; shapes
            that contradict ``env``; with ``into``, rows that do not fit the buffer (its
            schema, its episode ids); a file that is a link out of the dataset, a FIFO or
            no regular file; a file declaring more values than its bytes can hold
            (:mod:`._bounds`); JSON nested too deeply. Nothing is returned, or added,
            half-loaded.
        imitrl.fs.ReplacedWhileReading: (a ValueError) the dataset was replaced while it
            was read, every one of the tries.
    """
    data_dir = resolve_minari_root(path_or_id)

    def load(folder: OpenedFolder) -> tuple[Any, list[str], dict, int, dict[str, str]]:
        skipped: dict[str, str] = {}
        notes: list[str] = []
        with open_episodes(folder, skipped, pin=into is not None) as src:
            meta, where = src.meta, src.where
            if into is not None:
                rows, notes = stream_into(
                    into,
                    src,
                    first_episode=first_episode,
                    next_observation=next_observation,
                    env=env,
                    names=dict(_SOURCES),
                )
            else:
                episodes = [
                    check_episode(src.read(e), first_episode, next_observation)
                    for e in range(len(src))
                ]
                check_steps(sum(len(ep.step) for ep in episodes), meta, where)
                rows = episode_rows(episodes, next_observation)
                if env is not None:
                    names = dict(_SOURCES)
                    rows = conform_to_env(rows, env, where=where, notes=notes, names=names)
            return rows, notes, meta, len(src), skipped

    # a load that met a replacement in progress runs again on the new dataset
    rows, notes, meta, num_episodes, skipped = read_whole(data_dir, load, what="dataset")
    warn_skipped(data_dir, skipped, quiet=frozenset())
    return LoadedDemonstrations(
        rows=rows,
        source=data_dir,
        format=f"minari {meta.get('data_format', 'hdf5')} (minari {meta.get('minari_version', '?')})",
        num_episodes=num_episodes,
        loaded=dict(_LOADED),
        skipped=skipped,
        notes=notes,
        metadata=meta,
    )
