"""``bc_vs_dagger.py``'s tables and figure, from its results dict."""

from __future__ import annotations

from pathlib import Path

import _report
from imitrl.evaluation import t_interval

NAME = "bc_vs_dagger"


def fmt(values: list[float], digits: int = 2) -> str:
    """``mean [lo, hi]``, the 95% t-interval over seeds."""
    return _report.fmt_ci(t_interval(values), digits)


def markdown(results: dict, cfg) -> str:
    lines = [
        f"{cfg.seeds} seeds per env; {cfg.eval_episodes} greedy evaluation episodes per learner "
        f"(same initial states for every policy of a seed, the expert's and a uniformly random "
        f"policy's included); score = (R - R_random) / (R_expert - R_random); mean [95% "
        f"t-interval over seeds]. Total time {results['seconds']:.0f} s on "
        f"{results['machine']['cpu_count']} CPU cores (`torch.set_num_threads(1)`)"
        f"{' with parallel rollouts' if cfg.parallel else ''}.",
        "",
        f"Experts over {cfg.reference_episodes} episodes (seeded lanes; the random policy "
        "from the same initial states):",
        "",
        reference_table(results),
        "",
        "Normalised scores:",
        "",
        score_table(results, cfg),
        "",
        "Raw returns (same evaluation states):",
        "",
        return_table(results, cfg),
        "",
        f"![BC vs DAgger](results/{NAME}.png)",
    ]
    return "\n".join(lines)


def reference_table(results: dict) -> str:
    rows = [
        [
            _report.env_label(env_id),
            f"{r['expert']['mean']:.1f} [{r['expert']['ci'][0]:.1f}, {r['expert']['ci'][1]:.1f}]",
            f"{r['random']['mean']:.1f}",
        ]
        for env_id, r in results["references"].items()
    ]
    return _report.table(["env", "expert return", "uniform random"], rows)


def score_table(results: dict, cfg) -> str:
    rounds = range(1, cfg.relabel_rounds + 1)
    rows = []
    for env_id, per in results["tasks"].items():
        seeds = per["seeds"]
        firsts = [s["first_round_reached"] for s in seeds if s["first_round_reached"] is not None]
        last = [s["dagger_scores"][-1] for s in seeds]
        rows.append(
            [
                _report.env_label(env_id),
                per["demo"],
                fmt([s["bc_score"] for s in seeds]),
                *[fmt([s["dagger_scores"][k] for s in seeds]) for k in rounds],
                f"{len(firsts)}/{len(seeds)}"
                + (f" (round {min(firsts)}-{max(firsts)})" if firsts else ""),
                f"{sum(x >= cfg.threshold for x in last)}/{len(seeds)}",
                fmt([s["bc_matched_score"] for s in seeds])
                + f" (N={round(sum(s['bc_matched_rows'] for s in seeds) / len(seeds))})",
                f"{per['seconds']:.0f}",
            ]
        )
    header = [
        "env",
        "demo",
        "BC (same demo)",
        *[f"DAgger r{k}" for k in rounds],
        f">= {cfg.threshold} within {cfg.relabel_rounds} rounds",
        f">= {cfg.threshold} at r{cfg.relabel_rounds}",
        "BC, matched samples (mean N)",
        "s",
    ]
    return _report.table(header, rows)


def return_table(results: dict, cfg) -> str:
    rows = []
    for env_id, per in results["tasks"].items():
        seeds = per["seeds"]
        rows.append(
            [
                _report.env_label(env_id),
                fmt([s["expert_return"] for s in seeds], 1),
                fmt([s["random_return"] for s in seeds], 1),
                fmt([s["bc_return"] for s in seeds], 1),
                fmt([s["dagger_returns"][-1] for s in seeds], 1),
                fmt([s["bc_matched_return"] for s in seeds], 1),
                fmt([s["rows"][-1] for s in seeds], 0),
            ]
        )
    header = [
        "env",
        "expert",
        "uniform random",
        "BC",
        f"DAgger r{cfg.relabel_rounds}",
        "BC, matched",
        "expert labels used",
    ]
    return _report.table(header, rows)


def figure(results: dict, cfg, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from imitrl.plotting import save_figure

    tasks = list(results["tasks"].items())
    fig, axes = plt.subplots(1, len(tasks), figsize=(4 * len(tasks), 3.4), squeeze=False)
    rounds = list(range(cfg.relabel_rounds + 1))
    for ax, (env_id, per) in zip(axes[0], tasks):
        seeds = per["seeds"]
        for s in seeds:
            ax.plot(rounds, s["dagger_scores"], color="tab:blue", alpha=0.25, lw=0.8)
        stats = [t_interval([s["dagger_scores"][k] for s in seeds]) for k in rounds]
        ax.plot(rounds, [m for m, _, _ in stats], color="tab:blue", marker="o", label="DAgger")
        ax.fill_between(rounds, [lo for _, lo, _ in stats], [hi for _, _, hi in stats], alpha=0.2)
        m, lo, hi = t_interval([s["bc_matched_score"] for s in seeds])
        ax.errorbar(
            [rounds[-1] + 0.15],
            [m],
            yerr=[[m - lo], [hi - m]],
            color="tab:orange",
            marker="s",
            label="BC, matched samples",
        )
        ax.axhline(1.0, color="k", lw=0.8, label="expert")
        ax.axhline(cfg.threshold, color="k", lw=0.8, ls="--")
        ax.set_title(_report.env_label(env_id), fontsize=10)
        ax.set_xlabel("DAgger round (0 = BC on the demo)")
        ax.set_xticks(rounds)
        ax.set_ylim(min(-0.1, ax.get_ylim()[0]), 1.1)
    axes[0][0].set_ylabel("normalised return")
    axes[0][0].legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)  # every label on the canvas
    plt.close(fig)
