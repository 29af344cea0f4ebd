"""Section 5: compounding error on the chain, simulated and exact (see :mod:`.chain`)."""

from __future__ import annotations

import numpy as np

from imitrl.experiments.frozenlake import figures
from imitrl.experiments.frozenlake.chain import chain_exact, chain_monte_carlo
from imitrl.experiments.frozenlake.context import StudyContext

__all__ = ["compounding_error"]


def compounding_error(ctx: StudyContext) -> None:
    """Lost return of the cloned and the recovering imitator for each (eps, T) panel."""
    cfg, rep = ctx.config, ctx.report
    rep.section("5. Compounding error on the chain")
    panels = []
    for eps, T in cfg.chain_panels:
        rng = np.random.default_rng(cfg.chain_seed)
        gap_bc, gap_rec = chain_monte_carlo(eps, T, cfg.chain_samples, rng)
        ex_bc, ex_rec = chain_exact(eps, T)
        # no recovering loss among the samples (a small eps, few --chain-samples): no ratio
        ratio = float(gap_bc[-1] / gap_rec[-1]) if gap_rec[-1] > 0 else None
        shown = "undefined (no recovering loss sampled)" if ratio is None else f"{ratio:.1f}x"
        rep.line(
            f"lost return at T={T}: cloned {gap_bc[-1]:.2f} (eps T^2/2 = {eps * T**2 / 2:.2f}), "
            f"recovering {gap_rec[-1]:.2f} (eps T = {eps * T:.2f})"
        )
        rep.line(
            f"  eps={eps}: exact expectations cloned {ex_bc[-1]:.3f}, recovering {ex_rec[-1]:.3f}; "
            f"ratio measured {shown}, exact {ex_bc[-1] / ex_rec[-1]:.1f}x"
        )
        panels.append(
            {
                "eps": eps,
                "T": T,
                "cloned": gap_bc,
                "recovering": gap_rec,
                "cloned_exact": ex_bc,
                "recovering_exact": ex_rec,
                "ratio": ratio,
                "ratio_exact": float(ex_bc[-1] / ex_rec[-1]),
            }
        )
    rep.set("chain.panels", panels)
    figures.plot_chain(panels, ctx.figure("chain"))
