"""Write demonstration rows as a Minari 0.5 dataset in ``hdf5`` storage (:func:`save_minari`).

The layout is Minari's own (``minari/dataset/_storages/hdf5_storage.py`` and
``minari_storage.py``, Minari 0.5.4), the one :mod:`._hdf5` reads::

    <path>/data/main_data.hdf5   group "episode_<e>" per episode, e = 0..E-1 in row order,
                                 attrs id, total_steps; datasets observations [T+1, ...]
                                 (a group per Dict entry), actions [T, ...], rewards [T],
                                 terminations [T], truncations [T], infos (empty)
    <path>/data/metadata.json    total_episodes, total_steps, data_format "hdf5",
                                 jpeg_encoding false (images stored whole: lossless),
                                 observation_space / action_space (Minari's JSON),
                                 env_spec (with env_id), dataset_id, minari_version,
                                 dataset_size (MB)

Minari stores ``T + 1`` observations per episode: the rows' ``observation`` at steps
``0..T-1`` and the ``("next", "observation")`` of the last row (the final observation,
which a TorchRL rollout does not keep: rows without it are refused). The rows are checked
first (keys, contiguous episodes whose ``STEP`` runs 0..T-1, flags that end an episode
only at its last row), then written an episode at a time, each value checked against its
space (:mod:`._write_spaces`), into a temporary directory that becomes ``path`` only when
complete (:func:`~imitrl.fs.publish.publishing`: atomic, one writer per path). A full disk
is an :class:`imitrl.fs.DiskFullError` naming ``path``, which keeps what it held: HDF5
writes through :class:`~imitrl.datasets.minari._hdf5_out.HDF5Out`, which never lets a
failed write reach HDF5 (whose close then crashes the process).
"""

from __future__ import annotations

import json
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import torch
from tensordict import TensorDictBase

from imitrl import keys
from imitrl.data.buffer import DemonstrationBuffer
from imitrl.datasets._common import NestedKey, key_name
from imitrl.datasets.minari._hdf5 import MAIN_FILE
from imitrl.datasets.minari._hdf5_out import HDF5Out
from imitrl.datasets.minari._source import METADATA_FILE, METADATA_LIMIT
from imitrl.datasets.minari._write_spaces import check_space, serialize_space, space_values
from imitrl.fs.publish import publishing
from imitrl.fs.reading import OpenedFolder, parse_json

__all__ = ["MINARI_VERSION", "save_minari"]

MINARI_VERSION = "0.5.4"
"""the Minari release whose layout :func:`save_minari` writes (``metadata.json``'s
``minari_version``; in ``minari.supported_dataset_versions``)"""

_NEXT_OBS = (keys.NEXT, keys.OBSERVATION)
_FLAGS = ((keys.NEXT, keys.TERMINATED), (keys.NEXT, keys.TRUNCATED))


# ------------------------------------------------------------------ inputs
def _rows_to_write(
    data: DemonstrationBuffer | TensorDictBase, action_key: NestedKey
) -> TensorDictBase:
    """The ``[N]`` rows, once they hold every key a Minari episode is made of."""
    rows = data.data if isinstance(data, DemonstrationBuffer) else data
    if not isinstance(rows, TensorDictBase) or rows.batch_dims != 1 or rows.shape[0] == 0:
        raise ValueError("save_minari needs a non-empty buffer or a TensorDict of rows [N]")
    if action_key not in (keys.EXPERT_ACTION, keys.ACTION):
        raise ValueError(
            f"action_key must be {keys.EXPERT_ACTION!r} or {keys.ACTION!r}, got {action_key!r}"
        )
    need: list[NestedKey] = [
        keys.OBSERVATION,
        action_key,
        keys.EPISODE,
        keys.STEP,
        (keys.NEXT, keys.REWARD),
    ]
    need += [*_FLAGS, _NEXT_OBS]
    held = set(rows.keys(include_nested=True))
    missing = [key_name(k) for k in need if k not in held]
    if missing:
        hint = (
            f" (Minari stores each episode's final observation: keep {key_name(_NEXT_OBS)!r}, "
            "collected with rollout_episodes(..., next_observation=True) or read with "
            "load_minari(..., next_observation=True))"
            if key_name(_NEXT_OBS) in missing
            else ""
        )
        raise ValueError(f"rows lack {missing} to be written as a Minari dataset{hint}")
    return rows


def _spaces(
    observation_space: gymnasium.Space | None,
    action_space: gymnasium.Space | None,
    env_id: str | None,
) -> tuple[gymnasium.Space, gymnasium.Space, str | None]:
    """(observation space, action space, env_spec JSON or None): the spaces given, else
    those of ``gymnasium.make(env_id)``."""
    env_spec = None
    if env_id is not None:
        try:
            spec = gymnasium.spec(env_id)
        except gymnasium.error.Error as err:
            raise ValueError(f"env_id {env_id!r} is not a registered gymnasium id") from err
        try:
            env_spec = spec.to_json()
        except (TypeError, ValueError) as err:
            warnings.warn(f"{env_id}: env_spec not recorded ({err})", UserWarning, stacklevel=3)
        if observation_space is None or action_space is None:
            env = gymnasium.make(env_id)
            observation_space = observation_space or env.observation_space
            action_space = action_space or env.action_space
            env.close()
    if observation_space is None or action_space is None:
        raise ValueError(
            "save_minari needs observation_space and action_space (gymnasium spaces), or an "
            "env_id whose env gives them"
        )
    check_space(observation_space, "observation_space")
    check_space(action_space, "action_space")
    return observation_space, action_space, env_spec


def _episodes(rows: TensorDictBase) -> tuple[np.ndarray, np.ndarray]:
    """``(starts, lengths)`` of the episodes, each one contiguous block of rows whose
    ``STEP`` runs 0..length-1. Memory: the two int64 columns."""
    episode = rows.get(keys.EPISODE).cpu().numpy().reshape(-1)
    step = rows.get(keys.STEP).cpu().numpy().reshape(-1)
    n = len(episode)
    change = np.ones(n, dtype=bool)
    change[1:] = episode[1:] != episode[:-1]
    starts = np.flatnonzero(change)
    ids = episode[starts]
    if len(np.unique(ids)) != len(ids):
        raise ValueError(
            f"each episode must be one contiguous block of rows: {keys.EPISODE!r} ids "
            "reappear after another episode"
        )
    first = np.repeat(starts, np.diff(np.append(starts, n)))
    bad = np.flatnonzero(step != np.arange(n) - first)
    if len(bad):
        i = int(bad[0])
        raise ValueError(
            f"episode {int(episode[i])}: {keys.STEP!r} must run 0..length-1, got "
            f"{int(step[i])} at its row {i - int(first[i])}"
        )
    return starts, np.diff(np.append(starts, n))


def _replaceable(path: Path) -> None:
    """``overwrite=True`` replaces only a Minari dataset: a directory holding nothing but
    ``data/``, whose ``data/metadata.json`` (a regular file, read by descriptor, JSON not
    too deeply nested) names a ``data_format``. Else ValueError."""
    meta, why = None, ""
    try:
        with OpenedFolder(path / "data") as folder:
            text = folder.read_bytes(METADATA_FILE, named_by="overwrite", limit=METADATA_LIMIT)
        meta = parse_json(text, where=str(path / "data" / METADATA_FILE))
    except ValueError as err:
        why = f": {err}"
    if not isinstance(meta, dict) or not isinstance(meta.get("data_format"), str):
        raise ValueError(
            f"{path} is not a Minari dataset (no data/{METADATA_FILE} naming a data_format"
            f"{why}); overwrite=True replaces only a dataset: refusing to delete it"
        )
    other = sorted(p.name for p in path.iterdir() if p.name != "data")
    if other:
        raise ValueError(
            f"{path} holds {other} beside data/; overwrite=True replaces only a directory "
            "holding nothing but a Minari dataset: refusing"
        )


# ----------------------------------------------------------------- episodes
_WRITTEN = {
    (keys.OBSERVATION,),
    (keys.EPISODE,),
    (keys.STEP,),
    *((keys.NEXT, k) for k in (keys.REWARD, keys.DONE, keys.TERMINATED, keys.TRUNCATED)),
    (keys.NEXT, keys.OBSERVATION),
}
"""key paths (and everything under them) an episode group holds or ``load_minari`` derives"""


@dataclass
class _Unwritten:
    """Keys Minari has no place for that hold more than :func:`load_minari` recreates."""

    names: set[str]

    def note(self, part: TensorDictBase, action_key: NestedKey) -> None:
        """Add the leaf keys of ``part`` (one episode) that are neither written nor
        recreated by ``load_minari`` with the values they hold."""
        other = keys.ACTION if action_key == keys.EXPERT_ACTION else keys.EXPERT_ACTION
        recreated = {
            other: lambda v: torch.equal(v, part.get(action_key)),
            keys.EXPERT_EXECUTED: lambda v: bool(v.all()),
            keys.ROUND: lambda v: not bool(v.any()),
        }
        written = {*_WRITTEN, (action_key,)}
        for key in part.keys(include_nested=True, leaves_only=True):
            path = (key,) if isinstance(key, str) else tuple(key)
            if any(path[:i] in written for i in range(1, len(path) + 1)):
                continue
            check = recreated.get(key)
            if check is None or not check(part.get(key)):
                self.names.add(key_name(key))


def _flags(part: TensorDictBase, where: str) -> list[np.ndarray]:
    """``terminations``, ``truncations`` ``[T]`` bool; an episode may end only at its last row."""
    flags = []
    for key in _FLAGS:
        value = part.get(key)
        if value.dtype != torch.bool:
            raise ValueError(f"{where}: {key_name(key)!r} must be bool, got {value.dtype}")
        flags.append(value.reshape(len(part), -1)[:, 0].cpu().numpy())
    ends = np.flatnonzero(flags[0][:-1] | flags[1][:-1])
    if len(ends):
        raise ValueError(
            f"{where}: terminated or truncated at step {int(ends[0])}, before the episode's "
            f"last row {len(part) - 1} (each episode must end where its flags say)"
        )
    done = part.get((keys.NEXT, keys.DONE), None)
    if done is not None and not np.array_equal(
        done.reshape(len(part), -1)[:, 0].cpu().numpy(), flags[0] | flags[1]
    ):
        raise ValueError(f"{where}: ('next', 'done') differs from terminated | truncated")
    return flags


def _rewards(part: TensorDictBase, where: str) -> np.ndarray:
    """``[T]`` rewards in their own dtype (Minari writes whatever the env returned)."""
    reward = part.get((keys.NEXT, keys.REWARD))
    if reward.ndim > 2 or (reward.ndim == 2 and reward.shape[1] != 1):
        raise ValueError(f"{where}: rewards must be [N] or [N, 1], got {list(reward.shape)}")
    values = reward.reshape(-1).cpu().numpy()
    if values.dtype.kind not in "fiu":
        raise ValueError(f"{where}: rewards hold {values.dtype} values, expected numbers")
    if not np.isfinite(values).all():
        step = int(np.flatnonzero(~np.isfinite(values))[0])
        raise ValueError(
            f"{where}: the reward at step {step} is {values[step]} (NaN and inf refused)"
        )
    return values


def _put(group: Any, name: str, value: Any) -> None:
    """A numpy array (or a nested dict of them, a group each) as Minari writes it."""
    if isinstance(value, dict):
        sub = group.create_group(name)
        for k, v in value.items():
            _put(sub, k, v)
        return
    group.create_dataset(name, data=value, chunks=True, maxshape=(None, *value.shape[1:]))


def _write_episode(
    h5: Any,
    e: int,
    part: TensorDictBase,
    spaces: tuple[gymnasium.Space, gymnasium.Space],
    action_key: NestedKey,
    where: str,
) -> None:
    """Episode ``e`` (its ``T`` rows) as group ``episode_<e>``, every value checked."""
    obs = part.get(keys.OBSERVATION)
    final = part.get(_NEXT_OBS)
    observations = space_values(torch.cat([obs, final[-1:]]), spaces[0], f"{where}/observations")
    if not bool((final[:-1] == obs[1:]).all()):
        raise ValueError(
            f"{where}: ('next', 'observation') differs from the next row's observation; "
            "Minari holds one observation per step"
        )
    actions = space_values(part.get(action_key), spaces[1], f"{where}/actions ({action_key!r})")
    terminations, truncations = _flags(part, where)
    group = h5.create_group(f"episode_{e}")
    group.attrs["id"] = e
    group.attrs["total_steps"] = len(part)
    _put(group, "observations", observations)
    _put(group, "actions", actions)
    _put(group, "rewards", _rewards(part, where))
    _put(group, "terminations", terminations)
    _put(group, "truncations", truncations)
    group.create_group("infos")  # Minari's collector always writes one (empty: no infos)


def _metadata(
    data_dir: Path,
    episodes: int,
    steps: int,
    spaces: tuple[gymnasium.Space, gymnasium.Space],
    env_spec: str | None,
    dataset_id: str,
    description: str | None,
) -> dict[str, Any]:
    """``metadata.json`` as ``MinariStorage.new`` + ``update_episodes`` leave it."""
    size = sum(p.stat().st_size for p in data_dir.rglob("*") if p.is_file()) / 1e6
    meta: dict[str, Any] = {
        "total_episodes": episodes,
        "total_steps": steps,
        "data_format": "hdf5",
        "jpeg_encoding": False,
        "observation_space": serialize_space(spaces[0]),
        "action_space": serialize_space(spaces[1]),
        "dataset_id": dataset_id,
        "minari_version": MINARI_VERSION,
        "dataset_size": round(size, 1),
    }
    if env_spec is not None:
        meta["env_spec"] = env_spec
    if description is not None:
        meta["description"] = description
    return meta


def save_minari(
    data: DemonstrationBuffer | TensorDictBase,
    path: str | Path,
    *,
    observation_space: gymnasium.Space | None = None,
    action_space: gymnasium.Space | None = None,
    env_id: str | None = None,
    action_key: NestedKey = keys.EXPERT_ACTION,
    dataset_id: str | None = None,
    description: str | None = None,
    overwrite: bool = False,
) -> Path:
    """Write demonstrations as a Minari 0.5 dataset (``hdf5`` storage) that ``minari``'s
    own reader and :func:`load_minari` open (layout: the module docstring).

    Each episode ``e`` (renumbered 0..E-1 in row order; ``load_minari(...,
    first_episode=k)`` adds ``k`` back) becomes ``episode_<e>``: ``observations`` =
    ``OBSERVATION`` ``[T, ...]`` followed by the last row's ``("next", OBSERVATION)``
    (a nested TensorDict: one dataset per entry of a Dict space), ``actions`` =
    ``action_key`` ``[T, ...]``, ``rewards`` = ``("next", "reward")`` ``[T]`` in its own
    dtype, ``terminations`` / ``truncations`` ``[T]`` bool. ``load_minari(path,
    next_observation=True)`` gives back the same rows, value for value and dtype for
    dtype (values are cast to their space's dtype when exact: write float32 rows with
    float32 spaces). Minari has no place for other keys: ``ROUND``, ``EXPERT_EXECUTED``
    and the other action key are left out silently when ``load_minari`` recreates them
    (round 0, executed by the expert, both actions equal); anything else (``PIXELS``,
    learner-executed DAgger rows, extra keys) is named in a ``UserWarning``.

    Args:
        data: a buffer or ``[N]`` rows holding ``OBSERVATION``, ``action_key``,
            ``EPISODE``, ``STEP``, ``("next", reward|terminated|truncated|observation)``;
            each episode one contiguous block whose ``STEP`` runs 0..T-1.
        path: the dataset directory (``$MINARI_DATASETS_PATH/<dataset_id>`` for
            ``minari.load_dataset``); must not exist unless ``overwrite``.
        observation_space, action_space: the gymnasium spaces written to the metadata
            (Box, Discrete, MultiDiscrete, MultiBinary, Dict of them); each value must lie
            inside them. Default: those of ``gymnasium.make(env_id)``.
        env_id: a registered gymnasium id, recorded as ``env_spec`` (``minari``'s
            ``recover_environment``).
        action_key: the key written as Minari's ``actions``: ``EXPERT_ACTION`` (the label,
            default) or ``ACTION`` (what was executed).
        dataset_id: ``metadata.json``'s ``dataset_id`` (default: the directory's name).
        description: ``metadata.json``'s ``description``.
        overwrite: replace an existing Minari dataset that holds nothing else
            (:func:`_replaceable`); the old one stays whole until the new one is complete.

    Returns:
        the dataset directory (its ``data`` folder holds the files).

    Raises:
        ValueError: rows lacking a key (the final observation included), episodes not
            contiguous or ``STEP`` not 0..T-1, flags that end an episode before its last
            row, a ``("next", OBSERVATION)`` that is not the next row's observation,
            values outside their space, of another shape, NaN or inf, float data for an
            integer space; spaces Minari's JSON cannot hold; ``path`` exists (without
            ``overwrite``), is no replaceable dataset, is or holds the working directory,
            or another process is writing it. Under any error ``path`` keeps what it held.
        imitrl.fs.DiskFullError: the file system filled up (``path`` as it was).
    """
    rows = _rows_to_write(data, action_key)
    obs_space, act_space, env_spec = _spaces(observation_space, action_space, env_id)
    spaces = (obs_space, act_space)
    starts, lengths = _episodes(rows)
    dataset_id = dataset_id if dataset_id is not None else Path(path).expanduser().name
    unwritten = _Unwritten(set())
    what = "a Minari dataset"
    with publishing(path, overwrite=overwrite, replaceable=_replaceable, what=what) as tmp:
        data_dir = tmp / "data"
        data_dir.mkdir()
        out = HDF5Out(data_dir / MAIN_FILE, track_order=True)
        with out as h5:
            for e, (start, length) in enumerate(zip(starts.tolist(), lengths.tolist())):
                part = rows[start : start + length]
                where = f"episode {int(part.get(keys.EPISODE)[0])}"
                _write_episode(h5, e, part, spaces, action_key, where)
                unwritten.note(part, action_key)
                out.check()  # a full disk: stop at the episode that met it
        meta = _metadata(
            data_dir, len(starts), int(lengths.sum()), spaces, env_spec, dataset_id, description
        )
        (data_dir / METADATA_FILE).write_text(json.dumps(meta))
        with open(data_dir / METADATA_FILE, "rb") as f:  # on disk before it is published
            os.fsync(f.fileno())  # (HDF5Out fsynced the HDF5 file)
    if unwritten.names:
        warnings.warn(
            f"save_minari: Minari has no place for {sorted(unwritten.names)}; they are not "
            f"written (load_minari recreates only {keys.ROUND}=0, {keys.EXPERT_EXECUTED}=True "
            "and both actions equal)",
            UserWarning,
            stacklevel=2,
        )
    return Path(path).expanduser()
