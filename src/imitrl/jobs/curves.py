"""Training curves: TorchRL loggers during a run, ``curves.png`` after it.

Every run logs through a ``torchrl.record.loggers`` logger:

* ``bc/loss`` at every gradient step (``fit_bc``; DAgger counts steps across rounds),
* ``eval/return``, ``eval/return_lo``, ``eval/return_hi`` (mean and interval of the
  evaluation) at each round (BC has one, round 0), ``eval/expert_return`` at round 0,
* ``dagger/rows`` and ``dagger/final_loss`` per round (``dagger``).

The CSV files (``--out/logs/csv/<command>/scalars/<name>.csv``, one ``step,value`` line
each) are always written, and ``curves.png`` is drawn from them; ``--logger
tensorboard`` / ``wandb`` sends the same scalars there too. A rerun into the same
``--out`` replaces the CSV files (TorchRL's CSV logger appends).
"""

from __future__ import annotations

import importlib.util
import math
import shutil
from collections.abc import Sequence
from pathlib import Path

from torchrl.record.loggers import CSVLogger, Logger

__all__ = ["LOGGERS", "FanOut", "make_logger", "plot_curves", "read_scalars", "scalars_dir"]

LOGGERS = ("csv", "tensorboard", "wandb")
"""values of ``--logger``"""


class FanOut(Logger):
    """A TorchRL logger that hands every call to each of ``loggers`` in turn."""

    def __init__(self, *loggers: Logger) -> None:
        if not loggers:
            raise ValueError("FanOut needs at least one logger")
        self.loggers = loggers
        super().__init__(exp_name=loggers[0].exp_name, log_dir=loggers[0].log_dir)

    def _create_experiment(self) -> None:
        return None

    def log_scalar(self, name: str, value: float, step: int | None = None) -> None:
        for logger in self.loggers:
            logger.log_scalar(name, value, step=step)

    def log_video(self, name: str, video, **kwargs) -> None:
        for logger in self.loggers:
            logger.log_video(name, video, **kwargs)

    def log_hparams(self, cfg) -> None:
        for logger in self.loggers:
            logger.log_hparams(cfg)

    def log_histogram(self, name: str, data: Sequence, **kwargs) -> None:
        for logger in self.loggers:
            logger.log_histogram(name, data, **kwargs)

    def shutdown(self, timeout: float | None = None) -> None:
        for logger in self.loggers:
            logger.shutdown(timeout=timeout)
        super().shutdown(timeout=timeout)

    def __repr__(self) -> str:
        return f"FanOut({', '.join(map(repr, self.loggers))})"


def scalars_dir(out: Path, name: str) -> Path:
    """Where the CSV logger of run ``name`` writes its scalars."""
    return Path(out) / "logs" / "csv" / name / "scalars"


def make_logger(kind: str, out: Path, name: str, *, fresh: bool = True) -> Logger:
    """The run's logger: CSV files under ``out/logs/csv/name``, plus ``kind``'s backend.

    ``fresh`` removes the command's earlier CSV files first (TorchRL's CSV logger
    appends); a resumed run keeps them and logs its rounds after theirs.

    Raises:
        ValueError: unknown ``kind``; ``tensorboard`` or ``wandb`` not installed.
    """
    if kind not in LOGGERS:
        raise ValueError(f"--logger must be one of {', '.join(LOGGERS)}, got {kind!r}")
    if kind != "csv" and importlib.util.find_spec(kind) is None:
        raise ValueError(f"--logger {kind} needs the {kind!r} package (pip install {kind})")
    if fresh:
        shutil.rmtree(scalars_dir(out, name).parent, ignore_errors=True)
    csv = CSVLogger(exp_name=name, log_dir=str(Path(out) / "logs" / "csv"))
    if kind == "csv":
        return csv
    if kind == "tensorboard":
        from torchrl.record.loggers import TensorboardLogger

        other = TensorboardLogger(exp_name=name, log_dir=str(Path(out) / "logs" / "tensorboard"))
    else:
        from torchrl.record.loggers import WandbLogger

        other = WandbLogger(exp_name=name, save_dir=str(Path(out) / "logs"), project="imitrl")
    return FanOut(csv, other)


def read_scalars(directory: Path) -> dict[str, tuple[list[int], list[float]]]:
    """Every ``<name>.csv`` under ``directory`` as ``name -> (steps, values)``, by step."""
    curves = {}
    for path in sorted(Path(directory).rglob("*.csv")):
        name = path.relative_to(directory).with_suffix("").as_posix()
        rows = [line.split(",") for line in path.read_text().splitlines() if line]
        rows.sort(key=lambda r: int(r[0]))
        curves[name] = ([int(s) for s, _ in rows], [float(v) for _, v in rows])
    return curves


def plot_curves(directory: Path, path: Path, *, title: str) -> Path:
    """Loss vs step and return vs round (interval band, expert line), from the CSV files."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # imported when a run plots
    from matplotlib.figure import Figure

    curves = read_scalars(directory)
    fig = Figure(figsize=(10, 3.6), layout="constrained")
    FigureCanvasAgg(fig)
    loss_ax, ret_ax = fig.subplots(1, 2)
    if "bc/loss" in curves:
        steps, loss = curves["bc/loss"]
        loss_ax.plot(steps, loss, lw=0.8, color="tab:blue")
        if loss and min(loss) > 0:
            loss_ax.set_yscale("log")
    loss_ax.set(xlabel="gradient step", ylabel="training loss", title="loss per step")
    if "eval/return" in curves:
        rounds, mean = curves["eval/return"]
        lo, hi = curves["eval/return_lo"][1], curves["eval/return_hi"][1]
        # one episode has no interval (NaN bounds): draw the point without a bar
        err = [
            [0.0 if math.isnan(a) else m - a for m, a in zip(mean, lo)],
            [0.0 if math.isnan(b) else b - m for m, b in zip(mean, hi)],
        ]
        ret_ax.errorbar(rounds, mean, yerr=err, marker="o", capsize=3, label="learner")
        ret_ax.set_xticks(rounds)
    if "eval/expert_return" in curves:
        expert = curves["eval/expert_return"][1][0]
        ret_ax.axhline(expert, color="tab:orange", ls="--", label=f"expert ({expert:.1f})")
    ret_ax.set(xlabel="round", ylabel="mean return", title="evaluation per round")
    ret_ax.legend(loc="best", fontsize=8)
    fig.suptitle(title)
    fig.savefig(path, dpi=120)
    return Path(path)
