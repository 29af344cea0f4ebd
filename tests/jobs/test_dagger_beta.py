"""``imitrl dagger --beta-decay P`` (issue 46): Ross et al.'s schedule, beta = P^(i-1) in
relabel round i, from the command line; conflicting flags are one line."""

from __future__ import annotations

import json
import warnings

import pytest

from imitrl import keys
from imitrl.algorithms import Constant, Exponential
from imitrl.jobs.dagger import DAggerJob, beta_schedule
from tests.jobs.test_dagger_gate import TINY as GATE_TINY
from tests.jobs.test_dagger_gate import _main

TINY = [*GATE_TINY, "--rounds", "4"]  # four rounds (the last flag wins): betas 1, 0.5, 0.25


def test_the_schedule_is_ross_et_al_s_or_the_constant():
    base = {"env": "Pendulum-v1", "expert": "pendulum"}
    assert beta_schedule(DAggerJob(**base, beta=0.25)) == Constant(0.25)
    decay = beta_schedule(DAggerJob(**base, beta_decay=0.5))
    assert decay == Exponential(0.5) and [decay(i) for i in (1, 2, 3)] == [1.0, 0.5, 0.25]


def test_beta_decay_from_the_command_line_hands_round_one_to_the_expert(tmp_path):
    status, err = _main(*TINY, "--beta-decay", "0.5", "--out", str(tmp_path / "run"))
    assert status == 0, err
    rounds = json.loads((tmp_path / "run" / "results.json").read_text())["rounds"]
    assert [r["beta_next"] for r in rounds] == [1.0, 0.5, 0.25, None]
    executed = [r["expert_executed_fraction"] for r in rounds[:-1]]
    assert executed[0] == 1.0  # round 1: every action the expert's
    assert 0.0 < executed[1] < 1.0 and 0.0 <= executed[2] < 1.0  # the coin, seeded


@pytest.mark.parametrize(
    "extra, said",
    [(["--beta-decay", "0.5", "--beta", "0.5"], "give one"),
     (["--beta-decay", "0.5", "--gate", "0.5"], "--beta-decay out")],
)  # fmt: skip
def test_conflicting_beta_flags_are_one_line(extra, said, tmp_path):
    status, err = _main(*TINY, *extra, "--out", str(tmp_path / "run"))
    assert status == 2 and said in err and "Traceback" not in err
    assert not (tmp_path / "run").exists()


def test_a_lerobot_recording_keeps_each_rounds_beta_from_the_schedule(tmp_path):
    pytest.importorskip("pyarrow")
    from imitrl.datasets import load_lerobot  # the datasets extra

    status, err = _main(*TINY, "--beta-decay", "0.5", "--save-lerobot", "20",
                        "--out", str(tmp_path / "run"))  # fmt: skip
    assert status == 0, err
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rows = load_lerobot(tmp_path / "run" / "lerobot").rows
    rnd, beta = rows[keys.ROUND], rows[keys.BETA]
    assert [float(beta[rnd == r].unique()) for r in (1, 2, 3)] == [1.0, 0.5, 0.25]
    assert bool(rows[keys.EXPERT_EXECUTED][rnd == 1].all())  # round 1: the expert drove
