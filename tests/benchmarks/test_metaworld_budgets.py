"""benchmarks/metaworld_budgets.py and its report: a ladder of fit steps per loss as cells
with one reference a task and seed, the curve of a fit, and the report's numbers."""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

pytest.importorskip("metaworld")
from _loss_functions.run import window_means  # noqa: E402
from _metaworld_budgets_report import late_drop, markdown  # noqa: E402
from imitrl.learners import registry  # noqa: E402
from metaworld_budgets import BUDGETS, PROTOCOL, RECIPES, chosen, main, merge, plan  # noqa: E402


def test_every_rung_is_a_cell_and_every_task_and_seed_one_reference():
    budgets = chosen(("mse", "diffusion_unet"), None)
    cells, refs = plan(budgets, ("reach-v3", "push-v3"), range(2), False)
    rungs = sum(len(BUDGETS[loss].steps) for loss in ("mse", "diffusion_unet"))
    assert len(cells) == 2 * rungs * 2 and len(refs) == 2 * 2
    steps = {(d.name, loss, seed): d.protocol.bc for d, loss, seed, _ in cells}
    bc = steps[("push-v3/diffusion_unet/2000", "diffusion_unet", 1)]
    assert (bc.num_steps, bc.batch_size) == (2000, BUDGETS["diffusion_unet"].batch)
    assert {d.name for d, _, _ in refs} == {"reach-v3", "push-v3"}
    # BC alone, each fit's curve kept; the references evaluate as the cells do
    for d, _, _, _ in cells:
        assert d.protocol.rounds == 1 and d.protocol.curve_points > 0
        assert d.protocol.eval_episodes == refs[0][0].protocol.eval_episodes


def test_a_fit_curve_is_window_means():
    losses = torch.tensor([4.0, 2.0, 3.0, 1.0, 1.0, 1.0, 0.5])
    assert window_means(losses, 3) == [3.0, 1.0, 0.75]  # windows of 3, 2 and 2 steps
    assert window_means(losses[:2], 40) == [4.0, 2.0]  # fewer steps than points


def test_late_drop_compares_the_last_fifth_with_the_fifth_before():
    assert late_drop([10, 8, 6, 4, 2] * 2) == pytest.approx(1 - 3 / 7)  # (4+2)/(8+6)
    assert late_drop([5.0] * 10) == 0.0


def _payload() -> dict:
    """Two tasks, 2 seeds, 5 episodes; mse 320: 3 a seed, mse 2000 and diffusion_unet 2000:
    5; diffusion_unet 500: 1; the expert 5 everywhere."""
    rows = []
    wins = {
        ("mse", 320): 3,
        ("mse", 2000): 5,
        ("diffusion_unet", 500): 1,
        ("diffusion_unet", 2000): 5,
    }
    for task in ("reach-v3", "push-v3"):
        for (loss, steps), k in wins.items():
            for seed in (0, 1):
                rows.append({"task": f"{task}/{loss}/{steps}", "loss": loss, "seed": seed,
                             "algorithm": "bc", "successes": k, "episodes": 5, "score": k / 5,
                             "fit_seconds": steps / 100, "fit_steps": steps,
                             "fit_batch": BUDGETS[loss].batch,
                             "loss_curve": [1.0, 0.8, 0.6, 0.5, 0.4]})  # fmt: skip
    refs = [{"task": t, "policy": "expert", "seed": s, "successes": 5, "episodes": 5, "score": 1.0}
            for t in ("reach-v3", "push-v3") for s in (0, 1)]  # fmt: skip
    from dataclasses import asdict

    config = {"tasks": ["reach-v3", "push-v3"], "losses": ["mse", "diffusion_unet"], "seeds": 2,
              "jobs": 2, "quick": False, "protocol": asdict(PROTOCOL),
              "budgets": {"mse": {"steps": [320, 2000], "batch": 256},
                          "diffusion_unet": {"steps": [500, 2000], "batch": 64}}}  # fmt: skip
    return {"config": config, "rows": rows, "references": refs, "wall_seconds": 120.0,
            "load_average_start": [1.0], "load_average_end": [1.5]}  # fmt: skip


def test_the_report_gives_each_rung_its_success_time_and_late_fall():
    text = markdown(_payload(), "f.png")
    # mse 320: 12/20 pooled; IQM of 0.6 everywhere is 0.6 with a degenerate interval
    assert "| mse | 320 x 256 | 3.2 | 20.0% | 0.60 [0.39, 0.78] | 0.60 [0.60, 0.60] |" in text
    assert (
        "| diffusion_unet | 500 x 64 | 5.0 | 20.0% | 0.20 [0.08, 0.42] | 0.20 [0.20, 0.20] |"
        in text
    )
    assert (
        "| diffusion_unet | 2000 x 64 | 20.0 | 20.0% | 1.00 [0.84, 1.00] | 1.00 [1.00, 1.00] |"
        in text
    )
    # the top rung paired with each of mse's: diffusion_unet 2000 - mse 2000 = 0 on every
    # pair, and - mse 320 = 1.0 - 0.6 = 0.4 on every pair
    assert "| diffusion_unet 2000 | mse 2000 | 4 | 0.00 [0.00, 0.00] | 0 / 0 of 2 |" in text
    assert "| diffusion_unet 2000 | mse 320 | 4 | 0.40 [0.40, 0.40] | 2 / 0 of 2 |" in text
    assert "| reach-v3 | 0.60 [0.31, 0.83] | 1.00 [0.72, 1.00] | 0.20" in text


def test_bad_counts_are_one_line_before_anything_runs(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--seeds", "0"])
    assert exit_.value.code == 2 and "--seeds must be >= 1, got 0" in capsys.readouterr().err


def test_a_negative_curve_length_is_refused():
    from dataclasses import replace

    with pytest.raises(ValueError, match="curve_points must be >= 0, got -1"):
        replace(PROTOCOL, curve_points=-1)


def test_steps_keep_the_named_rungs_alone_and_refuse_a_loss_left_without_one():
    budgets = chosen(("diffusion_unet",), (4000,))
    assert budgets["diffusion_unet"].steps == (4000,)
    cells, _ = plan(budgets, ("reach-v3",), range(2), False)
    assert {d.name for d, _, _, _ in cells} == {"reach-v3/diffusion_unet/4000"}
    with pytest.raises(ValueError, match=r"mse has no rung in --steps \[4000\]"):
        chosen(("mse", "diffusion_unet"), (4000,))


def _part(rungs: dict[tuple[str, int], int], wall: float) -> dict:
    """_payload's shape for ``rungs`` alone."""
    whole = _payload()
    keep = {f"{t}/{loss}/{steps}" for t in whole["config"]["tasks"] for loss, steps in rungs}
    budgets: dict = {}
    for loss, steps in rungs:
        budgets.setdefault(loss, {"steps": [], "batch": BUDGETS[loss].batch})["steps"].append(steps)
    return {**whole, "rows": [r for r in whole["rows"] if r["task"] in keep],
            "config": {**whole["config"], "budgets": budgets, "losses": list(budgets)},
            "wall_seconds": wall, "command": f"metaworld_budgets.py part {wall} --out /tmp/x"}  # fmt: skip


def test_runs_of_disjoint_rungs_merge_into_the_report_of_one_run():
    whole = _payload()
    a = _part({("mse", 320): 0, ("mse", 2000): 0, ("diffusion_unet", 500): 0}, 60.0)
    b = _part({("diffusion_unet", 2000): 0}, 30.0)
    merged = merge([a, b])
    assert merged["config"]["budgets"] == whole["config"]["budgets"]
    assert merged["config"]["losses"] == ["mse", "diffusion_unet"]
    assert merged["wall_seconds"] == 90.0 and len(merged["references"]) == 4
    tables = markdown(whole, "f.png").split("\n\n", 1)[1]
    assert markdown(merged, "f.png").split("\n\n", 1)[1] == tables  # every number the same
    said = markdown(merged, "f.png")  # each part's command, without its --out folder
    assert "metaworld_budgets.py part 30.0: 0.5 min with 2 process(es)" in said
    assert "/tmp/x" not in said
    with pytest.raises(ValueError, match="repeats the cell"):
        merge([a, a])
    other = {**b, "references": [{**b["references"][0], "successes": 4}, *b["references"][1:]]}
    with pytest.raises(ValueError, match=r"another .* reference: the code changed"):
        merge([a, other])
    with pytest.raises(ValueError, match="another seeds"):
        merge([a, {**b, "config": {**b["config"], "seeds": 3}}])


def _one_task(part: dict, task: str) -> dict:
    """``part`` run with ``--tasks task`` alone."""
    return {**part, "config": {**part["config"], "tasks": [task]},
            "rows": [r for r in part["rows"] if r["task"].startswith(f"{task}/")],
            "references": [r for r in part["references"] if r["task"] == task]}  # fmt: skip


def test_parts_that_split_the_tasks_merge_and_a_rung_missing_a_task_is_refused():
    whole = _payload()
    a = _part({("mse", 320): 0, ("mse", 2000): 0, ("diffusion_unet", 500): 0}, 60.0)
    b = _part({("diffusion_unet", 2000): 0}, 30.0)
    reach, push = _one_task(b, "reach-v3"), _one_task(b, "push-v3")
    merged = merge([a, push, reach])  # in any order: the tasks keep MT10's
    assert merged["config"]["tasks"] == ["reach-v3", "push-v3"]
    tables = markdown(whole, "f.png").split("\n\n", 1)[1]
    assert markdown(merged, "f.png").split("\n\n", 1)[1] == tables
    with pytest.raises(ValueError, match=r"no run holds push-v3/diffusion_unet/2000 at seed"):
        merge([a, reach])
    with pytest.raises(ValueError, match="tasks outside MT10"):
        merge([a, {**reach, "config": {**reach["config"], "tasks": ["not-a-task-v3"]}}])


def test_a_merge_merged_again_names_the_runs_it_came_from():
    a = _part({("mse", 320): 0, ("mse", 2000): 0}, 60.0)
    b = _part({("diffusion_unet", 500): 0}, 30.0)
    c = _part({("diffusion_unet", 2000): 0}, 12.0)
    again = merge([{**merge([a, b]), "source": "first.json"}, c])
    assert len(again["merged_from"]) == 3 and "first.json" not in str(again["merged_from"])
    assert again["merged_from"][2].startswith("metaworld_budgets.py part 12.0: 0.2 min")
    assert again["wall_seconds"] == 102.0


def test_files_that_do_not_join_are_one_line_and_nothing_is_written(tmp_path, capsys):
    import json

    part = tmp_path / "a.json"
    part.write_text(json.dumps(_part({("mse", 320): 0}, 60.0)))
    with pytest.raises(SystemExit) as exit_:
        main(["--merge", str(part), str(part), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and "--merge: run 1 repeats the cell" in err
    assert "Traceback" not in err and not (tmp_path / "out").exists()


def test_the_meta_world_recipe_is_diffusion_unet_at_dp3s_horizons():
    """``diffusion_unet_mw``: the registry's Diffusion Policy predicting 4 actions from 2
    observations and executing 3 (DP3's Meta-World config), every other setting its own;
    a worker importing the module again registers nothing twice."""
    import importlib

    from torchrl.data import Bounded

    import _metaworld_recipes as recipes
    from imitrl.learners import TaskSpec, build, registry
    from imitrl.learners.diffusion_unet.entries import DIFFUSION_UNET

    try:
        importlib.reload(recipes)  # a second import registers nothing twice
        assert recipes.NAME in BUDGETS and RECIPES == recipes.__name__
        want = replace(DIFFUSION_UNET, horizon=4, action_steps=3)
        assert recipes.DIFFUSION_UNET_MW == want
        task = TaskSpec(action=Bounded(-1.0, 1.0, shape=(4,)), observation_dim=39)
        mw, plain = build(recipes.NAME, task, seed=0), build("diffusion_unet", task, seed=0)
        assert (mw.horizon, mw.history) == (4, 2) and (plain.horizon, plain.history) == (16, 2)
        assert mw.policy.execution.execute == 3
        count = sum(p.numel() for p in plain.parameters())
        assert sum(p.numel() for p in mw.parameters()) == count
    finally:  # the rest of the suite sees the library's registry
        registry.unregister(recipes.NAME)


def test_importing_the_script_registers_nothing():
    """Importing ``metaworld_budgets`` (as these tests and a merge do) registered the
    benchmark's entry for the whole process: the registry's name lists and every test
    parametrised over its entries saw it."""
    assert "diffusion_unet_mw" not in registry.names()
