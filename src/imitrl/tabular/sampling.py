"""Inverse-CDF sampling over a tabular MDP's ordered outcome lists, batched.

One uniform ``u`` picks an outcome of ``(s, a)`` as gymnasium's
``categorical_sample`` does: ``argmax(cumsum(p) > u)`` over the list in order, with
an all-False comparison (``u`` above a cumsum that rounds below 1) giving index 0.
Feeding it gymnasium's own uniforms reproduces gymnasium's trajectories exactly; feeding it
any other uniform source samples the same kernel.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from imitrl.tabular.mdp import TabularMDP

__all__ = ["ComposedTables", "OutcomeSampler", "play_compacted"]


class OutcomeSampler:
    """Batched transition sampler over flat outcome tables.

    The tables are laid out for 1-D ``take`` lookups (much cheaper than row gathers
    at batch sizes of 1e4-1e6): ``cdf_columns[k][s * A + a]`` and
    ``next_state[(s * A + a) * K + k]``.

    Args:
        mdp: the MDP whose outcome lists are sampled.
    """

    def __init__(self, mdp: TabularMDP) -> None:
        out = mdp.outcomes
        S, A, K = out.next_state.shape
        self.num_states, self.num_actions, self.num_outcomes = S, A, K
        cdf = out.cdf.reshape(S * A, K)
        self.cdf_columns = cdf.T.contiguous()  # [K, S*A] float64
        # gymnasium maps u >= cdf[-1] (a cumsum rounding below 1) to outcome 0.
        self._may_overflow = bool((cdf[:, -1] < 1.0).any())
        self.next_state = out.next_state.reshape(-1).contiguous()  # [S*A*K] int64
        self.reward = out.reward.reshape(-1).to(torch.float32).contiguous()  # [S*A*K]
        self.terminated = out.terminated.reshape(-1).contiguous()  # [S*A*K] bool
        self.initial_cdf = mdp.initial_cdf  # [S] float64
        self.terminal = mdp.terminal  # [S] bool
        self._lists: dict[str, list] | None = None

    def as_lists(self) -> dict[str, list]:
        """The tables as Python lists (``cdf`` per flat pair ``s * A + a``), for scalar loops."""
        if self._lists is None:
            self._lists = {
                "cdf": [tuple(row) for row in self.cdf_columns.T.tolist()],
                "next_state": self.next_state.tolist(),
                "reward": self.reward.double().tolist(),
                "terminated": self.terminated.tolist(),
                "initial_cdf": self.initial_cdf.tolist(),
            }
        return self._lists

    def initial(self, u: torch.Tensor) -> torch.Tensor:
        """``[N]`` int64 initial states from ``[N]`` float64 uniforms."""
        # searchsorted(right=True) counts the cdf entries <= u: the first index above u.
        k = torch.searchsorted(self.initial_cdf, u, right=True)
        return k.masked_fill(k >= self.num_states, 0)

    def compose(self, tables: torch.Tensor, goal: torch.Tensor) -> ComposedTables:
        """Compose ``[K, S]`` int action tables with the outcome lists (product states)."""
        K, S, Ko = tables.shape[0], self.num_states, self.num_outcomes
        copy = torch.arange(K).repeat_interleave(S)  # [K*S] policy of each product state
        pair = torch.arange(S).repeat(K) * self.num_actions + tables.reshape(-1).long()
        cols = pair[:, None] * Ko + torch.arange(Ko)  # [K*S, Ko] flat outcome ids
        nxt = self.next_state[cols]
        term = self.terminated[cols].reshape(-1)
        return ComposedTables(
            cdf=self.cdf_columns[:, pair].contiguous(),
            next_state=(nxt + (copy * S)[:, None]).reshape(-1).to(torch.int32),
            reward=self.reward[cols].reshape(-1).double(),
            terminated=term,
            win=term & goal[nxt].reshape(-1),
            may_overflow=self._may_overflow,
        )

    def pick(self, pair: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """``[N]`` int32 flat outcome ids ``pair * K + k`` for int32 pair ids ``s * A + a``.

        Works on a table whose columns are indexed by ``pair`` (``cdf_columns`` by
        default); int32 arithmetic and ``index_select`` run several times faster on a
        CPU than int64 arithmetic and ``take`` at 1e5-1e6 lanes.
        """
        return _pick(self.cdf_columns, pair, u, self._may_overflow)

    def outcome_index(
        self, state: torch.Tensor, action: torch.Tensor, u: torch.Tensor
    ) -> torch.Tensor:
        """``[N]`` int32 flat outcome ids ``(s * A + a) * K + k`` chosen by ``u``."""
        pair = state.to(torch.int32) * self.num_actions + action.to(torch.int32)
        return self.pick(pair, u)

    def step(
        self, state: torch.Tensor, action: torch.Tensor, u: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One transition for a batch.

        Args:
            state: ``[N]`` int64 states.
            action: ``[N]`` int64 actions in ``[0, A)`` (not checked here).
            u: ``[N]`` float64 uniforms in ``[0, 1)``.

        Returns:
            next_state ``[N]`` int64, reward ``[N]`` float32, terminated ``[N]`` bool.
        """
        flat = self.outcome_index(state, action, u)
        return (
            self.next_state.index_select(0, flat),
            self.reward.index_select(0, flat),
            self.terminated.index_select(0, flat),
        )


def _pick(
    cdf: torch.Tensor, pair: torch.Tensor, u: torch.Tensor, may_overflow: bool
) -> torch.Tensor:
    """Count of ``cdf[:, pair]`` entries <= ``u`` (the first entry above ``u``), as flat ids."""
    K = cdf.shape[0]
    k = (cdf[0].index_select(0, pair) <= u).to(torch.int32)
    for j in range(1, K):
        k += (cdf[j].index_select(0, pair) <= u).to(torch.int32)
    if may_overflow:
        k.masked_fill_(k >= K, 0)
    return pair * K + k


@dataclass(frozen=True)
class ComposedTables:
    """K deterministic table policies composed with the outcome lists.

    On the product index ``p = k * S + s`` (policy k in state s) one step is a
    compare-sum over the ``K_out`` CDF columns and three lookups. Built by
    :meth:`OutcomeSampler.compose`.
    """

    cdf: torch.Tensor  # [K_out, K*S] float64
    next_state: torch.Tensor  # [K*S*K_out] int32 product next states
    reward: torch.Tensor  # [K*S*K_out] float64
    terminated: torch.Tensor  # [K*S*K_out] bool
    win: torch.Tensor  # [K*S*K_out] bool: terminated in a goal state
    may_overflow: bool


def play_compacted(
    composed: ComposedTables,
    start: torch.Tensor,
    draw: Callable[[torch.Tensor, int], torch.Tensor],
    max_steps: int,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Play one episode per lane until it terminates or reaches ``max_steps``.

    Finished lanes leave the batch, so the cost is the number of steps played.

    Args:
        composed: the policies and the MDP (:meth:`OutcomeSampler.compose`).
        start: ``[N]`` product start states ``k * S + s``.
        draw: ``draw(lanes, t)`` returns float64 uniforms for the int32 lane ids still
            playing at step ``t`` (a generator's next numbers, or a stream's entries).
        max_steps: time limit.

    Returns:
        lengths ``[N]`` int64, returns ``[N]`` float64, success ``[N]`` bool (entered a
        goal state), truncated ``[N]`` bool (reached the time limit).
    """
    N = start.numel()
    p = start.to(torch.int32)
    lane = torch.arange(N, dtype=torch.int32)
    ret = torch.zeros(N, dtype=torch.float64)
    lengths = torch.full((N,), max_steps, dtype=torch.int64)
    returns = torch.zeros(N, dtype=torch.float64)
    success = torch.zeros(N, dtype=torch.bool)
    truncated = torch.zeros(N, dtype=torch.bool)
    for t in range(max_steps):
        flat = _pick(composed.cdf, p, draw(lane, t), composed.may_overflow)
        p = composed.next_state.index_select(0, flat)
        ret += composed.reward.index_select(0, flat)
        ended = composed.terminated.index_select(0, flat)
        last = t + 1 == max_steps
        if last or bool(ended.any()):
            done = torch.ones_like(ended) if last else ended
            fin = lane[done].long()
            lengths[fin] = t + 1
            returns[fin] = ret[done]
            success[fin] = composed.win.index_select(0, flat[done])
            truncated[fin] = last
            keep = ~done
            lane, p, ret = lane[keep], p[keep], ret[keep]
            if lane.numel() == 0:
                break
    return lengths, returns, success, truncated
