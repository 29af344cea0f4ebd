"""``beyond_cloning.py``'s tables and figure, from its results dict."""

from __future__ import annotations

import math
from pathlib import Path

import _report
from imitrl.evaluation import t_interval

NAME = "beyond_cloning"
LABELS = {"bc": "BC", "dagger": "DAgger", "bc_matched": "BC, matched", "gail": "GAIL",
          "airl": "AIRL", "irl": "exact IRL"}  # fmt: skip
COLORS = {"bc": "tab:gray", "dagger": "tab:blue", "bc_matched": "tab:orange", "gail": "tab:red",
          "airl": "tab:purple", "irl": "tab:green"}  # fmt: skip


# ------------------------------------------------------------------- the numbers
def curves(results: dict) -> dict[str, dict[str, list[list[dict]]]]:
    """``{task: {method: [per seed: [points with "score"]]}}``, normalised by the seed's
    references; BC is DAgger's round 0, "BC, matched" its extra point."""
    refs = {
        (r["task"], r["seed"]): (r["expert"], r["random"])
        for r in results["rows"]
        if r["method"] == "reference"
    }
    out: dict[str, dict[str, list[list[dict]]]] = {}
    for row in results["rows"]:
        if row["method"] == "reference":
            continue
        ref = refs[(row["task"], row["seed"])]
        points = [normalised(p, *ref) for p in row["points"]]
        per = out.setdefault(row["task"], {})
        if row["method"] == "dagger":
            per.setdefault("bc", []).append(points[:1])
            per.setdefault("dagger", []).append(points)
            if "bc_matched" in row:
                matched = {"env_steps": 0, **row["bc_matched"]}
                per.setdefault("bc_matched", []).append([normalised(matched, *ref)])
        else:
            per.setdefault(row["method"], []).append(points)
    return out


def normalised(point: dict, expert: float, rnd: float) -> dict:
    """``point`` with ``score = (raw - random) / (expert - random)``."""
    gap = expert - rnd
    return {**point, "score": (point["raw"] - rnd) / gap if gap else math.nan}


def fmt(values: list[float], digits: int = 2) -> str:
    """``mean [lo, hi]``, the 95% t-interval over seeds."""
    return _report.fmt_ci(t_interval(values), digits)


def first_reached(points: list[dict], threshold: float) -> int | None:
    """Env steps of the first evaluation at or above ``threshold`` (None: never)."""
    return next((p["env_steps"] for p in points if p["score"] >= threshold), None)


def seconds_by_cell(results: dict) -> dict[tuple[str, str], list[float]]:
    out: dict[tuple[str, str], list[float]] = {}
    for r in results["rows"]:
        if "seconds" in r:
            out.setdefault((r["task"], r["method"]), []).append(r["seconds"])
    return out


# ------------------------------------------------------------------------ tables
def markdown(results: dict) -> str:
    cfg = results["config"]
    tasks = ", ".join(_report.env_label(t) for t in results["tasks"])
    lines = [
        f"Tasks run: {tasks}; methods: {', '.join(results['methods'])}; {cfg['seeds']} seeds; "
        f"{cfg['eval_episodes']} greedy evaluation episodes per gym learner (the seed's "
        "initial states, the same for the expert and a uniformly random policy); FrozenLake "
        "scored by exact success probability in 100 steps. Score = (R - R_random) / "
        "(R_expert - R_random); mean [95% t-interval over seeds]. Env steps = the learner's "
        "own steps in the env (the demonstration's count as expert queries). Total time "
        f"{results['seconds']:.0f} s on {results['machine']['cpu_count']} CPU cores "
        f"({results['jobs']} process(es), `torch.set_num_threads(1)`)."
        + (f" {results['merged']}." if results.get("merged") else ""),
        "",
        "GAIL/AIRL budgets (PPO generator, the library's `AdversarialConfig` defaults "
        "otherwise; the normaliser's warm-up steps count as env steps):",
        "",
        budget_table(results),
        "",
        "References (mean over seeds of the per-seed evaluation):",
        "",
        reference_table(results),
        "",
        score_table(results),
        "",
        f"![beyond cloning](results/{NAME}.png)",
    ]
    return "\n".join(lines)


def budget_table(results: dict) -> str:
    rows = [
        [_report.env_label(t), results["demonstrations"][t], f"{b['total_steps']:,}",
         f"{b['rollout_steps']:,}", b["minibatch_size"], b["eval_every"], b["lr"],
         "linear" if b.get("anneal_lr") else "constant", b["gamma"],
         "yes" if b["absorbing"] else "no", f"{b['normalizer_warmup']:,}",
         "x".join(map(str, b["hidden"])), b.get("airl_entropy_weight", 1.0)]
        for t, b in results["budgets"].items()
    ]  # fmt: skip
    header = ["task", "demonstration", "env steps", "steps per round", "PPO minibatch",
              "eval every (rounds)", "lr", "lr schedule", "gamma", "absorbing states",
              "normaliser warm-up steps", "MLP", "AIRL's w (f - w log pi)"]  # fmt: skip
    return _report.table(header, rows)


def reference_table(results: dict) -> str:
    by_task: dict[str, list[dict]] = {}
    for r in results["rows"]:
        if r["method"] == "reference":
            by_task.setdefault(r["task"], []).append(r)
    rows = [
        [_report.env_label(t), fmt([r["expert"] for r in rs], 3), fmt([r["random"] for r in rs], 3)]
        for t, rs in by_task.items()
    ]
    return _report.table(["task", "expert", "uniform random"], rows)


def score_table(results: dict) -> str:
    thr = results["config"]["threshold"]
    secs = seconds_by_cell(results)
    rows = []
    for task, per in curves(results).items():
        for method in ("bc", "dagger", "bc_matched", "irl", "gail", "airl"):
            if method not in per:
                continue
            seeds = per[method]
            last = [s[-1] for s in seeds]
            firsts = [first_reached(s, thr) for s in seeds]
            hit = [f for f in firsts if f is not None]
            cell = "dagger" if method in ("bc", "bc_matched") else method
            s = secs.get((task, cell), [])
            rows.append(
                [
                    _report.env_label(task),
                    LABELS[method],
                    fmt([p["env_steps"] for p in last], 0),
                    fmt([p["expert_queries"] for p in last], 0),
                    fmt([p["score"] for p in last]),
                    f"{sum(p['score'] >= thr for p in last)}/{len(last)}",
                    f"{len(hit)}/{len(seeds)}"
                    + (
                        f" ({min(hit):,}-{max(hit):,})"
                        if hit and method in ("dagger", "gail", "airl")
                        else ""
                    ),
                    f"{sum(s) / len(s):.0f}" if s else "",
                ]
            )
    header = [
        "task",
        "method",
        "env steps",
        "expert queries",
        "score at the end",
        f">= {thr} at the end",
        f">= {thr} at any evaluation (env steps)",
        "s per seed",
    ]
    return _report.table(header, rows)


# ------------------------------------------------------------------------ figure
def _band(ax, xs: list[float], seeds: list[list[dict]], method: str) -> None:
    k = min(len(s) for s in seeds)
    stats = [t_interval([s[i]["score"] for s in seeds]) for i in range(k)]
    means = [m for m, _, _ in stats]
    ax.plot(xs[:k], means, color=COLORS[method], marker="o", ms=3, label=LABELS[method])
    if len(seeds) > 1:
        ax.fill_between(xs[:k], [lo for _, lo, _ in stats], [hi for _, _, hi in stats],
                        color=COLORS[method], alpha=0.2)  # fmt: skip


def _point(ax, x: float, seeds: list[list[dict]], method: str, marker: str) -> None:
    m, lo, hi = t_interval([s[-1]["score"] for s in seeds])
    err = [[m - lo], [hi - m]] if len(seeds) > 1 else None
    ax.errorbar([x], [m], yerr=err, color=COLORS[method], marker=marker, ms=6, capsize=3,
                ls="none", label=LABELS[method])  # fmt: skip


def _mean_x(seeds: list[list[dict]], key: str) -> list[float]:
    k = min(len(s) for s in seeds)
    return [sum(s[i][key] for s in seeds) / len(seeds) for i in range(k)]


def figure(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, NullFormatter

    from imitrl.plotting import save_figure

    data = curves(results)
    thr = results["config"]["threshold"]
    fig, axes = plt.subplots(2, len(data), figsize=(4 * len(data), 6.6), squeeze=False)
    for col, (task, per) in enumerate(data.items()):
        top, bottom = axes[0][col], axes[1][col]
        # -- against the learner's environment steps (BC, IRL: none)
        for method in ("dagger", "gail", "airl"):
            if method in per:
                _band(top, _mean_x(per[method], "env_steps"), per[method], method)
        for method, marker in (("bc", "s"), ("irl", "D")):
            if method in per:
                _point(top, 0, per[method], method, marker)
        top.set_xscale("symlog", linthresh=100)
        top.set_xlabel("learner env steps (symlog)")
        top.set_title(_report.env_label(task), fontsize=10)
        # -- against expert queries (GAIL/AIRL: the demonstration only, final score)
        if "dagger" in per:
            _band(bottom, _mean_x(per["dagger"], "expert_queries"), per["dagger"], "dagger")
        # the demonstration-only methods share an x: spread them a little to see each
        for method, marker, shift in (("bc", "s", 1.0), ("bc_matched", "^", 1.0),
                                      ("irl", "D", 1.06), ("gail", "*", 1.12),
                                      ("airl", "P", 1.18)):  # fmt: skip
            if method in per:
                x = sum(s[-1]["expert_queries"] for s in per[method]) / len(per[method])
                _point(bottom, x * shift, per[method], method, marker)
        bottom.set_xscale("log")
        bottom.set_xlabel("expert queries (log; GAIL/AIRL: end of budget)")
        for ax in (top, bottom):
            ax.xaxis.set_major_formatter(FuncFormatter(lambda x, _: f"{x:,.0f}"))
            ax.xaxis.set_minor_formatter(NullFormatter())
            ax.axhline(1.0, color="k", lw=0.8)
            ax.axhline(thr, color="k", lw=0.8, ls="--")
            ax.set_ylim(min(-0.1, ax.get_ylim()[0]), 1.15)
    axes[0][0].set_ylabel("normalised score")
    axes[1][0].set_ylabel("normalised score")
    handles: dict = {}
    for ax in axes.flat:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(lab, h)
    fig.legend(handles.values(), handles.keys(), loc="lower center", ncol=len(handles), fontsize=8)
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    save_figure(fig, path, dpi=110)  # every label on the canvas
    plt.close(fig)
