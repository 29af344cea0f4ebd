"""What every dataset reader returns, and how loaded rows are fitted to an env's specs.

A reader builds a whole TensorDict of rows in memory and validates it before it is
returned, so a malformed dataset raises before anything reaches a buffer (nothing is
ever half-loaded); ``load_lerobot(..., into=buffer)`` streams instead, and checks every
piece before the first reaches the buffer (:mod:`imitrl.datasets.lerobot._stream`). Rows carry the :class:`~imitrl.data.DemonstrationBuffer`'s required
keys: recorded demonstrations are round 0, executed by the expert (``ACTION`` =
``EXPERT_ACTION``, ``EXPERT_EXECUTED`` True) unless the dataset carries imitrl's own
columns for them.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict
from torchrl.envs import EnvBase

from imitrl import keys
from imitrl.data.validation import MAX_EPISODE_ID
from imitrl.fs.reading import OpenedFolder, ReplacedWhileReading

__all__ = [
    "EnvMismatchError",
    "LoadedDemonstrations",
    "NestedKey",
    "conform_to_env",
    "key_name",
    "open_in",
    "read_in",
]


class EnvMismatchError(ValueError):
    """A dataset that does not fit the env it is loaded for (an observation the env lacks,
    a shape it does not have): most often the wrong env, which the caller can name."""


NestedKey = str | tuple[str, ...]

# numpy dtype name (as LeRobot's info.json spells it) <-> torch dtype
TORCH_DTYPES: dict[str, torch.dtype] = {
    "float64": torch.float64,
    "float32": torch.float32,
    "float16": torch.float16,
    "int64": torch.int64,
    "int32": torch.int32,
    "int16": torch.int16,
    "int8": torch.int8,
    "uint8": torch.uint8,
    "bool": torch.bool,
}
NUMPY_NAMES: dict[torch.dtype, str] = {v: k for k, v in TORCH_DTYPES.items()}
# numpy has unsigned types torch lacks: widen them to the next signed type
WIDEN = {"uint16": "int32", "uint32": "int64"}


def exact_cast(values: np.ndarray, dtype: str, *, where: str) -> np.ndarray:
    """``values`` in the declared numpy ``dtype`` (LeRobot's ``info.json``, a Minari space)
    when no value changes; ValueError naming ``where`` otherwise.

    Kept: every cast that gives each value back (int64 -> int8 of small values, 0/1 ->
    bool, integers -> floating when exactly representable), and float64 -> float32,
    which may round but not overflow (LeRobot itself casts a float64 column to a declared
    float32; float32 data stored as float64 comes back exactly). Refused: floating ->
    integer or bool (truncation: 0.7 would load as 0, 0.3 as True), any other float
    narrowing that changes a value (float32 data declared float16), integers that wrap.
    """
    target = np.dtype(dtype)
    if values.dtype == target:
        return values
    if values.dtype.kind not in "fiub":
        raise ValueError(f"{where}: holds {values.dtype} values, expected numbers or booleans")
    if values.dtype.kind == "f" and target.kind != "f":
        raise ValueError(
            f"{where}: stores {values.dtype} values but declares dtype {dtype!r} (refusing to "
            "truncate floating data to integers or booleans)"
        )
    with np.errstate(all="ignore"):
        cast = values.astype(target)
        if values.dtype == np.float64 and target == np.float32:
            lost = np.isfinite(values) & ~np.isfinite(cast)
        else:
            back = cast.astype(values.dtype)
            lost = back != values
            if values.dtype.kind in "iu" and target.kind in "iu":  # a wrap that comes back
                lost |= (values < 0) != (cast < 0)  # (uint64 2**64 - 1 <-> int64 -1): its sign
            if values.dtype.kind == "f":
                lost &= ~(np.isnan(values) & np.isnan(back))
    if lost.any():
        bad = values.ravel()[np.flatnonzero(lost.ravel())[0]].item()
        raise ValueError(f"{where}: value {bad!r} does not fit the declared dtype {dtype!r}")
    return cast


def check_finite(array: np.ndarray, *, where: str) -> None:
    """ValueError naming ``where`` and the first frame if floating ``[N, ...]`` values hold
    NaN or inf."""
    if array.dtype.kind != "f":
        return
    flat = array.reshape(len(array), -1) if array.ndim else array.reshape(1, 1)
    bad = ~np.isfinite(flat)
    if bad.any():
        frame = int(np.flatnonzero(bad.any(axis=1))[0])
        value = flat[frame][bad[frame]][0]
        raise ValueError(
            f"{where}: frame {frame} holds {float(value)!r} (NaN and inf are refused: "
            "they would poison training)"
        )


def open_in(folder: OpenedFolder, relative: str, *, named_by: str) -> int:
    """``folder.open(relative)`` (a descriptor of a regular file inside the folder), every
    failure a ValueError: an ``OSError`` the open lets through when the file changes in
    the middle of it (a link swapped back for a file between its ``lstat`` and its
    ``readlink``) is reported as the change it is (:func:`_changed`)."""
    try:
        return folder.open(relative, named_by=named_by)
    except OSError as err:
        raise _changed(folder, relative, named_by, err) from None


def read_in(folder: OpenedFolder, relative: str, *, named_by: str, limit: int) -> bytes:
    """``folder.read_bytes(relative, limit=limit)``, every failure a ValueError (as
    :func:`open_in`)."""
    try:
        return folder.read_bytes(relative, named_by=named_by, limit=limit)
    except OSError as err:
        raise _changed(folder, relative, named_by, err) from None


def _changed(folder: OpenedFolder, relative: str, named_by: str, err: OSError) -> ValueError:
    if folder.replaced():
        return ReplacedWhileReading(f"{folder.root}: replaced while reading it ({relative})")
    return ValueError(
        f"{folder.root / relative}: changed while it was opened ({err.strerror}; {named_by} "
        "names it)"
    )


def key_name(key: NestedKey) -> str:
    """``("next", "reward") -> "next.reward"`` (how keys are named in messages and files)."""
    return key if isinstance(key, str) else ".".join(key)


def as_key(key: NestedKey | list) -> NestedKey:
    """A key read back from JSON (lists) as a tensordict key."""
    if isinstance(key, str):
        return key
    key = tuple(key)
    return key[0] if len(key) == 1 else key


@dataclass
class LoadedDemonstrations:
    """Demonstrations read from a dataset on disk.

    Extend a buffer with them: ``buffer.extend(loaded.rows)``.
    """

    rows: TensorDict
    """``[N]`` rows: ``OBSERVATION`` and/or ``PIXELS`` (a camera, uint8 ``[N, H, W, 3]``;
    several as ``("pixels", name)``), ``EXPERT_ACTION, ACTION, EXPERT_EXECUTED, EPISODE,
    ROUND, STEP`` and whatever else the dataset carried (``("next", "reward")``, ...),
    episodes back to back in the dataset's episode order"""
    source: Path
    """the directory read"""
    format: str
    """e.g. ``"lerobot v3.0"``, ``"lerobot v2.1"``, ``"minari hdf5"``"""
    num_episodes: int
    """episodes loaded"""
    tasks: list[str] = field(default_factory=list)
    """task strings; a ``"task_index"`` row entry indexes this list"""
    fps: float | None = None
    """recording rate (LeRobot), None where the format has none"""
    loaded: dict[str, str] = field(default_factory=dict)
    """dataset feature -> buffer key it was loaded into"""
    skipped: dict[str, str] = field(default_factory=dict)
    """dataset feature -> why it was not loaded (never dropped silently: a warning lists them)"""
    notes: list[str] = field(default_factory=list)
    """conversions applied (dtype casts, reshapes to the env's specs, derived keys)"""
    metadata: dict[str, Any] = field(default_factory=dict, repr=False)
    """the dataset's own metadata (``info.json`` / Minari ``metadata.json``)"""


def warn_skipped(source: Path, skipped: dict[str, str], quiet: frozenset[str]) -> None:
    """One warning naming every feature that was not loaded (except derivable bookkeeping)."""
    loud = {k: v for k, v in skipped.items() if k not in quiet}
    if loud:
        lines = "; ".join(f"{k!r}: {v}" for k, v in loud.items())
        warnings.warn(f"{source}: features not loaded: {lines}", UserWarning, stacklevel=3)


def required_rows(
    columns: dict[NestedKey, torch.Tensor],
    *,
    episode: torch.Tensor,
    step: torch.Tensor,
    first_episode: int = 0,
) -> TensorDict:
    """Complete the buffer's required keys: a label-only dataset was executed by the expert.
    ``episode + first_episode`` are the rows' ids, added as int64 and refused (ValueError)
    past the largest id a buffer holds, rather than wrapped around."""
    n = episode.shape[0]
    ids = episode.to(torch.int64)
    if n and int(ids.max()) + int(first_episode) >= MAX_EPISODE_ID:
        raise ValueError(
            f"episode id {int(ids.max())} + first_episode {int(first_episode)} passes the "
            f"largest episode id a buffer holds ({MAX_EPISODE_ID - 1}): number episodes from 0"
        )
    if keys.EXPERT_ACTION not in columns and keys.ACTION in columns:
        columns[keys.EXPERT_ACTION] = columns[keys.ACTION]
    if keys.ACTION not in columns and keys.EXPERT_ACTION in columns:
        columns[keys.ACTION] = columns[keys.EXPERT_ACTION].clone()
    columns.setdefault(keys.EXPERT_EXECUTED, torch.ones(n, dtype=torch.bool))
    columns.setdefault(keys.ROUND, torch.zeros(n, dtype=torch.int64))
    columns[keys.EPISODE] = ids + int(first_episode)
    columns[keys.STEP] = step.to(torch.int64)
    td = TensorDict({}, batch_size=[n])
    for key, value in columns.items():
        if value.shape[0] != n:
            raise ValueError(f"{key_name(key)!r} has {value.shape[0]} rows, expected {n}")
        td.set(key, value)
    return td


def _survives(value: torch.Tensor, cast: torch.Tensor) -> torch.Tensor:
    """Mask of the entries of ``value`` that ``cast`` (``value`` in another dtype) holds exactly;
    for float -> float only overflow counts (rounding float64 to float32 is accepted), except
    into a half-precision float, which must be exact (as :func:`exact_cast`)."""
    if value.dtype.is_floating_point:
        if cast.dtype.itemsize < min(4, value.dtype.itemsize):  # float16 / bfloat16
            back = cast.to(value.dtype)
            return (back == value) | (torch.isnan(value) & torch.isnan(back))
        return ~torch.isfinite(value) | torch.isfinite(cast)
    if value.dtype == torch.bool:
        return torch.ones_like(value)
    if cast.dtype.is_floating_point:
        # a float outside the integer range has no defined cast back: compare only inside it
        info = torch.iinfo(value.dtype)
        wide = cast.double()
        inside = torch.isfinite(wide) & (wide >= info.min) & (wide < info.max + 1.0)
        back = torch.where(inside, cast, torch.zeros_like(cast)).to(value.dtype)
        return inside & (back == value)
    return cast.to(value.dtype) == value


def _cast(
    value: torch.Tensor, dtype: torch.dtype, what: str, where: str, notes: list[str]
) -> torch.Tensor:
    """Cast to the env's dtype when no value changes: within a kind (float64 -> float32 may
    round but not overflow; int64 -> int32 must not wrap) or integer/bool -> floating when
    every value is exactly representable (Taxi's int64 rewards -> float32). Floating ->
    integer/bool and integer <-> bool are refused."""
    src_float, dst_float = value.dtype.is_floating_point, dtype.is_floating_point
    src_bool, dst_bool = value.dtype == torch.bool, dtype == torch.bool
    if (src_float and not dst_float) or (not src_float and not dst_float and src_bool != dst_bool):
        raise ValueError(
            f"{where}: {what} has dtype {value.dtype}, the env expects {dtype} (refusing to "
            "convert floating data to integers or booleans, or between integers and booleans)"
        )
    cast = value.to(dtype)
    kept = _survives(value, cast)
    if not bool(kept.all()):
        bad = value.flatten()[torch.nonzero(~kept.flatten())[0, 0]].item()
        raise ValueError(
            f"{where}: {what} holds {bad!r}, which the env's dtype {dtype} cannot hold "
            f"exactly (the dataset stores {value.dtype}; refusing a cast that changes values)"
        )
    exact = "" if src_float == dst_float else " (every value exactly representable)"
    notes.append(f"{what}: cast {value.dtype} -> {dtype} to match the env{exact}")
    return cast


def _fit(
    value: torch.Tensor,
    shape: torch.Size,
    dtype: torch.dtype,
    what: str,
    where: str,
    notes: list[str],
) -> torch.Tensor:
    """Reshape ``[N, *s]`` to ``[N, *shape]`` when only size-1 dims differ; cast where no
    value changes (:func:`_cast`)."""
    have = tuple(value.shape[1:])
    want = tuple(shape)
    if have != want:
        if [d for d in have if d != 1] == [d for d in want if d != 1]:
            value = value.reshape(value.shape[0], *want)
            notes.append(f"{what}: reshaped {list(have)} -> {list(want)} to match the env")
        else:
            raise EnvMismatchError(
                f"{where}: {what} has shape {list(have)} per frame, the env expects {list(want)}"
            )
    if value.dtype != dtype:
        value = _cast(value, dtype, what, where, notes)
    return value


def _derive_endings(rows: TensorDict, env: EnvBase, nxt_keys: list[str], notes: list[str]) -> None:
    """``("next", terminated|truncated)`` the env has and the dataset lacks, from ``done``.

    Recorded flags are kept as they are. With one of the two recorded, the other is
    ``done`` and not it. With only ``done``: an episode that ends (``done``) at exactly
    the env's time limit (:func:`~imitrl.envs.episode_limit`) ended by it, as gymnasium
    reports it when replayed: ``truncated=True, terminated=False``; every other ``done``
    is ``terminated``.
    """
    nxt = rows.keys(include_nested=True)
    if (keys.NEXT, keys.DONE) not in nxt:
        return
    done = rows.get((keys.NEXT, keys.DONE))
    flag = done.reshape(done.shape[0]).bool()
    term, trunc = (keys.NEXT, keys.TERMINATED), (keys.NEXT, keys.TRUNCATED)
    want = [
        k for k in (keys.TERMINATED, keys.TRUNCATED) if k in nxt_keys and (keys.NEXT, k) not in nxt
    ]
    if not want:
        return
    if term in nxt:
        truncated = flag & ~rows.get(term).reshape(flag.shape).bool()
        terminated = None
        notes.append("next.truncated: not in the dataset, taken as next.done & ~next.terminated")
    elif trunc in nxt:
        terminated = flag & ~rows.get(trunc).reshape(flag.shape).bool()
        truncated = None
        notes.append("next.terminated: not in the dataset, taken as next.done & ~next.truncated")
    else:
        from imitrl.envs.limits import episode_limit  # the envs package needs no datasets

        truncated = torch.zeros_like(flag)
        limit = episode_limit(env)
        if limit is not None:
            episode, step = rows.get(keys.EPISODE), rows.get(keys.STEP)
            last = torch.ones_like(flag)
            last[:-1] = episode[1:] != episode[:-1]
            truncated = flag & last & (step == limit - 1)
        terminated = flag & ~truncated
        by_limit = (
            f"{int(truncated.sum())} episode(s) end at the env's time limit ({limit} steps) "
            "and are truncated, every other done is terminated"
            if limit is not None
            else "the env has no time limit: every done is terminated"
        )
        notes.append(
            f"next.terminated/next.truncated: not in the dataset, from next.done: {by_limit}"
        )
    for k, value in ((keys.TERMINATED, terminated), (keys.TRUNCATED, truncated)):
        if k in want and value is not None:
            rows.set((keys.NEXT, k), value.reshape(done.shape).to(done.dtype))


def conform_to_env(
    rows: TensorDict, env: EnvBase, *, where: str, notes: list[str], names: dict[str, str]
) -> TensorDict:
    """Check (and where harmless, fit) loaded rows against ``env``'s specs.

    Observation (``OBSERVATION``, and the camera ``PIXELS`` where the rows have it; a
    recorded next observation, ``("next", OBSERVATION)``, as the observation) and
    action shapes must match the env's per-frame shapes (size-1 dims
    may be added or removed: LeRobot stores a per-frame scalar as shape ``[1]``);
    dtypes are cast within a kind (float64 -> float32, int32 -> int64; ints must not
    wrap, floats not overflow) and from integer or bool to floating when every value
    is exactly representable (int64 rewards -> float32); floating -> integer and
    integer <-> bool are refused, as is any cast that would change a value. Reward and
    done flags take the env's shapes and dtypes; ``terminated``/``truncated`` the dataset
    does not record are derived (:func:`_derive_endings`, noted in ``notes``), so that
    rows from the env and from the dataset can share one buffer.

    Args:
        names: buffer key name -> dataset feature, for error messages.
    """
    batch = len(env.batch_size)

    def per_frame(spec) -> tuple[torch.Size, torch.dtype]:
        return spec.shape[batch:], spec.dtype

    checks: list[tuple[NestedKey, Any]] = []
    key: NestedKey  # a name here, a nested key below
    for key in (keys.OBSERVATION, keys.PIXELS):  # the state, the camera: either or both
        spec = env.observation_spec.get(key, None)
        if spec is not None:
            checks.append((key, spec))
        elif key in rows.keys():
            raise EnvMismatchError(
                f"{where}: the dataset has {key!r} (from feature {names.get(key, '?')!r}), "
                f"the env has no {key!r} observation (leave the feature out with key_map)"
            )
    if not checks:
        raise ValueError(
            f"the env has no {keys.OBSERVATION!r} (or {keys.PIXELS!r}) observation to check "
            "the dataset against"
        )
    present = rows.keys(include_nested=True)  # a recorded next observation: as its own
    for k, spec in list(checks):
        if isinstance(k, str) and (keys.NEXT, k) in present:
            checks.append(((keys.NEXT, k), spec))
    action_spec = env.full_action_spec[keys.ACTION]
    checks += [(keys.EXPERT_ACTION, action_spec), (keys.ACTION, action_spec)]
    for key, spec in checks:
        if key not in rows.keys(include_nested=True):
            continue
        value = rows.get(key)
        if not isinstance(value, torch.Tensor):
            raise ValueError(
                f"{where}: {key_name(key)!r} is a nested group, the env expects a tensor"
            )
        shape, dtype = per_frame(spec)
        what = f"{key_name(key)!r} (from feature {names.get(key_name(key), '?')!r})"
        rows.set(key, _fit(value, shape, dtype, what, where, notes))
    reward_spec = env.full_reward_spec[keys.REWARD]
    done_specs = env.full_done_spec
    nxt_keys = [keys.REWARD, *[k for k in done_specs.keys() if isinstance(k, str)]]
    _derive_endings(rows, env, nxt_keys, notes)
    for k in nxt_keys:
        key = (keys.NEXT, k)
        if key not in rows.keys(include_nested=True):
            continue
        spec = reward_spec if k == keys.REWARD else done_specs[k]
        shape, dtype = per_frame(spec)
        what = f"{key_name(key)!r} (from feature {names.get(key_name(key), '?')!r})"
        rows.set(key, _fit(rows.get(key), shape, dtype, what, where, notes))
    return rows
