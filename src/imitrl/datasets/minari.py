"""Minari datasets read straight from their HDF5 file, offline, without the ``minari`` package.

Layout (``minari/dataset/_storages/hdf5_storage.py``, Minari 0.5)::

    <dataset>/data/metadata.json    dataset_id, total_episodes, total_steps, data_format,
                                    observation_space / action_space (Minari's JSON), env_spec,
                                    jpeg_encoding, minari_version, ...
    <dataset>/data/main_data.hdf5   one group per episode, "episode_<id>", attrs id, seed,
                                    total_steps; datasets observations [T+1, ...] (a group per
                                    Dict key, "_index_<i>" per Tuple entry), actions [T, ...],
                                    rewards [T], terminations [T], truncations [T], infos/...

(Older Minari kept the metadata in the HDF5 file's root attributes; that is read too.)
Row ``t`` of an episode is ``(observations[t], actions[t])`` with ``("next", reward)``
``= rewards[t]``, ``terminated = terminations[t]``, ``truncated = truncations[t]``,
``done = terminated | truncated``; ``observations[T]`` (the final observation) goes to
``("next", OBSERVATION)`` only with ``next_observation=True``. Why not TorchRL's
``MinariExperienceReplay``: in torchrl 0.14.1 it returns all-zero data for a local
dataset (see TORCHRL_NOTES.md).
"""

from __future__ import annotations

import io
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict
from torchrl.envs import EnvBase

from imitrl import keys
from imitrl.datasets._common import (
    LoadedDemonstrations,
    NestedKey,
    conform_to_env,
    required_rows,
    warn_skipped,
)

__all__ = ["load_minari", "resolve_minari_root"]

MAIN_FILE = "main_data.hdf5"
METADATA_FILE = "metadata.json"


def resolve_minari_root(path_or_id: str | Path) -> Path:
    """The ``data`` directory of a Minari dataset: a path (the dataset or its ``data``
    folder), or a dataset id under ``$MINARI_DATASETS_PATH`` (default ``~/.minari/datasets``).

    Raises:
        ValueError: nothing holding ``main_data.hdf5`` found (the message lists where it looked).
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
        f"no Minari dataset at {path_or_id!r} (looked for {MAIN_FILE} in "
        f"{[str(c) for c in candidates]}); this loader never downloads"
    )


def _metadata(data_dir: Path, h5file) -> dict[str, Any]:
    """``metadata.json`` (read before the HDF5 file: it names the storage format), else the
    HDF5 root attributes of Minari < 0.5 (``h5file`` is None when the file is not open yet)."""
    meta_path = data_dir / METADATA_FILE
    if meta_path.is_file():
        try:
            meta = json.loads(meta_path.read_text())
        except json.JSONDecodeError as err:
            raise ValueError(f"{meta_path} is not valid JSON: {err}") from err
    else:  # Minari < 0.5 kept the metadata as root attributes of the HDF5 file
        meta = {k: (v.item() if hasattr(v, "item") else v) for k, v in h5file.attrs.items()}
        meta = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in meta.items()}
        if not meta:
            raise ValueError(f"{meta_path} not found and {data_dir / MAIN_FILE} has no metadata")
    fmt = meta.get("data_format", "hdf5")
    if fmt != "hdf5":
        raise ValueError(f"{meta_path}: data_format {fmt!r} is not supported (only 'hdf5')")
    for field in ("observation_space", "action_space"):
        if field not in meta:
            raise ValueError(
                f"{meta_path}: no {field!r}; datasets that only record an env_spec are not "
                "supported (the env would have to be built to learn its spaces)"
            )
    return meta


def _space(text: str | dict, where: str) -> dict:
    try:
        space = json.loads(text) if isinstance(text, str) else text
    except json.JSONDecodeError as err:
        raise ValueError(f"{where}: the serialized space is not valid JSON: {err}") from err
    _check_space(space, where)
    return space


def _check_space(space: Any, where: str) -> None:
    """What :func:`_decode` reads of a space is there (a Box's shape, a Dict's subspaces)."""
    if not isinstance(space, dict) or "type" not in space:
        raise ValueError(f"{where}: not a Minari space description: {space!r}")
    kind = space["type"]
    if kind == "Box":
        shape = space.get("shape")
        if not isinstance(shape, list) or not all(isinstance(d, int) and d >= 0 for d in shape):
            raise ValueError(f"{where}: a Box space needs a 'shape' list of sizes, got {space!r}")
    elif kind == "Dict":
        if not isinstance(space.get("subspaces"), dict):
            raise ValueError(f"{where}: a Dict space needs a 'subspaces' mapping, got {space!r}")
        for name, sub in space["subspaces"].items():
            _check_space(sub, f"{where}[{name!r}]")
    elif kind == "Tuple":
        if not isinstance(space.get("subspaces"), list):
            raise ValueError(f"{where}: a Tuple space needs a 'subspaces' list, got {space!r}")
        for i, sub in enumerate(space["subspaces"]):
            _check_space(sub, f"{where}[{i}]")


def _is_image(space: dict) -> bool:
    # minari.dataset.minari_storage.is_image_space
    return (
        space["type"] == "Box"
        and space.get("dtype") == "uint8"
        and len(space["shape"]) in (2, 3)
        and space["shape"][0] >= 32
        and space["shape"][1] >= 32
        and np.all(np.asarray(space.get("low")) == 0)
        and np.all(np.asarray(space.get("high")) == 255)
    )


def _decode(node, space: dict, path: str, jpeg: bool, skipped: dict[str, str], where: str) -> Any:
    """HDF5 node + Minari space -> np.ndarray or nested dict (None for what cannot be a tensor)."""
    import h5py

    kind = space["type"]
    if kind in ("Dict", "Tuple"):
        if not isinstance(node, h5py.Group):
            raise ValueError(f"{where}: {path} should be a group for a {kind} space")
        subs = space["subspaces"]
        items = subs.items() if kind == "Dict" else ((f"_index_{i}", s) for i, s in enumerate(subs))
        out = {}
        for name, sub in items:
            if name not in node:
                raise ValueError(f"{where}: {path}/{name} is missing")
            value = _decode(node[name], sub, f"{path}/{name}", jpeg, skipped, where)
            if value is not None:
                out[name] = value
        return out
    if not isinstance(node, h5py.Dataset):
        raise ValueError(f"{where}: {path} should be a dataset for a {kind} space")
    if kind == "Text":
        skipped[path] = "Text space: strings cannot go into a tensor"
        return None
    if jpeg and _is_image(space):
        from PIL import Image

        frames = [np.asarray(Image.open(io.BytesIO(bytes(b)))) for b in node[()]]
        return np.stack(frames).astype(np.uint8).reshape(len(frames), *space["shape"])
    values = node[()]
    if kind == "Box":
        want = tuple(space["shape"])
        if tuple(values.shape[1:]) != want:
            raise ValueError(
                f"{where}: {path} has shape {list(values.shape[1:])} per step, the space "
                f"declares {list(want)}"
            )
        return values.astype(space.get("dtype", values.dtype), copy=False)
    if kind == "Discrete":
        if values.ndim != 1:
            raise ValueError(f"{where}: {path} should be one integer per step, got {values.shape}")
        return values.astype(np.int64, copy=False)
    if kind in ("MultiDiscrete", "MultiBinary"):
        return values
    raise ValueError(f"{where}: {path}: space type {kind!r} is not supported")


def _tensors(value: Any, steps: slice) -> Any:
    if isinstance(value, dict):
        return {k: _tensors(v, steps) for k, v in value.items()}
    return torch.from_numpy(np.ascontiguousarray(value[steps]))


def _length(value: Any) -> int:
    if isinstance(value, dict):
        lens = {_length(v) for v in value.values()}
        if len(lens) != 1:
            raise ValueError(f"entries of unequal length {sorted(lens)}")
        return lens.pop()
    return len(value)


def _cat(parts: list[Any], n: int) -> Any:
    if isinstance(parts[0], dict):
        return TensorDict({k: _cat([p[k] for p in parts], n) for k in parts[0]}, batch_size=[n])
    return torch.cat(parts)


@dataclass(frozen=True)
class _Episode:
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


def _open_hdf5(h5_path: Path):
    """The Minari HDF5 file, open for reading; ValueError when absent or unreadable."""
    import h5py

    if not h5_path.is_file():
        raise ValueError(f"{h5_path} not found")
    try:
        return h5py.File(h5_path, "r")
    except OSError as err:
        raise ValueError(f"{h5_path}: not a readable HDF5 file ({err})") from err


def _episode_groups(h5, meta: dict[str, Any], where: str) -> list[str]:
    """The ``episode_<id>`` groups of the HDF5 file, by id; as many as the metadata says."""
    names = [n for n in h5.keys() if n.startswith("episode_")]
    try:
        order = sorted(names, key=lambda n: int(n.removeprefix("episode_")))
    except ValueError as err:
        raise ValueError(f"{where}: unexpected group names {names}") from err
    if not order:
        raise ValueError(f"{where}: no episode groups")
    total = meta.get("total_episodes")
    if total is not None and int(total) != len(order):
        raise ValueError(
            f"{where}: metadata declares {total} episodes, the file holds {len(order)}"
        )
    return order


def _flags(group, here: str, obs: Any, act: Any, n: int) -> tuple[np.ndarray, np.ndarray]:
    """An episode's ``[T]`` terminations and truncations, once every array is checked to
    hold ``T`` steps (``T + 1`` observations) with ``T = n``, the number of rewards."""
    try:
        n_obs, n_act = _length(obs), _length(act)
    except ValueError as err:
        raise ValueError(f"{here}: observations have {err}") from err
    terminations = np.asarray(group["terminations"][()], dtype=bool)
    truncations = np.asarray(group["truncations"][()], dtype=bool)
    if n_obs != n + 1 or n_act != n or len(terminations) != n or len(truncations) != n:
        raise ValueError(
            f"{here}: {n_obs} observations, {n_act} actions, {n} rewards, "
            f"{len(terminations)} terminations, {len(truncations)} truncations; expected "
            "T + 1 observations and T of everything else"
        )
    declared = group.attrs.get("total_steps")
    if declared is not None and int(declared) != n:
        raise ValueError(f"{here}: attrs total_steps={int(declared)} but {n} rewards")
    return terminations, truncations


def _read_episode(
    group,
    name: str,
    spaces: tuple[dict, dict],
    jpeg: bool,
    skipped: dict[str, str],
    where: str,
    first_episode: int,
    next_observation: bool,
) -> _Episode:
    """One ``episode_<id>`` group, checked (per-step infos are listed in ``skipped``)."""
    here = f"{where}: {name}"
    for field in ("observations", "actions", "rewards", "terminations", "truncations"):
        if field not in group:
            raise ValueError(f"{here} has no {field!r}")
    rewards = np.asarray(group["rewards"][()])
    n = len(rewards)
    obs_space, act_space = spaces
    obs = _decode(group["observations"], obs_space, f"{name}/observations", jpeg, skipped, where)
    act = _decode(group["actions"], act_space, f"{name}/actions", jpeg, skipped, where)
    if obs is None or act is None:
        raise ValueError(f"{here}: observations and actions must be numeric")
    terminations, truncations = _flags(group, here, obs, act, n)
    if "infos" in group:
        for leaf in _leaves(group["infos"], "infos"):
            skipped[leaf] = "per-step infos are not loaded"
    episode_id = int(group.attrs.get("id", int(name.removeprefix("episode_"))))
    return _Episode(
        observation=_tensors(obs, slice(0, n)),
        next_observation=_tensors(obs, slice(1, n + 1)) if next_observation else None,
        action=_tensors(act, slice(0, n)),
        reward=torch.from_numpy(rewards.reshape(n, 1)),
        terminated=torch.from_numpy(terminations.reshape(n, 1)),
        truncated=torch.from_numpy(truncations.reshape(n, 1)),
        episode=torch.full((n,), episode_id + int(first_episode), dtype=torch.int64),
        step=torch.arange(n, dtype=torch.int64),
    )


def _read_episodes(
    h5,
    meta: dict[str, Any],
    data_dir: Path,
    skipped: dict[str, str],
    first_episode: int,
    next_observation: bool,
) -> list[_Episode]:
    """Every episode of the open HDF5 file, in id order, checked against the metadata."""
    where = str(data_dir / MAIN_FILE)
    obs_space = _space(meta["observation_space"], f"{data_dir / METADATA_FILE}: observation_space")
    act_space = _space(meta["action_space"], f"{data_dir / METADATA_FILE}: action_space")
    jpeg = bool(meta.get("jpeg_encoding", False))
    spaces = (obs_space, act_space)
    episodes = [
        _read_episode(h5[n], n, spaces, jpeg, skipped, where, first_episode, next_observation)
        for n in _episode_groups(h5, meta, where)
    ]
    frames = sum(len(ep.step) for ep in episodes)
    if meta.get("total_steps") is not None and int(meta["total_steps"]) != frames:
        raise ValueError(
            f"{where}: metadata declares {meta['total_steps']} steps, the episodes hold {frames}"
        )
    return episodes


def _rows(episodes: list[_Episode], next_observation: bool, where: str) -> TensorDict:
    """The ``[N]`` rows of every episode, back to back, with the buffer's required keys."""
    frames = sum(len(ep.step) for ep in episodes)
    if frames == 0:
        raise ValueError(f"{where}: the dataset holds no steps")
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
    """Read a local Minari dataset (``main_data.hdf5`` + metadata) into demonstration rows.

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
        Dict/Tuple spaces; Tuple entries are named ``_index_<i>`` as in the file),
        ``EXPERT_ACTION`` = ``ACTION``, ``("next", reward|done|terminated|truncated)`` as
        ``[N, 1]`` (TorchRL's layout), round 0, ``EXPERT_EXECUTED`` True. Per-step
        ``infos`` are not loaded (listed in ``skipped`` with a warning).

    Raises:
        ValueError: no ``main_data.hdf5``; unreadable file; metadata missing a space;
            an episode whose arrays have inconsistent lengths or shapes; episode counts or
            step totals that contradict the metadata; shapes that contradict ``env``.
    """
    data_dir = resolve_minari_root(path_or_id)
    meta = _metadata(data_dir, None) if (data_dir / METADATA_FILE).is_file() else None
    skipped: dict[str, str] = {}
    with _open_hdf5(data_dir / MAIN_FILE) as h5:
        if meta is None:
            meta = _metadata(data_dir, h5)
        episodes = _read_episodes(h5, meta, data_dir, skipped, first_episode, next_observation)
    where = str(data_dir / MAIN_FILE)
    rows = _rows(episodes, next_observation, where)
    notes: list[str] = []
    if env is not None:
        rows = conform_to_env(rows, env, where=where, notes=notes, names=dict(_SOURCES))
    # one entry per leaf, not per episode
    skipped = {k.split("/", 1)[1] if k.startswith("episode_") else k: v for k, v in skipped.items()}
    warn_skipped(data_dir, skipped, quiet=frozenset())
    return LoadedDemonstrations(
        rows=rows,
        source=data_dir,
        format=f"minari hdf5 (minari {meta.get('minari_version', '?')})",
        num_episodes=len(episodes),
        loaded=dict(_LOADED),
        skipped=skipped,
        notes=notes,
        metadata=meta,
    )


def _leaves(node, path: str) -> list[str]:
    """Paths of the datasets under ``node`` (itself, when it is one: infos stored whole)."""
    import h5py

    if not isinstance(node, h5py.Group):
        return [path]
    return [leaf for name, sub in node.items() for leaf in _leaves(sub, f"{path}/{name}")]
