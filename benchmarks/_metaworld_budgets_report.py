"""``metaworld_budgets.py``'s tables and figure: success per (task, loss, rung), the
expert-normalised IQM against fit time, how much each loss still fell late in its fit,
and each loss's top rung paired against ``mse``'s."""

from __future__ import annotations

import statistics
from collections import defaultdict
from pathlib import Path

import numpy as np

import _report
from _metaworld_report import fmt_rate, pooled
from _paired import paired_differences, paired_table
from imitrl.evaluation.aggregate import iqm, stratified_bootstrap
from imitrl.plotting import save_figure

BASELINE = "mse"
REPS = 2000


def _split(name: str) -> tuple[str, str, int]:
    task, loss, steps = name.split("/")
    return task, loss, int(steps)


def groups(payload: dict) -> tuple[dict, dict]:
    """``{(task, loss, steps): rows over seeds}`` and ``{task: the expert's rows}``."""
    cells: dict = defaultdict(list)
    for r in payload["rows"]:
        cells[_split(r["task"])].append(r)
    expert: dict = defaultdict(list)
    for r in payload["references"]:
        if r["policy"] == "expert":
            expert[r["task"]].append(r)
    return cells, expert


def rungs(payload: dict) -> list[tuple[str, int]]:
    """(loss, steps) in the config's order, fewest steps first."""
    budgets = payload["config"]["budgets"]
    return [(loss, s) for loss in payload["config"]["losses"] for s in budgets[loss]["steps"]]


def normalised(payload: dict) -> dict:
    """``{(loss, steps): [seeds, tasks]}`` of success / the expert's on the same seed's
    held-out starts (1 where the expert failed every episode)."""
    cells, expert = groups(payload)
    tasks = payload["config"]["tasks"]
    seed_row = {s: i for i, s in enumerate(sorted({r["seed"] for r in payload["rows"]}))}
    out = {}
    for loss, steps in rungs(payload):
        grid = np.full((len(seed_row), len(tasks)), np.nan)
        for j, task in enumerate(tasks):
            ref = {r["seed"]: r["score"] for r in expert[task]}
            for r in cells[(task, loss, steps)]:
                e = ref.get(r["seed"], 0.0)
                grid[seed_row[r["seed"]], j] = r["score"] / e if e > 0 else 1.0
        if not np.isnan(grid).any():
            out[(loss, steps)] = grid
    return out


def late_drop(curve: list[float]) -> float:
    """How much a training loss still fell late: 1 - (mean of the curve's last fifth) /
    (mean of the fifth before it); near 0 where the fit has flattened."""
    k = max(1, len(curve) // 5)
    last, before = np.mean(curve[-k:]), np.mean(curve[-2 * k : -k])
    return float(1.0 - last / before) if before > 0 else float("nan")


def _median(rows: list[dict], key: str) -> float:
    return statistics.median(r[key] for r in rows)


def aggregate_rows(payload: dict) -> list[dict]:
    """Per (loss, steps): IQM interval, pooled success, median fit seconds, median late
    drop of the training loss."""
    cells, _ = groups(payload)
    scores = normalised(payload)
    out = []
    for loss, steps in rungs(payload):
        rows = [r for t in payload["config"]["tasks"] for r in cells[(t, loss, steps)]]
        if not rows or (loss, steps) not in scores:
            continue
        curves = [r["loss_curve"] for r in rows if len(r.get("loss_curve") or []) >= 2]
        out.append(
            {
                "loss": loss,
                "steps": steps,
                "fit_steps": rows[0]["fit_steps"],  # the rung's (a --quick run's are tiny)
                "batch": rows[0]["fit_batch"],
                "iqm": stratified_bootstrap(scores[(loss, steps)], iqm, reps=REPS),
                "success": pooled(rows),
                "fit_seconds": _median(rows, "fit_seconds"),
                "late_drop": statistics.median(late_drop(c) for c in curves) if curves else None,
            }
        )
    return out


def _top_paired(payload: dict) -> tuple[str, str]:
    """Each loss's top rung against every rung of ``mse``, paired by task and seed: mse's
    own budget is not its longest fit (its success falls as its loss keeps falling), so
    each of its rungs is named beside the difference."""
    cells, _ = groups(payload)
    budgets = payload["config"]["budgets"]
    losses = payload["config"]["losses"]
    if BASELINE not in losses or len(losses) < 2:
        return "", ""
    found = []
    for loss in (x for x in losses if x != BASELINE):
        top = f"{loss} {budgets[loss]['steps'][-1]}"
        for steps in budgets[BASELINE]["steps"]:
            ref = f"{BASELINE} {steps}"
            rows = [{**r, "task": task, "loss": f"{x} {n}"} for (task, x, n), got in cells.items()
                    if f"{x} {n}" in (top, ref) for r in got]  # fmt: skip
            pairs = paired_differences(rows, lambda task, ref=ref: ref, group=("loss",))
            found += [{**f, "group": (top, ref)} for f in pairs]
    text = (
        f"Each loss at its own budget (its last rung) against each rung of {BASELINE}: success "
        "rate minus mse's on the same task and seed (the same demonstrations and held-out "
        "starts), mean over the task-seed pairs with a 95% t interval (`_paired.py`)."
    )
    return text, paired_table(found, ("loss and steps", "against"))


def _wall(payload: dict) -> str:
    """The run's wall time and load, or (a merged report) each part's."""
    if payload["config"]["jobs"] == "merged":
        return (
            f"Merged from runs of disjoint rungs ({'; '.join(payload['merged_from'])}), each "
            f"process at 1 thread on 2 cores; their wall times sum to "
            f"{payload['wall_seconds'] / 60:.1f} min."
        )
    return (
        f"Wall time {payload['wall_seconds'] / 60:.1f} min with {payload['config']['jobs']} "
        f"process(es) at 1 thread, 1-min load {payload['load_average_start'][0]:.2f} at the "
        f"start and {payload['load_average_end'][0]:.2f} at the end (2 cores)."
    )


def _horizons(config: dict) -> str:
    """Where a run holds ``diffusion_unet_mw``: how its chunks differ from
    ``diffusion_unet``'s (empty otherwise, so earlier runs render as they did)."""
    if "diffusion_unet_mw" not in config["losses"]:
        return ""
    return (
        " (predicting 16 actions, executing 8), diffusion_unet_mw the same network and recipe "
        "at the published Meta-World Diffusion Policy's horizons (predicting 4 actions from 2 "
        "observations, executing 3: DP3's `dp3.yaml`, arXiv 2403.03954)"
    )


def markdown(payload: dict, figure_name: str) -> str:
    config, proto = payload["config"], payload["config"]["protocol"]
    head = (
        f"MT10 tasks {len(config['tasks'])}, BC from {proto['demo_episodes']} demonstrations "
        f"of the scripted expert, {config['seeds']} seed(s); each loss at the fit steps of "
        f"its own (`BUDGETS`), its recipe's schedule at every rung; mse's MLP "
        f"{proto['learner']['hidden']} at lr {proto['learner']['lr']}, diffusion_unet at the "
        f"registry's CPU widths{_horizons(config)}; evaluation {proto['eval_episodes']} "
        "held-out episodes of at "
        f"most 500 steps (Meta-World's own limit), success = `info['success']` at any step. "
        + _wall(payload)
    )
    agg = aggregate_rows(payload)
    table = _report.table(
        ["loss", "fit steps x batch", "median fit s", "loss fall over the last fifth",
         "success (pooled)", "IQM, expert-normalised [95% CI]"],
        [[a["loss"], f"{a['fit_steps']} x {a['batch']}", f"{a['fit_seconds']:.1f}",
          "-" if a["late_drop"] is None else f"{100 * a['late_drop']:.1f}%",
          fmt_rate(*a["success"]), f"{a['iqm'].point:.2f} [{a['iqm'].low:.2f}, {a['iqm'].high:.2f}]"]
         for a in agg],
    )  # fmt: skip
    cells, expert = groups(payload)
    per_task = _report.table(
        ["task", *[f"{loss} {steps}" for loss, steps in rungs(payload)], "expert"],
        [[task, *[fmt_rate(*pooled(cells[(task, loss, steps)])) for loss, steps in rungs(payload)],
          fmt_rate(*pooled(expert[task]))] for task in config["tasks"]],
    )  # fmt: skip
    paired_text, paired = _top_paired(payload)
    parts = [
        head,
        "Across tasks, per loss and rung: the median fit's seconds (one thread), how much "
        "the training loss still fell over its last fifth (1 - the mean of the last fifth of "
        "its curve / the mean of the fifth before; median over fits), success pooled over "
        "every task and seed (95% Wilson), and the IQM of the expert-normalised success "
        "(success / the expert's on the same held-out starts) with its 95% stratified "
        f"bootstrap interval over seeds ({REPS} replicates).",
        table,
    ]
    if paired:
        parts += [paired_text, paired]
    parts += ["Success rate per task and rung (pooled over seeds, 95% Wilson interval).",
              per_task, f"![Each loss at its own budget]({figure_name})"]  # fmt: skip
    return "\n\n".join(parts)


def figure(payload: dict, path: Path) -> Path:
    """Left: IQM against the median fit's seconds, a line per loss over its rungs.
    Right: each loss's training loss at its last rung, relative to its first window,
    median and quartiles over tasks and seeds."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    agg = aggregate_rows(payload)
    cells, _ = groups(payload)
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.2))
    for k, loss in enumerate(payload["config"]["losses"]):
        mine = [a for a in agg if a["loss"] == loss]
        if not mine:
            continue
        x = [a["fit_seconds"] for a in mine]
        y = np.array([a["iqm"].point for a in mine])
        err = np.array([[a["iqm"].point - a["iqm"].low for a in mine],
                        [a["iqm"].high - a["iqm"].point for a in mine]])  # fmt: skip
        line = ax.errorbar(x, y, yerr=err, marker="o", capsize=3, label=loss)
        for a in mine:  # centred under its interval, every other loss's over it, in its
            # colour: rungs close in time, or two losses' rungs at one time, never collide
            up = k % 2 == 1
            ax.annotate(str(a["fit_steps"]), (a["fit_seconds"], a["iqm"].high if up else a["iqm"].low),
                        ha="center", va="bottom" if up else "top", textcoords="offset points",
                        xytext=(0, 4 if up else -4), fontsize=8, color=line[0].get_color())  # fmt: skip
        top = payload["config"]["budgets"][loss]["steps"][-1]
        curves = [np.asarray(r["loss_curve"]) for t in payload["config"]["tasks"]
                  for r in cells[(t, loss, top)] if len(r.get("loss_curve") or []) >= 2]  # fmt: skip
        if curves:
            rel = np.stack([c / c[0] for c in curves])
            done = cells[(payload["config"]["tasks"][0], loss, top)][0]["fit_steps"]
            steps = np.linspace(done / len(curves[0]), done, len(curves[0]))
            q1, med, q3 = np.quantile(rel, [0.25, 0.5, 0.75], axis=0)
            color = line[0].get_color()
            bx.plot(steps, med, color=color, label=f"{loss} ({done} steps)")
            bx.fill_between(steps, q1, q3, color=color, alpha=0.2)
    ax.set_xscale("log")
    lo, hi = ax.get_xlim()
    ax.set_xlim(lo / 1.5, hi * 1.5)  # room for the outer rungs' labels inside the axes
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_xlabel("median fit time per task and seed (s, one thread)")
    ax.set_ylabel("IQM of success / expert's (95% CI)")
    ax.set_ylim(-0.02, 1.05)
    ax.set_title("Success against fit time (labels: fit steps)")
    ax.legend(loc="lower right")
    bx.set_yscale("log")
    bx.set_xlabel("gradient step")
    bx.set_ylabel("training loss / its first window's")
    bx.set_title("Training loss at the last rung (median, quartiles)")
    bx.legend(loc="upper right")
    fig.suptitle(f"MT10 BC, {len(payload['config']['tasks'])} tasks, "
                 f"{payload['config']['seeds']} seed(s)")  # fmt: skip
    fig.tight_layout()
    return save_figure(fig, path)
