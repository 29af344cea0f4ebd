"""Where the study's episodes come from: gymnasium's stream, or batched TabularEnv lanes.

Both backends offer the same three operations on a *block* (one seeded stretch of
experiment, as the section seeds ``env.reset(seed=k)`` once per block):

* ``demonstrations(n_episodes, replicates)``: expert episodes, one row set per replicate;
* ``evaluate(tables, n_episodes)``: Monte Carlo success rate of each deterministic table;
* ``source(replicates)``: a DAgger episode source.

``FaithfulBackend`` plays everything on one gymnasium stream per block, in the
section's order (replicates one after another, interleaved with their fits and
evaluations): it reproduces the section's digits. ``BatchedBackend`` gives every
replicate its own lanes of one :class:`TabularEnv` over the ``K``-fold product MDP
(:meth:`TabularMDP.replicate`), so K datasets are collected, fitted and evaluated as
one batch; it evaluates ``eval_scale`` times more episodes.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType

from imitrl import keys
from imitrl.algorithms.dagger import EnvSource
from imitrl.envs.gym_stream import GymnasiumStream, GymnasiumStreamSource, play_episodes
from imitrl.envs.tabular_env import TabularEnv
from imitrl.policies.experts import Expert
from imitrl.policies.mixture import BetaMixer, behaviour_policy
from imitrl.runtime.rollout import rollout_episodes
from imitrl.tabular.mdp import TabularMDP

__all__ = ["BatchedBackend", "Block", "FaithfulBackend", "split_replicates"]


def split_replicates(rows: TensorDict, num_states: int, replicates: int) -> list[TensorDict]:
    """Rows of a product-MDP run, split by copy, with observations mapped back to ``[0, S)``."""
    copy = rows.get(keys.OBSERVATION) // num_states
    parts = []
    for k in range(replicates):
        part = rows[copy == k].clone()
        part.set(keys.OBSERVATION, part.get(keys.OBSERVATION) - k * num_states)
        parts.append(part)
    return parts


class _FaithfulBlock:
    def __init__(self, mdp: TabularMDP, expert_table: torch.Tensor, seed: int) -> None:
        self.mdp, self.expert_table = mdp, expert_table
        self.stream = GymnasiumStream(seed)

    def demonstrations(self, n_episodes: int, replicates: int = 1) -> list[TensorDict]:
        src = GymnasiumStreamSource(self.mdp, self.stream)
        expert = behaviour_policy(Expert.from_table(self.expert_table), None, BetaMixer(1.0))
        return [
            src.collect(expert, n_episodes, round_index=0, first_episode=0)
            for _ in range(replicates)
        ]

    def evaluate(self, tables: torch.Tensor, n_episodes: int) -> torch.Tensor:
        return torch.stack(
            [
                play_episodes(self.mdp, t, self.stream, n_episodes).success.double().mean()
                for t in tables
            ]
        )

    def source(self, replicates: int = 1) -> GymnasiumStreamSource:
        if replicates != 1:
            raise ValueError("the faithful protocol runs one replicate at a time")
        return GymnasiumStreamSource(self.mdp, self.stream)


class FaithfulBackend:
    """The section's protocol on gymnasium's own random stream."""

    name = "faithful"
    vectorised = False

    def __init__(self, mdp: TabularMDP, expert_table: torch.Tensor) -> None:
        self.mdp, self.expert_table = mdp, expert_table
        self.eval_scale = 1

    def block(self, seed: int) -> _FaithfulBlock:
        return _FaithfulBlock(self.mdp, self.expert_table, seed)


class _BatchedBlock:
    def __init__(self, mdp: TabularMDP, expert_table: torch.Tensor, seed: int) -> None:
        self.mdp, self.expert_table = mdp, expert_table
        self.generator = torch.Generator().manual_seed(seed)

    def _seed(self) -> int:
        return int(torch.randint(0, 2**31 - 1, (1,), generator=self.generator))

    def _product(self, replicates: int, lanes_each: int) -> tuple[TabularMDP, TabularEnv]:
        S = self.mdp.num_states
        product = self.mdp.replicate(replicates) if replicates > 1 else self.mdp
        start = int(torch.nonzero(self.mdp.initial).view(-1)[0])
        if (self.mdp.initial > 0).sum() != 1:
            raise ValueError(
                "the batched protocol pins lanes to copies and needs a single start state"
            )
        starts = (torch.arange(replicates) * S + start).repeat_interleave(lanes_each)
        env = TabularEnv(
            product, batch_size=(replicates * lanes_each,), seed=self._seed(), initial_state=starts
        )
        return product, env

    def demonstrations(self, n_episodes: int, replicates: int = 1) -> list[TensorDict]:
        _, env = self._product(replicates, n_episodes)
        expert = Expert.from_table(self.expert_table.repeat(replicates)).as_actor()
        rows = rollout_episodes(
            env,
            expert,
            replicates * n_episodes,
            exploration=ExplorationType.DETERMINISTIC,
            max_steps=10**6,
        )
        return split_replicates(rows, self.mdp.num_states, replicates)

    def evaluate(self, tables: torch.Tensor, n_episodes: int) -> torch.Tensor:
        # One TabularEnv plays every table's episodes, finished episodes compacted away.
        env = TabularEnv(self.mdp, batch_size=(1,), seed=self._seed())
        return env.play_tables(tables, n_episodes)["success"].double().mean(dim=1)

    def source(self, replicates: int = 1, episodes_per_round: int = 1) -> EnvSource:
        _, env = self._product(replicates, episodes_per_round)
        return EnvSource(env, exploration=ExplorationType.DETERMINISTIC, max_steps=10**6)


class BatchedBackend:
    """Independent TabularEnv lanes; replicates vectorised on the product MDP."""

    name = "batched"
    vectorised = True

    def __init__(self, mdp: TabularMDP, expert_table: torch.Tensor, eval_scale: int) -> None:
        self.mdp, self.expert_table, self.eval_scale = mdp, expert_table, int(eval_scale)

    def block(self, seed: int) -> _BatchedBlock:
        return _BatchedBlock(self.mdp, self.expert_table, seed)


Block = _FaithfulBlock | _BatchedBlock
"""One seeded stretch of experiment, of either backend (see the module docstring)."""
