"""benchmarks/peer_imitation.py (parts in benchmarks/_peer_imitation/): the summary's
ratios and medians, the tables with one library only, and - where the peer's venv exists -
the peer script's experts against imitrl's. test_benchmarks_smoke runs ``--quick``."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from _peer_imitation import runs  # noqa: E402
from _peer_imitation.report import markdown, summarise  # noqa: E402
from _peer_imitation.tasks import TASKS  # noqa: E402

PEER_PYTHON = Path("/work/peer_venv/bin/python")


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
@pytest.mark.skipif(not PEER_PYTHON.exists(), reason="no peer venv (see peer_imitation.py)")
def test_peer_experts_label_like_imitrl():
    report = runs.check_experts(str(PEER_PYTHON), timeout=600)
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
