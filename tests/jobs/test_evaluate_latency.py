"""``imitrl eval --inference-delay D --chunk-mode M`` (issue 48): a chunked checkpoint's
chunks executed under a delay; what cannot be is one line."""

from __future__ import annotations

import contextlib
import io
import json

import pytest

from imitrl.cli import main


def _main(*argv: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = main(list(argv))
    return status, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    root = tmp_path_factory.mktemp("runs")
    for loss in ("flow_chunk", "mse"):
        status, _, err = _main("bc", "--env", "Pendulum-v1", "--loss", loss, "--demos", "1",
                               "--steps", "10", "--eval-episodes", "2", "--max-episode-steps",
                               "30", "--out", str(root / loss), "--no-progress")  # fmt: skip
        assert status == 0, err
    return root


def test_without_a_delay_eval_is_the_runs_own(checkpoints):
    run = json.loads((checkpoints / "flow_chunk" / "results.json").read_text())
    status, out, _ = _main("eval", "--checkpoint", str(checkpoints / "flow_chunk"),
                           "--out", str(checkpoints / "e0"), "--no-progress")  # fmt: skip
    ev = json.loads((checkpoints / "e0" / "eval.json").read_text())
    assert status == 0 and "latency" not in ev and "inference delay" not in out
    assert ev["evaluation"]["mean_return"] == run["learner"]["mean_return"]
    # naive execution with no delay is the learner's own receding horizon, draw for draw
    status, out, _ = _main("eval", "--checkpoint", str(checkpoints / "flow_chunk"),
                           "--chunk-mode", "naive", "--no-progress")  # fmt: skip
    assert status == 0 and f"return {run['learner']['mean_return']:.2f}" in out


@pytest.mark.parametrize("mode", ["sync", "naive", "ensemble", "rtc"])
def test_every_mode_plays_under_a_delay(checkpoints, mode, tmp_path):
    status, out, err = _main("eval", "--checkpoint", str(checkpoints / "flow_chunk"),
                             "--inference-delay", "2", "--chunk-mode", mode,
                             "--out", str(tmp_path), "--no-progress")  # fmt: skip
    assert status == 0, err
    assert f"inference delay 2 steps, {mode} execution" in out
    ev = json.loads((tmp_path / "eval.json").read_text())
    assert ev["latency"] == {"inference_delay": 2, "mode": mode}
    assert ev["evaluation"]["episodes"] == 2


@pytest.mark.parametrize(
    "run, extra, said",
    [
        ("flow_chunk", ["--inference-delay", "5"], "delay <= execute <= horizon - delay"),
        ("mse", ["--inference-delay", "1"], "acts one action per query"),
        ("flow_chunk", ["--chunk-mode", "eager"], "--chunk-mode must be one of"),
    ],
)
def test_what_cannot_run_under_a_delay_is_one_line(checkpoints, run, extra, said):
    status, _, err = _main("eval", "--checkpoint", str(checkpoints / run), *extra,
                           "--no-progress")  # fmt: skip
    assert status == 2 and said in err and "Traceback" not in err


def test_an_expert_has_no_chunks_to_delay():
    status, _, err = _main("eval", "--expert", "pendulum", "--env", "Pendulum-v1",
                           "--inference-delay", "2", "--no-progress")  # fmt: skip
    assert status == 2 and "give --checkpoint" in err
