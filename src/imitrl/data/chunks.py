"""Action-chunk labels from buffer rows: the expert's next H actions within the episode.

A chunked learner predicts ``H`` actions at once (ACT, Zhao et al. 2023; Diffusion
Policy, Chi et al. 2023). Its label at row ``i`` (episode ``e``, step ``t``) is

    chunk[i, h] = label of the row (e, t + h),   h = 0 .. H-1,

``pad[i, h] = True`` where step ``t + h`` is past the episode's last row, or past the
first row from ``t`` on whose executed action was not the expert's (below); there the
chunk repeats its last valid label, as TorchRL's ``ActionChunkTransform`` pads
(``padding="same"``), and a loss that takes the mask leaves those entries out.

Why not ``ActionChunkTransform`` itself: it windows a time-structured ``[B, T, m]``
tensor (one trajectory window per row, or cut at ``("next", "done")``), while a
demonstration buffer holds flat rows of many episodes, in any order, identified by
``EPISODE`` and ``STEP``. :func:`chunk_labels` is the same windowing keyed by those
two columns; ``tests/data/test_chunks.py`` checks that both give the same digits on one
episode.

DAgger. A relabel round stores, at every state the learner visited, the expert's
label at that state (``EXPERT_ACTION``), whichever action was executed. The label of
the row at ``t + h`` is the expert's plan for ``t + h`` only if the expert's actions
were executed at ``t .. t + h - 1``: otherwise the state at ``t + h`` is one the
*behaviour policy* reached, and its label answers a different question (what the
expert would do from there, not what it would have done next). With an expert whose
choice is hidden (the two-way task's intent) such a chunk can even mix its modes: up at
``t`` by the episode's intent, down at ``t + 2`` because the learner went down
meanwhile. So a chunk extends over the rows that follow only while the executed action
was the expert's (``EXPERT_EXECUTED``, when the rows have it): a relabelled row of a
learner-driven round (beta = 0) keeps entry 0, the expert's label at its own state,
and pads the rest (its last valid label repeated, masked). Demonstrations, where the
expert drove, keep whole chunks.

Chunk-aware DAgger. Rows that carry the expert's own plan from their state
(``EXPERT_PLAN``, ``EXPERT_PLAN_PAD``: :class:`~imitrl.algorithms.expert_plan.ExpertPlanner`
records it during a relabel round, by letting the expert drive a snapshot of the simulator
and undoing it) take their chunks from it: whole chunks at every visited state, each
answering "what would the expert have done next".
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase

from imitrl import keys

__all__ = [
    "ACTION_CHUNK",
    "CHUNK_PAD",
    "EXPERT_CHUNK",
    "IS_INIT",
    "add_chunk_labels",
    "chunk_labels",
    "episode_order",
]

EXPERT_CHUNK = "expert_action_chunk"
"""``[N, H, *action]`` the expert's labels at steps ``t .. t+H-1`` of the row's episode"""
CHUNK_PAD = "expert_action_is_pad"
"""``[N, H]`` bool: the chunk entry lies past the episode's end (a repeated last label)"""
ACTION_CHUNK = "action_chunk"
"""``[N, H, *action]`` the actions a chunked learner predicts (written by the learner)"""
IS_INIT = "is_init"
"""TorchRL's ``InitTracker`` key: the lane was just reset (a chunked policy replans)"""


def episode_order(episode: torch.Tensor, step: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``order [N]``: the rows sorted by (episode, step); ``same [N-1]``: sorted row ``j+1``
    is in sorted row ``j``'s episode. ValueError unless each episode's steps are
    consecutive integers (rows may come in any order)."""
    episode, step = episode.long(), step.long()
    order = torch.argsort(step, stable=True)
    order = order[torch.argsort(episode[order], stable=True)]  # by (episode, step)
    e, t = episode[order], step[order]
    same = e[1:] == e[:-1]
    if bool((same & (t[1:] != t[:-1] + 1)).any()):
        raise ValueError("each episode's steps must be consecutive integers (a gap or a repeat)")
    return order, same


def chunk_labels(
    label: torch.Tensor,
    episode: torch.Tensor,
    step: torch.Tensor,
    horizon: int,
    *,
    expert_executed: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``chunk[i, h]`` = ``label`` of the row of episode ``episode[i]`` at step ``step[i] + h``.

    Args:
        label: ``[N, *action]`` per-row labels.
        episode: ``[N]`` int episode ids.
        step: ``[N]`` int step of each row in its episode; each episode's steps must be
            consecutive integers (rows may come in any order).
        horizon: ``H >= 1``.
        expert_executed: ``[N]`` bool, the row's executed action was the expert's; a
            chunk ends at the first row (from its own on) where it was not (module
            docstring). None: every row's was.

    Returns:
        ``chunk [N, H, *action]`` (past the chunk's end: its last valid label) and
        ``pad [N, H]`` bool (True past the end).
    """
    if int(horizon) != horizon or horizon < 1:
        raise ValueError(f"horizon must be a positive integer, got {horizon!r}")
    n = label.shape[0]
    if episode.shape != (n,) or step.shape != (n,):
        raise ValueError(
            f"need one episode id and step per row: label {tuple(label.shape)}, "
            f"episode {tuple(episode.shape)}, step {tuple(step.shape)}"
        )
    if expert_executed is not None and expert_executed.shape != (n,):
        raise ValueError(
            f"need one expert_executed flag per row, got {tuple(expert_executed.shape)} for {n} rows"
        )
    order, same = episode_order(episode, step)
    is_last = torch.ones(n, dtype=torch.bool)
    is_last[:-1] = ~same
    # last[j]: the sorted index of the final row of row j's chunk: the episode's last row,
    # or the first row from j on whose executed action was not the expert's
    stop = is_last if expert_executed is None else is_last | ~expert_executed[order].bool()
    end = torch.where(stop, torch.arange(n), n).flip(0)
    last = torch.cummin(end, 0).values.flip(0)
    ahead = torch.arange(n)[:, None] + torch.arange(int(horizon))[None, :]  # [N, H]
    pad_sorted = ahead > last[:, None]
    source = torch.minimum(ahead, last[:, None])  # past the end: the last row
    inverse = torch.empty_like(order)
    inverse[order] = torch.arange(n)
    chunk = label[order][source][inverse]  # [N, H, *action] in the rows' order
    return chunk, pad_sorted[inverse]


def add_chunk_labels(
    rows: TensorDictBase, horizon: int, *, label_key=keys.EXPERT_ACTION
) -> TensorDictBase:
    """``rows`` (a shallow copy) with :data:`EXPERT_CHUNK` and :data:`CHUNK_PAD` added
    (from the rows' ``EXPERT_PLAN`` where they carry one, module docstring).

    ``rows`` ``[N]`` need ``label_key``, ``EPISODE`` and ``STEP`` (what
    :func:`~imitrl.runtime.rollout_episodes` and a ``DemonstrationBuffer`` hold); where
    they have ``EXPERT_EXECUTED``, a chunk ends at the first row whose executed action
    was not the expert's (module docstring).
    """
    missing = [k for k in (label_key, keys.EPISODE, keys.STEP) if k not in rows.keys()]
    if missing:
        raise ValueError(f"chunk labels need {missing} in the rows (keys {list(rows.keys())})")
    if rows.batch_dims != 1:
        raise ValueError(f"rows must be [N], got batch_size {tuple(rows.batch_size)}")
    plan = rows.get(keys.EXPERT_PLAN, None) if label_key == keys.EXPERT_ACTION else None
    if plan is not None:  # the expert's own plans (chunk-aware DAgger): whole chunks
        if plan.shape[1] < horizon:
            raise ValueError(
                f"the rows' expert plans hold {plan.shape[1]} actions, the learner's chunks "
                f"{horizon}: collect the rounds with plans at least as long"
            )
        chunk, pad = plan[:, :horizon], rows.get(keys.EXPERT_PLAN_PAD)[:, :horizon]
    else:
        executed = rows.get(keys.EXPERT_EXECUTED, None)
        chunk, pad = chunk_labels(
            rows.get(label_key),
            rows.get(keys.EPISODE),
            rows.get(keys.STEP),
            horizon,
            expert_executed=executed if executed is None else executed.reshape(rows.shape[0]),
        )
    out = TensorDict(dict(rows.items()), batch_size=rows.batch_size)  # new dict, same tensors
    out.set(EXPERT_CHUNK, chunk)
    out.set(CHUNK_PAD, pad)
    return out
