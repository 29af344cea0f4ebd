"""HG-DAgger's rows: a round's intervention segments, each an episode of its own.

A human-gated round (Kelly et al. 2019) labels only the frames where the expert took
over (``EXPERT_EXECUTED``: the expert's action was executed). Those frames come in
streaks: the expert intervenes, drives for a while, and hands back. :func:`intervention_segments`
keeps them and makes each streak an episode of its own (``EPISODE`` numbered from
``first_episode`` in order, ``STEP`` from 0), so that everything keyed by episode and step
(chunk labels, observation histories, the buffer's episode checks) reads a segment as
the expert's own short demonstration, which it is. The rows' other entries, the env's
flags included, are kept as recorded.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from imitrl import keys

__all__ = ["intervention_segments"]


def intervention_segments(rows: TensorDictBase, first_episode: int) -> TensorDictBase:
    """The rows (episodes back to back, steps in order) where ``EXPERT_EXECUTED``, each
    streak renumbered as an episode from ``first_episode`` (module docstring)."""
    executed = rows.get(keys.EXPERT_EXECUTED).reshape(-1).bool()
    episode, step = rows.get(keys.EPISODE), rows.get(keys.STEP)
    previous = torch.zeros_like(executed)
    same = torch.zeros_like(executed)
    previous[1:] = executed[:-1]
    same[1:] = (episode[1:] == episode[:-1]) & (step[1:] == step[:-1] + 1)
    starts = executed & ~(previous & same)  # a kept row that does not continue a streak
    segment = torch.cumsum(starts.long(), 0) - 1  # the streak each row belongs to
    kept = rows[executed]
    seg = segment[executed]
    index = torch.arange(seg.shape[0])
    # each segment's first kept row: the kept rows that start one, in order (never a
    # write of many values to one index, whose winner torch does not fix on several
    # threads: a review saw steps from -200000 on 12 of 20 calls)
    first_row = torch.nonzero(starts[executed]).squeeze(1)
    kept.set(keys.EPISODE, int(first_episode) + seg)
    kept.set(keys.STEP, index - first_row[seg])
    return kept
