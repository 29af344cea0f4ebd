"""benchmarks/_paired.py: differences against a reference loss, pair by pair (task, seed)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from _paired import paired_differences, paired_table


def _row(task, loss, seed, score, algorithm="bc"):
    return {"task": task, "loss": loss, "seed": seed, "algorithm": algorithm, "score": score}


def test_differences_are_taken_pair_by_pair_against_each_tasks_reference():
    rows = [
        _row("a", "mse", 0, 0.5), _row("a", "mse", 1, 0.7), _row("a", "flow", 0, 0.6),
        _row("a", "flow", 1, 0.9), _row("b", "cross_entropy", 0, 0.2),
        _row("b", "flow", 0, 0.1), _row("b", "flow", 1, 0.4),  # seed 1 of b: no reference
        _row("c", "flow", 0, 1.0),  # a task with no reference loss
    ]  # fmt: skip
    ref = {"a": "mse", "b": "cross_entropy"}.get
    (found,) = paired_differences(rows, ref)
    assert found["group"] == ("flow", "bc") and found["pairs"] == 3 and found["tasks"] == 2
    diffs = [0.1, 0.2, -0.1]
    mean = sum(diffs) / 3
    assert found["diff"][0] == pytest.approx(mean)
    sd = (sum((d - mean) ** 2 for d in diffs) / 2) ** 0.5
    assert found["diff"][2] - mean == pytest.approx(
        4.302653 * sd / 3**0.5, rel=1e-5
    )  # t_{0.975, 2}
    assert (found["wins"], found["losses"]) == (1, 1)
    assert "| flow | bc | 3 | 0.07 [-0.31, 0.45] | 1 / 1 of 2 |" in paired_table(
        [found], ("loss", "algorithm")
    )
