"""``imitrl dagger --chunk-labels plan`` (issue 46): a chunked learner's relabel rounds
carry the expert's plans from the command line; what cannot plan is one line."""

from __future__ import annotations

import contextlib
import io

import pytest
import torch

from imitrl import keys
from imitrl.cli import main
from imitrl.data import DemonstrationBuffer

TINY = ["dagger", "--env", "Pendulum-v1", "--demos", "1", "--rounds", "2",
        "--episodes-per-round", "1", "--steps", "10", "--eval-episodes", "1",
        "--max-episode-steps", "30", "--no-progress"]  # fmt: skip


def _main(*argv: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = main(list(argv))
    return status, out.getvalue(), err.getvalue()


def test_the_command_trains_a_chunked_learner_on_plans(tmp_path):
    status, _, err = _main(*TINY, "--loss", "mse_chunk", "--chunk-labels", "plan",
                           "--out", str(tmp_path / "run"))  # fmt: skip
    assert status == 0, err
    buffer, _ = DemonstrationBuffer.load(tmp_path / "run" / "run")  # the run's checkpoint
    rows = buffer.data
    relabelled = rows[rows.get(keys.ROUND) == 1]
    assert relabelled.shape[0] == 30 and not relabelled.get(keys.EXPERT_EXECUTED).any()
    pad = relabelled.get(keys.EXPERT_PLAN_PAD)
    left = 30 - relabelled.get(keys.STEP)
    assert torch.equal(pad, torch.arange(pad.shape[1])[None, :] >= left[:, None])


@pytest.mark.parametrize(
    "extra, said",
    [
        (["--loss", "mse", "--chunk-labels", "plan"], "predicts one action"),
        (["--loss", "mse_chunk", "--chunk-labels", "plan", "--num-envs", "2"], "one lane"),
        (["--chunk-labels", "plans"], "--chunk-labels must be one of mask, plan"),
    ],
)
def test_what_cannot_plan_is_one_line(extra, said, tmp_path):
    status, _, err = _main(*TINY, *extra, "--out", str(tmp_path / "run"))
    assert status == 2 and said in err and "Traceback" not in err
    assert not (tmp_path / "run" / "results.json").exists()
