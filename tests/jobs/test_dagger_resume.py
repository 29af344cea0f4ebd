"""``imitrl dagger --resume`` of a finished run with other flags: refused before any work,
naming what differs, leaving nothing beside ``--out`` (a hostile review: other
``--eval-episodes``/``--eval-seed`` were taken silently, one run's rounds scored two ways;
another env printed 16 lines of weight shapes; a refused resume left a copy of ``--out``
beside it, called an unfinished run)."""

from __future__ import annotations

import json

import pytest
import torch

from imitrl.fs.run_folder import staging_folder
from imitrl.jobs.curves import read_scalars
from tests._cli import run_main

FLAGS = ["dagger", "--expert", "auto", "--demos", "1", "--rounds", "2",
         "--episodes-per-round", "1", "--steps", "10", "--hidden", "8,8",
         "--eval-episodes", "1", "--max-episode-steps", "30", "--no-progress"]  # fmt: skip


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    out = tmp_path_factory.mktemp("resume") / "run"
    status, err = _main(*FLAGS, "--env", "CartPole-v1", "--out", str(out))
    assert status == 0, err
    return out


def _files(folder):
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


@pytest.mark.parametrize(
    ("flags", "differs"),
    [
        (["--env", "CartPole-v1", "--eval-episodes", "2", "--eval-seed", "5"],
         "differs in ['eval_episodes', 'eval_seed']"),
        (["--env", "CartPole-v1", "--max-episode-steps", "40"], "differs in ['max_episode_steps']"),
        (["--env", "Acrobot-v1"], "differs in ['env']"),
        (["--env", "CartPole-v1", "--steps", "20"], "differs in ['bc']"),
        # a hostile review: these resumed, and the run recorded settings its first rounds
        # never had (--lr), or demonstrations it did not train on (--demos); --hidden
        # printed torch's lines of weight shapes
        (["--env", "CartPole-v1", "--lr", "0.01"], "differs in ['lr']"),
        (["--env", "CartPole-v1", "--demos", "2"], "differs in ['demos']"),
        (["--env", "CartPole-v1", "--hidden", "4"], "differs in ['hidden']"),
    ],
)  # fmt: skip
def test_a_resume_with_other_flags_is_refused_and_leaves_nothing(finished, flags, differs):
    before = _files(finished)
    status, err = _main(*FLAGS, "--rounds", "3", *flags, "--resume", "--out", str(finished))
    assert status == 2 and "saved by a run with another config" in err and differs in err, err
    assert "size mismatch" not in err and "is kept in" not in err
    assert len([line for line in err.splitlines() if line.startswith("imitrl")]) == 1, err
    assert not staging_folder(finished).exists()  # no copy of --out left beside it
    assert _files(finished) == before


def test_a_resume_with_the_same_flags_continues_the_finished_run(finished, tmp_path):
    import shutil

    out = tmp_path / "run"
    shutil.copytree(finished, out)
    status, err = _main(*FLAGS, "--env", "CartPole-v1", "--rounds", "3", "--resume",
                        "--out", str(out))  # fmt: skip
    assert status == 0, err
    rounds = json.loads((out / "results.json").read_text())["rounds"]
    assert [r["round"] for r in rounds] == [0, 1, 2]
    assert {(r["evaluation"]["episodes"], r["evaluation"]["seed"]) for r in rounds} == {(1, 10_000)}


def _main(*argv: str) -> tuple[int, str]:
    status, _, err = run_main(*argv)
    return status, err


@pytest.fixture(scope="module")
def whole(tmp_path_factory):
    """The uninterrupted run of three rounds."""
    out = tmp_path_factory.mktemp("whole") / "run"
    status, err = _main(*FLAGS, "--env", "CartPole-v1", "--rounds", "3", "--out", str(out))
    assert status == 0, err
    return out


def test_a_resumed_run_logs_the_interrupted_round_once(finished, whole, tmp_path):
    """A kill during round 2 leaves that round's fit losses, rows and evaluation in the
    CSV logs (a line maybe cut short); the resumed run logs them again. A hostile review:
    they appeared twice, in the CSV files and in curves.png. Now the logs of the resumed
    run equal those of the uninterrupted run, byte for byte."""
    import shutil

    out = tmp_path / "killed"
    shutil.copytree(finished, out)
    logs, whole_logs = _logs(out), _logs(whole)
    assert logs.keys() == whole_logs.keys() and len(logs) >= 5
    for name, text in logs.items():  # what the killed round 2 had logged before the kill
        later = whole_logs[name][len(text) :]
        assert whole_logs[name].startswith(text) and (later or name.startswith("eval/expert")), name
        cut = "" if name != "bc/loss.csv" else later.splitlines()[-1][:3]  # a line cut short
        (_scalars(out) / name).write_text(text + later + cut)
    status, err = _main(*FLAGS, "--env", "CartPole-v1", "--rounds", "3", "--resume",
                        "--out", str(out))  # fmt: skip
    assert status == 0, err
    assert _logs(out) == whole_logs


def test_a_resumed_run_writes_its_tensorboard_log_as_the_uninterrupted_run(
    finished, whole, tmp_path
):
    """TensorBoard's event files only grow: the steps a killed round had logged stayed in
    them and the resumed run logged them again (a hostile review). A resume writes the
    log again from the CSV files, cut back to the checkpoint: every scalar at every step
    once, as the uninterrupted run's CSV files hold it, in one event file. A run logged
    to CSV alone and resumed with ``--logger tensorboard`` gets its whole history."""
    pytest.importorskip("tensorboard")
    import shutil

    from torch.utils.tensorboard import SummaryWriter

    out = tmp_path / "killed"
    shutil.copytree(finished, out)
    board = out / "logs" / "tensorboard" / "dagger"
    stale = SummaryWriter(log_dir=str(board))  # what the killed round had sent
    for step in range(15, 30):
        stale.add_scalar("bc/loss", 99.0, global_step=step)
    stale.add_scalar("eval/return", -5.0, global_step=2)
    stale.close()
    status, err = _main(*FLAGS, "--env", "CartPole-v1", "--rounds", "3", "--resume",
                        "--logger", "tensorboard", "--out", str(out))  # fmt: skip
    assert status == 0, err
    assert len(list(board.glob("events.out.tfevents.*"))) == 1
    want = {
        name: [(s, repr(v)) for s, v in zip(steps, torch.tensor(values).float().tolist())]
        for name, (steps, values) in read_scalars(_scalars(whole)).items()
    }
    assert len(want) >= 5 and len(want["bc/loss"]) == 30
    assert _events(board) == want


def _events(folder) -> dict:
    """Every scalar of a TensorBoard folder as ``name -> [(step, value), ...]``, by step."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(folder), size_guidance={"scalars": 0})
    acc.Reload()
    return {  # values as text: an interval of one episode is nan, equal to itself here
        tag: sorted((e.step, repr(e.value)) for e in acc.Scalars(tag))
        for tag in acc.Tags()["scalars"]
    }


def _scalars(out):
    return out / "logs" / "csv" / "dagger" / "scalars"


def _logs(out):
    root = _scalars(out)
    return {p.relative_to(root).as_posix(): p.read_text() for p in sorted(root.rglob("*.csv"))}


def _resigned(run):
    """Redo a buffer checkpoint's checksums after an edit, as anyone may."""
    import hashlib

    manifest = json.loads((run / "manifest.json").read_text())
    for name, entry in manifest["content"]["files"].items():
        data = (run / name).read_bytes()
        entry.update(bytes=len(data), sha256=hashlib.sha256(data).hexdigest())
    canonical = json.dumps(manifest["content"], sort_keys=True, separators=(",", ":"))
    manifest["content_sha256"] = hashlib.sha256(canonical.encode()).hexdigest()
    (run / "manifest.json").write_text(json.dumps(manifest))


@pytest.mark.parametrize(
    ("edit", "said"),
    [
        (lambda s: s.update(records=s["records"] * 2), "4 round records for 2 rounds done"),
        (lambda s: s.update(records=[]), "0 round records for 2 rounds done"),
        (lambda s: s.update(next_round=0, records=[]), "bc_step 20 and"),
        (lambda s: s.update(bc_step=10**30), "the round records make 20 fit steps"),
        (lambda s: s["records"][1].update(rows_trained=5), "trained on 5 rows; its rounds make"),
        (lambda s: s["records"][0].update(beta_next=7.0), "beta_next and expert_executed_fraction"),
        (lambda s: s["records"][0]["info"].update(mean_return="abc"), "the saved evaluation is not"),
        (lambda s: s["records"][1].update(info=None), "round 1: the saved evaluation is not"),
        (lambda s: s["records"][1]["info"].update(return_ci=[1]), "the saved evaluation is not"),
    ],
)  # fmt: skip
def test_a_dagger_state_whose_records_are_not_its_run_is_refused(finished, tmp_path, edit, said):
    """A hostile review (the checksums redone after each edit): 50 copies of the records
    resumed into 151 rounds, none into one, next_round 0 re-ran round 0 on the relabelled
    rows; an edited evaluation ended the finished run in a traceback."""
    import shutil

    out = tmp_path / "run"
    shutil.copytree(finished, out)
    state = json.loads((out / "run" / "state.json").read_text())
    edit(state)
    (out / "run" / "state.json").write_text(json.dumps(state))
    _resigned(out / "run")
    status, err = _main(*FLAGS, "--env", "CartPole-v1", "--rounds", "3", "--resume",
                        "--out", str(out))  # fmt: skip
    assert status == 2 and said in err and "Traceback" not in err, err
    assert len(err.strip().splitlines()) == 1, err
