"""A loss the user registered is a CLI name: ``--loss module:name`` imports the module
(code the user named, as ``--expert module:function``), the run records the name with
its module, and ``imitrl eval`` rebuilds it only when the user names the module again
(issue 44: a registered loss could not be named on the command line)."""

from __future__ import annotations

import contextlib
import io
import json
import os
import sys

import pytest

from imitrl.cli import main
from tests import _child
from tests.conftest import EXAMPLES

LOSS = "mypkg.losses:l1_l2"


def run(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = main(argv)
    return status, out.getvalue(), err.getvalue()


def test_a_registered_loss_trains_from_the_cli_and_eval_needs_its_module_named(mypkg, tmp_path):
    out = tmp_path / "run"
    status, _, stderr = run(["bc", "--env", "Pendulum-v1", "--loss", LOSS, "--demos", "1",
                             "--steps", "20", "--eval-episodes", "2", "--max-episode-steps",
                             "20", "--out", str(out), "--no-progress"])  # fmt: skip
    assert status == 0, stderr
    assert json.loads((out / "config.json").read_text())["config"]["loss"] == LOSS
    learner = json.loads((out / "results.json").read_text())["learner"]

    # a fresh process: the checkpoint alone never imports mypkg
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(EXAMPLES), *sys.path])}
    cmd = [sys.executable, "-m", "imitrl", "eval", "--checkpoint", str(out), "--no-progress"]
    refused = _child.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert refused.returncode == 2, refused.stderr
    assert f"name it yourself: --loss {LOSS} (imitrl eval, imitrl compare)" in refused.stderr
    named = _child.run([*cmd, "--loss", LOSS], capture_output=True, text=True, env=env,
                           timeout=300)  # fmt: skip
    assert named.returncode == 0, named.stderr
    assert f"return {learner['mean_return']:.2f}" in named.stdout
    # compare takes the module as eval does (a hostile review: it had no way to name it)
    cmp = [sys.executable, "-m", "imitrl", "compare", "--a", str(out), "--b", "random",
           "--episodes", "2"]  # fmt: skip
    refused = _child.run(cmp, capture_output=True, text=True, env=env, timeout=300)
    assert refused.returncode == 2 and "imitrl never imports code" in refused.stderr
    compared = _child.run([*cmp, "--loss", LOSS], capture_output=True, text=True, env=env,
                          timeout=300)  # fmt: skip
    assert compared.returncode == 0, compared.stderr
    assert "paired episodes" in compared.stdout


@pytest.mark.parametrize(
    "loss, said",
    [
        ("no_such_module_x:l1_l2", "cannot import 'no_such_module_x'"),
        ("mypkg.losses:nope", "importing 'mypkg.losses' registered no loss 'nope'"),
        # a hostile review: the built-in mse trained, recorded as the module's
        ("mypkg.losses:mse", "registered no loss 'mse' ('mse' is imitrl's own loss: --loss mse)"),
        (":l1_l2", "expected a registered name or module:name"),
    ],
)
def test_a_loss_module_that_registers_nothing_is_refused_in_one_line(mypkg, loss, said):
    status, _, stderr = run(["bc", "--env", "Pendulum-v1", "--loss", loss, "--no-progress"])
    assert status == 2 and said in stderr and "Traceback" not in stderr
