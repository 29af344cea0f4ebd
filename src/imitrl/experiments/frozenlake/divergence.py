"""Section 6: the expert's and the clone's state distributions drift apart (exact)."""

from __future__ import annotations

import torch

from imitrl.experiments.frozenlake import figures
from imitrl.experiments.frozenlake.context import StudyContext
from imitrl.tabular.finite_horizon import state_distributions, total_variation

__all__ = ["CLAIM_STEP", "divergence"]

CLAIM_STEP = 20
"""the step of the section's claim on the clone's mass in a hole ("22 percent by step 20")"""


def divergence(ctx: StudyContext) -> None:
    """Total variation at ``tv_steps``, mass in the holes, occupancy maps (exact kernel evolution)."""
    cfg, mdp, rep = ctx.config, ctx.mdp, ctx.report
    rep.section("6. The divergence of the state distributions (exact kernel evolution)")
    H = max(cfg.tv_steps)
    assert ctx.clone_table is not None  # section 3 set it
    d_exp = state_distributions(mdp, ctx.expert_table, H)  # [H + 1, S]
    d_clo = state_distributions(mdp, ctx.clone_table, H)
    for t in cfg.tv_steps:
        tv = float(total_variation(d_exp[t], d_clo[t]))
        rep.line(f"after {t:>2} steps: total variation {tv:.3f}")
        rep.set(f"divergence.tv.{t}", tv)
    holes = torch.nonzero(mdp.terminal & ~mdp.goal).view(-1)
    for h in holes.tolist():
        rep.set(
            f"divergence.hole_mass.{h}", {"expert": float(d_exp[H, h]), "clone": float(d_clo[H, h])}
        )
    if holes.numel():
        h = int(holes[torch.argmax(d_clo[H, holes])])
        rep.line(
            f"mass in the hole at s={h} after {H} steps: expert {float(d_exp[H, h]):.3f}, clone {float(d_clo[H, h]):.3f}"
        )
        rep.set("divergence.worst_hole", h)
    if holes.numel() and H >= CLAIM_STEP:  # the section's claim is about step 20
        at = {h: {"expert": float(d_exp[CLAIM_STEP, h]), "clone": float(d_clo[CLAIM_STEP, h])}
              for h in holes.tolist()}  # fmt: skip
        rep.set(f"divergence.hole_mass_at_{CLAIM_STEP}", at)
        worst = int(holes[torch.argmax(d_clo[CLAIM_STEP, holes])])
        rep.set(f"divergence.worst_hole_at_{CLAIM_STEP}", worst)
    occ_exp, occ_clo = d_exp[1:].mean(0), d_clo[1:].mean(0)
    rep.set("divergence.occupancy", {"expert": occ_exp, "clone": occ_clo, "steps": H})
    figures.plot_occupancy(
        mdp.desc,
        [occ_exp.numpy(), occ_clo.numpy()],
        [ctx.expert_table.numpy(), ctx.clone_table.numpy()],
        ["expert occupancy", "clone occupancy"],
        ctx.figure("occupancy"),
        shape=None
        if mdp.desc is not None
        else figures.grid_shape(cfg.env_id, cfg.make_kwargs, ctx.S),
    )
