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


LONGEST_FIRST = (
    "benchmarks/test_benchmarks_smoke.py",
    "fs/test_fs_hostile.py",
    "datasets/minari/test_minari_hostile.py",
    "cli/test_cli.py",
    "experiments/frozenlake/test_study.py",
    "experiments/frozenlake/test_study_faults.py",
    "datasets/lerobot/test_lerobot_hostile.py",
    "algorithms/test_ray_source.py",
    "envs/test_metaworld.py",
    "datasets/minari/test_bounds.py",
    "test_readme_examples.py",
)
"""test files (under ``tests/``) handed to the xdist workers before the rest, longest
first: each took 28-200 s of a worker in a quiet run, the median file under 2 s. Given out
last, one of them kept one worker busy while the other sat idle (20 s at the end of a
9.8-minute run). Only the order changes; every file still runs."""


def pytest_collection_modifyitems(config, items):
    """:data:`LONGEST_FIRST` files first (``--no-loadscope-reorder`` in ``pyproject.toml``
    makes xdist hand files out in this order), the rest as collected."""
    root = Path(__file__).resolve().parent
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}

    def key(item) -> int:
        path = Path(str(item.path)).resolve()
        name = path.relative_to(root).as_posix() if path.is_relative_to(root) else ""
        return rank.get(name, len(LONGEST_FIRST))

    items.sort(key=key)  # stable: within a file, and among the rest, collection order


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
