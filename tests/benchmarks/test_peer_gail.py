"""The GAIL peer harness: each protocol's settings, the plan of processes (plain scripts,
the collector trick and the shipped command as rows of their own), the command's flags
as imitrl's own parser reads them, and every ratio labelled with its protocol and process."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

import _report  # noqa: E402
import peer_gail  # noqa: E402
from _peer_imitation import runs  # noqa: E402
from _peer_imitation.gail_report import markdown, summarise  # noqa: E402
from _peer_imitation.gail_tasks import (  # noqa: E402
    EVAL_SEED,
    IMITATION,
    IMITATION_AIRL,
    IMITRL,
    IMITRL_AIRL,
    LEARNER_HIDDEN,
    TASKS,
    command_flags,
    quick,
    settings,
)


def test_own_gives_each_library_its_settings_and_matched_gives_imitrl_imitations():
    cart = TASKS["cartpole"]
    assert settings(cart, "imitation", "own") == IMITATION == settings(cart, "imitation", "matched")
    assert settings(cart, "imitrl", "own") == IMITRL
    matched = settings(cart, "imitrl", "matched")
    assert {k: matched[k] for k in IMITRL} == {k: IMITATION[k] for k in IMITRL}
    # a task's lr and gamma bind both libraries under both protocols
    pend = TASKS["pendulum"]
    for library in ("imitrl", "imitation"):
        for protocol in ("own", "matched"):
            s = settings(pend, library, protocol)
            assert (s["lr"], s["gamma"]) == (1e-3, 0.9)
    with pytest.raises(ValueError, match="protocol must be one of"):
        settings(cart, "imitrl", "beta0")
    # equal env steps: whole rounds on both sides, n_steps = rollout_steps / lanes
    for task in TASKS.values():
        assert task.total_steps % task.rollout_steps == 0 and task.rollout_steps % task.lanes == 0


def test_airl_rows_take_imitations_airl_tutorial_and_imitrls_airl_defaults():
    cart, pend = TASKS["cartpole_airl"], TASKS["pendulum_airl"]
    assert cart.method == pend.method == "airl" and TASKS["cartpole"].method == "gail"
    assert settings(cart, "imitation", "own") == IMITATION_AIRL
    assert settings(cart, "imitation", "matched") == IMITATION_AIRL
    assert settings(cart, "imitrl", "own") == IMITRL_AIRL
    assert (IMITATION_AIRL["clip_epsilon"], IMITATION_AIRL["discriminator_updates"]) == (0.1, 16)
    matched = settings(cart, "imitrl", "matched")  # imitation's numbers, imitrl's own w
    assert {k: matched[k] for k in IMITATION_AIRL} == IMITATION_AIRL
    assert matched["entropy_weight"] == IMITRL_AIRL["entropy_weight"] == 1.0
    # Pendulum: the task's lr, gamma and imitrl's recommended w = 0 under both protocols
    for protocol in ("own", "matched"):
        s = settings(pend, "imitrl", protocol)
        assert (s["lr"], s["gamma"], s["entropy_weight"]) == (1e-3, 0.9, 0.0)
        assert "entropy_weight" not in settings(pend, "imitation", protocol)
    # imitation's demonstration batch fits in the demonstrations' transitions
    assert pend.demo_episodes * 200 >= IMITATION_AIRL["discriminator_batch"]


def _run(library, protocol, seed, wall, ret, process=None):
    phases = {"imports": 1.0, "setup": 0.5, "train": wall - 2.0, "evaluation": 0.5,
              "in_process": wall - (0.25 if library == "imitrl" else 1.25)}  # fmt: skip
    if process == "command":  # the shipped command reports its job's clock alone
        phases = {"job": wall - 3.0}
    run = {"task": "cartpole", "library": library, "protocol": protocol, "seed": seed,
           "wall": wall, "phases": phases, "returns": {"final": ret}}  # fmt: skip
    return run if process is None else {**run, "process": process}


def test_every_ratio_is_labelled_with_its_protocol_and_judged_per_seed():
    runs = [
        _run("imitrl", "own", 0, 8.0, 500.0), _run("imitation", None, 0, 20.0, 480.0),
        _run("imitrl", "matched", 0, 12.0, 470.0),
        _run("imitrl", "own", 1, 9.0, 500.0), _run("imitation", None, 1, 20.0, 500.0),
        _run("imitrl", "matched", 1, 11.0, 500.0),
    ]  # fmt: skip
    summary = summarise(runs)["cartpole"]
    assert set(summary) == {"own", "matched"}
    assert summary["own"]["phases"]["wall"]["ratios"] == [0.4, 0.45]
    assert summary["own"]["wall_met"] is True and summary["own"]["returns_met"] is True
    assert summary["matched"]["phases"]["wall"]["ratios"] == [0.6, 0.55]
    assert summary["matched"]["wall_met"] is False
    assert summary["matched"]["returns_met"] is False  # 470 < 480 on seed 0
    raw = {"config": {"seeds": 2}, "imitrl_versions": {}, "peer_versions": None,
           "summary": summarise(runs), "wall_seconds": 1.0}  # fmt: skip
    lines = [line for line in markdown(raw).splitlines() if line.startswith("| cartpole")]
    # the headline (own, the plain script) in bold
    assert [line.split("|")[2].strip() for line in lines] == ["**own**", "matched"]
    assert "0.40 / 0.45" in lines[0] and "**no**" in lines[1]
    # the process outside the child's clock (start and exit), each side's own
    assert summary["own"]["phases"]["outside"]["imitrl"] == [0.25, 0.25]
    assert summary["own"]["phases"]["outside"]["imitation"] == [1.25, 1.25]
    assert "| 0.2 / 0.2 | 1.2 / 1.2 |" in lines[0]
    # the median and every seed, each judged in its own column
    uneven = [_run("imitrl", "own", s, w, 500.0) for s, w in enumerate((8.0, 9.0, 11.0))]
    uneven += [_run("imitation", None, s, 20.0, 480.0) for s in range(3)]
    own = summarise(uneven)["cartpole"]["own"]
    assert own["wall_met"] is True and own["wall_met_each_seed"] is False  # 0.55 on seed 2
    assert summary["own"]["wall_met_each_seed"] is True
    raw = {"config": {"seeds": 3, "bytecode": "imitrl's modules byte-compiled"},
           "imitrl_versions": {}, "peer_versions": None, "summary": summarise(uneven),
           "wall_seconds": 1.0}  # fmt: skip
    text = markdown(raw)
    assert "Bytecode: imitrl's modules byte-compiled." in text
    (line,) = [x for x in text.splitlines() if x.startswith("| cartpole | **own**")]
    assert line.split("|")[-4:-1] == [" yes ", " **no** ", " yes "]


def test_the_plan_runs_plain_scripts_the_collector_trick_and_the_command():
    assert peer_gail.PLAN == (
        ("imitrl", "own", "plain"),
        ("imitation", None, "plain"),
        ("imitrl", "matched", "plain"),
        ("imitrl", "own", "collector_trick"),
        ("imitrl", "own", "command"),
    )
    assert peer_gail.plan(False) == peer_gail.PLAN
    quick_plan = peer_gail.plan(True)  # imitrl's side alone, its command included
    assert [job[0] for job in quick_plan] == ["imitrl"] * 4
    assert ("imitrl", "own", "command") in quick_plan
    spec = TASKS["cartpole"].spec(0, "imitrl", "own", "collector_trick")
    assert spec["process"] == "collector_trick" and spec["learner_hidden"] == [64, 64]
    with pytest.raises(ValueError, match="process must be one of"):
        TASKS["cartpole"].spec(0, "imitrl", "own", "command")  # the command reads no spec


def test_the_trick_and_the_command_are_rows_of_their_own_beside_the_headline():
    runs_ = []
    for seed, peer in enumerate((20.0, 10.0)):
        runs_ += [
            _run("imitrl", "own", seed, 8.0, 500.0, "plain"),
            _run("imitation", None, seed, peer, 480.0, "plain"),
            _run("imitrl", "matched", seed, 12.0, 470.0, "plain"),
            _run("imitrl", "own", seed, 6.0, 500.0, "collector_trick"),
            _run("imitrl", "own", seed, 16.0, 490.0, "command"),
        ]
    summary = summarise(runs_)["cartpole"]
    assert list(summary) == ["own", "matched", "own, collector trick", "own, command as shipped"]
    assert [k for k, v in summary.items() if v["headline"]] == ["own"]
    assert summary["own"]["phases"]["wall"]["ratios"] == [0.4, 0.8]
    trick, command = summary["own, collector trick"], summary["own, command as shipped"]
    assert trick["phases"]["wall"]["ratios"] == [0.3, 0.6]  # over imitation's same seed
    assert command["phases"]["wall"]["ratios"] == [0.8, 1.6]
    assert (
        command["phases"]["train"]["ratios"] == [] and command["phases"]["outside"]["imitrl"] == []
    )
    assert command["returns_met"] is True and command["wall_met"] is False
    raw = {"config": {"seeds": 2, "plan": [list(j) for j in peer_gail.PLAN]},
           "imitrl_versions": {}, "peer_versions": None, "summary": summarise(runs_),
           "wall_seconds": 1.0}  # fmt: skip
    text = markdown(raw)
    lines = [line for line in text.splitlines() if line.startswith("| cartpole")]
    names = [line.split("|")[2].strip() for line in lines]
    assert names == ["**own**", "matched", "own, collector trick", "own, command as shipped"]
    assert "| 0.80 / 1.60 | 1.20 | - | - | 1.2 / 1.2 |" in lines[3]  # no phases, no start + exit
    assert "5 fresh processes in turn" in text and "the shipped `imitrl gail`" in text
    assert "plain Python script" in text


def test_results_without_a_process_read_as_plain_scripts():
    runs_ = [_run("imitrl", "own", 0, 8.0, 500.0), _run("imitation", None, 0, 20.0, 480.0)]
    summary = summarise(runs_)["cartpole"]
    assert list(summary) == ["own"] and summary["own"]["process"] == "plain"
    raw = {"config": {"seeds": 1}, "imitrl_versions": {}, "peer_versions": None,
           "summary": summarise(runs_), "wall_seconds": 1.0}  # fmt: skip
    text = markdown(raw)  # a results file of before: what its children did, not "plain"
    assert "three fresh processes in turn" in text and "predate issue 43" in text
    assert "plain Python script" not in text


@pytest.mark.parametrize("name", list(TASKS))
def test_the_command_flags_are_the_own_scripts_settings_as_imitrls_parser_reads_them(name):
    """``imitrl gail`` / ``imitrl airl``'s own parser takes every flag of
    ``command_flags`` (its ``ValueError`` checks included) and describes the training
    config the ``own`` script builds, the same learner, lanes, demonstrations and
    evaluation."""
    from _peer_imitation.gail_imitrl import algorithm_config
    from imitrl.cli import COMMANDS, build_parser
    from imitrl.cli.flags import config_from_args

    for task in (TASKS[name], quick(TASKS[name])):
        argv = command_flags(task, 3, "/tmp/out")
        assert argv[0] == task.method
        args = build_parser(flags_for=[argv[0]]).parse_args(argv)
        job = config_from_args(COMMANDS[argv[0]].config, args)
        spec = task.spec(3, "imitrl", "own")
        assert job.algorithm_config() == algorithm_config(spec)
        s = settings(task, "imitrl", "own")
        assert (job.env, job.num_envs, job.demos) == (task.env_id, task.lanes, task.demo_episodes)
        assert (job.lr, job.hidden, job.loss) == (s["lr"], LEARNER_HIDDEN, "default")
        assert (job.eval_episodes, job.eval_seed) == (task.eval_episodes, EVAL_SEED + 3)
        assert (job.eval_every, job.device, job.progress, args.threads) == (0, "cpu", False, 1)
        assert str(job.out) == "/tmp/out"


def test_a_full_run_without_a_peer_python_stops_before_anything_is_written(monkeypatch, tmp_path):
    monkeypatch.delenv(runs.PEER_ENV, raising=False)
    monkeypatch.setattr(peer_gail, "run_jobs", lambda *a: pytest.fail("ran without a peer"))
    with pytest.raises(SystemExit, match=r"--peer-python.*IMITRL_PEER_PYTHON"):
        peer_gail.main(["--out", str(tmp_path / "out")])
    assert not (tmp_path / "out").exists()
    assert peer_gail.build_parser().parse_args([]).peer_python is None
    assert "/work/" not in peer_gail.__doc__


def test_the_command_row_runs_the_shipped_command_and_reads_its_results(tmp_path):
    """The ``command`` row is ``imitrl gail ...`` as a whole process of its own: its wall
    time measured around the command, its return the one its results.json records, and
    the run it records the ``own`` settings."""
    import json

    task = quick(TASKS["pendulum"])
    row = peer_gail.run_one(
        task, 1, "imitrl", "own", "command", peer_python=None,
        imitrl_python=sys.executable, workdir=tmp_path, timeout=600,
    )  # fmt: skip
    out = tmp_path / "pendulum-command-1"
    results = json.loads((out / "results.json").read_text())
    assert row["returns"]["final"] == results["learner"]["mean_return"]
    assert row["wall"] > row["phases"]["job"] == results["seconds"] > 0
    assert row["env_steps"] == task.total_steps and row["demo_rows"] == 200
    assert (row["process"], row["protocol"], row["library"]) == ("command", "own", "imitrl")
    shipped = _report.portable_args(runs.imitrl_command(sys.executable))
    assert row["argv"][: len(shipped)] == shipped  # recorded without one machine's paths
    assert not any(a.startswith("/") for a in row["argv"])
    config = json.loads((out / "config.json").read_text())["config"]
    s = settings(task, "imitrl", "own")
    assert (config["lr"], config["gamma"], config["seed"]) == (s["lr"], s["gamma"], 1)
    assert (config["num_envs"], config["total_steps"]) == (task.lanes, task.total_steps)
    assert config["eval_seed"] == EVAL_SEED + 1 and config["hidden"] == list(LEARNER_HIDDEN)
