"""benchmarks/peer_imitation.py (parts in benchmarks/_peer_imitation/): the plan of
processes (plain scripts, and the collector trick as a row of its own), the summary's
ratios and medians, the tables with one library only, the peer's python (a flag or
``$IMITRL_PEER_PYTHON``, no default path), and - where ``$IMITRL_PEER_PYTHON`` names the
peer's venv - the peer script's experts against imitrl's. test_benchmarks_smoke runs
``--quick``."""

from __future__ import annotations

import os
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

from _peer_imitation import runs  # noqa: E402
from _peer_imitation.report import markdown, summarise  # noqa: E402
from _peer_imitation.tasks import PROCESSES, TASKS, quick  # noqa: E402

PEER_PYTHON = os.environ.get(runs.PEER_ENV)
"""the peer's venv's python where the environment names one (peer_imitation.py's docstring)"""


def fake_run(task, library, seed, wall, bc, final, tables=None):
    """A child's report: every phase ``wall / 10`` except imports (``wall / 2``)."""
    phases = {
        k: wall / 10
        for k in (
            "setup",
            "bc",
            "dagger",
            "dagger_collect",
            "dagger_fit",
            "evaluation",
            "in_process",
        )
    }
    phases["imports"] = wall / 2
    run = {
        "task": task,
        "library": library,
        "seed": seed,
        "wall": wall,
        "phases": phases,
        "returns": {"bc": bc, "final": final},
        "greedy_tables": tables or {},
        "rows": 10,
    }
    return run


def test_summary_pairs_seeds_and_takes_medians_of_ratios():
    runs_ = []
    for seed, (ours, theirs) in enumerate([(1.0, 4.0), (2.0, 4.0), (3.0, 2.0)]):
        runs_.append(fake_run("cartpole", "imitrl", seed, ours, 20.0, 500.0))
        runs_.append(
            fake_run("cartpole", "imitation", seed, theirs, 30.0, [500.0, 480.0, 499.0][seed])
        )
    s = summarise(runs_, {"cartpole": [500.0] * 3})["cartpole"]
    wall = s["phases"]["wall"]
    assert wall["ratios"] == [0.25, 0.5, 1.5]
    assert wall["median_ratio"] == 0.5 and wall["met"] is True  # target <= 0.5
    assert wall["median_seconds"] == {"imitrl": 2.0, "imitation": 4.0}
    bc = s["phases"]["bc"]
    assert bc["median_ratio"] == pytest.approx(0.5) and bc["met"] is False  # target <= 0.33
    assert s["phases"]["imports"]["met"] is None  # no target
    assert s["returns"]["imitation"]["final"] == [500.0, 480.0, 499.0]
    assert s["returns_met"] is True  # median 500 >= median 499


def test_frozenlake_is_judged_on_exact_success_not_the_sampled_return():
    runs_ = []
    for seed in range(3):
        ours = fake_run("frozenlake", "imitrl", seed, 1.0, 0.2, 0.80)  # lucky samples
        theirs = fake_run("frozenlake", "imitation", seed, 1.0, 0.2, 0.70)
        ours["exact_success"] = {"bc": 0.19, "final": 0.71}
        theirs["exact_success"] = {"bc": 0.19, "final": 0.7298}
        runs_ += [ours, theirs]
    s = summarise(runs_, {"frozenlake": [0.7298] * 3})["frozenlake"]
    assert s["returns_met"] is False


def test_tables_render_with_imitrl_alone():
    """``--quick`` runs one library: ratios and the peer's columns read ``-``."""
    runs_ = [fake_run("pendulum", "imitrl", 0, 3.0, -900.0, -400.0)]
    raw = {
        "config": {"seeds": 1},
        "summary": summarise(runs_, {"pendulum": [-150.0]}),
        "wall_seconds": 3.0,
        "imitrl_versions": {"torch": "2.13.0"},
        "peer_versions": None,
    }
    text = markdown(raw)
    assert "| pendulum | whole process | 3.00 | - | - | - | <= 0.5 |  |" in text
    assert "| pendulum | -150.0 | -900.0 | - | -400.0 | - |  |" in text


@pytest.mark.slow  # a process in the peer's venv; peer_imitation.py runs this check first
@pytest.mark.skipif(
    not PEER_PYTHON or not Path(PEER_PYTHON).exists(),
    reason=f"no peer venv: set {runs.PEER_ENV} (see peer_imitation.py)",
)
def test_peer_experts_label_like_imitrl():
    report = runs.check_experts(runs.peer_python(None), timeout=600)
    assert set(report) == {t.env_id for t in TASKS.values()}
    assert report["CartPole-v1"]["max_difference"] == 0
    assert report["FrozenLake-v1"]["max_difference"] == 0
    assert report["Pendulum-v1"]["max_difference"] <= 1e-5


def test_each_protocol_is_a_row_of_its_own_and_the_spec_says_what_it_runs():
    """``own`` and ``matched`` runs of one task never pair across protocols; the spec
    carries the protocol and each library's evaluation lanes (imitation's 50 as its
    scripts evaluate; imitrl's 16)."""
    runs_ = []
    for protocol, (ours, theirs) in (("own", (1.0, 4.0)), ("matched", (3.0, 2.0))):
        for library, wall in (("imitrl", ours), ("imitation", theirs)):
            run = fake_run("pendulum", library, 0, wall, -900.0, -300.0)
            runs_.append({**run, "protocol": protocol})
    s = summarise(runs_, {"pendulum": [-150.0]})
    assert list(s) == ["pendulum, own", "pendulum, matched"]
    assert s["pendulum, own"]["phases"]["wall"]["ratios"] == [0.25]
    assert s["pendulum, matched"]["phases"]["wall"]["ratios"] == [1.5]
    assert s["pendulum, matched"]["expert"] == [-150.0]
    spec = TASKS["cartpole"].spec(2, "matched")
    assert spec["protocol"] == "matched" and spec["eval_lanes"] == {"imitrl": 16, "imitation": 50}
    from imitrl.jobs.evaluate import EVAL_LANES

    assert spec["eval_lanes"]["imitrl"] == EVAL_LANES  # what imitrl's own jobs evaluate on
    assert TASKS["cartpole"].spec(2)["protocol"] == "own"
    with pytest.raises(ValueError, match="protocol must be one of"):
        TASKS["cartpole"].spec(0, "beta_half")


def test_imitrl_children_import_this_checkout_and_the_install_is_reported(monkeypatch, tmp_path):
    """Whichever venv runs imitrl's children, they import this checkout's ``src``
    (PYTHONPATH first); the report names that venv and its extras, and a venv whose imitrl
    is another one is refused before anything is timed."""
    import tensordict
    import torch

    env = runs._child_env("imitrl")
    assert env["PYTHONPATH"].split(":")[0] == str(ROOT / "src")
    assert "PYTHONPATH" not in runs._child_env("imitation")
    install = runs.imitrl_install(sys.executable)
    assert Path(install["imitrl"]).resolve() == (ROOT / "src" / "imitrl" / "__init__.py")
    assert install["versions"]["torch"] == torch.__version__
    assert install["versions"]["tensordict"] == tensordict.__version__
    assert set(install["optional_packages"]) <= set(runs.OPTIONAL)
    from _peer_imitation.report import install_line

    assert "requirements alone" in install_line({**install, "optional_packages": []})
    assert "with ray, mujoco installed" in install_line(
        {**install, "optional_packages": ["ray", "mujoco"]}
    )
    assert install_line(None) == ""
    with pytest.raises(RuntimeError, match=r"no python at .*--imitrl-python"):
        runs.imitrl_install(str(tmp_path / "bin" / "python"))
    monkeypatch.setattr(runs, "SRC", tmp_path)  # a checkout the venv's imitrl is not from
    with pytest.raises(RuntimeError, match="imports imitrl from"):
        runs.imitrl_install(sys.executable)


def test_the_gail_rows_run_from_peer_imitation(monkeypatch):
    """``peer_imitation.py --gail ...`` is ``peer_gail.py ...``: its GAIL rows, the other
    arguments passed on as given."""
    import peer_gail
    import peer_imitation

    seen = []
    monkeypatch.setattr(peer_gail, "main", seen.append)
    peer_imitation.main(["--seeds", "5", "--gail", "--imitrl-python", "/x/python"])
    assert seen == [["--seeds", "5", "--imitrl-python", "/x/python"]]
    assert "--gail" in peer_imitation.__doc__ and "peer_gail.py" in peer_imitation.__doc__


def test_the_plan_runs_plain_scripts_beside_imitation_and_the_trick_as_its_own_row():
    """Per (task, seed): both libraries under both protocols as plain scripts, then imitrl
    ``own`` with the command's collector trick; ``--quick`` runs imitrl's side alone."""
    assert runs.PLAN[0] == ("imitrl", "own", "plain")  # the headline's imitrl run first
    assert set(runs.PLAN) == {
        (lib, protocol, "plain") for lib in runs.LIBRARIES for protocol in ("own", "matched")
    } | {("imitrl", "own", "collector_trick")}
    assert all(process in PROCESSES for _, _, process in runs.PLAN)
    assert all(p == "plain" for lib, _, p in runs.PLAN if lib == "imitation")
    assert runs.plan(False) == runs.PLAN
    assert runs.plan(True) == tuple(job for job in runs.PLAN if job[0] == "imitrl")
    assert len(runs.plan(True)) == 3
    spec = TASKS["cartpole"].spec(1, "own", "default", "collector_trick")
    assert spec["process"] == "collector_trick" and TASKS["cartpole"].spec(1)["process"] == "plain"
    with pytest.raises(ValueError, match="process must be one of"):
        TASKS["cartpole"].spec(1, "own", "default", "gc_off")


@pytest.mark.parametrize(("tasks", "jobs"), [(3, 3), (2, 4), (3, 1), (1, 5)])
def test_a_full_run_is_every_pair_and_the_smoke_run_covers_every_task_and_job(tasks, jobs):
    """A full run: every (task, seed, job); ``--quick``: each task and each job at least
    once, in ``max`` runs a seed, every seed alike."""
    names, plan = (
        [f"t{i}" for i in range(tasks)],
        [(f"lib{j}", "own", "plain") for j in range(jobs)],
    )
    full = runs.order(names, 2, plan)
    assert full == [(t, s, *job) for t in names for s in range(2) for job in plan]
    smoke = runs.order(names, 2, plan, quick=True)
    assert len(smoke) == 2 * max(tasks, jobs)
    for seed in range(2):
        these = [r for r in smoke if r[1] == seed]
        assert {r[0] for r in these} == set(names)
        assert {r[2:] for r in these} == set(plan)


def _planned_runs(walls: dict, seeds=(0, 1)) -> list[dict]:
    """Fake reports of :data:`runs.PLAN` in its order; ``walls[(library, protocol,
    process)]`` the wall seconds of each seed."""
    out = []
    for seed in seeds:
        for library, protocol, process in runs.PLAN:
            wall = walls[library, protocol, process][seed]
            run = fake_run("cartpole", library, seed, wall, 20.0, 100.0 + seed)
            out.append({**run, "protocol": protocol, "process": process, "gc_frozen": 0})
    return out


def test_the_collector_trick_row_pairs_with_imitations_own_run_of_the_same_seed():
    walls = {
        ("imitrl", "own", "plain"): [2.0, 3.0],
        ("imitation", "own", "plain"): [8.0, 4.0],
        ("imitrl", "matched", "plain"): [3.0, 3.0],
        ("imitation", "matched", "plain"): [6.0, 12.0],
        ("imitrl", "own", "collector_trick"): [1.0, 2.0],
    }
    runs_ = _planned_runs(walls)
    runs_[-1]["gc_frozen"] = 600_000  # seed 1's collector-trick run
    s = summarise(runs_, {"cartpole": [500.0, 500.0]})
    assert list(s) == ["cartpole, own", "cartpole, matched", "cartpole, own, collector trick"]
    assert s["cartpole, own"]["phases"]["wall"]["ratios"] == [0.25, 0.75]
    assert s["cartpole, matched"]["phases"]["wall"]["ratios"] == [0.5, 0.25]
    trick = s["cartpole, own, collector trick"]
    assert trick["phases"]["wall"]["ratios"] == [0.125, 0.5]  # over imitation's own runs
    assert trick["phases"]["wall"]["median_seconds"] == {"imitrl": 1.5, "imitation": 6.0}
    assert trick["process"] == "collector_trick" and trick["protocol"] == "own"
    assert [k for k, v in s.items() if v["headline"]] == ["cartpole, own"]
    assert trick["expert"] == [500.0, 500.0] and trick["returns_met"] is True
    raw = {
        "config": {"seeds": 2},
        "summary": s,
        "wall_seconds": 30.0,
        "imitrl_versions": {},
        "peer_versions": {"imitation": "1.0.1"},
    }
    text = markdown(raw)
    assert "| cartpole, own, collector trick | whole process | 1.50 | 6.00 | 0.12 / 0.50 |" in text
    assert "| cartpole, own | whole process | 2.50 | 6.00 | 0.25 / 0.75 | 0.50 |" in text
    assert "plain Python scripts" in text and "`<task>, own, collector trick`" in text
    assert "300,000 objects frozen" in text  # the median over the trick's seeds
    # without a collector-trick run the head names no such row
    plain_only = [r for r in runs_ if r["process"] == "plain"]
    text = markdown({**raw, "summary": summarise(plain_only, {})})
    assert "plain Python scripts" in text and "collector trick" not in text


def test_results_without_a_process_read_as_plain_scripts():
    """Results from before the field (every imitrl child then took the collector trick
    unasked, unrecorded) read as ``plain``: one row per (task, protocol), as they did."""
    runs_ = [
        {**fake_run("pendulum", lib, 0, wall, -900.0, -300.0), "protocol": "own"}
        for lib, wall in (("imitrl", 1.0), ("imitation", 4.0))
    ]
    assert all("process" not in r for r in runs_)
    s = summarise(runs_, {})
    assert list(s) == ["pendulum, own"] and s["pendulum, own"]["process"] == "plain"
    assert s["pendulum, own"]["phases"]["wall"]["ratios"] == [0.25]
    assert s["pendulum, own"]["gc_frozen"] == [None]
    raw = {"config": {"seeds": 1}, "summary": s, "wall_seconds": 1.0,
           "imitrl_versions": {}, "peer_versions": None}  # fmt: skip
    text = markdown(raw)  # the head does not call them plain scripts: they were not
    assert "predate issue 43" in text and "plain Python scripts" not in text


def test_the_peer_python_comes_from_the_flag_or_the_environment(monkeypatch, tmp_path):
    """No default path: ``--peer-python``, else ``$IMITRL_PEER_PYTHON``; with neither, or
    a path with no python, ``SystemExit`` naming both ways before anything runs."""
    monkeypatch.delenv(runs.PEER_ENV, raising=False)
    with pytest.raises(SystemExit, match=r"--peer-python.*IMITRL_PEER_PYTHON"):
        runs.peer_python(None)
    missing = str(tmp_path / "venv" / "bin" / "python")
    with pytest.raises(SystemExit, match=r"no python at .*\(--peer-python\).*IMITRL_PEER_PYTHON"):
        runs.peer_python(missing)
    monkeypatch.setenv(runs.PEER_ENV, missing)
    with pytest.raises(SystemExit, match=r"no python at .*\(\$IMITRL_PEER_PYTHON\)"):
        runs.peer_python(None)
    python = tmp_path / "python"
    python.touch()
    assert runs.peer_python(str(python)) == str(python)  # the flag over the variable
    monkeypatch.setenv(runs.PEER_ENV, str(python))
    assert runs.peer_python(None) == str(python)
    import peer_imitation

    assert peer_imitation.build_parser().parse_args([]).peer_python is None
    assert "/work/" not in peer_imitation.__doc__  # no machine's path: $PEER_VENV


def test_a_full_run_without_a_peer_python_stops_before_anything_is_written(monkeypatch, tmp_path):
    import peer_imitation

    monkeypatch.delenv(runs.PEER_ENV, raising=False)
    started = []
    monkeypatch.setattr(runs, "run_all", lambda *a, **k: started.append(a))
    with pytest.raises(SystemExit, match="IMITRL_PEER_PYTHON"):
        peer_imitation.main(["--out", str(tmp_path / "out"), "--tasks", "cartpole"])
    assert started == [] and not (tmp_path / "out").exists()


def test_the_imitrl_command_is_the_console_script_beside_the_python(tmp_path):
    python = tmp_path / "bin" / "python"
    assert runs.imitrl_command(str(python)) == [str(python), "-m", "imitrl"]
    python.parent.mkdir()
    (python.parent / "imitrl").touch()
    assert runs.imitrl_command(str(python)) == [str(python.parent / "imitrl")]


def test_imitrl_children_are_plain_scripts_unless_asked_for_the_collector_trick(tmp_path):
    """A real child of each process kind, on FrozenLake's smoke budget: the plain one
    freezes nothing, the collector-trick one freezes its import-time heap, and both
    train the same learner (the trick touches no number)."""
    task = quick(TASKS["frozenlake"])

    def one(process: str) -> dict:
        return runs.run_once(
            task, 0, "imitrl", peer_python=None, workdir=tmp_path, timeout=600,
            process=process,
        )  # fmt: skip

    with ThreadPoolExecutor(2) as pool:
        plain, trick = pool.map(one, PROCESSES)
    assert (plain["process"], trick["process"]) == PROCESSES
    assert plain["gc_frozen"] == 0 and trick["gc_frozen"] > 10_000
    assert plain["returns"] == trick["returns"]
    assert plain["greedy_tables"] == trick["greedy_tables"]
    with pytest.raises(ValueError, match="peer venv"):
        runs.run_once(task, 0, "imitation", peer_python=None, workdir=tmp_path, timeout=1)
