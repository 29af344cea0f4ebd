"""Section 1: the expert by value iteration, its exact success, and its demonstrations."""

from __future__ import annotations

import math

import torch

from imitrl import keys
from imitrl.experiments.frozenlake.context import StudyContext
from imitrl.tabular.dp import value_iteration
from imitrl.tabular.finite_horizon import reachable_states, success_probability

__all__ = ["expert_and_demos"]


def expert_and_demos(ctx: StudyContext) -> None:
    """Print the expert and its exact success; draw the demonstrations into ``ctx.demos``."""
    cfg, mdp, rep = ctx.config, ctx.mdp, ctx.report
    V = value_iteration(mdp, cfg.vi_iters)[-1]
    start = int(torch.nonzero(mdp.initial).view(-1)[0])
    T = mdp.max_steps
    rep.section("1. The expert and its demonstrations")
    exact = ctx.exact(ctx.expert_table)
    no_limit = success_probability(mdp, ctx.expert_table, math.inf)
    rep.line(
        f"expert by value iteration (gamma {cfg.gamma}, {cfg.vi_iters} sweeps): pi* = {ctx.expert_table.tolist()}"
    )
    rep.line(
        f"V*(s={start}) = {float(V[start]):.6f}; exact success within {T} steps {exact:.6f}, with no time limit {no_limit:.6f}"
    )
    rep.set("expert.policy", ctx.expert_table)
    rep.set("expert.V_start", float(V[start]))
    rep.set("expert.exact_success", exact)
    rep.set("expert.exact_success_no_limit", no_limit)
    rep.set("expert.time_limit", T)
    block = ctx.backend.block(cfg.demo_seed)
    demos = block.demonstrations(cfg.demo_episodes)[0]
    ctx.demos = demos
    reachable = torch.nonzero(reachable_states(mdp) & ~mdp.terminal).view(-1).tolist()
    covered = sorted(set(demos.get(keys.OBSERVATION).tolist()))
    rep.line(
        f"{demos.shape[0]} state-action pairs from {cfg.demo_episodes} expert episodes, "
        f"covering {len(covered)} of {len(reachable)} reachable states"
    )
    rep.line(f"never demonstrated: states {sorted(set(reachable) - set(covered))}")
    rep.set("demos.pairs", demos.shape[0])
    rep.set("demos.states_covered", len(covered))
    rep.set("demos.reachable_states", len(reachable))
    rep.set("demos.uncovered", sorted(set(reachable) - set(covered)))
