"""``loss_functions.py``'s aggregate statistics across tasks and seeds: table and figure.

The estimators of Agarwal et al. (2021) from :mod:`imitrl.evaluation.aggregate`, on
the expert-normalised scores ``[seeds, tasks]`` of each loss (a run is a seed: one
trained learner per task, evaluated over its episodes), over the tasks every continuous
loss applies to (the tasks MSE ran on): interquartile mean, optimality gap (``gamma =
1``, the expert), probability of improvement over MSE, each with a 95% stratified
percentile-bootstrap interval (the seeds of each task resampled, the tasks kept), and
performance profiles (the fraction of runs above each normalised score ``tau``),
with their bootstrap bands.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

import _report
from imitrl.evaluation.aggregate import (
    iqm,
    optimality_gap,
    performance_profile,
    probability_of_improvement,
    stratified_bootstrap,
    stratified_bootstrap_pair,
)

BASELINE = "mse"
"""the loss every other one is compared with (probability of improvement)"""
REPS = 2000
"""bootstrap replicates of a full run (``--reps``)"""
TAUS = np.linspace(0.0, 1.0, 41)
"""thresholds of the performance profiles (normalised score)"""
ALGORITHMS = ("bc", "dagger")


def score_matrices(rows: list[dict], losses: list[str]) -> tuple[list[str], dict]:
    """The tasks the baseline ran on, and ``{(loss, algorithm): [seeds, tasks]}`` of the
    normalised scores of every loss that ran on all of them, seeds in common."""
    tasks = list(dict.fromkeys(r["task"] for r in rows if r["loss"] == BASELINE))
    out = {}
    for loss in losses:
        for algorithm in ALGORITHMS:
            by_task = {
                t: {r["seed"]: r["normalized"] for r in rows
                    if (r["task"], r["loss"], r["algorithm"]) == (t, loss, algorithm)}
                for t in tasks
            }  # fmt: skip
            if not tasks or any(not v for v in by_task.values()):
                continue
            seeds = sorted(set.intersection(*(set(v) for v in by_task.values())))
            if seeds:
                out[(loss, algorithm)] = np.array([[by_task[t][s] for t in tasks] for s in seeds])
    return tasks, out


def aggregate(rows: list[dict], losses: list[str], *, reps: int = REPS) -> dict:
    """Point estimates and ``reps``-replicate bootstrap intervals of every loss and
    algorithm (JSON-able)."""
    tasks, scores = score_matrices(rows, losses)
    entries = []
    for (loss, algorithm), x in scores.items():
        entry = {"loss": loss, "algorithm": algorithm, "runs": x.shape[0]}
        for name, statistic in (("iqm", iqm), ("optimality_gap", optimality_gap)):
            ci = stratified_bootstrap(x, statistic, reps=reps, seed=0)
            entry[name] = (ci.point, ci.low, ci.high)
        base = scores.get((BASELINE, algorithm))
        if base is not None and loss != BASELINE and base.shape == x.shape:
            ci = stratified_bootstrap_pair(x, base, probability_of_improvement, reps=reps, seed=0)
            entry["p_improve"] = (ci.point, ci.low, ci.high)
        point, low, high = stratified_bootstrap(
            x, lambda s: performance_profile(s, TAUS), reps=reps, seed=0
        )
        entry["profile"] = [point.tolist(), low.tolist(), high.tolist()]
        entries.append(entry)
    return {"tasks": tasks, "taus": TAUS.tolist(), "reps": reps, "entries": entries}


def table(agg: dict) -> str:
    """IQM, optimality gap and P(loss > MSE) with their intervals, one row per loss."""
    header = ["loss", "BC IQM", "BC optimality gap", "BC P(> MSE)"]
    header += ["DAgger IQM", "DAgger optimality gap", "DAgger P(> MSE)"]
    nan = (math.nan, math.nan, math.nan)
    by = {(e["loss"], e["algorithm"]): e for e in agg["entries"]}
    rows = []
    for loss in dict.fromkeys(e["loss"] for e in agg["entries"]):
        cells = [loss]
        for algorithm in ALGORITHMS:
            e = by.get((loss, algorithm), {})
            cells += [_report.fmt_ci(e.get(k, nan)) for k in ("iqm", "optimality_gap")]
            cells.append(_report.fmt_ci(e["p_improve"]) if "p_improve" in e else "-")
        rows.append(cells)
    return _report.table(header, rows)


def markdown(agg: dict, figure: str | None) -> str:
    text = _report.section(
        f"**Aggregate over the continuous tasks** ({', '.join(agg['tasks'])}; Agarwal et al. "
        "2021): interquartile mean (IQM) and optimality gap (mean shortfall below the "
        "expert, 0 is best) of the expert-normalised scores, and the probability that the "
        f"loss beats {BASELINE.upper()} on a task (P > 0.5: better). A run is a seed; "
        f"[95% stratified bootstrap interval, {agg.get('reps', REPS)} replicates: the seeds of each task "
        "resampled].",
        table(agg),
    )
    if figure:
        text += f"\n\n![aggregate statistics and performance profiles]({figure})"
    return text


def figure(agg: dict, path: Path) -> None:
    """IQM, optimality gap, P(> MSE) with intervals; performance profiles for BC and DAgger."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    entries = agg["entries"]
    losses = list(dict.fromkeys(e["loss"] for e in entries))
    by = {(e["loss"], e["algorithm"]): e for e in entries}
    fig = plt.figure(figsize=(16, 10))
    grid = fig.add_gridspec(2, 3, height_ratios=[1.1, 1])
    colours = {"bc": "tab:blue", "dagger": "tab:orange"}
    metrics = (
        ("iqm", "IQM of normalised score (higher is better)"),
        ("optimality_gap", "optimality gap (lower is better)"),
        ("p_improve", f"P(loss > {BASELINE.upper()})"),
    )
    for col, (metric, title) in enumerate(metrics):
        ax = fig.add_subplot(grid[0, col])
        for j, algorithm in enumerate(ALGORITHMS):
            for i, loss in enumerate(losses):
                e = by.get((loss, algorithm), {})
                if metric not in e:
                    continue
                point, low, high = e[metric]
                ax.errorbar(
                    point, i + 0.18 * (2 * j - 1), xerr=[[point - low], [high - point]],
                    fmt="o", color=colours[algorithm], ms=4, capsize=2,
                    label=algorithm if i == 0 else None,
                )  # fmt: skip
        if metric == "p_improve":
            ax.axvline(0.5, color="k", lw=0.8, ls="--")
            ax.set_xlim(0, 1)
        ax.set_yticks(range(len(losses)), losses if col == 0 else [""] * len(losses))
        ax.set_ylim(len(losses) - 0.5, -0.5)
        ax.grid(axis="x", alpha=0.3)
        ax.set_title(title, fontsize=10)
        if col == 0:
            marks = ax.get_legend_handles_labels()  # drawn in the legend panel, off the data
    cmap = plt.get_cmap("tab20")
    taus = np.asarray(agg["taus"])
    for col, algorithm in enumerate(ALGORITHMS):
        ax = fig.add_subplot(grid[1, col])
        for i, loss in enumerate(losses):
            e = by.get((loss, algorithm))
            if e is None:
                continue
            point, low, high = (np.asarray(v) for v in e["profile"])
            style = "-" if i < 10 else "--"
            ax.plot(taus, point, style, color=cmap(i % 20), lw=1.4, label=loss)
            ax.fill_between(taus, low, high, color=cmap(i % 20), alpha=0.08)
        ax.set_xlabel("normalised score tau")
        ax.set_ylabel("fraction of runs with score > tau")
        ax.set_title(f"performance profiles, {algorithm.upper()}", fontsize=10)
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
    handles, labels = fig.axes[-1].get_legend_handles_labels()
    legend_ax = fig.add_subplot(grid[1, 2])
    legend_ax.axis("off")
    legend_ax.add_artist(
        legend_ax.legend(*marks, loc="upper center", ncol=2, fontsize=9, title="algorithm")
    )
    legend_ax.legend(handles, labels, loc="lower center", ncol=2, fontsize=9, title="loss")
    fig.suptitle(
        f"Aggregate over {', '.join(agg['tasks'])} (runs = seeds; 95% stratified bootstrap)",
        fontsize=11,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
