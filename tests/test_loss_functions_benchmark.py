"""benchmarks/loss_functions.py (and its parts in benchmarks/_loss_functions/): smoke run,
reproducible cells, statistics, CONTRIBUTING's example."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from imitrl.objectives import registry
from imitrl.objectives.registry import TaskSpec
from imitrl.tabular import success_probability
from tests.test_benchmarks_smoke import committed

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from _loss_functions.run import loss_cell, run  # noqa: E402
from _loss_functions.tasks import TASKS, TwoWay, tasks  # noqa: E402

TIMING = {"fit_seconds", "eval_seconds", "cell_seconds"}


@pytest.mark.slow  # test_benchmarks_smoke runs --quick in the default suite; this checks its cells
def test_quick_run_covers_every_loss_on_every_task(tmp_path, lake, expert_table):
    """``--quick`` without ``--out`` writes to a temporary directory, never the committed
    README or results, and covers every loss on every task."""
    before = committed()
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "loss_functions.py"), "--quick"],
        env={**os.environ, "TMPDIR": str(tmp_path)},  # where --quick writes
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert committed() == before, "loss_functions.py --quick rewrote committed results"
    (result,) = tmp_path.rglob("loss_functions.json")
    data = json.loads(result.read_text())
    assert data["machine"]["torch"].startswith("2.13")
    (figure,) = tmp_path.rglob("loss_functions.png")
    assert figure.stat().st_size > 10_000
    cells = {(r["task"], r["loss"], r["algorithm"]) for r in data["rows"]}
    factories = tasks(quick_mode=True)
    for task in TASKS:
        spec = factories[task]().spec()
        for loss in registry.names(spec):
            assert (task, loss, "bc") in cells and (task, loss, "dagger") in cells
    assert {(r["task"], r["policy"]) for r in data["references"]} == {
        (t, p) for t in TASKS for p in ("expert", "random")
    }
    two_way = [r for r in data["rows"] if r["task"] == "two_way"]
    assert all(
        abs(r["modes_above"] + r["modes_below"] + r["modes_neither"] - 1) < 1e-6 for r in two_way
    )
    # the report prints the two-way mode table with a measured verdict per loss
    assert "does the learner keep both of the expert's modes?" in proc.stdout
    assert re.search(r"\| diffusion \| bc \|.*\| (keeps|averages|collapses|mixed)", proc.stdout)
    # FrozenLake's references are exact: value iteration's policy and the uniform policy
    refs = {r["policy"]: r["score"] for r in data["references"] if r["task"] == "frozenlake"}
    assert refs["expert"] == success_probability(lake, expert_table, 100)
    assert refs["random"] == success_probability(lake, torch.full((16, 4), 0.25).double(), 100)


@pytest.mark.parametrize(("task", "loss"), [("two_way", "diffusion"), ("pendulum", "gaussian_nll")])
def test_cells_are_reproducible_from_their_seed(task, loss):
    a = loss_cell(task, loss, 3, True)
    b = loss_cell(task, loss, 3, True)
    strip = [{k: v for k, v in r.items() if k not in TIMING} for r in a]
    assert strip == [{k: v for k, v in r.items() if k not in TIMING} for r in b]
    c = loss_cell(task, loss, 4, True)
    assert strip != [{k: v for k, v in r.items() if k not in TIMING} for r in c]


def test_contributing_example_registers_a_loss_that_the_benchmark_runs():
    text = (ROOT / "CONTRIBUTING.md").read_text()
    block = re.search(
        r"<!-- BEGIN add-a-loss example -->\s*```python\n(.*?)```\s*<!-- END add-a-loss example -->",
        text,
        re.S,
    )
    assert block is not None, "CONTRIBUTING.md lost its 'Adding a loss' example"
    try:
        exec(compile(block.group(1), "CONTRIBUTING.md", "exec"), {})
        entry = registry.get("l1_l2")
        assert entry.applies_to(TaskSpec(action=TwoWay(None).spec().action, observation_dim=2))
        raw = run(tasks=["two_way"], losses=["l1_l2"], seeds=1, quick_mode=True)
        assert [(r["loss"], r["algorithm"]) for r in raw["rows"]] == [
            ("l1_l2", "bc"),
            ("l1_l2", "dagger"),
        ]
        assert 0.0 <= raw["rows"][0]["score"] <= 1.0
    finally:
        if "l1_l2" in registry.names():
            registry.unregister("l1_l2")


def test_quick_without_out_never_writes_the_committed_results(monkeypatch):
    import _report
    from _loss_functions.report import NAME

    written = []
    monkeypatch.setattr(_report, "update_readme", lambda *a: written.append(a))
    out = _report.destination(NAME, quick=True, out=None)
    assert out is not None and out.resolve() != _report.RESULTS.resolve()
    _report.write(NAME, {"rows": []}, "table", out_dir=out)
    assert (out / f"{NAME}.json").exists() and written == []
