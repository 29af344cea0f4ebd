"""curves.png: the evaluation panel plots success where the env reports it (issue 44); a
resumed run's logs cut back to its checkpoint, its TensorBoard log written again."""

from __future__ import annotations

import pytest

from imitrl.jobs import curves as curves_module
from imitrl.jobs.bc import log_evaluation
from imitrl.jobs.curves import make_logger, plot_curves, read_scalars, scalars_dir, trim_scalars


def _ev(ret: float, success: float | None) -> dict:
    ev = {"mean_return": ret, "return_ci": [ret - 1.0, ret + 1.0]}
    if success is not None:
        ev |= {
            "success_rate": success,
            "success_ci": [max(0.0, success - 0.1), min(1.0, success + 0.1)],
        }
    return ev


def _panel_labels(tmp_path, monkeypatch, learner: list[dict], expert: dict) -> tuple[str, list]:
    logger = make_logger("csv", tmp_path, "dagger")
    for k, ev in enumerate(learner):
        log_evaluation(logger, k, ev, expert if k == 0 else None)
    logger.shutdown()
    saved = []
    monkeypatch.setattr(
        "imitrl.plotting.save_figure", lambda fig, path, **kw: saved.append(fig) or path
    )
    plot_curves(scalars_dir(tmp_path, "dagger"), tmp_path / "curves.png", title="t")
    (ax,) = [a for a in saved[0].axes if a.get_title().startswith("evaluation")]
    return ax.get_ylabel(), [line.get_label() for line in ax.get_lines()]


def test_a_env_reporting_success_is_plotted_by_success(tmp_path, monkeypatch):
    """A Meta-World learner returning 481 at 90% success against an expert's 353 at 100%:
    the curve shows the learner below the expert, not above it."""
    label, lines = _panel_labels(tmp_path, monkeypatch, [_ev(481.0, 0.9), _ev(470.0, 0.8)],
                                 _ev(353.0, 1.0))  # fmt: skip
    assert label == "success rate" and "expert (100%)" in lines
    logged = read_scalars(scalars_dir(tmp_path, "dagger"))
    assert logged["eval/success"][1] == [0.9, 0.8] and logged["eval/return"][1] == [481.0, 470.0]


def test_a_env_without_success_is_plotted_by_return(tmp_path, monkeypatch):
    label, lines = _panel_labels(tmp_path, monkeypatch, [_ev(200.0, None)], _ev(500.0, None))
    assert label == "mean return" and "expert (500.0)" in lines
    assert curves_module.read_scalars(scalars_dir(tmp_path, "dagger")).get("eval/success") is None


def test_trim_scalars_keeps_what_keep_accepts_and_drops_cut_lines(tmp_path):
    root = scalars_dir(tmp_path, "dagger")
    (root / "bc").mkdir(parents=True)
    (root / "bc" / "loss.csv").write_text("0,1.5\n1,1.25\n2,1.0\n3,0.5\n4,0.")
    (root / "eval").mkdir()
    (root / "eval" / "return.csv").write_text("0,10.0\n1,20.0\n")
    (root / "eval" / "success.csv").write_text("0,0.5\n")
    seen = []

    def keep(scalar, step):
        seen.append(scalar)
        return step < (2 if scalar == "bc/loss" else 1)

    assert trim_scalars(tmp_path, "dagger", keep) == 4  # 2 losses, 1 cut line, 1 return
    assert (root / "bc" / "loss.csv").read_text() == "0,1.5\n1,1.25\n"
    assert (root / "eval" / "return.csv").read_text() == "0,10.0\n"
    assert (root / "eval" / "success.csv").read_text() == "0,0.5\n"
    assert set(seen) == {"bc/loss", "eval/return", "eval/success"}
    assert read_scalars(root)["bc/loss"] == ([0, 1], [1.5, 1.25])
    assert trim_scalars(tmp_path / "none", "dagger", keep) == 0  # no logs yet: nothing to cut


def test_rebuild_tensorboard_writes_the_csv_files_once_and_drops_older_event_files(tmp_path):
    """The TensorBoard writer inside the run's logger is replaced by one holding every CSV
    line at its step, once; the event files written before are gone; a CSV-only logger
    is left alone."""
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from imitrl.jobs.curves import rebuild_tensorboard

    logger = make_logger("tensorboard", tmp_path, "dagger")
    for step in range(4):
        logger.log_scalar("bc/loss", 1.0 / (step + 1), step=step)
    logger.log_scalar("eval/return", 7.0, step=0)
    before = logger.loggers[1].experiment
    before.flush()
    assert trim_scalars(tmp_path, "dagger", lambda scalar, step: step < 2) == 2
    assert rebuild_tensorboard(logger, tmp_path, "dagger") == 3
    board = tmp_path / "logs" / "tensorboard" / "dagger"
    assert len(list(board.glob("events.out.tfevents.*"))) == 1
    assert logger.loggers[1].experiment is not before  # the run logs on through the new one
    logger.log_scalar("bc/loss", 0.125, step=2)
    logger.shutdown()
    acc = EventAccumulator(str(board))
    acc.Reload()
    assert [(e.step, e.value) for e in acc.Scalars("bc/loss")] == [(0, 1.0), (1, 0.5), (2, 0.125)]
    assert [(e.step, e.value) for e in acc.Scalars("eval/return")] == [(0, 7.0)]
    csv_only = make_logger("csv", tmp_path / "other", "dagger")
    csv_only.log_scalar("bc/loss", 1.0, step=0)
    assert rebuild_tensorboard(csv_only, tmp_path / "other", "dagger") == 0
