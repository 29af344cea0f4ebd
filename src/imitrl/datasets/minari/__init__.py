"""Minari datasets read straight from their files, offline, without the ``minari`` package.

Both storage formats of Minari 0.5 are read: ``hdf5`` (``data/main_data.hdf5``, one
group per episode: :mod:`._hdf5`) and ``arrow`` / ``parquet`` (one folder per episode:
:mod:`._arrow`); ``data/metadata.json`` names the format (``data_format``) and the
spaces. Every array is checked against its space before it is converted
(:mod:`._spaces`: no cast that changes a value, Discrete actions in range, no NaN or
inf) and every episode against its own records (:mod:`._episodes`: lengths, boolean
flags, one value of reward per step, unique ids). Why not TorchRL's
``MinariExperienceReplay``: in torchrl 0.14.1 it returns all-zero data for a local
dataset (see TORCHRL_NOTES.md).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from torchrl.envs import EnvBase

from imitrl import keys
from imitrl.datasets._common import LoadedDemonstrations, conform_to_env, warn_skipped
from imitrl.datasets.minari._arrow import read_columns
from imitrl.datasets.minari._episodes import Steps, check_episode, check_ids, episode_rows
from imitrl.datasets.minari._hdf5 import MAIN_FILE, attrs_metadata, open_hdf5, read_hdf5
from imitrl.datasets.minari._spaces import parse_space

__all__ = ["load_minari", "resolve_minari_root"]

METADATA_FILE = "metadata.json"
FORMATS = ("hdf5", "arrow", "parquet")


def resolve_minari_root(path_or_id: str | Path) -> Path:
    """The ``data`` directory of a Minari dataset: a path (the dataset or its ``data``
    folder), or a dataset id under ``$MINARI_DATASETS_PATH`` (default ``~/.minari/datasets``).

    Raises:
        ValueError: nothing holding ``main_data.hdf5`` or ``metadata.json`` found (the
            message lists where it looked).
    """
    path = Path(path_or_id)
    candidates = [path, path / "data"]
    if not path.is_absolute() and not path.exists():
        base = Path(os.environ.get("MINARI_DATASETS_PATH", Path.home() / ".minari" / "datasets"))
        candidates += [base / path / "data"]
    for c in candidates:
        if (c / MAIN_FILE).is_file() or (c / METADATA_FILE).is_file():
            return c
    raise ValueError(
        f"no Minari dataset at {path_or_id!r} (looked for {MAIN_FILE} or {METADATA_FILE} in "
        f"{[str(c) for c in candidates]}); this loader never downloads"
    )


def _metadata_json(path: Path) -> dict[str, Any]:
    try:
        meta = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path} is not valid JSON: {err}") from err
    if not isinstance(meta, dict):
        raise ValueError(f"{path}: expected a JSON object, got {type(meta).__name__}")
    return meta


def _spaces(meta: dict[str, Any], where: str) -> tuple[dict, dict]:
    """The observation and action spaces the metadata declares."""
    fmt = meta.get("data_format", "hdf5")
    if fmt not in FORMATS:
        raise ValueError(f"{where}: data_format {fmt!r} is not supported (only {FORMATS})")
    for field in ("observation_space", "action_space"):
        if field not in meta:
            raise ValueError(
                f"{where}: no {field!r}; datasets that only record an env_spec are not "
                "supported (the env would have to be built to learn its spaces)"
            )
    return (
        parse_space(meta["observation_space"], f"{where}: observation_space"),
        parse_space(meta["action_space"], f"{where}: action_space"),
    )


def _read_steps(data_dir: Path, skipped: dict[str, str]) -> tuple[list[Steps], dict, str]:
    """Every episode's arrays, the metadata, and the file (or folder) messages name."""
    meta_path = data_dir / METADATA_FILE
    meta = _metadata_json(meta_path) if meta_path.is_file() else None
    fmt = (meta or {}).get("data_format", "hdf5")
    if fmt == "hdf5":
        where = str(data_dir / MAIN_FILE)
        with open_hdf5(data_dir / MAIN_FILE) as h5:
            meta = meta if meta is not None else attrs_metadata(h5, where)
            spaces = _spaces(meta, str(meta_path) if meta_path.is_file() else where)
            jpeg = bool(meta.get("jpeg_encoding", False))
            steps = read_hdf5(h5, spaces, jpeg, skipped, where)
        return steps, meta, where
    spaces = _spaces(meta, str(meta_path))  # arrow / parquet: metadata.json named the format
    jpeg = bool(meta.get("jpeg_encoding", False))
    return read_columns(data_dir, fmt, spaces, jpeg, skipped), meta, str(data_dir)


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
            that contradict ``env``. Nothing is returned half-loaded.
    """
    data_dir = resolve_minari_root(path_or_id)
    skipped: dict[str, str] = {}
    steps, meta, where = _read_steps(data_dir, skipped)
    check_ids(steps, meta, where)
    episodes = [check_episode(s, first_episode, next_observation) for s in steps]
    rows = episode_rows(episodes, meta, next_observation, where)
    notes: list[str] = []
    if env is not None:
        rows = conform_to_env(rows, env, where=where, notes=notes, names=dict(_SOURCES))
    warn_skipped(data_dir, skipped, quiet=frozenset())
    return LoadedDemonstrations(
        rows=rows,
        source=data_dir,
        format=f"minari {meta.get('data_format', 'hdf5')} (minari {meta.get('minari_version', '?')})",
        num_episodes=len(episodes),
        loaded=dict(_LOADED),
        skipped=skipped,
        notes=notes,
        metadata=meta,
    )
