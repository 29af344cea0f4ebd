"""``loss_functions.py``'s statistics, tables and figure, from the raw rows of a run."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

import _report
from _loss_functions import aggregate
from _paired import paired_differences, paired_table
from imitrl.envs import corridor, multimodal
from imitrl.evaluation import t_interval
from imitrl.learners import registry
from imitrl.learners.act.entries import ACT_BATCH, ACT_LR

NAME = "loss_functions"
UNIT_SCORES = ("frozenlake", "two_way")
"""tasks whose score is a probability, in results written before the task definitions"""
BASE_FIELDS = {
    "task", "loss", "seed", "algorithm", "exploration", "rows_trained", "demo_rows",
    "final_loss", "score", "normalized", "returns", "exact_return",
}  # fmt: skip
"""row fields that are not a task's own diagnostics"""
NAN = (math.nan, math.nan, math.nan)


def _unit(task: str, definitions: dict) -> bool:
    """Whether ``task``'s score is a probability."""
    if task in definitions:
        return definitions[task]["score"] in ("success", "exact")
    return task in UNIT_SCORES


# ------------------------------------------------------------------- statistics
def summarize(rows: list[dict], references: list[dict]) -> dict[str, Any]:
    """Per (task, loss, algorithm): mean and interval of the score and the normalised score."""
    ref = {}
    for task in dict.fromkeys(r["task"] for r in references):  # in run order, not hash order
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
    diagnostics = {t: _diagnostics([r for r in rows if r["task"] == t]) for t in ref}
    summary = []
    for (task, loss, algorithm), rs in groups.items():
        entry = {"task": task, "loss": loss, "algorithm": algorithm, "seeds": len(rs)}
        for metric in ("score", "normalized"):
            entry[metric] = t_interval([r[metric] for r in rs])
        for metric in diagnostics[task]:
            entry[metric] = t_interval([r.get(metric) for r in rs])
        summary.append(entry)
    return {"reference": ref, "groups": summary}


def _diagnostics(rows: list[dict]) -> list[str]:
    """A task's own numeric fields in its rows (mode fractions, outcomes), timings aside."""
    names = dict.fromkeys(k for r in rows for k in r)
    return [
        k for k in names
        if k not in BASE_FIELDS and not k.endswith("_seconds")
        and all(isinstance(r.get(k), (int, float, type(None))) for r in rows)
        and any(isinstance(r.get(k), (int, float)) for r in rows)
    ]  # fmt: skip


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
def markdown(summary: dict, raw: dict, figures: dict[str, str]) -> str:
    config, protocols, wall = raw["config"], raw["protocols"], raw["wall_seconds"]
    definitions = raw.get("tasks", {})
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
        "InvertedPendulum = mean return over held-out episodes; two-way, corridor = success "
        "rate. Normalised = (score - random) / (expert - random). Mean [95% t-interval] over "
        "seeds (clipped to [0, 1] for probabilities). "
        "BC = DAgger's round 0; DAgger = its last round.",
        "",
        score_table(summary, definitions),
    ]
    if summary.get("aggregate", {}).get("entries"):
        lines += ["", aggregate.markdown(summary["aggregate"], figures.get("aggregate"))]
    paired = paired_differences(raw["rows"], reference_loss(raw["rows"]), score="normalized")
    if paired:
        lines += [
            "",
            "Paired differences against each task's reference loss (`mse` for continuous "
            "actions, `cross_entropy` for discrete ones): normalised score minus the "
            "reference's on the same task and seed (the same demonstrations and held-out "
            "episodes), mean over the task-seed pairs with a 95% t interval, and the tasks "
            "whose mean difference is above or below 0 (`_paired.py`):",
            "",
            paired_table(paired, ("loss", "algorithm")),
        ]
    if any(g["task"] == "two_way" for g in summary["groups"]):
        lines += ["", two_way_table(summary)]
    if any(g["task"] == "corridor" for g in summary["groups"]):
        lines += ["", corridor_table(summary)]
    lines += [
        "",
        "Budget per task (identical for every loss but ACT, which trains at batch "
        f"{ACT_BATCH} and lr {ACT_LR}, its own recipe; a relabel round's fit continues the "
        "last learner for the round steps, or refits a fresh one where there are none):",
        "",
        budget_table(protocols),
    ]
    if figures.get("scores"):
        lines += ["", f"![normalised scores and mode fractions]({figures['scores']})"]
    return "\n".join(lines)


def reference_loss(rows: list[dict]):
    """``task -> its reference loss``: ``mse`` where the task has it, else ``cross_entropy``
    (a discrete task's default), else None."""
    have: dict[str, set[str]] = {}
    for r in rows:
        have.setdefault(r["task"], set()).add(r["loss"])

    def reference(task: str) -> str | None:
        losses = have.get(task, set())
        return next((n for n in ("mse", "cross_entropy") if n in losses), None)

    return reference


def _tasks(summary: dict) -> list[str]:
    """Task names in the order the run gave them."""
    return list(dict.fromkeys(g["task"] for g in summary["groups"]))


def score_table(summary: dict, definitions: dict) -> str:
    groups, ref = summary["groups"], summary["reference"]
    header = ["task", "loss", "BC score", "BC normalised", "DAgger score", "DAgger normalised"]
    rows = []
    for task in [t for t in _tasks(summary) if t in ref]:
        unit = _unit(task, definitions)
        d = 3 if unit else 1
        expert, random = ref[task]["expert"], ref[task]["random"]
        rows.append([f"**{task}**", f"expert {expert:.{d}f}, random {random:.{d}f}", *[""] * 4])
        for loss in _losses(groups, task):
            bc, dg = _group(groups, task, loss, "bc"), _group(groups, task, loss, "dagger")
            if bc is None:
                continue
            cells = [_report.fmt_ci(bc["score"], d, unit=unit), _report.fmt_ci(bc["normalized"])]
            if dg is None:  # a dataset-only task: BC alone
                cells += ["-", "-"]
            else:
                cells += [
                    _report.fmt_ci(dg["score"], d, unit=unit),
                    _report.fmt_ci(dg["normalized"]),
                ]
            rows.append([task, loss, *cells])
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
                [
                    loss,
                    algorithm,
                    *[_report.fmt_ci(g.get(c, NAN), unit=True) for c in cells],
                    verdict(g),
                ]
            )
    return _report.section(
        "**Two-way obstacle: does the learner keep both of the expert's modes?** Fraction "
        f"of the learner's actions at {multimodal.DECISION_STATES} decision states within 0.25 "
        "of the expert's pass-below action (-0.5), of its pass-above action (+0.5), and "
        "near neither (of which *middle*: within 0.25 of the modes' mean, 0); the "
        "policy acts as its entry says (sampled for the generative losses, greedy/mean "
        "otherwise; a chunked learner plans afresh and acts its chunk's first action). "
        "Mean [95% t-interval] over seeds; the verdict is computed from these numbers.",
        _report.table(header, rows),
    )


def corridor_verdict(group: dict) -> str:
    """A sentence from the corridor's measured outcomes and mode fractions."""
    lanes = [group[f"lane_{i}"] for i in range(4)]
    middle = max(group["modes_fork1_middle"][0], group["modes_fork2_middle"][0])
    if all(lane[1] > 0.05 for lane in lanes) and group["score"][0] >= 0.9:
        return "commits: all four routes (each lane's lower bound > 0.05), succeeds"
    if middle > 0.5:
        return "averages: steers towards the middle at a fork, into the divider"
    if group["reversals"][0] > 0.5:
        return "switches: turns back in the decision windows (a mode per step)"
    if sum(lane[0] > 0.05 for lane in lanes) <= 2:
        return "collapses to at most two routes"
    return "mixed"


def corridor_table(summary: dict) -> str:
    groups = [g for g in summary["groups"] if g["task"] == "corridor"]
    header = ["loss", "algorithm", "success", "lane 0", "lane 1", "lane 2", "lane 3"]
    header += ["hit fork 1", "hit fork 2", "hit wall", "turn-backs", "fork 1 middle"]
    header += ["fork 2 middle"]
    header += ["verdict"]
    rows = []
    for loss in _losses(groups):
        for algorithm in ("bc", "dagger"):
            g = _group(groups, "corridor", loss, algorithm)
            if g is None:
                continue
            unit = [
                "score", "lane_0", "lane_1", "lane_2", "lane_3", "hit_fork1", "hit_fork2",
                "hit_wall",
            ]  # fmt: skip
            cells = [_report.fmt_ci(g[c], unit=True) for c in unit]
            cells.append(_report.fmt_ci(g["reversals"], 1))
            cells += [_report.fmt_ci(g[f"modes_fork{f}_middle"], unit=True) for f in (1, 2)]
            rows.append([loss, algorithm, *cells, corridor_verdict(g)])
    return _report.section(
        "**Forking corridor: does the learner commit to one of the four routes?** Fraction "
        "of the evaluation episodes reaching each lane (0 lowest; the expert: 1/4 each) or "
        "hitting the first or a second divider or a wall; turn-backs = steps per episode whose action "
        "points the other way from the step before inside the decision windows (the "
        "expert: 0; a policy sampling a mode per step: several); *middle* = fraction of "
        f"the learner's actions at {corridor.DECISION_STATES} decision states of each fork "
        "within 0.25 of the two modes' mean (a mean regressor's action). Mean [95% "
        "t-interval] over seeds; the verdict is computed from these numbers.",
        _report.table(header, rows),
    )


def budget_table(protocols: dict[str, dict]) -> str:
    header = [
        "task",
        "demo episodes",
        "DAgger rounds x episodes",
        "fit steps x batch",
        "round steps",
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
                p.get("round_steps") or "refit",
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

    from imitrl.plotting import save_figure

    groups = summary["groups"]
    tasks = _tasks(summary)
    extra = [p for p, t in ((_modes_panel, "two_way"), (_corridor_panel, "corridor")) if t in tasks]
    cols = 3
    rows = math.ceil((len(tasks) + len(extra)) / cols)
    fig, grid = plt.subplots(rows, cols, figsize=(5.6 * cols, 4.4 * rows), squeeze=False)
    axes = list(grid.reshape(-1))
    for ax in axes[len(tasks) + len(extra) :]:
        ax.set_visible(False)
    for ax, task in zip(axes, tasks):
        _score_panel(ax, groups, task)
    # one legend for the score panels, in a strip of its own above them (never over a bar)
    fig.legend(*axes[0].get_legend_handles_labels(), loc="upper center", ncol=2)
    for ax, panel in zip(axes[len(tasks) :], extra):
        panel(ax, groups)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.35 / (4.4 * rows)))
    save_figure(fig, path, dpi=100)  # every label on the canvas
    plt.close(fig)


def _score_panel(ax, groups: list[dict], task: str) -> None:
    """Normalised BC and DAgger scores of every loss on ``task``, with intervals."""
    losses = _losses(groups, task)
    for j, (algorithm, colour) in enumerate((("bc", "tab:blue"), ("dagger", "tab:orange"))):
        for i, loss in enumerate(losses):
            g = _group(groups, task, loss, algorithm)
            if g is None:
                continue
            mean, lo, hi = g["normalized"]
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
    ax.set_yticks(range(len(losses)), losses, fontsize=8)
    ax.axvline(1.0, color="k", lw=0.8, ls="--")
    ax.axvline(0.0, color="k", lw=0.8)
    ax.set_title(task)
    ax.set_xlabel("expert-normalised score")
    ax.invert_yaxis()


def _stacked(ax, names: list[str], parts: dict[str, list[float]], colours) -> None:
    left = [0.0] * len(names)
    for (part, values), colour in zip(parts.items(), colours):
        ax.barh(names, values, left=left, color=colour, label=part)
        left = [a + b for a, b in zip(left, values)]
    ax.set_xlim(0, 1)
    ax.tick_params(axis="y", labelsize=8)
    ax.invert_yaxis()


def _modes_panel(ax, groups: list[dict]) -> None:
    """Where the two-way BC learners' actions fall at the decision states."""
    two_way = [g for g in groups if g["task"] == "two_way" and g["algorithm"] == "bc"]
    parts = {
        "near -0.5 (below)": [g["modes_below"][0] for g in two_way],
        "near 0 (the mean)": [g["modes_middle"][0] for g in two_way],
        "elsewhere": [g["modes_neither"][0] - g["modes_middle"][0] for g in two_way],
        "near +0.5 (above)": [g["modes_above"][0] for g in two_way],
    }
    colours = ("tab:green", "tab:red", "tab:gray", "tab:purple")
    _stacked(ax, [g["loss"] for g in two_way], parts, colours)
    ax.set_title("two_way, BC: actions at the decision")
    ax.set_xlabel("fraction of actions (mean over seeds)")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2, fontsize=8)


def _corridor_panel(ax, groups: list[dict]) -> None:
    """Where the corridor's BC learners' episodes end: a lane, or a divider."""
    rows = [g for g in groups if g["task"] == "corridor" and g["algorithm"] == "bc"]
    parts = {f"lane {i}": [g[f"lane_{i}"][0] for g in rows] for i in range(4)}
    parts["hit fork 1"] = [g["hit_fork1"][0] for g in rows]
    parts["hit fork 2"] = [g["hit_fork2"][0] for g in rows]
    parts["hit wall"] = [g["hit_wall"][0] for g in rows]
    colours = ("#1b9e77", "#66a61e", "#7570b3", "#e7298a", "tab:red", "tab:orange", "tab:gray")
    _stacked(ax, [g["loss"] for g in rows], parts, colours)
    ax.set_title("corridor, BC: where the episodes end")
    ax.set_xlabel("fraction of episodes (mean over seeds)")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=3, fontsize=8)


# ------------------------------------------------------------------------ output
def report(raw: dict[str, Any], out_dir: Path | None) -> str:
    """Summary, figures, results JSON and (``out_dir`` None) the README block, from raw rows."""
    summary = summarize(raw["rows"], raw["references"])
    reps = raw["config"].get("bootstrap_reps", aggregate.REPS)
    summary["aggregate"] = aggregate.aggregate(raw["rows"], _losses(summary["groups"]), reps=reps)
    raw["config"].setdefault("cpu_count", raw.get("machine", {}).get("cpu_count", "?"))
    results = _report.results_dir(out_dir)
    figures = {}
    fig_path = results / f"{NAME}.png"
    figure(summary, fig_path)
    figures["scores"] = f"results/{fig_path.name}"
    paths = [fig_path]
    if summary["aggregate"]["entries"]:
        agg_path = results / f"{NAME}_aggregate.png"
        aggregate.figure(summary["aggregate"], agg_path)
        figures["aggregate"] = f"results/{agg_path.name}"
        paths.append(agg_path)
    md = markdown(summary, raw, figures)
    payload = {**raw, "summary": summary}
    path = _report.write(NAME, json.loads(json.dumps(payload, default=str)), md, out_dir=out_dir)
    print(md)
    print(f"\nwrote {path} and {', '.join(map(str, paths))}")
    return md
