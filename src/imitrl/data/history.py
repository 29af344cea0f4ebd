"""Observation histories from buffer rows: the last ``n`` observations of the row's episode.

Diffusion Policy conditions on the observations of the last ``T_o`` steps (its
observation horizon, 2 in the paper). A row's history at episode ``e``, step ``t`` is

    history[i, j] = observation of the row (e, max(t - (n - 1) + j, 0)),   j = 0 .. n-1,

oldest first: before the episode's first step the first observation is repeated, as
the paper's code pads (and as a policy acting at an episode's start must, having seen
only one observation). Rows may come in any order; each episode's steps must be
consecutive. :func:`add_observation_history` adds it to rows as :data:`OBS_HISTORY`;
a policy acting in an env builds the same history from the observations it has seen
since the lane's reset.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase

from imitrl import keys
from imitrl.data.chunks import episode_order

__all__ = ["OBS_HISTORY", "add_observation_history", "history_key", "observation_history"]


def history_key(key):
    """The key of ``key``'s history: ``"<key>_history"`` (the last part of a nested key)."""
    if isinstance(key, tuple):
        return (*key[:-1], f"{key[-1]}_history")
    return f"{key}_history"


OBS_HISTORY = history_key(keys.OBSERVATION)
"""``[N, n, *obs]`` the row's last ``n`` observations in its episode, oldest first"""


def observation_history(
    obs: torch.Tensor, episode: torch.Tensor, step: torch.Tensor, n: int
) -> torch.Tensor:
    """``history [N, n, *obs]`` of every row (module docstring).

    Args:
        obs: ``[N, *obs]`` per-row observations.
        episode, step: ``[N]`` int episode id and step of each row.
        n: the history's length (``n = 1``: the observation itself).
    """
    if int(n) != n or n < 1:
        raise ValueError(f"the history length must be a positive integer, got {n!r}")
    rows = obs.shape[0]
    if episode.shape != (rows,) or step.shape != (rows,):
        raise ValueError(
            f"need one episode id and step per row: obs {tuple(obs.shape)}, episode "
            f"{tuple(episode.shape)}, step {tuple(step.shape)}"
        )
    order, same = episode_order(episode, step)
    starts = torch.ones(rows, dtype=torch.bool)
    starts[1:] = ~same
    first = torch.cummax(torch.where(starts, torch.arange(rows), 0), 0).values  # episode start
    back = torch.arange(int(n) - 1, -1, -1)  # n-1 .. 0 steps back, oldest first
    source = torch.maximum(torch.arange(rows)[:, None] - back[None, :], first[:, None])
    inverse = torch.empty_like(order)
    inverse[order] = torch.arange(rows)
    return obs[order][source][inverse]


def add_observation_history(
    rows: TensorDictBase, n: int, *, obs_key=keys.OBSERVATION, out_key=OBS_HISTORY
) -> TensorDictBase:
    """``rows`` (a shallow copy) with ``out_key`` = the history of ``obs_key`` added."""
    missing = [k for k in (obs_key, keys.EPISODE, keys.STEP) if k not in rows.keys(True)]
    if missing:
        raise ValueError(f"observation histories need {missing} in the rows")
    if rows.batch_dims != 1:
        raise ValueError(f"rows must be [N], got batch_size {tuple(rows.batch_size)}")
    history = observation_history(rows.get(obs_key), rows.get(keys.EPISODE), rows.get(keys.STEP), n)
    out = TensorDict(dict(rows.items()), batch_size=rows.batch_size)  # new dict, same tensors
    out.set(out_key, history)
    return out
