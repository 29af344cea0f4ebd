"""Finite-horizon ground truth: exact state distributions under a time limit.

With ``d_0 = initial`` and ``d_{t+1} = d_t P_pi`` (terminal states absorbing), an
episode cut by a time limit of ``T`` steps, as gymnasium's ``TimeLimit`` cuts it,
ends in distribution ``d_T``. Everything a Monte Carlo evaluation estimates for a
tabular policy has an exact value here.
"""

from __future__ import annotations

from typing import Any

import torch

from imitrl.tabular.mdp import TabularMDP
from imitrl.tabular.policy import kernel_under, policy_probs, reward_under

__all__ = [
    "expected_episode_length",
    "expected_return",
    "occupancy",
    "reachable_states",
    "state_distributions",
    "success_probability",
    "total_variation",
]


def _horizon(mdp: TabularMDP, horizon: float | None) -> int:
    """``horizon`` (an integer, or a whole float) or the MDP's time limit, as an int."""
    T = mdp.max_steps if horizon is None else horizon
    if T is None:
        raise ValueError(f"no horizon given and {mdp.name!r} has no time limit (max_steps)")
    if int(T) != T or T < 0:
        raise ValueError(f"horizon must be a non-negative integer, got {T!r}")
    return int(T)


def state_distributions(
    mdp: TabularMDP, pi: Any, horizon: int | None = None, *, initial: Any | None = None
) -> torch.Tensor:
    """``[T + 1, S]`` float64 state distributions ``d_0 .. d_T`` under ``pi``.

    Args:
        pi: ``[S]`` actions or ``[S, A]`` probabilities.
        horizon: ``T``; defaults to the MDP's time limit.
        initial: ``[S]`` start distribution; defaults to ``mdp.initial``.
    """
    T = _horizon(mdp, horizon)
    P_pi = kernel_under(mdp, pi)
    d = torch.empty(T + 1, mdp.num_states, dtype=torch.float64)
    d[0] = mdp.initial if initial is None else torch.as_tensor(initial, dtype=torch.float64)
    if d[0].shape != (mdp.num_states,):
        raise ValueError(f"initial must have shape [{mdp.num_states}]")
    for t in range(T):
        d[t + 1] = d[t] @ P_pi
    return d


def success_probability(
    mdp: TabularMDP, pi: Any, horizon: int | float | None = None, *, initial: Any | None = None
) -> float:
    """Probability of entering a goal state within ``horizon`` steps.

    Args:
        horizon: number of steps; None uses the MDP's time limit; ``math.inf`` gives
            the probability with no time limit (an exact absorption probability).
        initial: ``[S]`` start distribution; defaults to ``mdp.initial``.
    """
    if horizon == float("inf"):
        return _absorption_probability(mdp, pi, initial)
    d = state_distributions(mdp, pi, _horizon(mdp, horizon), initial=initial)
    return float(d[-1][mdp.goal].sum())


def _absorption_probability(mdp: TabularMDP, pi: Any, initial: Any | None = None) -> float:
    """``Pr(reach a goal state ever)`` by a linear solve on the states that can reach one."""
    P_pi = kernel_under(mdp, pi)
    S = mdp.num_states
    # Backward reachability of the goal set through positive-probability edges.
    can = mdp.goal.clone()
    adj = P_pi > 0
    while True:
        grown = can | (adj & can[None, :]).any(dim=1)
        grown &= ~(mdp.terminal & ~mdp.goal)
        if torch.equal(grown, can):
            break
        can = grown
    x = torch.zeros(S, dtype=torch.float64)
    x[mdp.goal] = 1.0
    unknown = can & ~mdp.terminal
    if unknown.any():
        A = torch.eye(int(unknown.sum()), dtype=torch.float64) - P_pi[unknown][:, unknown]
        b = P_pi[unknown][:, mdp.goal].sum(dim=1)
        x[unknown] = torch.linalg.solve(A, b)
    start = mdp.initial if initial is None else torch.as_tensor(initial, dtype=torch.float64)
    return float(start @ x)


def expected_return(
    mdp: TabularMDP,
    pi: Any,
    horizon: int | None = None,
    *,
    gamma: float = 1.0,
    initial: Any | None = None,
) -> float:
    """Expected (by default undiscounted) return ``sum_{t<T} gamma^t d_t . r_pi`` in ``T`` steps."""
    d = state_distributions(mdp, pi, horizon, initial=initial)
    r_pi = reward_under(mdp, pi)
    discounts = gamma ** torch.arange(d.shape[0] - 1, dtype=torch.float64)
    return float((discounts[:, None] * d[:-1] * r_pi[None, :]).sum())


def expected_episode_length(
    mdp: TabularMDP, pi: Any, horizon: int | None = None, *, initial: Any | None = None
) -> float:
    """Expected number of steps of an episode cut at ``horizon``: ``sum_{t<T} Pr(not terminal at t)``."""
    d = state_distributions(mdp, pi, horizon, initial=initial)
    return float((1.0 - d[:-1][:, mdp.terminal].sum(dim=1)).sum())


def total_variation(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """``0.5 * sum_s |p[..., s] - q[..., s]|`` over the last dimension."""
    p, q = torch.as_tensor(p), torch.as_tensor(q)
    if p.shape != q.shape:
        raise ValueError(
            f"distributions must have the same shape, got {tuple(p.shape)} and {tuple(q.shape)}"
        )
    return 0.5 * (p - q).abs().sum(dim=-1)


def occupancy(
    mdp: TabularMDP, pi: Any, horizon: int | None = None, *, include_initial: bool = False
) -> torch.Tensor:
    """``[S]`` average state distribution over the steps of a ``horizon``-step episode.

    ``include_initial=False`` averages ``d_1 .. d_T`` (where the agent stands after
    each of its ``T`` moves); ``True`` averages ``d_0 .. d_{T-1}`` (where it decides).
    Mass parked in absorbing terminal states keeps counting, so a hole that swallows
    the agent early shows up as occupancy of the hole.
    """
    d = state_distributions(mdp, pi, horizon)
    steps = d[:-1] if include_initial else d[1:]
    return steps.mean(dim=0)


def reachable_states(mdp: TabularMDP, pi: Any | None = None) -> torch.Tensor:
    """``[S]`` bool: states reachable from the initial support under ``pi``.

    ``pi=None`` means any action (reachable under some policy).
    """
    if pi is None:
        adj = (mdp.P > 0).any(dim=1)
    else:
        probs = policy_probs(pi, mdp.num_states, mdp.num_actions)
        adj = ((probs[:, :, None] > 0) & (mdp.P > 0)).any(dim=1)
    seen = mdp.initial > 0
    frontier = seen.clone()
    while frontier.any():
        nxt = adj[frontier].any(dim=0) & ~seen
        seen |= nxt
        frontier = nxt
    return seen
