"""``loss_functions.py``'s statistics, tables and figure, from the raw rows of a run."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

import _report
from _loss_functions.tasks import TASKS, TwoWay
from imitrl.evaluation import t_interval
from imitrl.objectives import registry

NAME = "loss_functions"
UNIT_SCORES = ("frozenlake", "two_way")
"""tasks whose score is a probability"""


# ------------------------------------------------------------------- statistics
def summarize(rows: list[dict], references: list[dict]) -> dict[str, Any]:
    """Per (task, loss, algorithm): mean and interval of the score and the normalised score."""
    ref = {}
    for task in {r["task"] for r in references}:
        e = t_interval(
            [r["score"] for r in references if r["task"] == task and r["policy"] == "expert"]
        )
        z = t_interval(
            [r["score"] for r in references if r["task"] == task and r["policy"] == "random"]
        )
        ref[task] = {"expert": e[0], "random": z[0]}
    for r in rows:
        e, z = ref[r["task"]]["expert"], ref[r["task"]]["random"]
        r["normalized"] = (r["score"] - z) / (e - z) if e != z else math.nan
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["task"], r["loss"], r["algorithm"]), []).append(r)
    summary = []
    for (task, loss, algorithm), rs in groups.items():
        entry = {"task": task, "loss": loss, "algorithm": algorithm, "seeds": len(rs)}
        for metric in ("score", "normalized"):
            entry[metric] = t_interval([r[metric] for r in rs])
        if task == "two_way":
            for metric in [k for k in rs[0] if k.startswith("modes") or k == "passed_above"]:
                entry[metric] = t_interval([r[metric] for r in rs])
        summary.append(entry)
    return {"reference": ref, "groups": summary}


def _digits(task: str) -> int:
    return 3 if task in UNIT_SCORES else 1


def _losses(groups: list[dict], task: str | None = None) -> list[str]:
    """Loss names in the groups (of ``task``), registry order first."""
    present = [g["loss"] for g in groups if task is None or g["task"] == task]
    known = [n for n in registry.names() if n in present]
    return known + [n for n in dict.fromkeys(present) if n not in known]


def _group(groups: list[dict], task: str, loss: str, algorithm: str) -> dict | None:
    found = [g for g in groups if (g["task"], g["loss"], g["algorithm"]) == (task, loss, algorithm)]
    return found[0] if found else None


def verdict(group: dict) -> str:
    """A sentence from the measured mode fractions (never assumed)."""
    below, middle, above = (group[f"modes_{k}"] for k in ("below", "middle", "above"))
    if below[1] > 0.1 and above[1] > 0.1:
        return "keeps both modes (each mode's lower 95% bound > 0.1)"
    if middle[0] > 0.5:
        return "averages the modes (most actions near their mean, 0)"
    if min(below[0], above[0]) < 0.05 and max(below[0], above[0]) > 0.5:
        return "collapses to one mode"
    return "mixed: neither both modes nor one clearly"


# ------------------------------------------------------------------------ tables
def markdown(
    summary: dict, config: dict, protocols: dict[str, dict], wall: float, figure: str | None
) -> str:
    jobs = config["jobs"]
    # where the files went does not change a number
    command = re.sub(
        r" --out \S+", "", config.get("command", "python benchmarks/loss_functions.py")
    )
    lines = [
        f"{'Smoke' if config['quick'] else 'Full'} run: `{command}`, {config['seeds']} seeds, "
        f"**wall time {wall / 60:.1f} min** on {config.get('cpu_count', '?')} CPU cores "
        f"({jobs} process{'es' if jobs > 1 else ''}, 1 torch thread each; wall times move with "
        "the machine's load, the scores do not).",
        "",
        "Score: FrozenLake = exact success probability (from the MDP); CartPole, Pendulum, "
        "InvertedPendulum = mean return over held-out episodes; two-way = success rate. "
        "Normalised = (score - random) / (expert - random). Mean [95% t-interval] over seeds "
        "(clipped to [0, 1] for probabilities). "
        "BC = DAgger's round 0; DAgger = its last round.",
        "",
        score_table(summary),
    ]
    if any(g["task"] == "two_way" for g in summary["groups"]):
        lines += ["", two_way_table(summary)]
    lines += [
        "",
        "Budget per task (identical for every loss; one learner per seed and round):",
        "",
        budget_table(protocols),
    ]
    if figure:
        lines += ["", f"![normalised scores and two-way mode fractions]({figure})"]
    return "\n".join(lines)


def score_table(summary: dict) -> str:
    groups, ref = summary["groups"], summary["reference"]
    header = ["task", "loss", "BC score", "BC normalised", "DAgger score", "DAgger normalised"]
    rows = []
    for task in [t for t in TASKS if t in ref]:
        d, unit = _digits(task), task in UNIT_SCORES
        expert, random = ref[task]["expert"], ref[task]["random"]
        rows.append([f"**{task}**", f"expert {expert:.{d}f}, random {random:.{d}f}", *[""] * 4])
        for loss in _losses(groups, task):
            bc, dg = _group(groups, task, loss, "bc"), _group(groups, task, loss, "dagger")
            if bc is None:
                continue
            rows.append(
                [
                    task,
                    loss,
                    _report.fmt_ci(bc["score"], d, unit=unit),
                    _report.fmt_ci(bc["normalized"]),
                    _report.fmt_ci(dg["score"], d, unit=unit),
                    _report.fmt_ci(dg["normalized"]),
                ]
            )
    return _report.table(header, rows)


def two_way_table(summary: dict) -> str:
    two_way = [g for g in summary["groups"] if g["task"] == "two_way"]
    header = [
        "loss",
        "algorithm",
        "below",
        "neither",
        "(middle)",
        "above",
        "success",
        "passed above",
        "verdict",
    ]
    rows = []
    for loss in _losses(two_way):
        for algorithm in ("bc", "dagger"):
            g = _group(two_way, "two_way", loss, algorithm)
            if g is None:
                continue
            cells = ("modes_below", "modes_neither", "modes_middle", "modes_above")
            cells += ("score", "passed_above")
            rows.append(
                [loss, algorithm, *[_report.fmt_ci(g[c], unit=True) for c in cells], verdict(g)]
            )
    return _report.section(
        "**Two-way obstacle: does the learner keep both of the expert's modes?** Fraction "
        f"of the learner's actions at {TwoWay.decision_states} decision states within 0.25 "
        "of the expert's pass-below action (-0.5), of its pass-above action (+0.5), and "
        "near neither (of which *middle*: within 0.25 of the modes' mean, 0); the "
        "policy acts as its entry says (sampled for diffusion, greedy/mean otherwise). "
        "Mean [95% t-interval] over seeds; the verdict is computed from these numbers.",
        _report.table(header, rows),
    )


def budget_table(protocols: dict[str, dict]) -> str:
    header = [
        "task",
        "demo episodes",
        "DAgger rounds x episodes",
        "fit steps x batch",
        "network",
        "lr",
        "eval",
    ]
    rows = []
    for task, p in protocols.items():
        bc = p["bc"] if "bc" in p else p["fit"]  # results written before Protocol.fit -> .bc
        rows.append(
            [
                task,
                p["demo_episodes"],
                f"{p['rounds'] - 1} x {p['episodes_per_round']}",
                f"{bc['num_steps']} x {bc['batch_size'] or 'full'}",
                "table" if task == "frozenlake" else "x".join(map(str, p["learner"]["hidden"])),
                p["learner"]["lr"],
                "exact" if task == "frozenlake" else f"{p['eval_episodes']} episodes",
            ]
        )
    return _report.table(header, rows)


# ------------------------------------------------------------------------ figure
def figure(summary: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = summary["groups"]
    tasks = [t for t in TASKS if any(g["task"] == t for g in groups)]
    cols = 3
    rows = math.ceil((len(tasks) + 1) / cols)
    fig, grid = plt.subplots(rows, cols, figsize=(5.2 * cols, 3.6 * rows), squeeze=False)
    axes = list(grid.reshape(-1))
    for ax in axes[len(tasks) + 1 :]:
        ax.set_visible(False)
    for ax, task in zip(axes, tasks):
        _score_panel(ax, groups, task)
    axes[0].legend(loc="lower right")
    _modes_panel(axes[len(tasks)], groups)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _score_panel(ax, groups: list[dict], task: str) -> None:
    """Normalised BC and DAgger scores of every loss on ``task``, with intervals."""
    losses = _losses(groups, task)
    for j, (algorithm, colour) in enumerate((("bc", "tab:blue"), ("dagger", "tab:orange"))):
        for i, loss in enumerate(losses):
            mean, lo, hi = _group(groups, task, loss, algorithm)["normalized"]
            err = [[mean - lo], [hi - mean]] if not math.isnan(lo) else None
            ax.barh(
                i + 0.4 * j - 0.2,
                mean,
                height=0.4,
                color=colour,
                xerr=err,
                capsize=2,
                label=algorithm if i == 0 else None,
            )
    ax.set_yticks(range(len(losses)), losses)
    ax.axvline(1.0, color="k", lw=0.8, ls="--")
    ax.axvline(0.0, color="k", lw=0.8)
    ax.set_title(task)
    ax.set_xlabel("expert-normalised score")
    ax.invert_yaxis()


def _modes_panel(ax, groups: list[dict]) -> None:
    """Where the two-way BC learners' actions fall at the decision states."""
    two_way = [g for g in groups if g["task"] == "two_way" and g["algorithm"] == "bc"]
    if not two_way:
        return
    names = [g["loss"] for g in two_way]
    left = [0.0] * len(names)
    parts = {
        "near -0.5 (below)": [g["modes_below"][0] for g in two_way],
        "near 0 (the mean)": [g["modes_middle"][0] for g in two_way],
        "elsewhere": [g["modes_neither"][0] - g["modes_middle"][0] for g in two_way],
        "near +0.5 (above)": [g["modes_above"][0] for g in two_way],
    }
    colours = ("tab:green", "tab:red", "tab:gray", "tab:purple")
    for (part, values), colour in zip(parts.items(), colours):
        ax.barh(names, values, left=left, color=colour, label=part)
        left = [a + b for a, b in zip(left, values)]
    ax.set_xlim(0, 1)
    ax.set_title("two_way, BC: actions at the decision")
    ax.set_xlabel("fraction of actions (mean over seeds)")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=2, fontsize=8)
    ax.invert_yaxis()


# ------------------------------------------------------------------------ output
def report(raw: dict[str, Any], out_dir: Path | None) -> str:
    """Summary, figure, results JSON and (``out_dir`` None) the README block, from raw rows."""
    summary = summarize(raw["rows"], raw["references"])
    raw["config"].setdefault("cpu_count", raw.get("machine", {}).get("cpu_count", "?"))
    fig_path = _report.results_dir(out_dir) / f"{NAME}.png"
    figure(summary, fig_path)
    md = markdown(
        summary, raw["config"], raw["protocols"], raw["wall_seconds"], f"results/{fig_path.name}"
    )
    payload = {**raw, "summary": summary}
    path = _report.write(NAME, json.loads(json.dumps(payload, default=str)), md, out_dir=out_dir)
    print(md)
    print(f"\nwrote {path} and {fig_path}")
    return md
