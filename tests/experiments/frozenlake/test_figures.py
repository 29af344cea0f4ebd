"""Every figure the project writes keeps its labels inside the canvas.

Each test draws figures with the real plotting functions (a small study run, synthetic
inputs with long labels, training curves from CSV scalars, the benchmarks' figures from
their committed results) while :class:`matplotlib.figure.Figure`'s ``savefig`` is
recorded, then asserts :func:`imitrl.plotting.outside_canvas` finds nothing cut off.
"""

from __future__ import annotations

import json
import os
import stat
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from matplotlib.figure import Figure
from torchrl.record.loggers import CSVLogger

from imitrl.cli import main
from imitrl.evaluation.evaluate import wilson_interval
from imitrl.experiments.frozenlake import figures, figures_irl, outputs
from imitrl.jobs.curves import plot_curves, scalars_dir
from imitrl.plotting import outside_canvas

BENCH = Path(__file__).resolve().parents[3] / "benchmarks"
SMALL = ["--no-progress", "--eval-episodes", "50", "--sweep-sizes", "1,3",
         "--sweep-datasets", "2", "--sweep-eval-episodes", "20", "--chain-samples", "200",
         "--dagger-rounds", "2", "--irl-steps", "5", "--irl-sizes", "1", "--irl-datasets", "2",
         "--ex-datasets", "3", "--ex-demo-counts", "1,3"]  # fmt: skip


@pytest.fixture
def saved(monkeypatch) -> dict[str, Figure]:
    """Every figure saved while the test runs, by file stem (``Figure.savefig`` recorded)."""
    drawn: dict[str, Figure] = {}
    real = Figure.savefig

    def savefig(self, fname, *args, **kwargs):
        real(self, fname, *args, **kwargs)
        drawn[Path(fname).stem] = self

    monkeypatch.setattr(Figure, "savefig", savefig)
    return drawn


def _cut_off(drawn: dict[str, Figure]) -> dict[str, list[str]]:
    """``figure -> [text of each artist outside the canvas]`` for the figures that have any."""
    bad = {}
    for name, fig in drawn.items():
        out = outside_canvas(fig)
        if out:
            bad[name] = [getattr(a, "get_text", lambda a=a: type(a).__name__)() for a in out]
    return bad


def test_the_check_finds_a_label_off_the_canvas():
    fig = Figure(figsize=(3, 2), layout="constrained")
    ax = fig.add_subplot(1, 1, 1)
    ax.set_xlabel("inside")
    fig.text(1.05, 0.5, "past the right edge")
    assert [a.get_text() for a in outside_canvas(fig)] == ["past the right edge"]
    fig = Figure(figsize=(3, 2))  # default margins: the x tick labels and label fall off
    fig.add_subplot(1, 1, 1).set_xlabel("below")
    assert "below" in [a.get_text() for a in outside_canvas(fig)]


def test_study_figures_of_a_small_run(tmp_path, saved):
    """The study's own inputs: dagger.png's two-line ticks, ex_budget.png's 0.7275 ticks."""
    umask = os.umask(0o022)  # a common umask, whatever this process had
    try:
        assert main(["frozenlake", "--out", str(tmp_path / "out"), *SMALL]) == 0
    finally:
        os.umask(umask)
    assert set(saved) == set(outputs.FIGURES)
    assert _cut_off(saved) == {}
    # issue 44: the study's folder was 0700 (tempfile.mkdtemp) unlike every other output
    assert stat.S_IMODE((tmp_path / "out").stat().st_mode) == 0o755


@pytest.mark.parametrize(
    "env, flags",
    [
        ("CliffWalking-v1", ["--max-steps", "60", "--probe-states", "0,36"]),
        ("Taxi-v4", ["--no-irl", "--probe-states", "0,1"]),
    ],
)
def test_study_figures_of_other_envs(tmp_path, saved, env, flags):
    out = tmp_path / "out"
    assert main(["frozenlake", "--out", str(out), "--env-id", env, "--no-exercises",
                 *SMALL, *flags]) == 0  # fmt: skip
    assert _cut_off(saved) == {}
    occupancy = saved["occupancy"]
    if env.startswith("CliffWalking"):  # a 4 x 12 grid, one map per policy
        assert [im.get_array().shape for ax in occupancy.axes for im in ax.images] == [(4, 12)] * 2
    else:  # no grid: curves, the expert's drawn above the clone's and unlike it
        (ax,) = [a for a in occupancy.axes if a.lines]
        lines = {line.get_label(): line for line in ax.lines}
        expert, clone = lines["expert occupancy"], lines["clone occupancy"]
        assert expert.get_zorder() > clone.get_zorder()
        assert expert.get_linestyle() != clone.get_linestyle()


def test_study_figures_with_long_labels(tmp_path, saved):
    """Synthetic inputs: many rounds with large pair counts, narrow ranges, many sizes."""
    n = 100
    rates = [0.0, 0.5, 1.0, 0.99]
    ci = [wilson_interval(int(r * n), n) for r in rates]
    figures.plot_dagger([3, 60_000, 120_000, 240_000], rates, ci, rates, 1.0, tmp_path / "d.png")
    budget = np.array([130, 200, 460, 12_000])
    near = np.array([0.7298765, 0.7110123, 0.7298765, 0.7298765])
    figures.plot_budget(budget, near, near - 1e-4, near, 0.7298765, tmp_path / "b.png")
    figures.plot_corruption(
        ["BC", "DAgger"], np.full((2, 3), 0.731234), np.full((2, 3), 0.7), tmp_path / "c.png"
    )
    sizes = [1, 3, 10, 30, 100]
    figures.plot_sweep(
        sizes, [np.ones(3) * 0.5] * 5, [np.ones(3) * 0.5] * 5, 0.7, tmp_path / "s.png"
    )
    counts = [1, 3, 10, 1000]
    figures.plot_demo_counts(counts, np.full((4, 3), 0.5), np.full((4, 3), 0.9), 0.7,
                             tmp_path / "dc.png")  # fmt: skip
    figures.plot_state_errors(np.array([0.0, 0.5, 1.0]), np.array([1.0, 0.0, 0.5]), [0, 14, 15],
                              tmp_path / "se.png")  # fmt: skip
    grid = np.array([list(b"SFFFFFFF"), list(b"FFFHFFFG")], dtype="S1")
    figures.plot_occupancy(grid, [np.full(16, 0.06)] * 2, [np.zeros(16)] * 2, ["a", "b"],
                           tmp_path / "o.png")  # fmt: skip
    figures.plot_occupancy(None, [np.full(48, 0.02)] * 2, [np.zeros(48)] * 2, ["a", "b"],
                           tmp_path / "o12.png", shape=(4, 12))  # fmt: skip
    figures_irl.plot_reward(grid, np.linspace(-3, 3, 16), np.zeros(16), tmp_path / "r.png")
    figures_irl.plot_irl_sweep({1: {k: np.ones(2) for k in ("irl", "bc", "dagger")}}, 0.7,
                               tmp_path / "irl.png")  # fmt: skip
    row = {m: {"normalised_return": 0.5} for m in ("airl_g", "airl_f", "maxent", "source_expert")}
    figures_irl.plot_airl_transfer([{"target": "source", "dataset": "10 episodes", **row}],
                                   tuple(row), tmp_path / "airl.png")  # fmt: skip
    figures.plot_chain([{"eps": 0.01, "cloned": np.ones(50), "cloned_exact": np.ones(50),
                         "recovering": np.ones(50)}] * 2, tmp_path / "ch.png")  # fmt: skip
    assert len(saved) == 12
    assert _cut_off(saved) == {}


def _log(out: Path, command: str, scalars: dict[str, list[tuple[int, float]]]) -> Path:
    logger = CSVLogger(exp_name=command, log_dir=str(out / "logs" / "csv"))
    for name, rows in scalars.items():
        for step, value in rows:
            logger.log_scalar(name, value, step=step)
    return scalars_dir(out, command)


def _evaluations(steps: list[int]) -> dict[str, list[tuple[int, float]]]:
    return {
        "eval/return": [(s, 100.0 + s / 100) for s in steps],
        "eval/return_lo": [(s, 90.0 + s / 100) for s in steps],
        "eval/return_hi": [(s, 110.0 + s / 100) for s in steps],
        "eval/expert_return": [(0, 500.0)],
    }


@pytest.mark.parametrize("command", ["bc", "dagger", "gail", "airl"])
def test_curves_draw_what_each_command_logs(tmp_path, saved, command):
    if command in ("bc", "dagger"):
        scalars = {"bc/loss": [(i, 1.0 / (i + 1)) for i in range(200)], **_evaluations([0, 1])}
        panels = ["loss per step"]
    else:
        steps = [2048 * (k + 1) for k in range(50)]
        scalars = {
            f"{command}/discriminator_loss": [(s, 1.3) for s in steps],
            f"{command}/discriminator_grad_penalty": [(s, 0.0) for s in steps],
            f"{command}/loss_objective": [(s, -0.01) for s in steps],
            f"{command}/loss_critic": [(s, 5.0) for s in steps],
            **_evaluations([0, *steps[9::10]]),
        }
        panels = ["discriminator", "generator (PPO policy)", "generator (PPO value)"]
    directory = _log(tmp_path, command, scalars)
    plot_curves(directory, tmp_path / "curves.png", title=f"imitrl {command} on CartPole-v1")
    fig = saved["curves"]
    axes = [ax for ax in fig.axes if ax.get_visible()]
    assert [ax.get_title() for ax in axes] == [*panels, axes[-1].get_title()]
    assert all(ax.lines for ax in axes)  # no empty panel
    (learner,) = [c for c in axes[-1].containers if c.get_label() == "learner"]
    assert list(learner.lines[0].get_xdata()) == [s for s, _ in scalars["eval/return"]]
    assert _cut_off(saved) == {}


def _benchmark(module: str):
    sys.path.insert(0, str(BENCH))
    try:
        return __import__(module, fromlist=["figure"])
    finally:
        sys.path.remove(str(BENCH))


def test_benchmark_figures_from_committed_results(tmp_path, saved):
    results = {n: json.loads((BENCH / "results" / f"{n}.json").read_text())
               for n in ("bc_vs_dagger", "beyond_cloning", "camera", "loss_functions")}  # fmt: skip
    r = results["bc_vs_dagger"]
    _benchmark("_bc_vs_dagger_report").figure(r, SimpleNamespace(**r["config"]), tmp_path / "a.png")
    _benchmark("_beyond_cloning_report").figure(results["beyond_cloning"], tmp_path / "b.png")
    r = results["camera"]
    _benchmark("camera").figure(r, SimpleNamespace(**r["config"]), tmp_path / "c.png")
    summary = results["loss_functions"]["summary"]
    _benchmark("_loss_functions.report").figure(summary, tmp_path / "d.png")
    if summary.get("aggregate", {}).get("entries"):
        _benchmark("_loss_functions.aggregate").figure(summary["aggregate"], tmp_path / "e.png")
    assert {"a", "b", "c", "d"} <= set(saved)
    assert _cut_off(saved) == {}
