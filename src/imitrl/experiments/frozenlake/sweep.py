"""Section 4: how typical was the dataset? Clones from redrawn datasets of each size."""

from __future__ import annotations

import numpy as np

from imitrl.experiments.frozenlake import figures
from imitrl.experiments.frozenlake.context import StudyContext
from imitrl.experiments.frozenlake.replicates import replicated_clones

__all__ = ["sweep"]


def sweep(ctx: StudyContext) -> None:
    """``sweep_datasets`` clones per dataset size: measured and exact success, median and worst."""
    cfg, rep = ctx.config, ctx.report
    rep.section("4. How typical was the dataset: redrawn datasets")
    block = ctx.backend.block(cfg.sweep_seed)
    n_eval = ctx.eval_episodes(cfg.sweep_eval_episodes)
    all_rates, all_exact = [], []
    for n in cfg.sweep_sizes:
        tables, measured, _ = replicated_clones(
            ctx, block, cfg.sweep_datasets, n, cfg.sweep_fit_steps, n_eval, f"sweep {n} ep"
        )
        assert measured is not None  # n_eval >= 1 (StudyConfig's bounds)
        rates = measured.double().numpy()
        exact = ctx.exact_each(tables)
        order = np.sort(rates)
        rep.line(
            f"{n:>2} episodes: median success {np.median(order):.0%}, worst {order[0]:.0%}, over {cfg.sweep_datasets} datasets"
            f"  (exact: median {np.median(exact):.1%}, worst {exact.min():.1%})"
        )
        rep.set(
            f"sweep.{n}",
            {
                "rates": order.tolist(),
                "median": float(np.median(order)),
                "worst": float(order[0]),
                "exact": np.sort(exact).tolist(),
                "exact_median": float(np.median(exact)),
                "exact_worst": float(exact.min()),
                "episodes": n_eval,
            },
        )
        all_rates.append(rates)
        all_exact.append(exact)
    figures.plot_sweep(
        cfg.sweep_sizes, all_rates, all_exact, ctx.exact(ctx.expert_table), ctx.figure("sweep")
    )
