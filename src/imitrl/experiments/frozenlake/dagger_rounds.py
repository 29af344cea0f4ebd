"""Section 7: DAgger from the section's demonstrations, each round evaluated and priced."""

from __future__ import annotations

from imitrl.algorithms.dagger import EpisodeSource, dagger
from imitrl.evaluation.evaluate import wilson_interval
from imitrl.experiments.frozenlake import figures
from imitrl.experiments.frozenlake.backends import _BatchedBlock
from imitrl.experiments.frozenlake.context import StudyContext
from imitrl.learners.actor_critic import ActorCritic
from imitrl.learners.learner import Learner
from imitrl.policies.experts import Expert

__all__ = ["dagger_rounds"]


def dagger_rounds(ctx: StudyContext) -> None:
    """Relabel the learner's states, aggregate, refit; success of every round's learner."""
    cfg, rep = ctx.config, ctx.report
    rep.section("7. DAgger: relabel the learner's states, aggregate, refit")
    block = ctx.backend.block(cfg.dagger_seed)
    n = ctx.eval_episodes(cfg.eval_episodes)
    assert ctx.demos is not None  # section 1 set them
    buffer = ctx.buffer(ctx.demos.clone())
    rounds: list[dict] = []

    def on_fit(k: int, learner: Learner) -> None:
        assert isinstance(learner, ActorCritic)  # ctx.learner's table
        table = learner.greedy_table()
        rate = float(block.evaluate(table[None], n)[0])
        exact = ctx.exact(table)
        lo, hi = wilson_interval(round(rate * n), n)
        rep.line(
            f"round {k}: trained on {len(buffer):>3} pairs, success rate {rate:.1%}  (exact {exact:.2%})"
        )
        rounds.append(
            {
                "round": k,
                "pairs": len(buffer),
                "rate": rate,
                "ci": [lo, hi],
                "exact": exact,
                "policy": table.tolist(),
            }
        )

    source: EpisodeSource
    if ctx.backend.vectorised:
        assert isinstance(block, _BatchedBlock)  # the batched backend's
        source = block.source(1, cfg.dagger_episodes)
    else:
        source = block.source()
    dagger(
        source,
        Expert.from_table(ctx.expert_table),
        ctx.learner,
        buffer,
        ctx.dagger_config(cfg.dagger_episodes, cfg.fit_steps),
        on_fit=on_fit,
        progress=cfg.progress,
    )
    rep.set("dagger.rounds", rounds)
    figures.plot_dagger(
        [r["pairs"] for r in rounds],
        [r["rate"] for r in rounds],
        [r["ci"] for r in rounds],
        [r["exact"] for r in rounds],
        ctx.exact(ctx.expert_table),
        ctx.figure("dagger"),
    )
