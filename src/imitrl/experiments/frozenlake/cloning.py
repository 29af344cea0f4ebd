"""Sections 2 and 3: behaviour cloning on the demonstrations, then the clone acting on its own."""

from __future__ import annotations

import numpy as np
import torch

from imitrl import keys
from imitrl.algorithms.bc import BCConfig, fit_bc
from imitrl.evaluation.evaluate import wilson_interval
from imitrl.experiments.frozenlake.context import StudyContext

__all__ = ["behaviour_cloning", "evaluation"]


def behaviour_cloning(ctx: StudyContext) -> None:
    """Fit ``ctx.clone`` to ``ctx.demos``; print its loss and pi(.|s) at the probe states."""
    cfg, rep = ctx.config, ctx.report
    rep.section("2. Behaviour cloning")
    buffer = ctx.buffer(ctx.demos)
    clone = ctx.learner()
    fit = fit_bc(clone, buffer, BCConfig(num_steps=cfg.fit_steps, batch_size=None))  # full batch
    ctx.clone = clone
    rep.line(f"cross-entropy on the demonstrations after the fit: {fit.final_loss:.3f}")
    rep.set("bc.cross_entropy", fit.final_loss)
    for s in cfg.probe_states:
        probs = clone.probs(np.int64(s)).astype(np.float32)
        rep.line(f"clone pi(.|s={s}): {np.round(probs, 3)}")
        rep.set(f"bc.probs.{s}", probs.astype(float).tolist())


def evaluation(ctx: StudyContext) -> None:
    """Success rates of the expert and of the greedy clone (``ctx.clone_table``), exact beside."""
    cfg, rep = ctx.config, ctx.report
    rep.section("3. Acting on its own")
    assert ctx.clone is not None and ctx.demos is not None  # sections 1 and 2 set them
    clone_table = ctx.clone.greedy_table()
    ctx.clone_table = clone_table
    demos = ctx.demos
    mistakes = int(
        (clone_table[demos.get(keys.OBSERVATION)] != demos.get(keys.EXPERT_ACTION)).sum()
    )
    n = ctx.eval_episodes(cfg.eval_episodes)
    block = ctx.backend.block(cfg.eval_seed)
    rates = block.evaluate(torch.stack([ctx.expert_table, clone_table]), n)
    rep.line(f"mistakes on the {demos.shape[0]} demonstration pairs: {mistakes}")
    rep.line(f"success rate: expert {float(rates[0]):.1%}, clone {float(rates[1]):.1%}")
    rep.set("bc.mistakes", mistakes)
    rep.set("bc.policy", clone_table)
    for name, table, rate in (
        ("expert", ctx.expert_table, rates[0]),
        ("clone", clone_table, rates[1]),
    ):
        exact = ctx.exact(table)
        lo, hi = wilson_interval(round(float(rate) * n), n)
        rep.line(
            f"  {name:<6} measured {float(rate):.1%} (95% CI {lo:.1%}-{hi:.1%}, {n} episodes) vs exact {exact:.2%}"
        )
        rep.set(
            f"evaluation.{name}",
            {"rate": float(rate), "ci": [lo, hi], "episodes": n, "exact": exact},
        )
