"""DAgger rounds as a LeRobot v3.0 dataset in LeRobot's DAgger schema (:func:`save_dagger_lerobot`).

LeRobot's DAgger strategy records a robot's autonomous and correction frames and tags the
corrections ``intervention=True``. imitrl's rounds carry more: every visited state has the
expert's label. :func:`save_dagger_lerobot` writes them so that LeRobot reads them as its own
DAgger recordings and imitrl reads back every round:

==========================  ===========================================================
``action``                  the expert's label (``EXPERT_ACTION``): what a policy trains on
``intervention``            bool ``(1,)``: the expert's action was executed on this frame
                            (``EXPERT_EXECUTED``; a gate's take-over, beta's coin, or every
                            frame of a demonstration)
``imitrl.executed_action``  the action executed (``ACTION``): on an intervention frame
                            the expert's, as in LeRobot's ``action``; else the learner's
``imitrl.round``            the round that collected the frame (0: the demonstrations)
``imitrl.beta``             the round's probability of executing the expert's action (1 in
                            a round of demonstrations, -1 where a gate decided or the
                            source did not say: ``NO_BETA``)
``imitrl.policy_version``   the fit whose learner acted: ``round - 1``; -1 for round 0
==========================  ===========================================================

Rows that already carry ``BETA`` and ``POLICY_VERSION`` (a run that started from such a
dataset) keep theirs. The rounds must come in order, one per episode (demonstrations,
round 0, anywhere), as :func:`~imitrl.datasets.lerobot.load_lerobot` requires on the way
back.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase

from imitrl import keys
from imitrl.data.buffer import DemonstrationBuffer
from imitrl.data.provenance import NO_BETA
from imitrl.datasets.lerobot._write import save_lerobot

__all__ = ["round_betas", "save_dagger_lerobot"]


def round_betas(rows: TensorDictBase, betas: Mapping[int, float]) -> torch.Tensor:
    """``[N]`` float32 each row's round's beta (``betas``; a round it lacks: 1 where every
    row of the round executed the expert's action, a demonstration, else
    :data:`~imitrl.data.provenance.NO_BETA`)."""
    rounds = rows.get(keys.ROUND).reshape(-1)
    executed = rows.get(keys.EXPERT_EXECUTED).reshape(rows.shape[0], -1).all(-1)
    out = torch.full((rounds.shape[0],), NO_BETA, dtype=torch.float32)
    for r in rounds.unique().tolist():
        at = rounds == r
        if r in betas:
            out[at] = float(betas[r])
        elif bool(executed[at].all()):
            out[at] = 1.0
    return out


def _check_rounds(rows: TensorDictBase) -> None:
    rounds = rows.get(keys.ROUND).reshape(-1)
    episode = rows.get(keys.EPISODE).reshape(-1)
    new = torch.ones_like(episode, dtype=torch.bool)
    new[1:] = episode[1:] != episode[:-1]
    inside = torch.nonzero(~new & (rounds != torch.roll(rounds, 1))).flatten()
    latest = torch.cummax(rounds, 0).values  # the last DAgger round so far
    back = torch.nonzero((rounds[1:] > 0) & (rounds[1:] < latest[:-1])).flatten()
    if len(inside) or len(back):
        i = int(inside[0]) if len(inside) else int(back[0]) + 1
        before = int(rounds[i - 1]) if len(inside) else int(latest[i - 1])
        raise ValueError(
            f"row {i} (episode {int(episode[i])}): round {int(rounds[i])} after round "
            f"{before}: DAgger rounds are written in order, one round per episode "
            "(demonstrations, round 0, anywhere)"
        )


def save_dagger_lerobot(
    data: DemonstrationBuffer | TensorDictBase,
    path: str | Path,
    *,
    fps: int,
    betas: Mapping[int, float] | None = None,
    **kwargs: Any,
) -> Path:
    """Write a DAgger buffer (demonstrations and every relabel round) as a LeRobot v3.0
    dataset in LeRobot's DAgger schema (the module docstring's columns).

    Args:
        data: the buffer (read whole: a disk buffer's rows are read into memory) or its rows.
        path: the dataset directory, as :func:`~imitrl.datasets.lerobot.save_lerobot`.
        fps: frames per second.
        betas: round -> its beta, for rows without ``BETA`` (:func:`round_betas`).
        **kwargs: the other arguments of :func:`~imitrl.datasets.lerobot.save_lerobot`
            (``tasks``, ``overwrite``, ``video``, ...).
    """
    rows = data.data if isinstance(data, DemonstrationBuffer) else data
    if not isinstance(rows, TensorDictBase) or rows.batch_dims != 1 or rows.shape[0] == 0:
        raise ValueError("save_dagger_lerobot needs a non-empty buffer or a TensorDict [N]")
    for k in (keys.ROUND, keys.EPISODE, keys.EXPERT_EXECUTED):
        if k not in rows.keys():
            raise ValueError(f"DAgger rows need {k!r} to be written in LeRobot's DAgger schema")
    rows = rows.to_tensordict()  # a copy: the provenance columns are added to it
    _check_rounds(rows)
    if keys.BETA not in rows.keys():
        rows.set(keys.BETA, round_betas(rows, betas or {}))
    if keys.POLICY_VERSION not in rows.keys():
        rows.set(keys.POLICY_VERSION, (rows.get(keys.ROUND).reshape(-1) - 1).clamp_min(-1))
    return save_lerobot(rows, path, fps=fps, **kwargs)
