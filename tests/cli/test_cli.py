"""`imitrl` commands: help documents every flag, bc/dagger/eval end to end, bad flags exit 2.

Every run is in-process (``imitrl.cli.main`` returns the exit status) on CartPole-v1
with episodes cut to a few dozen steps and a few gradient steps.
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib.util
import io
import json
import sys
import textwrap

import pytest
from torchrl.envs.utils import ExplorationType

from imitrl.cli import COMMANDS, main
from imitrl.cli.flags import field_docs
from imitrl.envs import make_env
from imitrl.experts import cartpole_expert
from imitrl.jobs import BCJob, DAggerJob, bench, run_bc
from imitrl.jobs.curves import read_scalars, scalars_dir
from imitrl.limits import flag_of
from imitrl.runtime import rollout_episodes
from tests import _child

TINY = [
    "--env", "CartPole-v1", "--expert", "cartpole", "--demos", "1", "--steps", "20",
    "--batch-size", "16", "--hidden", "16,16", "--eval-episodes", "3",
    "--max-episode-steps", "30",
]  # fmt: skip
DAGGER = ["--rounds", "2", "--episodes-per-round", "1"]


def run(argv: list[str]) -> tuple[int, str, str]:
    """``main(argv)`` with stdout and stderr captured: (status, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = main(argv)
    return status, out.getvalue(), err.getvalue()


def help_text(argv: list[str], capsys) -> str:
    with pytest.raises(SystemExit) as exit_info:
        main([*argv, "--help"])
    assert exit_info.value.code == 0
    return capsys.readouterr().out


@pytest.fixture(scope="module")
def bc_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("bc")
    status, stdout, stderr = run(["bc", *TINY, "--out", str(out), "--progress"])
    assert status == 0, stderr
    return out, stdout, stderr


@pytest.fixture(scope="module")
def dagger_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("dagger")
    status, stdout, stderr = run(["dagger", *TINY, *DAGGER, "--out", str(out), "--no-progress"])
    assert status == 0, stderr
    return out, stdout


# ------------------------------------------------------------------------- help
def test_help_lists_every_command(capsys):
    text = help_text([], capsys)
    names = {"bc", "dagger", "gail", "airl", "eval", "compare", "bench", "frozenlake"}
    for name in names:
        assert name in text
    assert set(COMMANDS) == names


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_every_config_field_is_a_documented_flag(name, capsys):
    cls = COMMANDS[name].config
    flat = "".join(help_text([name], capsys).split())  # argparse rewraps the help
    docs = field_docs(cls)
    for f in dataclasses.fields(cls):
        assert docs.get(f.name), f"{cls.__name__}.{f.name} has no docstring"
        flag = (
            f.name.upper() if f.metadata.get("positional") or f.metadata.get("remainder") else None
        )
        flag = flag or f.metadata.get("repeat")  # a repeatable flag: its own name
        assert (flag or flag_of(f)) in flat
        assert "".join(docs[f.name].split()) in flat, f"{name} --help lacks {f.name}'s doc"


def test_help_lists_the_names_a_flag_accepts(capsys):
    text = help_text(["bc"], capsys)
    assert "inverted_double_pendulum" in text and "cross_entropy" in text
    assert "bc_vs_dagger" in help_text(["bench"], capsys)


# ------------------------------------------------------------------ bc and eval
def test_bc_writes_results_checkpoint_and_curves(bc_run):
    out, stdout, stderr = bc_run
    results = json.loads((out / "results.json").read_text())
    assert results["command"] == "bc"
    assert results["demonstrations"] == {"source": "expert cartpole", "episodes": 1, "rows": 30}
    for who in ("expert", "learner"):
        ev = results[who]
        assert ev["episodes"] == 3 and len(ev["return_ci"]) == 2
        assert 0 < ev["mean_return"] <= 30
    assert results["expert"]["mean_return"] == 30.0
    assert (out / "learner.pt").is_file() and (out / "config.json").is_file()
    curves = read_scalars(scalars_dir(out, "bc"))
    assert curves["bc/loss"][0] == list(range(20))  # one row per gradient step
    assert curves["eval/return"] == ([0], [results["learner"]["mean_return"]])
    assert (out / "curves.png").stat().st_size > 10_000
    # report lines on stdout, the progress bar on stderr only
    assert "learner: return" in stdout and "expert: return" in stdout
    assert "bc fit" in stderr and "bc fit" not in stdout and "%|" not in stdout


def test_eval_of_the_checkpoint_reproduces_the_learner(bc_run):
    out, _, _ = bc_run
    saved = json.loads((out / "results.json").read_text())["learner"]
    status, stdout, stderr = run(["eval", "--checkpoint", str(out), "--eval-episodes", "3"])
    assert status == 0, stderr
    assert f"return {saved['mean_return']:.2f}" in stdout
    status, _, stderr = run(
        ["eval", "--checkpoint", str(out), "--eval-episodes", "3", "--out", str(out / "again")]
    )
    assert status == 0, stderr
    again = json.loads((out / "again" / "eval.json").read_text())["evaluation"]
    assert again["mean_return"] == saved["mean_return"]
    assert again["return_ci"] == saved["return_ci"]


@pytest.mark.parametrize("loss", ["mse", "diffusion"])  # greedy, and a sampled policy
def test_eval_reproduces_a_registry_learner_to_the_digit(loss, tmp_path):
    argv = ["--env", "Pendulum-v1", "--expert", "pendulum", "--loss", loss, "--demos", "1",
            "--steps", "10", "--batch-size", "16", "--hidden", "16,16", "--eval-episodes", "3",
            "--max-episode-steps", "30", "--no-progress"]  # fmt: skip
    status, _, stderr = run(["bc", *argv, "--out", str(tmp_path / "run")])
    assert status == 0, stderr
    saved = json.loads((tmp_path / "run" / "results.json").read_text())["learner"]
    assert saved["return_ci"][0] < saved["return_ci"][1]  # returns differ between episodes
    assert saved["exploration"] == ("random" if loss == "diffusion" else "deterministic")
    status, _, stderr = run(
        ["eval", "--checkpoint", str(tmp_path / "run"), "--eval-episodes", "3",
         "--out", str(tmp_path / "eval")]
    )  # fmt: skip
    assert status == 0, stderr
    assert json.loads((tmp_path / "eval" / "eval.json").read_text())["evaluation"] == saved


def test_eval_of_an_expert(tmp_path):
    status, stdout, stderr = run(
        ["eval", "--expert", "cartpole", "--env", "CartPole-v1", "--max-episode-steps", "30",
         "--eval-episodes", "2", "--out", str(tmp_path)]
    )  # fmt: skip
    assert status == 0, stderr
    assert "expert cartpole on CartPole-v1: return 30.00" in stdout
    assert json.loads((tmp_path / "eval.json").read_text())["evaluation"]["mean_return"] == 30.0


def test_run_bc_is_a_function_of_its_config(tmp_path):
    config = BCJob(demos=1, num_steps=5, batch_size=8, hidden=(8,), eval_episodes=2,
                   max_episode_steps=20, progress=False, out=tmp_path / "a")  # fmt: skip
    first = run_bc(config)
    second = run_bc(dataclasses.replace(config, out=tmp_path / "b"))
    assert first["final_loss"] == second["final_loss"]
    assert first["learner"] == second["learner"]


# ---------------------------------------------------------------------- dagger
def test_dagger_writes_a_record_per_round(dagger_run):
    out, stdout = dagger_run
    results = json.loads((out / "results.json").read_text())
    rounds = results["rounds"]
    assert [r["round"] for r in rounds] == [0, 1]
    assert rounds[0]["rows_trained"] == 30 and rounds[1]["rows_trained"] > 30
    assert results["learner"] == rounds[-1]["evaluation"]
    curves = read_scalars(scalars_dir(out, "dagger"))
    assert curves["bc/loss"][0] == list(range(40))  # steps counted across rounds
    assert curves["eval/return"][0] == [0, 1]
    assert curves["dagger/rows"][1] == [30.0, float(rounds[1]["rows_trained"])]
    assert (out / "curves.png").stat().st_size > 10_000
    assert "round 0 (30 rows)" in stdout and "round 1" in stdout


def test_dagger_with_a_user_expert_module(tmp_path, monkeypatch):
    (tmp_path / "tests_helper_module.py").write_text(
        textwrap.dedent(
            """
            import torch
            from imitrl.policies import Expert

            GAINS = torch.tensor([0.5, 1.0, 10.0, 2.0])

            def act(obs):
                return ((obs * GAINS).sum(-1) > 0).long()

            def fn():
                return Expert.from_callable(act)

            def not_an_expert():
                return 42
            """
        )
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    for expert, kind in (
        ("tests_helper_module:fn", "builder"),
        ("tests_helper_module:act", "callable"),
    ):
        out = tmp_path / kind
        status, _, stderr = run(
            ["dagger", *TINY, *DAGGER, "--expert", expert, "--expert-kind", kind,
             "--out", str(out), "--no-progress"]
        )  # fmt: skip
        assert status == 0, stderr
        results = json.loads((out / "results.json").read_text())
        assert results["expert"]["mean_return"] == 30.0  # the same gains as the built-in
    status, _, stderr = run(["dagger", *TINY, "--expert", "tests_helper_module:not_an_expert"])
    assert status == 2 and "--expert-kind callable" in stderr


def test_bc_and_dagger_from_a_lerobot_dataset(tmp_path):
    pytest.importorskip("pyarrow")
    from imitrl.datasets import save_lerobot

    env = make_env("CartPole-v1", seed=3, max_episode_steps=30)
    rows = rollout_episodes(
        env, cartpole_expert().as_actor(), 2, exploration=ExplorationType.DETERMINISTIC,
        max_steps=100,
    )  # fmt: skip
    root = save_lerobot(rows, tmp_path / "demos", fps=50)
    out = tmp_path / "run"
    status, _, stderr = run(
        ["dagger", *TINY, *DAGGER, "--dataset", str(root), "--out", str(out), "--no-progress"]
    )
    assert status == 0, stderr
    results = json.loads((out / "results.json").read_text())
    assert results["demonstrations"]["rows"] == 60 and results["rounds"][1]["rows_trained"] > 60
    # behaviour cloning needs no expert when the demonstrations are on disk
    status, stdout, stderr = run(
        ["bc", *TINY, "--expert", "none", "--dataset", str(root), "--out", str(tmp_path / "bc"),
         "--no-progress"]
    )  # fmt: skip
    assert status == 0, stderr
    results = json.loads((tmp_path / "bc" / "results.json").read_text())
    assert results["expert"] is None and "expert:" not in stdout
    assert results["demonstrations"] == {"source": str(root), "episodes": 2, "rows": 60}


def test_tensorboard_logger_writes_events_beside_the_csv(tmp_path):
    pytest.importorskip("tensorboard")
    status, _, stderr = run(
        ["bc", *TINY, "--steps", "3", "--logger", "tensorboard", "--out", str(tmp_path),
         "--no-progress"]
    )  # fmt: skip
    assert status == 0, stderr
    assert list((tmp_path / "logs" / "tensorboard").rglob("events.out.tfevents.*"))
    assert read_scalars(scalars_dir(tmp_path, "bc"))["bc/loss"][0] == [0, 1, 2]


# ----------------------------------------------------------------------- bench
def test_bench_runs_the_script_with_the_remaining_args(tmp_path, monkeypatch, capfd):
    (tmp_path / "echo_args.py").write_text("import sys\nprint(sys.argv[1:])\nsys.exit(3)\n")
    (tmp_path / "_helper.py").write_text("")
    monkeypatch.setattr(bench, "BENCHMARKS_DIR", tmp_path)
    assert bench.available(tmp_path) == ["echo_args"]
    assert main(["bench", "echo_args", "--quick", "--out", "x"]) == 3  # the script's status
    assert "['--quick', '--out', 'x']" in capfd.readouterr().out
    assert "bc_vs_dagger" in bench.available()  # the checkout's own benchmarks


def test_bench_never_writes_the_committed_results_unless_told(tmp_path, monkeypatch, capfd):
    """Issue 44: ``imitrl bench loss_functions --task ...`` without ``--out`` rewrote
    benchmarks/README.md and results/; a full run now gets ``--out results/bench/NAME``
    under the current folder, unless it names its own place or asks for the committed one."""
    scripts = tmp_path / "benchmarks"
    scripts.mkdir()
    (scripts / "echo_args.py").write_text("import sys\nprint(sys.argv[1:])\n")
    monkeypatch.setattr(bench, "BENCHMARKS_DIR", scripts)
    monkeypatch.chdir(tmp_path)
    assert main(["bench", "echo_args", "--seeds", "1"]) == 0
    captured = capfd.readouterr()
    chosen = str(tmp_path / "results" / "bench" / "echo_args")
    assert f"['--seeds', '1', '--out', '{chosen}']" in captured.out
    assert "committed benchmarks/results/ are left alone" in captured.err
    for given in (["--out", "mine"], ["--out=mine"], ["--quick"]):
        assert main(["bench", "echo_args", *given]) == 0
        assert f"{given}" in capfd.readouterr().out  # passed on untouched
    # a render writes the README block too (a hostile review: it refreshed the committed one)
    assert main(["bench", "echo_args", "--render", "r.json"]) == 0
    assert f"['--render', 'r.json', '--out', '{chosen}']" in capfd.readouterr().out
    assert main(["bench", "echo_args", "--seeds", "1", bench.WRITE_COMMITTED]) == 0
    assert "['--seeds', '1']" in capfd.readouterr().out  # the maintainer's refresh
    # a script killed by a signal: the shell's 128 + N, said (was 241 and nothing)
    (scripts / "killed.py").write_text("import os, signal\nos.kill(os.getpid(), signal.SIGTERM)\n")
    assert main(["bench", "killed", "--quick"]) == 143
    assert "the script was killed by SIGTERM" in capfd.readouterr().err


# -------------------------------------------------------------------- bad flags
@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["bc", "--env", "NoSuchEnv-v0"], "unknown gymnasium env id 'NoSuchEnv-v0'"),
        (["bc", "--expert", "carpole"], "unknown expert 'carpole'"),
        (["bc", "--expert", "no_such_module_xyz:fn"], "cannot import 'no_such_module_xyz'"),
        (["bc", "--loss", "nope"], "unknown loss 'nope'"),
        (["bc", "--loss", "mse"], "loss 'mse' does not apply"),
        (["bc", "--dataset", "/no/such/dir"], "--dataset /no/such/dir: no such directory"),
        (["bc", "--env", "Pendulum-v1", "--expert", "cartpole"], "use --expert pendulum"),
        (["bc", "--logger", "paper"], "--logger must be one of csv, tensorboard, wandb"),
        (["dagger", "--expert", "none", "--dataset", "x"], "dagger needs --expert"),
        (["eval"], "give exactly one of --checkpoint or --expert"),
        (["eval", "--checkpoint", "/no/such/run"], "expected config.json and learner.pt"),
        (["bench", "no_such_benchmark"], "unknown benchmark 'no_such_benchmark'; available:"),
    ],
)
def test_bad_flags_exit_2_with_one_line(argv, message, tmp_path):
    status, stdout, stderr = run([*argv, "--out", str(tmp_path)] if argv[0] != "bench" else argv)
    assert status == 2
    assert message in stderr
    assert stderr.count("\n") == 1 and "Traceback" not in stderr
    assert stdout == ""


def test_wandb_without_the_package_is_a_clear_error(tmp_path):
    if importlib.util.find_spec("wandb") is not None:
        pytest.skip("wandb is installed")
    status, _, stderr = run(["bc", *TINY, "--logger", "wandb", "--out", str(tmp_path)])
    assert status == 2 and "--logger wandb needs the 'wandb' package" in stderr


def test_malformed_values_are_usage_errors(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["bc", "--steps", "many"])
    assert exit_info.value.code == 2
    assert "invalid int value: 'many'" in capsys.readouterr().err


def test_dagger_config_keeps_every_bc_flag():
    bc_fields = {f.name for f in dataclasses.fields(BCJob)}
    assert bc_fields <= {f.name for f in dataclasses.fields(DAggerJob)}
    with pytest.raises(ValueError, match="--beta must be in"):
        DAggerJob(beta=1.5)


def test_a_missing_extra_is_named_with_its_install_line(tmp_path):
    """Issue 44: ``--dataset`` after the base install failed with ``No module named
    'pyarrow'``; every extra's module now gets the line that installs it."""
    from imitrl.cli import EXTRAS, missing_extra

    dataset = tmp_path / "demos"  # a LeRobot dataset's marker: read with pyarrow
    (dataset / "meta").mkdir(parents=True)
    (dataset / "meta" / "info.json").write_text('{"codebase_version": "v3.0"}')
    code = (
        "import sys; sys.modules['pyarrow'] = None\n"  # pyarrow absent, as in the base install
        "from imitrl.cli import main\n"
        f"sys.exit(main(['bc', '--env', 'CartPole-v1', '--dataset', {str(dataset)!r},"
        f" '--out', {str(tmp_path / 'out')!r}]))"
    )
    proc = _child.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 2, proc.stderr
    assert "pip install 'imitrl[datasets]'" in proc.stderr and "Traceback" not in proc.stderr
    for module, extra in EXTRAS.items():
        err = ModuleNotFoundError(f"No module named {module!r}", name=f"{module}.sub")
        assert missing_extra(err) == f" (the {extra!r} extra: pip install 'imitrl[{extra}]')"
    named = ModuleNotFoundError("needs pip install 'imitrl[hub]'", name="huggingface_hub")
    assert missing_extra(named) == "" and missing_extra(ValueError("x")) == ""
    assert missing_extra(ModuleNotFoundError("No module named 'nope'", name="nope")) == ""


def test_a_dataset_for_another_env_names_env_and_its_default(tmp_path):
    """Issue 44: a dataset recorded on one env and loaded for another got a shape error
    that did not say which env it was loaded for, nor that it was the default."""
    pytest.importorskip("pyarrow")
    from imitrl.datasets import EnvMismatchError, save_lerobot
    from imitrl.experts import pendulum_expert

    env = make_env("Pendulum-v1", seed=3, max_episode_steps=20)
    rows = rollout_episodes(env, pendulum_expert(), 1, max_steps=20)
    root = save_lerobot(rows, tmp_path / "pendulum", fps=20)
    for argv, named in (([], "--env is CartPole-v1 (the default)"),
                        (["--env", "Acrobot-v1"], "--env is Acrobot-v1:")):  # fmt: skip
        status, _, stderr = run(["bc", "--expert", "none", "--dataset", str(root), *argv,
                                 "--out", str(tmp_path / "out"), "--no-progress"])  # fmt: skip
        assert status == 2 and named in stderr and "Traceback" not in stderr
        assert "pass the env the dataset was recorded on" in stderr
    assert issubclass(EnvMismatchError, ValueError)  # callers catching ValueError still do
    # the failed runs left nothing that blocks the corrected rerun in the same --out
    # (issue 44: they left --out/logs, and the rerun was refused as "holds a previous run")
    status, _, stderr = run(["bc", "--expert", "none", "--dataset", str(root), "--env",
                             "Pendulum-v1", "--steps", "5", "--eval-episodes", "2",
                             "--out", str(tmp_path / "out"), "--no-progress"])  # fmt: skip
    assert status == 0, stderr
    assert (tmp_path / "out" / "results.json").is_file()
