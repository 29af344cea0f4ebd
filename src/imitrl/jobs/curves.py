"""Training curves: TorchRL loggers during a run, ``curves.png`` after it.

Every run logs through a ``torchrl.record.loggers`` logger:

* ``bc/loss`` at every gradient step (``fit_bc``; DAgger counts steps across rounds),
* ``eval/return``, ``eval/return_lo``, ``eval/return_hi`` (mean and interval of the
  evaluation) at each round (BC has one, round 0), ``eval/expert_return`` at step 0,
* ``dagger/rows`` and ``dagger/final_loss`` per round (``dagger``),
* GAIL/AIRL: ``<gail|airl>/discriminator_loss`` (and ``_grad_penalty``, ``_accuracy``s),
  ``loss_objective``, ``loss_critic`` (, ``loss_entropy``) of PPO and ``learned_reward``
  per round at step = env steps, and ``eval/return`` (with its interval) at env step 0
  (the untrained learner) and at each ``--eval-every`` round's env steps.

``curves.png`` draws each command's loss panels (:data:`LAYOUTS`) and the evaluations.

The CSV files (``--out/logs/csv/<command>/scalars/<name>.csv``, one ``step,value`` line
each) are always written, and ``curves.png`` is drawn from them; ``--logger
tensorboard`` / ``wandb`` sends the same scalars there too. A rerun into the same
``--out`` replaces the CSV files (TorchRL's CSV logger appends); a resumed run first cuts
them back to what its checkpoint holds (:func:`trim_scalars`) and writes its TensorBoard
log again from them (:func:`rebuild_tensorboard`), so a round a kill interrupted is logged
once, as resumed (wandb's server-side history keeps it twice).
"""

from __future__ import annotations

import importlib.util
import math
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from torchrl.record.loggers import CSVLogger, Logger

from imitrl.jobs.names import LOGGERS  # one list, also read by --help

__all__ = [
    "LAYOUTS",
    "LOGGERS",
    "FanOut",
    "Layout",
    "Panel",
    "make_logger",
    "plot_curves",
    "read_scalars",
    "rebuild_tensorboard",
    "scalars_dir",
    "trim_scalars",
]


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


def trim_scalars(out: Path, name: str, keep: Callable[[str, int], bool]) -> int:
    """Cut run ``name``'s CSV files in ``out`` back to the lines ``keep(scalar, step)``
    accepts, and drop any line a kill cut short; returns how many lines went.

    A resumed run calls it before it logs anything: the steps the interrupted run logged
    after its last checkpoint are logged again as the resumed run replays them (TorchRL's
    CSV logger appends, so they used to appear twice). Each file is replaced whole
    (:func:`imitrl.fs.replace_file`): a kill meanwhile leaves it as it was."""
    from imitrl.fs import replace_file

    directory = scalars_dir(out, name)
    dropped = 0
    for path in sorted(directory.rglob("*.csv")) if directory.is_dir() else ():
        scalar = path.relative_to(directory).with_suffix("").as_posix()
        lines = path.read_text().splitlines()
        kept = [line for line in lines if _kept(line, scalar, keep)]
        if len(kept) < len(lines):
            dropped += len(lines) - len(kept)
            replace_file(path, "".join(f"{line}\n" for line in kept).encode())
    return dropped


def rebuild_tensorboard(logger: Logger, out: Path, name: str) -> int:
    """Write a resumed run's TensorBoard log again from its CSV files, which
    :func:`trim_scalars` cut back to its checkpoint; returns the scalars written.

    TensorBoard's event files only grow, so the steps an interrupted run logged after its
    last checkpoint stayed in them, and the resumed run logged them again (a hostile
    review: each appeared twice). The CSV files hold every scalar the run logged, so
    ``logger``'s TensorBoard writer (inside a :class:`FanOut`, or alone) is closed, a
    new one writes each CSV line at its step, and then the older event files of its folder
    go: a kill before that leaves them beside the new one, and the next resume rebuilds
    the log again. wandb's history lives on its server: a wandb run keeps the steps twice.
    Any other logger is left as it is."""
    from torchrl.record.loggers import TensorboardLogger

    written = 0
    for inner in getattr(logger, "loggers", (logger,)):
        if not isinstance(inner, TensorboardLogger):
            continue
        from torch.utils.tensorboard import SummaryWriter

        folder = Path(inner.experiment.log_dir)
        inner.experiment.close()
        older = set(folder.glob("events.out.tfevents.*"))
        writer = SummaryWriter(log_dir=str(folder))
        for scalar, (steps, values) in read_scalars(scalars_dir(out, name)).items():
            for step, value in zip(steps, values):
                writer.add_scalar(scalar, value, global_step=step)
                written += 1
        writer.flush()
        for path in older:
            path.unlink(missing_ok=True)
        inner.experiment = writer
    return written


def _kept(line: str, scalar: str, keep: Callable[[str, int], bool]) -> bool:
    """Whether one line is a whole ``step,value`` line that ``keep`` accepts."""
    step, _, value = line.partition(",")
    try:
        at, _ = int(step), float(value)
    except ValueError:  # cut short by a kill
        return False
    return keep(scalar, at)


def read_scalars(directory: Path) -> dict[str, tuple[list[int], list[float]]]:
    """Every ``<name>.csv`` under ``directory`` as ``name -> (steps, values)``, by step."""
    curves = {}
    for path in sorted(Path(directory).rglob("*.csv")):
        name = path.relative_to(directory).with_suffix("").as_posix()
        rows = [line.split(",") for line in path.read_text().splitlines() if line]
        rows.sort(key=lambda r: int(r[0]))
        curves[name] = ([int(s) for s, _ in rows], [float(v) for _, v in rows])
    return curves


@dataclass(frozen=True)
class Panel:
    """One loss panel of ``curves.png``: the scalars it draws against one x axis."""

    title: str
    series: tuple[str, ...]
    """scalar names, each drawn as one line (labelled by its name without the prefix)"""
    xlabel: str
    ylabel: str


@dataclass(frozen=True)
class Layout:
    """What a command logs: its loss panels, and what the evaluation's step counts."""

    panels: tuple[Panel, ...]
    eval_x: str
    """x label of the evaluation panel: "round" (BC, DAgger) or "env step" (GAIL, AIRL)"""


def _adversarial(name: str) -> Layout:
    """GAIL's and AIRL's scalars (:func:`imitrl.algorithms.adversarial.loop._log`)."""
    return Layout(
        panels=(
            Panel("discriminator", (f"{name}/discriminator_loss", f"{name}/discriminator_grad_penalty"),
                  "env step", "loss (last step of each round)"),
            Panel("generator (PPO policy)", (f"{name}/loss_objective", f"{name}/loss_entropy"),
                  "env step", "loss (mean of the round's last epoch)"),
            Panel("generator (PPO value)", (f"{name}/loss_critic",),
                  "env step", "loss (mean of the round's last epoch)"),
        ),
        eval_x="env step",
    )  # fmt: skip


_BC = Layout(
    panels=(Panel("loss per step", ("bc/loss",), "gradient step", "training loss"),),
    eval_x="round",
)
LAYOUTS = {"bc": _BC, "dagger": _BC, "gail": _adversarial("gail"), "airl": _adversarial("airl")}
"""what each command's ``curves.png`` draws, by command (the run folder's name)"""


def _loss_panel(ax, panel: Panel, curves: dict) -> None:
    """The panel's logged scalars, one line each (one that is 0 throughout, such as the
    gradient penalty when it is off, left out); log scale over a decade or more."""
    drawn = [n for n in panel.series if n in curves and any(v != 0 for v in curves[n][1])]
    values = [v for name in drawn for v in curves[name][1]]
    for i, name in enumerate(drawn):
        steps, value = curves[name]
        style = {"marker": "o", "ms": 3} if len(steps) < 30 else {}
        ax.plot(steps, value, lw=0.8, color=f"C{i}", label=name.split("/", 1)[-1], **style)
    if values and min(values) > 0 and max(values) >= 10 * min(values):
        ax.set_yscale("log")
    if len(drawn) > 1:
        ax.legend(loc="best", fontsize=7)
    ax.set(xlabel=panel.xlabel, ylabel=panel.ylabel, title=panel.title)


def _eval_panel(ax, curves: dict, xlabel: str) -> None:
    """Success rate at each evaluation where the env reports it (Meta-World), else the
    mean return (interval bars), the expert's as a dashed line."""
    metric, label = (
        ("success", "success rate") if "eval/success" in curves else ("return", "mean return")
    )
    if f"eval/{metric}" in curves:
        steps, mean = curves[f"eval/{metric}"]
        lo, hi = curves[f"eval/{metric}_lo"][1], curves[f"eval/{metric}_hi"][1]
        # one episode has no interval (NaN bounds): draw the point without a bar
        err = [
            [0.0 if math.isnan(a) else m - a for m, a in zip(mean, lo)],
            [0.0 if math.isnan(b) else b - m for m, b in zip(mean, hi)],
        ]
        ax.errorbar(steps, mean, yerr=err, marker="o", capsize=3, label="learner", zorder=3)
        if xlabel == "round":
            ax.set_xticks(steps)
    if f"eval/expert_{metric}" in curves:
        expert = curves[f"eval/expert_{metric}"][1][0]
        shown = f"{expert:.0%}" if metric == "success" else f"{expert:.1f}"
        ax.axhline(expert, color="tab:orange", ls="--", label=f"expert ({shown})")
    ax.set(xlabel=xlabel, ylabel=label, title=f"evaluation per {xlabel}")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="best", fontsize=8)


def plot_curves(directory: Path, path: Path, *, title: str, command: str | None = None) -> Path:
    """Losses vs step and return at each evaluation (interval bars, expert line), from the
    CSV files under ``directory``.

    ``command`` picks the panels (:data:`LAYOUTS`); None: the run folder's name, as
    :func:`scalars_dir` lays it out (``out/logs/csv/<command>/scalars``). A command
    without a layout draws every ``*loss*`` scalar against its step.
    """
    from matplotlib.figure import Figure  # imported when a run plots

    from imitrl.plotting import save_figure

    curves = read_scalars(directory)
    command = Path(directory).parent.name if command is None else command
    layout = LAYOUTS.get(command) or Layout(
        panels=(Panel("losses", tuple(n for n in curves if "loss" in n), "step", "loss"),),
        eval_x="step",
    )
    n = len(layout.panels) + 1
    cols = 2 if n > 2 else n
    rows = -(-n // cols)
    fig = Figure(figsize=(5.0 * cols, 3.6 * rows + 0.3))
    axes = fig.subplots(rows, cols, squeeze=False).ravel()
    for ax, panel in zip(axes, layout.panels):
        _loss_panel(ax, panel, curves)
    _eval_panel(axes[len(layout.panels)], curves, layout.eval_x)
    for ax in axes[n:]:
        ax.set_visible(False)
    fig.suptitle(title)
    return save_figure(fig, path, dpi=120)
