"""Inverse-CDF sampling over a tabular MDP's ordered outcome lists, batched.

One uniform ``u`` picks an outcome of ``(s, a)`` as gymnasium's
``categorical_sample`` does: ``argmax(cumsum(p) > u)`` over the list in order, with
an all-False comparison (``u`` above a cumsum that rounds below 1) giving index 0.
Feeding it gymnasium's own uniforms reproduces gymnasium's trajectories exactly; feeding it
any other uniform source samples the same kernel.
"""

from __future__ import annotations

import torch

from imitrl.tabular.mdp import TabularMDP

__all__ = ["OutcomeSampler"]


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

    def outcome_index(
        self, state: torch.Tensor, action: torch.Tensor, u: torch.Tensor
    ) -> torch.Tensor:
        """``[N]`` int64 flat outcome ids ``(s * A + a) * K + k`` chosen by ``u``."""
        sa = state * self.num_actions + action
        k = (self.cdf_columns[0].take(sa) <= u).long()
        for j in range(1, self.num_outcomes):
            k += self.cdf_columns[j].take(sa) <= u
        if self._may_overflow:
            k.masked_fill_(k >= self.num_outcomes, 0)
        return sa * self.num_outcomes + k

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
        return self.next_state.take(flat), self.reward.take(flat), self.terminated.take(flat)
