"""What every section of the FrozenLake study reads: the config, the MDP, the expert, the
backend, the report, and the results earlier sections leave for later ones.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict
from torchrl.data import Categorical
from tqdm.auto import tqdm

from imitrl.algorithms.bc import BCConfig
from imitrl.algorithms.dagger import DAggerConfig
from imitrl.data.buffer import DemonstrationBuffer
from imitrl.experiments.frozenlake.backends import BatchedBackend, FaithfulBackend
from imitrl.experiments.frozenlake.config import StudyConfig
from imitrl.experiments.frozenlake.outputs import FIGURES
from imitrl.experiments.frozenlake.report import Report
from imitrl.learners import TaskSpec, build
from imitrl.learners.actor_critic import ActorCritic
from imitrl.tabular.finite_horizon import state_distributions, success_probability
from imitrl.tabular.mdp import TabularMDP

__all__ = ["StudyContext", "decision_distribution"]


@dataclass
class StudyContext:
    """The study's shared state; sections 1-3 fill ``demos``, ``clone`` and ``clone_table``."""

    config: StudyConfig
    mdp: TabularMDP
    expert_table: torch.Tensor
    """``[S]`` the expert's greedy action per state"""
    backend: FaithfulBackend | BatchedBackend
    report: Report
    demos: TensorDict | None = None
    """section 1's demonstration rows (observation, expert_action, episode, ...)"""
    clone: ActorCritic | None = None
    """section 2's behaviour clone"""
    clone_table: torch.Tensor | None = None
    """``[S]`` the clone's greedy action per state (section 3)"""
    _exact: dict = field(default_factory=dict)

    @property
    def S(self) -> int:
        return self.mdp.num_states

    @property
    def A(self) -> int:
        return self.mdp.num_actions

    def exact(self, table: torch.Tensor) -> float:
        """Exact success probability within the time limit of the ``[S]`` greedy table."""
        key = tuple(table.tolist())  # replicates often share a table: price each once
        if key not in self._exact:
            self._exact[key] = success_probability(self.mdp, table)
        return self._exact[key]

    def exact_each(self, tables: torch.Tensor) -> np.ndarray:
        """``[K]`` exact success of each of the ``[K, S]`` tables."""
        return np.array([self.exact(t) for t in tables])

    def figure(self, name: str) -> Path:
        """Where figure ``name`` (one of :data:`outputs.FIGURES`) is drawn: the staging folder."""
        if name not in FIGURES:
            raise ValueError(f"unknown figure {name!r}: add it to outputs.FIGURES")
        return self.report.out / f"{name}.png"

    def eval_episodes(self, episodes: int) -> int:
        """Monte Carlo episodes of an estimate: ``episodes`` times the backend's scale."""
        return episodes * self.backend.eval_scale

    def buffer(
        self, rows: TensorDict | None = None, num_states: int | None = None
    ) -> DemonstrationBuffer:
        buf = DemonstrationBuffer(num_states=num_states or self.S, action_spec=Categorical(self.A))
        if rows is not None:
            buf.extend(rows)
        return buf

    def learner(self, copies: int = 1) -> ActorCritic:
        """A zero-initialised tabular actor-critic over ``copies * S`` states."""
        learner = build(
            "cross_entropy", TaskSpec(action=self.A, num_states=self.S * copies), lr=self.config.lr
        )
        assert isinstance(learner, ActorCritic)  # cross_entropy on integer states: a table
        return learner

    def dagger_config(self, episodes_per_round: int, fit_steps: int) -> DAggerConfig:
        """The study's DAgger: ``config.dagger_rounds`` full-batch fits of ``fit_steps``."""
        return DAggerConfig(
            rounds=self.config.dagger_rounds,
            episodes_per_round=episodes_per_round,
            bc=BCConfig(num_steps=fit_steps, batch_size=None),  # the section's full batch
        )

    def bar(self, iterable, desc: str, total: int | None = None):
        return tqdm(iterable, desc=desc, total=total, disable=not self.config.progress, leave=False)


def decision_distribution(mdp: TabularMDP, table: torch.Tensor) -> torch.Tensor:
    """``[S]`` where the policy takes its decisions: mean of d_0 .. d_{T-1} over live states."""
    d = state_distributions(mdp, table)[:-1]
    live = d * (~mdp.terminal).double()
    total = live.sum()
    return live.sum(0) / total
