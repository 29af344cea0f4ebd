"""``imitrl dagger --save-lerobot FPS`` and ``--dataset-frames`` (issue 48).

The run writes every round in LeRobot's DAgger schema after each fit; a round that fails
leaves every earlier one in the staged run, readable, and ``--resume`` ends with the dataset
of an uninterrupted run; a run started from such a dataset continues its rounds; ``imitrl
bc`` trains on a LeRobot DAgger recording, all of it or its interventions alone.
"""

from __future__ import annotations

import contextlib
import io
import json
import warnings

import pytest
import torch

from imitrl import keys
from imitrl.algorithms import EnvSource
from imitrl.cli import main
from imitrl.datasets import load_lerobot
from imitrl.fs.run_folder import staging_folder
from tests.datasets.lerobot.test_interventions import lerobot_recording

TINY = ["dagger", "--env", "Pendulum-v1", "--demos", "1", "--rounds", "4",
        "--episodes-per-round", "1", "--steps", "20", "--eval-episodes", "1",
        "--max-episode-steps", "30", "--gate", "0.5", "--save-lerobot", "20",
        "--no-progress"]  # fmt: skip


def _main(*argv: str) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        status = main(list(argv))
    return status, err.getvalue()


def _rows(root):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_lerobot(root).rows


def _same(a, b) -> None:
    assert set(a.keys(True, True)) == set(b.keys(True, True))
    for key in a.keys(True, True):
        assert torch.equal(a[key], b[key]), key


def test_the_rounds_match_the_runs_record(tmp_path):
    status, err = _main(*TINY, "--out", str(tmp_path / "run"))
    assert status == 0, err
    results = json.loads((tmp_path / "run" / "results.json").read_text())
    rows = _rows(tmp_path / "run" / "lerobot")
    rnd, flags = rows[keys.ROUND], rows[keys.EXPERT_EXECUTED]
    assert int((rnd == 0).sum()) == int(flags[rnd == 0].sum()) == 30  # the demonstration
    for r in results["rounds"][:-1]:  # relabel round r + 1, played by fit r's learner
        at = rnd == r["round"] + 1
        assert (int(at.sum()), int(flags[at].sum())) == (r["rows_collected"], r["interventions"])
        assert rows[keys.POLICY_VERSION][at].eq(r["round"]).all()
        assert rows[keys.BETA][at].eq(-1.0).all()  # a gate decided, not a coin


def test_a_failed_round_keeps_the_earlier_ones_and_resume_ends_as_one_run(tmp_path, monkeypatch):
    status, err = _main(*TINY, "--out", str(tmp_path / "whole"))
    assert status == 0, err
    collect = EnvSource.collect

    def failing(self, behaviour, episodes, *, round_index, first_episode):
        if round_index == 3:
            raise RuntimeError("the robot's arm came off")
        return collect(
            self, behaviour, episodes, round_index=round_index, first_episode=first_episode
        )

    monkeypatch.setattr(EnvSource, "collect", failing)
    out = tmp_path / "cut"
    with pytest.raises(RuntimeError, match="arm came off"):
        main([*TINY, "--out", str(out)])
    kept = _rows(staging_folder(out) / "lerobot")  # written after fit 2, before round 3
    assert sorted(kept[keys.ROUND].unique().tolist()) == [0, 1, 2]
    whole = _rows(tmp_path / "whole" / "lerobot")
    _same(kept, whole[: kept.shape[0]])  # the rounds so far, as the uninterrupted run's
    monkeypatch.setattr(EnvSource, "collect", collect)
    status, err = _main(*TINY, "--out", str(out), "--resume")
    assert status == 0, err
    _same(_rows(out / "lerobot"), whole)


def test_a_run_from_a_dagger_dataset_continues_its_rounds(tmp_path):
    status, err = _main(*TINY, "--out", str(tmp_path / "first"))
    assert status == 0, err
    first = tmp_path / "first" / "lerobot"
    status, err = _main(*TINY, "--rounds", "2", "--dataset", str(first),
                        "--out", str(tmp_path / "next"))  # fmt: skip
    assert status == 0, err
    before, after = _rows(first), _rows(tmp_path / "next" / "lerobot")
    _same(after[: before.shape[0]], before)
    new = after[before.shape[0] :]
    assert new[keys.ROUND].eq(4).all() and new[keys.POLICY_VERSION].eq(3).all()


@pytest.mark.parametrize("frames, rows", [("all", 30), ("interventions", 15)])
def test_bc_trains_on_a_lerobot_dagger_recording(tmp_path, frames, rows):
    root, _ = lerobot_recording(tmp_path)
    out = tmp_path / "bc"
    status, err = _main("bc", "--env", "none", "--dataset", str(root), "--dataset-frames",
                        frames, "--steps", "5", "--out", str(out), "--no-progress")  # fmt: skip
    assert status == 0, err
    assert json.loads((out / "results.json").read_text())["demonstrations"]["rows"] == rows


def test_interventions_of_a_dataset_without_them_are_one_line(tmp_path):
    root, _ = lerobot_recording(tmp_path, features=("observation.state", "action"))
    status, err = _main("bc", "--env", "none", "--dataset", str(root), "--dataset-frames",
                        "interventions", "--out", str(tmp_path / "bc"), "--no-progress")  # fmt: skip
    assert status == 2 and "has no intervention column" in err and "Traceback" not in err
    status, err = _main("bc", "--env", "Pendulum-v1", "--dataset-frames", "interventions",
                        "--out", str(tmp_path / "bc"), "--no-progress")  # fmt: skip
    assert status == 2 and "--dataset-frames chooses frames of --dataset" in err
    assert not (tmp_path / "bc").exists()


def test_a_run_starts_from_a_recording_in_lerobots_own_schema(tmp_path):
    """A dataset with LeRobot's columns only (``observation.state``, ``action``,
    ``intervention``; no imitrl column, as LeRobot's DAgger strategy records one): its frames
    are round 0 with their interventions kept, and the run's rounds come after."""
    from imitrl.datasets import save_lerobot

    status, err = _main(*TINY, "--rounds", "2", "--out", str(tmp_path / "first"))
    assert status == 0, err
    rows = _rows(tmp_path / "first" / "lerobot")
    flags = rows[keys.EXPERT_EXECUTED].clone()
    flags[::3] = ~flags[::3]  # a recording's own pattern of corrections
    rows.set(keys.EXPERT_EXECUTED, flags)
    rec = save_lerobot(rows, tmp_path / "rec", fps=20,
                       features=["observation.state", "action", "intervention"])  # fmt: skip
    (rec / "meta" / "imitrl.json").unlink()  # read as LeRobot's own
    status, err = _main(
        *TINY, "--rounds", "2", "--dataset", str(rec), "--out", str(tmp_path / "next")
    )
    assert status == 0, err
    after = _rows(tmp_path / "next" / "lerobot")
    n = rows.shape[0]
    assert after[keys.ROUND][:n].eq(0).all() and after[keys.ROUND][n:].eq(1).all()
    assert torch.equal(after[keys.EXPERT_EXECUTED][:n], flags)
    assert torch.equal(after[keys.EXPERT_ACTION][:n], rows[keys.EXPERT_ACTION])
