"""Exercise 4: DAgger's budget. BC and DAgger given the same number of expert queries."""

from __future__ import annotations

import math

import torch
from tensordict import TensorDict

from imitrl.experiments.frozenlake import figures
from imitrl.experiments.frozenlake.backends import Block
from imitrl.experiments.frozenlake.context import StudyContext
from imitrl.experiments.frozenlake.replicates import (
    demos_with_budget,
    fit_tables,
    replicated_dagger,
)

__all__ = ["ex_budget"]


def _dagger_and_equal_budget(
    ctx: StudyContext, block: Block, K: int
) -> tuple[list[TensorDict], torch.Tensor, torch.Tensor, list[TensorDict]]:
    """K replicates of: demonstrations, DAgger from them, expert demos of DAgger's query count.

    Returns the demonstrations, DAgger's ``[K, S]`` final tables, its ``[K]`` query
    counts, and the row sets of exactly that many expert pairs.
    """
    cfg = ctx.config
    if ctx.backend.vectorised:
        demos = block.demonstrations(cfg.demo_episodes, K)
        dagger_tables, budgets = replicated_dagger(ctx, block, demos, cfg.ex_fit_steps)
        return demos, dagger_tables, budgets, demos_with_budget(ctx, block, budgets)
    demos, bc_rows = [], []
    table_each: list[torch.Tensor] = []
    budget_each: list[torch.Tensor] = []
    for _ in ctx.bar(range(K), "budget"):  # stream order: demos, DAgger, budgeted demos
        d = block.demonstrations(cfg.demo_episodes)[0]
        t, b = replicated_dagger(ctx, block, [d], cfg.ex_fit_steps)
        bc_rows += demos_with_budget(ctx, block, b)
        demos.append(d)
        table_each.append(t[0])
        budget_each.append(b[0])
    return demos, torch.stack(table_each), torch.stack(budget_each), bc_rows


def ex_budget(ctx: StudyContext) -> None:
    """Exact success of DAgger, of BC with DAgger's query count, and of BC on the demos alone."""
    cfg, rep = ctx.config, ctx.report
    rep.section("Exercise 4. DAgger's budget: BC and DAgger at an equal number of expert queries")
    block = ctx.backend.block(cfg.ex_seed + 2)
    K = cfg.ex_datasets
    demos, dagger_tables, budgets, bc_rows = _dagger_and_equal_budget(ctx, block, K)
    bc_tables, _ = fit_tables(ctx, bc_rows, cfg.ex_fit_steps)
    demo_tables, _ = fit_tables(ctx, demos, cfg.ex_fit_steps)
    dg = ctx.exact_each(dagger_tables)
    bc = ctx.exact_each(bc_tables)
    bc0 = ctx.exact_each(demo_tables)
    diff = dg - bc
    se = diff.std(ddof=1) / math.sqrt(K) if K > 1 else float("nan")
    rep.line(
        f"{K} seeds; DAgger {cfg.dagger_rounds} rounds x {cfg.dagger_episodes} relabelled episodes from {cfg.demo_episodes} demonstrations"
    )
    rep.line(
        f"expert queries per seed: mean {budgets.double().mean():.0f} (min {int(budgets.min())}, max {int(budgets.max())})"
    )
    rep.line(
        f"exact success: DAgger {dg.mean():.3f}, BC with the same queries {bc.mean():.3f}, BC on the {cfg.demo_episodes} demonstrations {bc0.mean():.3f}"
    )
    rep.line(
        f"paired difference DAgger - BC: {diff.mean():+.3f} (standard error {se:.3f}); DAgger ahead on {int((diff > 1e-9).sum())}, behind on {int((diff < -1e-9).sum())} of {K}"
    )
    rep.set(
        "exercises.budget",
        {
            "budget": budgets,
            "dagger": dg,
            "bc_equal_budget": bc,
            "bc_demos": bc0,
            "diff_mean": float(diff.mean()),
            "diff_se": se,
        },
    )
    figures.plot_budget(
        budgets.numpy(), dg, bc, bc0, ctx.exact(ctx.expert_table), ctx.figure("ex_budget")
    )
