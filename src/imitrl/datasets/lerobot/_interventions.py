"""What a LeRobot dataset's DAgger columns must hold, checked as its frames are read.

LeRobot's DAgger strategy (``lerobot/rollout/strategies/dagger.py``) records autonomous and
correction frames and tags the corrections ``intervention=True`` (bool, shape ``(1,)``); the
frame's ``action`` is the action sent to the robot, the human's on a correction. imitrl reads
``intervention`` into ``EXPERT_EXECUTED`` and writes it back (``save_lerobot``), beside its
own ``imitrl.round``, ``imitrl.beta`` and ``imitrl.policy_version``. Refused, naming the data
file, the episode and the frame:

* an ``intervention`` value that is not a boolean: other tools declare the column int64 or
  float32, which is read when every value is 0 or 1 (then as booleans), and refused for any
  other value (a 2, a 0.5);
* an intervention frame without its corrected action: a null, NaN or infinite value of a
  feature is refused where the column is read (:func:`feature_values`), and a dataset with
  interventions and no action feature at all is refused here;
* rounds out of order: ``imitrl.round`` must be the same on every frame of an episode, and
  a DAgger round (1, 2, ...) may not come after a later one (:class:`RoundOrder` carries
  the last one across the pieces of a streamed load); demonstrations (round 0) may come
  anywhere, as episodes LeRobot's recorder added to the dataset since do;
  ``imitrl.beta`` and ``imitrl.policy_version`` must be the same on every frame of an
  episode.

Everything is checked before a row reaches a buffer (a streamed load checks every piece
before it adds one), so a dataset refused at its fifth round leaves nothing of it behind.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.compute as pc
import torch

from imitrl import keys
from imitrl.datasets._arrow import column_to_tensor, decode_images
from imitrl.datasets._common import NestedKey, key_name
from imitrl.datasets.lerobot._layout import INTERVENTION
from imitrl.limits import MAX_ROUNDS

__all__ = [
    "RoundOrder",
    "check_dagger_columns",
    "feature_values",
    "own_episodes",
    "own_ids_follow",
]

_PER_EPISODE = {keys.ROUND: "round", keys.BETA: "beta", keys.POLICY_VERSION: "policy version"}


def _first_bad_row(column: pa.ChunkedArray | pa.Array) -> tuple[int, str] | None:
    """The first row of a column holding a null, NaN or infinite value, and which."""
    arr = column.combine_chunks() if isinstance(column, pa.ChunkedArray) else column
    rows = pa.array(range(len(arr)), pa.int64())
    while (
        pa.types.is_list(arr.type)
        or pa.types.is_fixed_size_list(arr.type)
        or (pa.types.is_large_list(arr.type))
    ):
        nulls = arr.is_null().to_numpy(zero_copy_only=False)
        if nulls.any():
            return int(rows[int(nulls.argmax())].as_py()), "null"
        rows = pc.take(rows, pc.list_parent_indices(arr))
        arr = arr.flatten()
    nulls = arr.is_null().to_numpy(zero_copy_only=False)
    if nulls.any():
        return int(rows[int(nulls.argmax())].as_py()), "null"
    if pa.types.is_floating(arr.type):
        finite = pc.is_finite(arr).to_numpy(zero_copy_only=False)
        if not finite.all():
            return int(rows[int((~finite).argmax())].as_py()), "NaN or infinite"
    return None


def feature_values(
    table: pa.Table, name: str, feature: dict, folder: Any, path: Path
) -> torch.Tensor:
    """Feature ``name`` of one data file's ``table`` as a tensor (images decoded); a value
    that cannot be read (a null, NaN or inf, among others) is refused naming the episode and
    the frame that hold it, and an intervention frame's missing action says so."""
    where = f"{path}: feature {name!r}"
    if feature["dtype"] == "image":
        return decode_images(
            table.column(name), shape=tuple(feature["shape"]), folder=folder, where=where
        )
    try:
        return column_to_tensor(
            table.column(name), shape=tuple(feature["shape"]), dtype=feature["dtype"], where=where
        )
    except ValueError as err:
        bad = _first_bad_row(table.column(name))
        if bad is None or "episode_index" not in table.column_names:
            raise
        row, _ = bad
        episode = table.column("episode_index")[row].as_py()
        frame = table.column("frame_index")[row].as_py()
        hint = ""
        acted = "action" in name  # the hint is about the corrected action alone
        if (
            acted
            and INTERVENTION in table.column_names
            and bool(table.column(INTERVENTION)[row].as_py())
        ):
            hint = ": an intervention frame, which must carry the corrected action"
        raise ValueError(f"{err} (episode {episode}, frame {frame}{hint})") from err


class RoundOrder:
    """The round of the last episode checked, carried across the pieces of one load."""

    def __init__(self) -> None:
        self.last: tuple[int, int] | None = None
        """(round, episode index) of the last DAgger round (round >= 1) checked"""


def _where(file_of: Callable[[int], Path], episode: torch.Tensor, frame: torch.Tensor, i: int):
    return f"{file_of(i)}: episode {int(episode[i])}, frame {int(frame[i])}"


def _booleans(
    value: torch.Tensor, episode: torch.Tensor, frame: torch.Tensor, file_of, name: str
) -> torch.Tensor:
    if value.dtype == torch.bool:
        return value
    flat = value.reshape(value.shape[0], -1)
    bad = torch.nonzero(((flat != 0) & (flat != 1)).any(-1)).flatten()
    if len(bad):
        i = int(bad[0])
        raise ValueError(
            f"{_where(file_of, episode, frame, i)}: {name!r} holds {flat[i].tolist()}, not a "
            "boolean (True/False, or 0/1 in an integer or float column)"
        )
    return value != 0


def _episode_heads(episode: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(heads, first)`` of frames in episode order: each episode's first frame, and each
    frame's episode counted from 0."""
    starts = torch.ones_like(episode, dtype=torch.bool)
    starts[1:] = episode[1:] != episode[:-1]
    return torch.nonzero(starts).flatten(), torch.cumsum(starts.long(), 0) - 1


def own_ids(own: torch.Tensor, episode: torch.Tensor) -> torch.Tensor | None:
    """imitrl's episode ids (``own``, one a frame) of frames in episode order (``episode``:
    LeRobot's ``episode_index``), one per LeRobot episode, where each is a whole number
    >= 0 constant over its episode; None where one is not (an edited column: a float id
    cast to an integer would join two episodes, a negative one no buffer accepts)."""
    heads, first = _episode_heads(episode)
    own = own.reshape(-1)
    if own.is_floating_point() and not bool((own == own.floor()).all()):
        return None
    if own.numel() and int(own.min()) < 0:
        return None
    return own[heads].long() if bool((own == own[heads][first]).all()) else None


def _ascending(ids: torch.Tensor) -> bool:
    """Each id above the one before: episodes in the order imitrl wrote them, none twice
    (ids out of order, as a merge of two datasets leaves them, would be refused by a
    buffer read in pieces and accepted whole)."""
    return bool((ids[1:] > ids[:-1]).all())


def own_episodes(
    out: dict, episode: torch.Tensor, file_of: Callable[[int], Path], *, keep: bool | None = None
) -> None:
    """Frames ``[N]`` of a whole dataset in episode order (``episode``: LeRobot's
    ``episode_index``): imitrl's own episode ids (``imitrl.episode``) are kept only where
    they follow LeRobot's episodes one to one, ascending (:func:`own_ids_follow`);
    otherwise (LeRobot's ``aggregate_datasets`` renumbers ``episode_index`` alone, so two
    merged datasets repeat ids) they are dropped, with a warning, and the rows take
    LeRobot's ``episode_index``.

    ``keep``: decided already for the whole dataset (a stream's pieces, by
    :func:`own_ids_follow`, which warned): True keeps the ids, False drops them silently."""
    if keys.EPISODE not in out:
        return
    if keep is None:
        keep = own_ids_follow([(out[keys.EPISODE], episode)], file_of(0))
    if not keep:
        del out[keys.EPISODE]


def own_ids_follow(parts: Iterable[tuple[torch.Tensor, torch.Tensor]], where: Path) -> bool:
    """Whether imitrl's episode ids follow LeRobot's episodes one to one across every part
    ``(own, episode)`` of a dataset read in pieces (each part's frames in episode order):
    whole numbers >= 0, constant over each episode and ascending across the pieces. Warns
    when they do not (:func:`own_episodes` then drops them from every piece alike)."""
    seen: list[torch.Tensor] = []
    for own, episode in parts:
        ids = own_ids(own, episode)
        if ids is None:
            _warn_own_ids(where)
            return False
        seen.append(ids)
    every = torch.cat(seen) if seen else torch.zeros(0, dtype=torch.int64)
    if not _ascending(every):
        _warn_own_ids(where)
        return False
    return True


def _warn_own_ids(where: Path) -> None:
    warnings.warn(
        f"{where}: imitrl's episode ids ({key_name(keys.EPISODE)!r}) do not follow "
        "LeRobot's episodes one to one (a merge renumbers episode_index alone): the rows "
        "take LeRobot's episode_index",
        UserWarning,
        stacklevel=4,
    )


def check_dagger_columns(
    out: dict[NestedKey, torch.Tensor],
    episode: torch.Tensor,
    frame: torch.Tensor,
    file_of: Callable[[int], Path],
    order: RoundOrder,
    intervention_name: str = INTERVENTION,
) -> None:
    """Frames ``[N]`` in episode order (``out``: buffer key -> values; ``episode`` and
    ``frame``: LeRobot's ``episode_index`` and ``frame_index``) against the module
    docstring's rules; ``EXPERT_EXECUTED`` becomes boolean in ``out``."""
    if keys.EXPERT_EXECUTED in out:
        column = out[keys.EXPERT_EXECUTED]
        if column.numel() != column.shape[0]:  # one flag a frame
            raise ValueError(
                f"{file_of(0)}: {intervention_name!r} holds {tuple(column.shape[1:])} values a "
                "frame; an intervention flag is one boolean a frame"
            )
        executed = _booleans(column, episode, frame, file_of, intervention_name)
        out[keys.EXPERT_EXECUTED] = executed
        flags = executed.reshape(executed.shape[0], -1).any(-1)
        if flags.any() and keys.EXPERT_ACTION not in out and keys.ACTION not in out:
            i = int(torch.nonzero(flags)[0, 0])
            raise ValueError(
                f"{_where(file_of, episode, frame, i)}: an intervention frame without its "
                "corrected action (the dataset has no action feature; map one with key_map)"
            )
    heads, first = _episode_heads(episode)
    for key, what in _PER_EPISODE.items():
        if key not in out:
            continue
        value = out[key].reshape(out[key].shape[0])
        head = value[heads][first]
        differs = value != head
        if differs.any():
            i = int(torch.nonzero(differs)[0, 0])
            raise ValueError(
                f"{_where(file_of, episode, frame, i)}: {what} {value[i].item()}, but the "
                f"episode began with {what} {head[i].item()} (one {what} per episode)"
            )
    if keys.ROUND in out:
        _check_order(out[keys.ROUND].reshape(-1), heads, episode, frame, file_of, order)


def _check_order(rounds, heads, episode, frame, file_of, order: RoundOrder) -> None:
    for i in heads.tolist():
        now = (int(rounds[i]), int(episode[i]))
        if not 0 <= now[0] <= MAX_ROUNDS:
            raise ValueError(
                f"{_where(file_of, episode, frame, i)}: round {now[0]}, expected 0 (the "
                f"demonstrations) to {MAX_ROUNDS} (imitrl.limits.MAX_ROUNDS)"
            )
        if now[0] == 0:  # demonstrations: recorded before the rounds, or added since
            continue
        if order.last is not None and now[0] < order.last[0]:
            raise ValueError(
                f"{_where(file_of, episode, frame, i)}: round {now[0]} after round "
                f"{order.last[0]} (episode {order.last[1]}): a dataset's DAgger rounds come "
                "in order"
            )
        order.last = now
