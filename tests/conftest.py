"""Shared fixtures: the section's MDP and expert, built once per session."""

from __future__ import annotations

import os
import sys
from pathlib import Path

# One torch thread in every process the tests start too (benchmark scripts, `python -c`
# children, Ray workers, spawned pools), not this one alone: on a 2-core machine with two
# xdist workers, children at torch's default of a thread a core made the suite's wall time
# swing by minutes between runs. A test that measures threads sets its own.
os.environ["OMP_NUM_THREADS"] = "1"

import pytest
import torch

from imitrl.tabular import TabularMDP, greedy, value_iteration

torch.set_num_threads(1)


@pytest.fixture(autouse=True)
def _own_environment():
    """Each test starts from the environment the session started with: what one sets in
    ``os.environ`` (imitrl sets ``MUJOCO_GL`` to render Meta-World without a display) ends
    with it, as it would with its process, and never reaches another test's children."""
    saved = dict(os.environ)
    yield
    if os.environ != saved:
        os.environ.clear()
        os.environ.update(saved)


@pytest.fixture(scope="session")
def lake() -> TabularMDP:
    """Slippery FrozenLake-v1 (4x4) with gamma 0.95."""
    return TabularMDP.from_gym("FrozenLake-v1", 0.95)


@pytest.fixture(scope="session")
def expert_table(lake: TabularMDP) -> torch.Tensor:
    """``[16]`` value-iteration greedy policy of the slippery lake."""
    return greedy(lake.backup(value_iteration(lake, 1000)[-1]))


EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
"""the user-side package ``mypkg`` (experts, a registered loss) the README's examples import"""


@pytest.fixture
def mypkg(monkeypatch):
    """``examples/`` importable for the test; afterwards ``mypkg`` forgotten and the loss
    it registers (``l1_l2``) unregistered, as before."""
    from imitrl.learners import registry

    monkeypatch.syspath_prepend(str(EXAMPLES))
    yield
    for name in [m for m in sys.modules if m == "mypkg" or m.startswith("mypkg.")]:
        del sys.modules[name]
    if "l1_l2" in registry.names():
        registry.unregister("l1_l2")
