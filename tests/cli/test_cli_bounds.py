"""Every number of the command line is range-checked, in the config (issue 42, finding 7).

Each bad value of each numeric flag of each command (0, -1, past its limit, nan, inf,
huge integers, floats where integers go) is one line on stderr naming the flag, exit
status 2, before the command's function runs and before anything is written under
``--out``. The function is replaced by one that raises :class:`Ran`, so a value the
config lets through is caught without running the job it would start (``--demos
1000000000000`` grows past 4 GB; ``--steps 1000000000000000`` asks torch for 4 PB).

The same limits hold for the Python API (the config's ``__post_init__``) and show in
``--help``. The checkpoint half of the issue is in ``tests/jobs/test_checkpoint_hostile.py``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io

import pytest

from imitrl.cli import COMMANDS, main
from imitrl.limits import flag_of

HUGE = str(10**30)
"""an integer no count of this library reaches"""

BASE = {
    "bc": ["bc"],
    "dagger": ["dagger"],
    "gail": ["gail"],
    "airl": ["airl"],
    "eval": ["eval", "--expert", "cartpole", "--env", "CartPole-v1"],
    "frozenlake": ["frozenlake"],
}
"""each command with the flags it needs to get as far as its config"""

RUNS = {
    "bc": ("imitrl.jobs.bc", "run_bc"),
    "dagger": ("imitrl.jobs.dagger", "run_dagger"),
    "gail": ("imitrl.jobs.gail", "run_gail"),
    "airl": ("imitrl.jobs.gail", "run_airl"),
    "eval": ("imitrl.jobs.evaluate", "run_eval"),
    "frozenlake": ("imitrl.experiments.frozenlake.study", "run_study"),
}
"""the function each command runs: replaced here by one that raises :class:`Ran`"""

THREADS = {"--threads": ["0", "-1", "1025", HUGE]}
SEEDS = ["-1", "2147483648", str(2**64)]
BC = {
    "--num-envs": ["0", "-1", "257", HUGE],
    "--max-episode-steps": ["0", "-1", "1000001", HUGE],
    "--demos": ["-1", "10001", "1000000000000", "1e12", "2.5"],
    "--hidden": ["0", "-1", "65537", "16384,16384", "65536,65536", ",".join(["8"] * 65), "2.5"],
    "--lr": ["0", "-1", "nan", "inf", "-inf", "1e39"],
    "--steps": ["-1", "10000001", "1000000000000000", "1e15", "2.5"],
    "--batch-size": ["0", "-1", "1048577", HUGE],
    "--warmup-steps": ["-1", "10000001", "2.5"],
    "--full-batch-max-rows": ["0", "-1", "2.5"],
    "--eval-episodes": ["0", "-1", "100001", "1000000000000", "1e12"],
    "--eval-seed": SEEDS,
    "--seed": SEEDS,
    "--nproc": ["0", "-1", "1025", HUGE],
    **THREADS,
}
DAGGER = {
    **BC,
    "--rounds": ["0", "10001", HUGE],
    "--episodes-per-round": ["0", "10001", HUGE],
    "--beta": ["-0.5", "1.5", "nan", "inf"],
    "--beta-decay": ["-0.5", "1.5", "nan", "inf"],
    "--workers": ["0", "1025", HUGE],
    "--gate": ["-1", "nan", "inf"],
    "--save-lerobot": ["0", "-1", "100001", "2.5", HUGE],
}
GAIL = {
    "--num-envs": ["0", "-1", "257", HUGE],
    "--max-episode-steps": ["0", "1000001"],
    "--demos": ["-1", "10001", "1000000000000"],
    "--hidden": ["0", "16384,16384"],
    "--lr": ["0", "-1", "nan", "inf", "1e39"],
    "--total-steps": ["0", "1000000001", HUGE],
    "--rollout-steps": ["0", "1048577", HUGE],
    "--ppo-epochs": ["0", "10001", HUGE],
    "--minibatch-size": ["0", "1048577", HUGE],
    "--discriminator-updates": ["-1", "10001", HUGE],
    "--discriminator-batch": ["0", "1048577", HUGE],
    "--discriminator-lr": ["0", "nan", "inf", "1e39"],
    "--grad-penalty": ["-1", "nan", "inf", "1e39"],
    "--gamma": ["-0.5", "1.5", "nan"],
    "--gae-lambda": ["-0.5", "1.5", "nan"],
    "--entropy-coeff": ["-1", "nan", "inf", "1e39"],
    "--clip-epsilon": ["0", "-1", "nan", "inf"],
    "--max-grad-norm": ["0", "-1", "nan", "inf"],
    "--discriminator-hidden": ["0", "16384,16384"],
    "--normalizer-warmup": ["-1", "1048577", HUGE],
    "--eval-episodes": ["0", "100001", HUGE],
    "--eval-seed": SEEDS,
    "--eval-every": ["-1", "2.5"],
    "--seed": SEEDS,
    "--nproc": ["0", "-1", "1025", HUGE],
    **THREADS,
}
AIRL = {**GAIL, "--entropy-weight": ["-1", "nan", "inf"]}
EVAL = {
    "--max-episode-steps": ["0", "-1", "1000001", HUGE],
    "--inference-delay": ["-1", "1000001", "1.5", HUGE],
    "--eval-episodes": ["0", "-1", "100001", "1000000000000", "1e12"],
    "--eval-seed": SEEDS,
    **THREADS,
}
_STUDY_COUNTS = {  # flag: its limit
    "--eval-scale": 1_000,
    "--vi-iters": 100_000,
    "--demo-episodes": 10_000,
    "--fit-steps": 10_000_000,
    "--eval-episodes": 100_000,
    "--sweep-datasets": 1_000,
    "--sweep-fit-steps": 10_000_000,
    "--sweep-eval-episodes": 100_000,
    "--chain-samples": 10_000_000,
    "--dagger-rounds": 10_000,
    "--dagger-episodes": 10_000,
    "--ex-datasets": 1_000,
    "--ex-fit-steps": 10_000_000,
    "--ex-error-datasets": 1_000,
    "--irl-steps": 10_000_000,
    "--irl-datasets": 1_000,
    "--airl-rounds": 10_000,
    "--max-steps": 1_000_000,
    "--sweep-sizes": 10_000,
    "--tv-steps": 1_000_000,
    "--ex-demo-counts": 10_000,
    "--irl-sizes": 10_000,
    "--airl-sizes": 10_000,
}
FROZENLAKE = {
    **{flag: ["0", str(most + 1), HUGE] for flag, most in _STUDY_COUNTS.items()},
    **{
        f"--{block}-seed": SEEDS
        for block in ("demo", "eval", "sweep", "chain", "dagger", "ex", "irl", "airl")
    },
    "--probe-states": ["-1"],
    "--chain-panels": ["0.05:0", "0.05:1000001", "0.01:1000", "nan:10"],  # 20000 x 1000 flips
    "--gamma": ["0", "1.5", "nan"],
    "--lr": ["0", "inf"],
    "--irl-lr": ["0", "inf"],
    "--airl-beta": ["0", "inf"],
    "--ex-corruption": ["-0.5", "1.5", "nan"],
    **THREADS,
}
BAD = {"bc": BC, "dagger": DAGGER, "gail": GAIL, "airl": AIRL, "eval": EVAL,
       "frozenlake": FROZENLAKE}  # fmt: skip
CASES = [
    (command, flag, value)
    for command, flags in BAD.items()
    for flag, values in flags.items()
    for value in values
]


class Ran(BaseException):
    """The command's function was called: its config let the value through."""


def test_the_table_names_every_numeric_flag_of_every_command():
    """A numeric field added to a config without a row here fails this test."""
    import typing

    def numeric(tp) -> bool:
        return tp in (int, float) or any(numeric(a) for a in typing.get_args(tp))

    for name, flags in BAD.items():
        cls = COMMANDS[name].config
        hints = typing.get_type_hints(cls)
        fields = {flag_of(f): f.name for f in dataclasses.fields(cls)}
        wanted = {f for f, name in fields.items() if numeric(hints[name])} | {"--threads"}
        assert wanted == set(flags), (name, wanted ^ set(flags))


@pytest.mark.parametrize(("command", "flag", "value"), CASES, ids=lambda x: str(x)[:24])
def test_every_bad_number_is_one_line_exit_2_and_nothing_runs(
    command, flag, value, tmp_path, monkeypatch
):
    import importlib

    module, name = RUNS[command]

    def ran(config):
        raise Ran(config)

    monkeypatch.setattr(importlib.import_module(module), name, ran)
    out = tmp_path / "out"
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        try:
            status = main([*BASE[command], flag, value, "--out", str(out)])
        except SystemExit as stop:  # argparse: a value its type cannot read
            status = stop.code
        except Ran:
            status = "ran: the config accepted it"
    text = err.getvalue()
    assert status == 2, (status, text)
    assert text.count("\n") == 1 and "Traceback" not in text, text
    field = flag[2:].replace("-", "_")  # GAILConfig's own checks name the field
    assert flag in text or field in text, text
    assert not out.exists(), "a refused command wrote to --out"


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda c: c.BCJob(num_steps=10**15), r"--steps must be an integer in \[0, 10_000_000\]"),
        (lambda c: c.BCJob(demos=10**12), r"--demos must be an integer in \[0, 10_000\]"),
        (lambda c: c.BCJob(seed=-1), r"--seed must be an integer >= 0, got -1"),
        (lambda c: c.BCJob(eval_episodes=2.0), r"--eval-episodes must be an integer"),
        (lambda c: c.BCJob(hidden=(0,)), r"--hidden must be a list of layer widths"),
        (
            lambda c: c.BCJob(hidden=(16384, 16384)),
            r"at least 268_500_993 weights, more than the 100_000_000",
        ),
        (lambda c: c.BCJob(lr=float("inf")), r"--lr must be a positive number or none, got inf"),
        (
            lambda c: c.BCJob(lr=1e39),
            r"--lr must be a positive number or none, got 1e\+39 \(past float32's largest",
        ),
        (lambda c: c.DAggerJob(rounds=10**6), r"--rounds must be an integer in \[1, 10_000\]"),
        (lambda c: c.GAILJob(total_steps=10**12), r"--total-steps must be an integer in"),
        (
            lambda c: c.GAILJob(grad_penalty=float("nan")),
            r"--grad-penalty must be a non-negative number, got nan",
        ),
    ],
)
def test_the_python_api_meets_the_same_limits(make, message):
    from imitrl.jobs import configs

    with pytest.raises(ValueError, match=message):
        make(configs)


def test_eval_and_the_study_meet_them_too():
    from imitrl.experiments.frozenlake.config import StudyConfig
    from imitrl.jobs import EvalJob

    with pytest.raises(ValueError, match=r"--eval-episodes must be an integer in \[1, 100_000\]"):
        EvalJob(expert="cartpole", env="CartPole-v1", eval_episodes=10**12)
    with pytest.raises(ValueError, match=r"--chain-samples 20000 x --chain-panels horizon 1000"):
        StudyConfig(chain_panels=((0.01, 1000),))


@pytest.mark.parametrize("command", sorted(BAD))
def test_help_shows_every_limit(command, capsys):
    from imitrl.limits import Bound

    with pytest.raises(SystemExit):
        main([command, "--help"])
    flat = " ".join(capsys.readouterr().out.split())
    cls = COMMANDS[command].config
    for f in dataclasses.fields(cls):
        bound = f.metadata.get("bound")
        if isinstance(bound, Bound):
            assert f"must be {bound.help(f.default)}" in flat, f.name
    assert "--threads N" in flat and "must be an integer in [1, 1_024]" in flat
    if "hidden" in {f.name for f in dataclasses.fields(cls)}:
        assert "at most 64 layers implying at most 100_000_000 weights" in flat
