"""``imitrl dagger --gate TAU [--label interventions]`` (issue 48): a gated expert and
HG-DAgger from the command line; conflicting flags are one line."""

from __future__ import annotations

import contextlib
import io
import json

import pytest

from imitrl.cli import main

TINY = ["dagger", "--env", "Pendulum-v1", "--demos", "1", "--rounds", "3",
        "--episodes-per-round", "1", "--steps", "20", "--eval-episodes", "1",
        "--max-episode-steps", "40", "--no-progress"]  # fmt: skip


def _main(*argv: str) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        status = main(list(argv))
    return status, err.getvalue()


def test_hg_dagger_from_the_command_line_labels_the_interventions(tmp_path):
    status, err = _main(*TINY, "--gate", "1.0", "--label", "interventions",
                        "--out", str(tmp_path / "run"))  # fmt: skip
    assert status == 0, err
    rounds = json.loads((tmp_path / "run" / "results.json").read_text())["rounds"]
    relabel = rounds[:-1]
    assert all(r["rows_collected"] == r["interventions"] for r in relabel)
    assert [r["rows_trained"] for r in rounds] == [40, 40 + relabel[0]["rows_collected"],
                                                   40 + sum(r["rows_collected"] for r in relabel)]  # fmt: skip


@pytest.mark.parametrize(
    "extra, said",
    [(["--label", "interventions"], "give --gate"),
     (["--gate", "0.5", "--beta", "0.5"], "leave --beta at 0"),
     (["--gate", "0.5", "--label", "some"], "--label must be all or interventions")],
)  # fmt: skip
def test_conflicting_gate_flags_are_one_line(extra, said, tmp_path):
    status, err = _main(*TINY, *extra, "--out", str(tmp_path / "run"))
    assert status == 2 and said in err and "Traceback" not in err
    assert not (tmp_path / "run").exists()
