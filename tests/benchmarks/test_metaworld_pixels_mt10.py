"""benchmarks/metaworld_pixels_mt10.py: the published numbers as the paper averages them,
the report's pooled rates and means, and its refusals."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

pytest.importorskip("metaworld")
from imitrl.envs.metaworld import MT10  # noqa: E402
from metaworld_pixels import beta_schedule, dagger_cell  # noqa: E402
from metaworld_pixels_mt10 import (  # noqa: E402
    PUBLISHED,
    QUICK,
    SOURCE,
    figure,
    main,
    markdown,
    pooled,
    series,
)


def test_the_published_table_covers_mt10_and_gives_the_papers_means():
    # the issue quotes the paper's MT10 means: Diffusion Policy 67.1%, DP3 75.5%; a
    # mistyped row would move them
    assert set(PUBLISHED) == set(MT10)
    for method, mean in (("Diffusion Policy", 67.1), ("DP3", 75.5)):
        assert sum(PUBLISHED[t][method][0] for t in MT10) / len(MT10) == pytest.approx(mean)
        assert all(0 <= PUBLISHED[t][method][1] <= 100 for t in MT10)


def _payload() -> dict:
    """reach: expert 10/10 a seed, BC 2 and 4, DAgger 5 and 7; push: expert 9 and 10, BC
    0, DAgger 1 and 0."""
    wins = {"reach-v3": ((10, 10), (2, 4), (5, 7)), "push-v3": ((9, 10), (0, 0), (1, 0))}
    cells = []
    for task, (expert, bc, dagger) in wins.items():
        for seed in (0, 1):
            cells.append({"task": task, "seed": seed, "rows": 1000,
                          "expert": {"success": expert[seed] / 10, "episodes": 10},
                          "bc": {"success": bc[seed] / 10, "episodes": 10},
                          "dagger": {"success": dagger[seed] / 10, "episodes": 10}})  # fmt: skip
    budget = {"seeds": 2, "demos": 10, "rounds": 3, "episodes": 3, "steps": 600, "eval": 10,
              "max_steps": 200, "beta_decay": 0.5}  # fmt: skip
    return {"budget": budget, "tasks": list(wins), "jobs": 2, "cells": cells,
            "published": {"source": SOURCE, "tasks": {t: PUBLISHED[t] for t in wins}},
            "wall_seconds": 600.0, "load_average_start": [1.0, 1.0, 1.0],
            "load_average_end": [2.0, 2.0, 2.0]}  # fmt: skip


def test_rates_pool_the_seeds_and_the_means_weigh_each_task_once(tmp_path):
    payload = _payload()
    reach = [c for c in payload["cells"] if c["task"] == "reach-v3"]
    assert pooled(reach, "bc") == (6, 20) and pooled(reach, "dagger") == (12, 20)
    text = markdown(payload, "x.png")
    assert "| reach-v3 | 1.00 [0.84, 1.00] (20/20) | 0.30 [0.15, 0.52] (6/20) |" in text
    assert "| push-v3 | 0.95 [0.76, 0.99] (19/20) | 0.00 [0.00, 0.16] (0/20) |" in text
    assert "0.18 ± 0.02 | 0.24 ± 0.01 |" in text  # reach's published row
    # means over the two tasks: expert (1 + 0.95) / 2, BC 0.15, DAgger (0.6 + 0.05) / 2;
    # published (18 + 30) / 2 and (24 + 51) / 2
    assert "| **mean over tasks** | 0.97 | 0.15 | 0.33 | 0.24 | 0.38 |" in text
    assert "wall time 10.0 min" in text and "Meta-World v3" in text
    assert "13 expert-driven episodes and 3 mixed ones" in text
    # 200-step episodes, as the published runs': the note does not say they differ there
    assert "Not the same env version, budget or evaluation." in text
    payload["budget"]["max_steps"] = 150
    assert "budget, episode length or evaluation" in markdown(payload, "x.png")
    assert figure(payload, tmp_path / "f.png").stat().st_size > 10_000


def test_the_figures_bars_are_the_rates_and_their_intervals():
    bars = series(_payload())
    y, lo, hi = bars["DAgger (here)"]
    assert y == [0.6, 0.05]  # 12/20 and 1/20
    assert lo[0] == pytest.approx(0.6 - 0.3866, abs=1e-3)  # Wilson 95% of 12/20
    assert hi[0] == pytest.approx(0.7812 - 0.6, abs=1e-3)
    y, lo, hi = bars["DP3 (Ze et al.)"]
    assert y == [0.24, 0.51] and lo == [0.01, 0.03] and hi == [0.01, 0.03]
    # a published bar stays within [0, 1]: door-open's 98 +- 3 reaches 1.00, not 1.01
    payload = _payload()
    payload["tasks"] = ["door-open-v3"]
    payload["cells"] = [{**c, "task": "door-open-v3"} for c in payload["cells"][:2]]
    payload["published"]["tasks"] = {"door-open-v3": PUBLISHED["door-open-v3"]}
    y, lo, hi = series(payload)["Diffusion Policy (Ze et al.)"]
    assert y == [0.98] and lo == [0.03] and hi == [pytest.approx(0.02)]


def test_a_cells_dagger_follows_the_budgets_beta_schedule():
    """Round 1 all expert, round 2 a fair coin (p = 0.5), as the budget names; a budget
    without one keeps beta 0 (the section's DAgger, metaworld_pixels.py's budgets)."""
    assert dagger_cell(0, {**QUICK, "rounds": 3}, task="reach-v3")["betas"] == [1.0, 0.5]
    without = {k: v for k, v in QUICK.items() if k != "beta_decay"}
    assert [beta_schedule(without)(k) for k in (1, 2, 3)] == [0.0, 0.0, 0.0]


def test_a_zero_job_count_is_refused(capsys):
    with pytest.raises(SystemExit):
        main(["--jobs", "0", "--out", "unused"])
    assert "--jobs must be >= 1, got 0" in capsys.readouterr().err
