"""Dynamic programming on a :class:`TabularMDP`: exact, float64, pure functions."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import torch

from imitrl.tabular.bellman import backup_arrays, backup_dense
from imitrl.tabular.mdp import TabularMDP
from imitrl.tabular.policy import kernel_under, reward_under

__all__ = ["backup", "converged_values", "greedy", "policy_evaluation", "value_iteration"]


def backup(mdp: TabularMDP, V: torch.Tensor) -> torch.Tensor:
    """Bellman backup ``Q[s, a] = r[s, a] + gamma * sum_s' P[s, a, s'] V[s']``.

    Args:
        V: ``[S]`` state values.

    Returns:
        ``[S, A]`` float64 action values.
    """
    return backup_dense(mdp.P, mdp.r, mdp.gamma, V)


def _sweeps(mdp: TabularMDP) -> Iterator[np.ndarray]:
    """``V_1, V_2, ...``: the sweeps ``V_{k+1}[s] = max_a Q_k[s, a]`` from ``V_0 = 0``."""
    r, gamma_P = mdp.r.numpy(), mdp.gamma * mdp.P.numpy()
    V = np.zeros(mdp.num_states)
    while True:
        V = backup_arrays(r, gamma_P, V).max(axis=1)
        yield V


def value_iteration(mdp: TabularMDP, num_iters: int = 1000) -> torch.Tensor:
    """Sweep ``V_{k+1}[s] = max_a Q_k[s, a]`` from ``V_0 = 0``.

    Returns:
        ``[num_iters, S]`` history of the iterates ``V_1 .. V_n``; ``[-1]`` is the
        final estimate (after k sweeps the error is at most
        ``gamma^k * max|r| / (1 - gamma)``).
    """
    if int(num_iters) != num_iters or num_iters < 1:
        raise ValueError(f"num_iters must be a positive integer, got {num_iters!r}")
    history = np.empty((int(num_iters), mdp.num_states))
    for k, V in zip(range(int(num_iters)), _sweeps(mdp)):
        history[k] = V
    return torch.from_numpy(history)


def converged_values(mdp: TabularMDP, max_sweeps: int) -> tuple[torch.Tensor, int]:
    """``(V*, sweeps)``: value iteration from ``V_0 = 0`` until a sweep changes no state's
    value by more than float64's rounding (each state relative to itself, so a state far
    from any reward, whose value is still 0 or tiny, keeps the sweeps going until its
    value arrives: a fixed number of sweeps leaves a state farther than that from the
    reward at 0, all its actions tied).

    Raises:
        ValueError: not converged within ``max_sweeps``.
    """
    V = np.zeros(mdp.num_states)
    tol = 4 * np.finfo(np.float64).eps
    for sweep, new in zip(range(1, int(max_sweeps) + 1), _sweeps(mdp)):
        if np.all(np.abs(new - V) <= tol * np.abs(new)):
            return torch.from_numpy(new), sweep
        V = new
    raise ValueError(
        f"value iteration on {mdp.name!r} did not converge in {int(max_sweeps)} sweeps "
        f"(gamma {mdp.gamma})"
    )


def greedy(Q: torch.Tensor) -> torch.Tensor:
    """``[S]`` int64 greedy actions ``argmax_a Q[s, a]``; exact ties go to the lowest action."""
    Q = torch.as_tensor(Q)
    if Q.ndim != 2:
        raise ValueError(f"Q must have shape [S, A], got {tuple(Q.shape)}")
    # torch.argmax returns the first maximal index, i.e. the lowest action on ties.
    return Q.argmax(dim=1)


def policy_evaluation(mdp: TabularMDP, pi: Any) -> torch.Tensor:
    """Exact discounted value ``V_pi = (I - gamma P_pi)^{-1} r_pi`` of a tabular policy.

    Args:
        pi: ``[S]`` actions or ``[S, A]`` probabilities.

    Returns:
        ``[S]`` float64 values. With ``gamma == 1`` terminal states are pinned at 0 and
        the system is solved on the others; it must then terminate with probability 1.

    Raises:
        ValueError: ``gamma == 1`` and the policy can avoid termination forever.
    """
    P_pi, r_pi = kernel_under(mdp, pi), reward_under(mdp, pi)
    S = mdp.num_states
    if mdp.gamma < 1.0:
        return torch.linalg.solve(torch.eye(S, dtype=torch.float64) - mdp.gamma * P_pi, r_pi)
    live = ~mdp.terminal
    A_live = torch.eye(int(live.sum()), dtype=torch.float64) - P_pi[live][:, live]
    V = torch.zeros(S, dtype=torch.float64)
    try:
        sol = torch.linalg.solve(A_live, r_pi[live])
    except RuntimeError as err:  # singular: a closed class of non-terminal states
        raise ValueError(
            "undiscounted policy evaluation needs a policy that terminates with probability 1; "
            "this one can stay among non-terminal states forever (use gamma < 1 or a time limit)"
        ) from err
    if not torch.isfinite(sol).all():
        raise ValueError("undiscounted policy evaluation diverged: the policy does not terminate")
    V[live] = sol
    return V
