"""Exercise 3: where a clone's errors are, state by state, against the expert's visitation."""

from __future__ import annotations

import torch
from tensordict import TensorDict

from imitrl import keys
from imitrl.experiments.frozenlake import figures
from imitrl.experiments.frozenlake.context import StudyContext, decision_distribution
from imitrl.experiments.frozenlake.replicates import replicated_clones
from imitrl.tabular.finite_horizon import reachable_states

__all__ = ["ex_state_errors"]


def _coverage(rows: list[TensorDict], S: int) -> torch.Tensor:
    """``[S]`` float64 fraction of the row sets in which each state appears."""
    coverage = torch.zeros(S, dtype=torch.float64)
    for r in rows:
        seen = torch.zeros(S, dtype=torch.bool)
        seen[r.get(keys.OBSERVATION)] = True
        coverage += seen.double()
    coverage /= len(rows)
    return coverage


def ex_state_errors(ctx: StudyContext) -> None:
    """Per frozen state: the expert's visitation, dataset coverage, and how often clones err."""
    cfg, mdp, rep = ctx.config, ctx.mdp, ctx.report
    rep.section("Exercise 3. Where the errors are")
    block = ctx.backend.block(cfg.ex_seed + 1)
    tables, _, rows = replicated_clones(
        ctx, block, cfg.ex_error_datasets, cfg.demo_episodes, cfg.ex_fit_steps, 0, "state errors"
    )
    live = torch.nonzero(reachable_states(mdp) & ~mdp.terminal).view(-1)
    visit = decision_distribution(mdp, ctx.expert_table)
    error = (tables != ctx.expert_table).double().mean(0)
    coverage = _coverage(rows, ctx.S)
    rep.line(
        f"{len(rows)} datasets of {cfg.demo_episodes} expert episodes; per frozen state, sorted by the expert's visitation:"
    )
    rep.line(" state | expert visitation | in dataset | clone wrong | expert action")
    order = live[torch.argsort(visit[live], descending=True)]
    for s in order.tolist():
        rep.line(
            f"{s:>6} | {float(visit[s]):>17.4f} | {float(coverage[s]):>10.2f} | {float(error[s]):>11.2f} | {int(ctx.expert_table[s])}"
        )
    zero_default = [s for s in order.tolist() if int(ctx.expert_table[s]) == 0]
    rep.line(
        "shape: the error is (1 - coverage) where the expert's action is not 0, and 0 where it is "
        f"(states {zero_default}: the untouched row's tie-break picks action 0); coverage rises with visitation, "
        "so errors concentrate on the rarely visited states"
    )
    rep.set(
        "exercises.state_errors",
        {
            "states": live,
            "visitation": visit[live],
            "coverage": coverage[live],
            "error": error[live],
        },
    )
    figures.plot_state_errors(
        visit[live].numpy(), error[live].numpy(), live.tolist(), ctx.figure("ex_state_errors")
    )
