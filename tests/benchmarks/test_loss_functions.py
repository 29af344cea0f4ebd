"""benchmarks/loss_functions.py (and its parts in benchmarks/_loss_functions/): smoke run,
reproducible cells, tasks from outside, aggregate report, CONTRIBUTING's example."""

from __future__ import annotations

import json
import os
import re
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from imitrl.learners import registry
from imitrl.tabular import success_probability
from tests import _child
from tests.benchmarks.test_benchmarks_smoke import committed

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

from _loss_functions.parse import parse_task  # noqa: E402
from _loss_functions.run import loss_cell, plan, run  # noqa: E402
from _loss_functions.tasks import TASKS, build, quick  # noqa: E402

TIMING = {"fit_seconds", "eval_seconds", "cell_seconds", "cell_cpu_seconds"}


@pytest.mark.slow  # test_benchmarks_smoke runs --quick in the default suite; this checks its cells
def test_quick_run_covers_every_loss_on_every_task(tmp_path, lake, expert_table):
    """``--quick`` without ``--out`` writes to a temporary directory, never the committed
    README or results, and covers every loss on every task."""
    before = committed()
    proc = _child.run(
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
    default = [t for t, d in TASKS.items() if d.in_default_run]
    for task in default:
        spec = build(TASKS[task], quick_mode=True).spec()
        for loss in registry.names(spec):
            assert (task, loss, "bc") in cells and (task, loss, "dagger") in cells
    assert {(r["task"], r["policy"]) for r in data["references"]} == {
        (t, p) for t in default for p in ("expert", "random")
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
    a = loss_cell(TASKS[task], loss, 3, True)
    b = loss_cell(TASKS[task], loss, 3, True)
    strip = [{k: v for k, v in r.items() if k not in TIMING} for r in a]
    assert strip == [{k: v for k, v in r.items() if k not in TIMING} for r in b]
    c = loss_cell(TASKS[task], loss, 4, True)
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
        assert entry.applies_to(build(TASKS["two_way"]).spec())
        raw = run(tasks=[TASKS["two_way"]], losses=["l1_l2"], seeds=1, quick_mode=True)
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


TINY_EXPERT = """
import torch


def act(obs):
    # Pendulum-v1: observation (cos, sin, angular velocity) -> torque in [-2, 2]
    return (-2.0 * obs[..., 1:2] - 0.5 * obs[..., 2:3]).clamp(-2.0, 2.0)
"""


def test_a_task_from_outside_runs_end_to_end(tmp_path, monkeypatch):
    """``--task`` with an expert given as module:function, on a tiny budget: BC and DAgger
    rows, references, the aggregate over the tasks MSE ran on, and the figures."""
    (tmp_path / "tiny_expert.py").write_text(TINY_EXPERT)
    monkeypatch.syspath_prepend(str(tmp_path))
    import loss_functions

    task = (
        "name=tiny,env=Pendulum-v1,expert=tiny_expert:act,expert_kind=callable,"
        "demos=1,rounds=2,episodes=1,steps=20,batch=32,hidden=16x16,eval=2,max_episode_steps=20"
    )
    out = tmp_path / "out"
    args = ["--task", task, "--losses", "mse", "flow_chunk", "--seeds", "2", "--reps", "50"]
    loss_functions.main([*args, "--out", str(out)])
    data = json.loads((out / "loss_functions.json").read_text())
    assert data["tasks"]["tiny"]["expert"] == "tiny_expert:act"
    assert data["protocols"]["tiny"]["bc"]["num_steps"] == 20
    cells = sorted((r["loss"], r["algorithm"], r["seed"]) for r in data["rows"])
    assert cells == sorted(
        (loss, a, s) for loss in ("mse", "flow_chunk") for a in ("bc", "dagger") for s in (0, 1)
    )
    assert all(r["task"] == "tiny" and len(r["returns"]) == 2 for r in data["rows"])
    assert {r["policy"] for r in data["references"]} == {"expert", "random"}
    entries = data["summary"]["aggregate"]["entries"]
    assert {(e["loss"], e["algorithm"]) for e in entries} == {
        (loss, a) for loss in ("mse", "flow_chunk") for a in ("bc", "dagger")
    }
    assert (out / "loss_functions_aggregate.png").stat().st_size > 10_000


def test_parse_task_reads_every_key_and_rejects_bad_ones():
    t = parse_task(
        "name=a,env=mypkg:Reach-v0,expert=mypkg:act,expert_kind=callable,demos=3,rounds=2,"
        "episodes=4,steps=100,batch=64,hidden=32x16,lr=0.01,eval=7,score=success,round_steps=20"
    )
    assert (t.name, t.env, t.expert, t.expert_kind, t.score) == (
        "a",
        "mypkg:Reach-v0",
        "mypkg:act",
        "callable",
        "success",
    )
    p = t.protocol
    assert (p.demo_episodes, p.rounds, p.episodes_per_round, p.eval_episodes) == (3, 2, 4, 7)
    assert (
        p.round_steps == 20 and parse_task("name=b,env=X,expert=m:f").protocol.round_steps is None
    )
    assert (p.bc.num_steps, p.bc.batch_size, p.learner.hidden, p.learner.lr) == (
        100,
        64,
        (32, 16),
        0.01,
    )
    # a dataset alone: BC only
    d = parse_task("name=d,env=Pendulum-v1,dataset=/data/x")
    assert d.dataset == "/data/x" and d.expert is None and d.protocol.rounds == 1
    for bad, match in (
        ("name=a,env=X,expert=m:f,colour=red", "unknown keys"),
        ("env=X,expert=m:f", "name= and env="),
        ("name=a,env=X", "expert .* or a dataset"),
        ("name=a,env=X,dataset=/d,rounds=3", "needs an expert"),
        ("name=a,env=X,expert=m:f,score=median", "score must be"),
        ("name=a,env=X,expert", "key=value"),
        ("name=a,env=X,expert=m:f,round_steps=0", "round_steps must be a positive"),
    ):
        with pytest.raises(ValueError, match=match):
            parse_task(bad)


def test_imitrl_bench_losses_runs_loss_functions(monkeypatch, tmp_path):
    from imitrl.jobs import bench

    monkeypatch.chdir(tmp_path)
    calls = []
    monkeypatch.setattr(
        bench.subprocess,
        "run",
        lambda cmd, check: calls.append(cmd) or type("P", (), {"returncode": 0}),
    )
    out = bench.run_bench(bench.BenchJob("losses", ("--task", "name=a,env=X,expert=m:f")))
    chosen = str(tmp_path / "results" / "bench" / "loss_functions")
    assert out == {"benchmark": "loss_functions", "returncode": 0, "out": chosen}
    assert calls[0][1].endswith("benchmarks/loss_functions.py")
    # issue 44: a run from outside writes under the current folder, never the committed results
    assert calls[0][2:] == ["--task", "name=a,env=X,expert=m:f", "--out", chosen]


def test_aggregate_takes_the_tasks_mse_ran_on_and_seeds_as_runs():
    from _loss_functions.aggregate import aggregate, score_matrices

    def row(task, loss, seed, algorithm, x):
        return {"task": task, "loss": loss, "seed": seed, "algorithm": algorithm, "normalized": x}

    rows = [row("lake", "cross_entropy", s, a, 0.5) for s in range(3) for a in ("bc", "dagger")]
    for t, task in enumerate(("a", "b")):
        for s in range(3):
            for a in ("bc", "dagger"):
                rows.append(row(task, "mse", s, a, 0.1 * s + t))
                rows.append(row(task, "flow", s, a, 0.1 * s + t + 0.05))
    tasks, scores = score_matrices(rows, ["mse", "flow", "cross_entropy"])
    assert tasks == ["a", "b"]  # the discrete task is left out: MSE did not run there
    assert set(scores) == {(loss, a) for loss in ("mse", "flow") for a in ("bc", "dagger")}
    np.testing.assert_allclose(scores[("mse", "bc")], [[0.0, 1.0], [0.1, 1.1], [0.2, 1.2]])
    agg = aggregate(rows, ["mse", "flow"], reps=50)
    flow = next(e for e in agg["entries"] if (e["loss"], e["algorithm"]) == ("flow", "bc"))
    # per task, flow beats mse in 6 of 9 seed pairs (s_flow >= s_mse), ties none: 6/9
    assert flow["p_improve"][0] == pytest.approx(6 / 9)
    assert "p_improve" not in next(e for e in agg["entries"] if e["loss"] == "mse")


def test_an_import_that_fails_is_one_line_naming_the_flag(capsys):
    """``--import mypkg.losses`` without ``examples`` on the path was a traceback."""
    import loss_functions

    with pytest.raises(SystemExit) as exit_:
        loss_functions.main(["--import", "no_such_pkg.losses", "--quick"])
    assert exit_.value.code == 2
    said = capsys.readouterr().err
    assert "--import no_such_pkg.losses: cannot import 'no_such_pkg.losses'" in said
    assert "Traceback" not in said


def test_no_applicable_loss_is_a_clear_error():
    """A discrete task with only continuous losses chosen has no cell: the run says so
    before any work (it used to fail later, drawing an empty figure)."""
    with pytest.raises(
        ValueError,
        match=r"--losses mse: applies to none of the tasks \['cartpole'\] \(it takes continuous",
    ):
        run(tasks=[TASKS["cartpole"]], losses=["mse"], seeds=1, quick_mode=True)


def test_relabel_rounds_warm_start_for_the_round_steps_and_act_keeps_its_batch():
    from imitrl.learners.act.entries import ACT_BATCH

    proto = quick(TASKS["two_way"].protocol)  # 5 BC steps, then 3 per relabel round
    assert TASKS["two_way"].protocol.round_steps is not None
    mse = {r["algorithm"]: r for r in loss_cell(TASKS["two_way"], "mse", 0, True)}
    assert mse["bc"]["fit_steps"] == proto.bc.num_steps
    assert mse["dagger"]["fit_steps"] == proto.bc.num_steps + (proto.rounds - 1) * 3
    assert mse["bc"]["fit_batch"] == proto.bc.batch_size
    act = loss_cell(TASKS["two_way"], "act", 0, True)
    assert {r["fit_batch"] for r in act} == {ACT_BATCH}


def test_runs_of_disjoint_cells_merge_into_the_run_of_all_of_them():
    from _loss_functions.merge import merge

    def raw(losses, seeds=1):
        out = run(tasks=[TASKS["corridor"]], losses=losses, seeds=seeds, quick_mode=True)
        out["wall_seconds"] = 1.0
        out["config"] = {"seeds": seeds, "tasks": ["corridor"], "losses": losses, "jobs": 1,
                         "quick": True, "command": f"run {losses}"}  # fmt: skip
        return out

    def cells(rows):
        return sorted(tuple(sorted((k, v) for k, v in r.items() if k not in TIMING)) for r in rows)

    both = raw(["mse", "l1"])
    merged = merge([raw(["mse"]), raw(["l1"])])
    assert cells(merged["rows"]) == cells(both["rows"])  # the same digits, cell for cell
    assert len(merged["references"]) == len(both["references"])
    assert [p["command"] for p in merged["config"]["parts"]] == ["run ['mse']", "run ['l1']"]
    with pytest.raises(ValueError, match="more than one run"):
        merge([raw(["mse"]), raw(["mse"])])
    with pytest.raises(ValueError, match="different numbers of seeds"):
        merge([raw(["mse"]), raw(["l1"], seeds=2)])
    changed = raw(["l1"])
    changed["references"][0]["score"] += 1
    with pytest.raises(ValueError, match="reference"):
        merge([raw(["mse"]), changed])
    # a hostile review: a part whose config said 2 seeds and whose rows held 1 merged
    claims = raw(["l1"])
    claims["config"]["seeds"] = 2
    with pytest.raises(ValueError, match=r"'l1', 'bc'\) has seeds \[0\]; the runs' configs say 2"):
        merge([raw(["mse"], seeds=2), claims])


def test_a_requested_loss_that_does_not_apply_is_named_never_dropped(capsys):
    """Issue 44: a requested loss that did not apply to a task was dropped without a word,
    and a typo in --losses ended in a traceback."""
    tasks = [TASKS["frozenlake"], TASKS["pendulum"]]
    cells, refs = plan(tasks, ["mse", "cross_entropy"], [0, 1], True)
    assert {(c[0].name, c[1]) for c in cells} == {
        ("pendulum", "mse"),
        ("frozenlake", "cross_entropy"),
    }
    assert len(cells) == 4 and len(refs) == 4
    err = capsys.readouterr().err
    assert "mse does not apply to ['frozenlake']: runs on ['pendulum']" in err
    assert "cross_entropy does not apply to ['pendulum']" in err
    with pytest.raises(
        ValueError, match=r"--losses mse: applies to none of the tasks \['frozenlake'\]"
    ):
        plan([TASKS["frozenlake"]], ["mse"], [0], True)
    typo = _child.run(
        [sys.executable, "loss_functions.py", "--quick", "--losses", "mes"],
        cwd=ROOT / "benchmarks", capture_output=True, text=True,
    )  # fmt: skip
    assert typo.returncode != 0 and "Traceback" not in typo.stderr
    assert "--losses: unknown loss 'mes'; registered:" in typo.stderr
