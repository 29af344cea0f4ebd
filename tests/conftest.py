"""Shared fixtures: the section's MDP and expert, built once per session."""

from __future__ import annotations

import pytest
import torch

from imitrl.tabular import TabularMDP, greedy, value_iteration

torch.set_num_threads(1)


@pytest.fixture(scope="session")
def lake() -> TabularMDP:
    """Slippery FrozenLake-v1 (4x4) with gamma 0.95."""
    return TabularMDP.from_gym("FrozenLake-v1", 0.95)


@pytest.fixture(scope="session")
def expert_table(lake: TabularMDP) -> torch.Tensor:
    """``[16]`` value-iteration greedy policy of the slippery lake."""
    return greedy(lake.backup(value_iteration(lake, 1000)[-1]))
