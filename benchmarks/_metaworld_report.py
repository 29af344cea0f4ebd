"""The Meta-World suites' tables and figure (``metaworld_mt10.py``, ``metaworld_mt50.py``):
success per task with Wilson intervals, the aggregate across tasks (IQM, optimality gap,
probability of improvement over MSE with stratified bootstrap intervals), and the DAgger
target of the suite (``config["suite"]``; a payload without one is MT10's)."""

from __future__ import annotations

import statistics
from collections import defaultdict
from pathlib import Path

import numpy as np

import _report
from _paired import paired_differences, paired_table
from imitrl.envs.metaworld import MAX_STEPS
from imitrl.envs.metaworld import TASKS as TASKS_OF
from imitrl.evaluation import wilson_interval
from imitrl.evaluation.aggregate import (
    iqm,
    optimality_gap,
    stratified_bootstrap,
    stratified_bootstrap_pair,
)
from imitrl.plotting import save_figure

ALGORITHMS = ("bc", "dagger", "bc_matched")
LABELS = {"bc": "BC", "dagger": "DAgger", "bc_matched": "BC at DAgger's queries"}
TARGET = 0.95
TARGETS = {"MT10": (8, 5), "MT50": (45, 10)}
"""per suite: the tasks on which DAgger must reach ``TARGET`` x the expert's success, from at
most this many demonstrations (issues 29 and 46)"""
BASELINE = "mse"
REPS = 2000


def _split(name: str) -> tuple[str, int]:
    task, demos = name.split("/")
    return task, int(demos.removesuffix("demo"))


def pooled(rows: list[dict]) -> tuple[int, int]:
    return sum(r["successes"] for r in rows), sum(r["episodes"] for r in rows)


def fmt_rate(k: int, n: int) -> str:
    if n == 0:
        return "-"
    lo, hi = wilson_interval(k, n)
    return f"{k / n:.2f} [{lo:.2f}, {hi:.2f}]"


def groups(payload: dict) -> tuple[dict, dict]:
    cells: dict = defaultdict(list)  # (task, demos, loss, algorithm) -> rows over seeds
    for r in payload["rows"]:
        task, demos = _split(r["task"])
        cells[(task, demos, r["loss"], r["algorithm"])].append(r)
    expert: dict = defaultdict(list)  # (task, demos) -> expert rows over seeds
    for r in payload["references"]:
        if r["policy"] == "expert":
            expert[_split(r["task"])].append(r)
    return cells, expert


def normalised(payload: dict) -> dict:
    """``{(loss, demos, algorithm): [seeds, tasks]}`` of success / the expert's success
    on the same seed's held-out starts (1 where the expert failed every episode)."""
    cells, expert = groups(payload)
    config = payload["config"]
    seed_row = {s: i for i, s in enumerate(sorted({r["seed"] for r in payload["rows"]}))}
    out = {}
    for loss in config["losses"]:
        for demos in config["demos"]:
            for algorithm in ALGORITHMS:
                grid = np.full((len(seed_row), len(config["tasks"])), np.nan)
                for j, task in enumerate(config["tasks"]):
                    ref = {r["seed"]: r["score"] for r in expert[(task, demos)]}
                    for r in cells.get((task, demos, loss, algorithm), []):
                        e = ref.get(r["seed"], 0.0)
                        grid[seed_row[r["seed"]], j] = r["score"] / e if e > 0 else 1.0
                if not np.isnan(grid).any():
                    out[(loss, demos, algorithm)] = grid
    return out


def target_counts(payload: dict) -> dict:
    """``{(loss, demos): tasks where DAgger's pooled success >= TARGET x the expert's}``."""
    cells, expert = groups(payload)
    config = payload["config"]
    out = {}
    for loss in config["losses"]:
        for demos in config["demos"]:
            met = []
            for task in config["tasks"]:
                k, n = pooled(cells.get((task, demos, loss, "dagger"), []))
                ek, en = pooled(expert[(task, demos)])
                if _reaches(k, n, ek, en):
                    met.append(task)
            out[(loss, demos)] = met
    return out


def suite(payload: dict) -> str:
    """The payload's task set (``MT10`` for results written before ``suite`` was)."""
    return payload["config"].get("suite", "MT10")


def _rounds(proto: dict) -> str:
    """How DAgger's relabel rounds fit: warm-started for ``round_steps``, or fresh."""
    p = proto.get("beta_decay")
    beta = "0" if p is None else f"p^(i-1) = {p}^(i-1) in round i (Ross et al.)"
    if proto["round_steps"] is None:
        return f"beta {beta}, a fresh learner each round, {proto['bc']['num_steps']} steps"
    return f"beta {beta}, warm start, {proto['round_steps']} steps a round"


def _reaches(k: int, n: int, ek: int, en: int) -> bool:
    """``k/n`` successes at least ``TARGET`` x the expert's ``ek/en``."""
    return n > 0 and en > 0 and k / n >= TARGET * (ek / en)


SHORT_KINDS = {
    "episode": "one more success would reach it",
    "matched": "BC at DAgger's queries reaches it (the same number of expert labels, "
    "all from the expert's own episodes)",
    "neither": "BC at DAgger's queries is short too",
}
"""how far short a task is, in the order the report names them"""


def short_kinds(payload: dict, loss: str, demos: int, tasks: list[str]) -> dict:
    """``{kind: [(task, DAgger's k/n, BC at its queries' k/n, the expert's k/n)]}`` for
    the ``tasks`` short of the target: one success short (``episode``), else where BC at
    DAgger's queries reaches it (``matched``) or not (``neither``; also where the run has
    no BC at DAgger's queries)."""
    cells, expert = groups(payload)
    out: dict = {kind: [] for kind in SHORT_KINDS}
    for task in tasks:
        k, n = pooled(cells.get((task, demos, loss, "dagger"), []))
        mk, mn = pooled(cells.get((task, demos, loss, "bc_matched"), []))
        ek, en = pooled(expert[(task, demos)])
        if _reaches(k + 1, n, ek, en):
            kind = "episode"
        elif _reaches(mk, mn, ek, en):
            kind = "matched"
        else:
            kind = "neither"
        out[kind].append((task, (k, n), (mk, mn), (ek, en)))
    return out


def _short_of(payload: dict, counts: dict) -> str:
    """The tasks short of the target for the (loss, demonstrations) that reached most,
    grouped by how far (:func:`short_kinds`), with DAgger's, BC at its queries' and the
    expert's pooled successes on each."""
    (loss, demos), met = max(counts.items(), key=lambda kv: len(kv[1]))
    short = [t for t in payload["config"]["tasks"] if t not in met]
    if not short:
        return ""
    parts = []
    for kind, found in short_kinds(payload, loss, demos, short).items():
        if not found:
            continue
        named = []
        for task, (k, n), (mk, mn), (ek, en) in found:
            matched = f", BC at its queries {mk}/{mn}" if mn else ""
            named.append(f"{task} (DAgger {k}/{n}{matched}, the expert {ek}/{en})")
        parts.append(f"{SHORT_KINDS[kind]}, {len(found)}: " + ", ".join(named))
    return (
        f" Short of it ({loss}, {demos} demonstrations), {len(short)} tasks; "
        + "; ".join(parts)
        + "."
    )


def against_matched(rows: list[dict]) -> list[dict]:
    """Paired differences (``_paired.py``) of one loss's algorithms against BC at DAgger's
    queries on the same task and seed; each entry's ``group``: (the algorithm's label,
    demonstrations)."""
    rows = [{**r, "demos": _split(r["task"])[1], "loss": LABELS[r["algorithm"]]} for r in rows]
    return paired_differences(rows, lambda task: LABELS["bc_matched"], group=("loss", "demos"))


def _paired(payload: dict) -> tuple[str, str]:
    """The paired differences' sentence and table: each loss against ``BASELINE``; with
    one loss, DAgger and BC against BC at DAgger's queries (the same labels)."""
    how = (
        "on the same task and seed (the same demonstrations and held-out starts), mean over "
        "the task-seed pairs with a 95% t interval, and the tasks whose mean difference is "
        "above or below 0 (`_paired.py`)."
    )
    if len(payload["config"]["losses"]) == 1:
        text = f"Paired differences against BC at DAgger's queries: success rate minus its success rate {how}"
        return text, paired_table(against_matched(payload["rows"]), ("algorithm", "demos"))
    rows = [{**r, "demos": _split(r["task"])[1], "algorithm": LABELS[r["algorithm"]]}
            for r in payload["rows"]]  # fmt: skip
    found = paired_differences(rows, lambda task: BASELINE, group=("loss", "demos", "algorithm"))
    text = f"Paired differences against {BASELINE}: success rate minus {BASELINE}'s {how}"
    table = paired_table(found, ("loss", "demos", "algorithm"))
    matched = dagger_against_matched(payload["rows"])
    if matched:
        table += (
            "\n\nDAgger against BC at DAgger's queries (the same number of expert labels), "
            "per loss: DAgger's success rate minus BC at DAgger's queries' on the same task "
            "and seed.\n\n" + paired_table(matched, ("loss", "demos", "algorithm"))
        )
    return text, table


def dagger_against_matched(rows: list[dict]) -> list[dict]:
    """Per loss and number of demonstrations, DAgger minus BC at DAgger's queries on the
    same task and seed (:func:`against_matched`, one loss at a time); each entry's
    ``group``: (loss, demonstrations, "DAgger")."""
    out = []
    for loss in dict.fromkeys(r["loss"] for r in rows):
        mine = [r for r in rows if r["loss"] == loss and r["algorithm"] in ("dagger", "bc_matched")]
        for found in against_matched(mine):
            label, demos = found["group"]
            out.append({**found, "group": (loss, demos, label)})
    return out


def markdown(payload: dict, figure_name: str) -> str:
    """The README section of a run: its protocol, the target's verdict, the per-task
    table, the aggregate table, the paired differences and the figure."""
    head, verdict, per_task = _head(payload), _verdict(payload), _per_task(payload)
    aggregate = _aggregate(payload)
    paired_text, paired = _paired(payload)  # after the aggregate, as its draws always were
    return "\n\n".join(
        [
            head,
            verdict,
            "Success rate per task (pooled over seeds, 95% Wilson interval); DAgger's "
            "queries: the expert-labelled rows its last fit saw (demonstrations included), "
            "the budget BC at DAgger's queries gets.",
            per_task,
            "Across tasks: expert-normalised success (success / the expert's on the same "
            "held-out starts), 95% stratified bootstrap intervals over seeds "
            f"({REPS} replicates).",
            aggregate,
            paired_text,
            paired,
            f"![Meta-World {suite(payload)}]({figure_name})",
        ]
    )


def _head(payload: dict) -> str:
    """The run's protocol and where its wall time went."""
    config, proto = payload["config"], next(iter(payload["config"]["protocol"].values()))
    bc = proto["bc"]
    return (
        f"{suite(payload)} tasks {len(config['tasks'])}, demonstrations {config['demos']}, "
        f"losses {config['losses']}, {config['seeds']} seed(s); each cell: demonstrations of the "
        f"scripted expert, BC fit {bc['num_steps']} steps x batch {bc['batch_size']} "
        f"(ACT: its own batch), MLP {proto['learner']['hidden']} lr {proto['learner']['lr']}, "
        f"DAgger {proto['rounds'] - 1} relabel rounds x {proto['episodes_per_round']} "
        f"episodes ({_rounds(proto)}), BC at "
        f"DAgger's query budget; evaluation {proto['eval_episodes']} held-out episodes of at "
        f"most {proto['max_episode_steps'] or MAX_STEPS} steps"
        + (" (Meta-World's own limit)" if proto["max_episode_steps"] is None else "")
        + ", success = `info['success']` at any step. "
        + (
            f"Wall time {payload['wall_seconds'] / 60:.1f} min with {config['jobs']} "
            f"process(es) at 1 thread, 1-min load {payload['load_average_start'][0]:.2f} at "
            f"the start and {payload['load_average_end'][0]:.2f} at the end (2 cores)."
            if config["jobs"] != "merged"
            else f"Merged from runs of disjoint cells ({'; '.join(payload['merged_from'])}); "
            "their wall times sum to "
            f"{payload['wall_seconds'] / 60:.1f} min."
        )
    )


def _verdict(payload: dict) -> str:
    """Whether the suite's target is met, the tasks each loss reached, and those short."""
    name = suite(payload)
    counts = target_counts(payload)
    need, most_demos = TARGETS[name]
    best = max(counts.items(), key=lambda kv: len(kv[1]))
    met = len(best[1]) >= need and best[0][1] <= most_demos
    return (
        f"**Target** (DAgger >= {TARGET:.2f} of the expert's success on >= {need} of "
        f"{len(TASKS_OF[name])} tasks from <= {most_demos} demonstrations): "
        f"{'met' if met else 'not met'}. Tasks reached, per loss and demonstrations: "
        + "; ".join(f"{loss} {d} demo(s): {len(t)}" for (loss, d), t in counts.items())
        + "."
        + _short_of(payload, counts)
    )


def _per_task(payload: dict) -> str:
    """Success per task, demonstrations and loss, for each algorithm and the expert."""
    config = payload["config"]
    cells, expert = groups(payload)
    rows = []
    for task in config["tasks"]:
        for demos in config["demos"]:
            for loss in config["losses"]:
                got = {a: cells.get((task, demos, loss, a), []) for a in ALGORITHMS}
                queries = [r["rows_trained"] for r in got["dagger"]]
                rows.append(
                    [task, demos, loss]
                    + [fmt_rate(*pooled(got[a])) for a in ALGORITHMS]
                    + [f"{statistics.median(queries):.0f}" if queries else "-"]
                    + [fmt_rate(*pooled(expert[(task, demos)]))]
                )
    return _report.table(
        ["task", "demos", "loss", *[LABELS[a] for a in ALGORITHMS], "DAgger queries", "expert"],
        rows,
    )


def _aggregate(payload: dict) -> str:
    """IQM, optimality gap and P(better than the baseline) of the expert-normalised
    success, per loss, demonstrations and algorithm."""
    agg_rows = []
    scores = normalised(payload)
    for (loss, demos, algorithm), grid in scores.items():
        i = stratified_bootstrap(grid, iqm, reps=REPS)
        g = stratified_bootstrap(grid, optimality_gap, reps=REPS)
        base = scores.get((BASELINE, demos, algorithm))
        p = "-"
        if base is not None and loss != BASELINE:
            pi = stratified_bootstrap_pair(grid, base, reps=REPS)
            p = f"{pi.point:.2f} [{pi.low:.2f}, {pi.high:.2f}]"
        agg_rows.append(
            [
                loss,
                demos,
                LABELS[algorithm],
                f"{i.point:.2f} [{i.low:.2f}, {i.high:.2f}]",
                f"{g.point:.2f} [{g.low:.2f}, {g.high:.2f}]",
                p,
            ]
        )
    return _report.table(
        ["loss", "demos", "algorithm", "IQM", "optimality gap", f"P(better than {BASELINE})"],
        agg_rows,
    )


def figure(payload: dict, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    config = payload["config"]
    scores = normalised(payload)
    cells, expert = groups(payload)
    demos = max(config["demos"])
    tasks = config["tasks"]
    if len(tasks) <= 12:  # MT10: tasks and aggregate side by side
        fig, (ax1, ax2) = plt.subplots(
            1, 2, figsize=(13, 4.6), gridspec_kw={"width_ratios": [3, 2]}
        )
    else:  # MT50: the tasks across the top, the aggregate under them
        fig, (ax1, ax2) = plt.subplots(
            2, 1, figsize=(max(13, 0.32 * len(tasks)), 8), gridspec_kw={"height_ratios": [3, 1.2]}
        )
    x = np.arange(len(tasks))
    loss = config["losses"][0]
    width = 0.2
    bars = [("expert", None), *[(a, a) for a in ALGORITHMS]]
    for i, (label, algorithm) in enumerate(bars):
        values = []
        for task in tasks:
            rows = (
                expert[(task, demos)]
                if algorithm is None
                else cells.get((task, demos, loss, algorithm), [])
            )
            k, n = pooled(rows)
            values.append(k / n if n else np.nan)
        ax1.bar(x + (i - 1.5) * width, values, width, label=LABELS.get(label, "expert"))
    ax1.set_xticks(x, [t.removesuffix("-v3") for t in tasks], rotation=35, ha="right")
    ax1.set_ylim(0, 1.05)
    ax1.set_ylabel("success rate (pooled over seeds)")
    ax1.set_title(f"per task, {loss}, {demos} demonstration(s)")
    handles, names = ax1.get_legend_handles_labels()
    side_by_side = len(tasks) <= 12
    if side_by_side:  # a figure legend in a strip of its own, under the rotated task names
        legend = fig.legend(handles, names, fontsize=8, loc="lower center", ncol=4, frameon=True)
    else:  # above the task panel, beside its title
        ax1.legend(handles, names, fontsize=8, loc="lower right", bbox_to_anchor=(1, 1), ncol=4)
    labels, points, errs = [], [], []
    for (name, d, algorithm), grid in scores.items():
        i = stratified_bootstrap(grid, iqm, reps=REPS)
        labels.append(f"{name} {d}d {LABELS[algorithm]}")
        points.append(i.point)
        errs.append((i.point - i.low, i.high - i.point))
    y = np.arange(len(labels))
    ax2.errorbar(points, y, xerr=np.array(errs).T if errs else None, fmt="o", ms=4, capsize=2)
    ax2.set_yticks(y, labels, fontsize=7)
    ax2.invert_yaxis()
    ax2.axvline(1.0, color="grey", lw=0.8, ls="--")
    ax2.set_xlabel("IQM of expert-normalised success (95% bootstrap)")
    ax2.set_title(f"aggregate over {suite(payload)}")
    if side_by_side:
        fig.tight_layout(rect=(0, 0.07, 1, 1))
        legend.set_bbox_to_anchor((ax1.get_position().x0 + ax1.get_position().width / 2, 0.0))
    else:
        fig.tight_layout()
    return save_figure(fig, path)
