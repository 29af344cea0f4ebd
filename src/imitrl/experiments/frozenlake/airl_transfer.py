"""Section 8b: AIRL's disentangled reward against MaxEnt IRL's, under changed dynamics, exactly.

Section 8's reward on the state entered, recovered by MaxEnt IRL and planned against
under other dynamics, pays the plan to loiter: a state reward is identified only up to
shaping. AIRL (:mod:`imitrl.tabular.airl`) learns a reward ``g(s)`` and a shaping
potential ``h(s)`` apart, and its ``g`` should survive a change of kernel. Here, exactly:

* the demonstrator is Boltzmann-rational (AIRL's model of it): soft-optimal for
  ``--airl-beta`` times the env's reward, discount ``--gamma``; its episodes are drawn
  from ``--airl-seed`` (``--airl-sizes`` of them), and the unlimited-data limit (its
  exact occupancy) is a dataset too;
* from each dataset: AIRL (``g``, and its state-action ``f`` with the source kernel's
  shaping baked in) and MaxEnt IRL (section 8's reward on the state entered, from the
  same episodes);
* each reward planned against under the source and every ``--irl-transfer`` target
  kernel; each plan scored exactly under that kernel's true reward: its discounted
  return from the start, normalised so that a uniform policy scores 0 and the target's
  own optimal policy 1, and its success probability within the time limit.
"""

from __future__ import annotations

import importlib

import torch

from imitrl.experiments.frozenlake import figures_irl
from imitrl.experiments.frozenlake.context import StudyContext
from imitrl.experiments.frozenlake.irl import transfer_mdps
from imitrl.tabular import airl as _airl
from imitrl.tabular.dp import greedy, policy_evaluation, value_iteration
from imitrl.tabular.finite_horizon import success_probability
from imitrl.tabular.mdp import TabularMDP

_irl = importlib.import_module("imitrl.tabular.maxent_irl")

__all__ = ["METHODS", "airl_transfer"]

METHODS = ("airl_g", "airl_f", "maxent", "source_expert")
"""the plans scored under each target: AIRL's ``g``; AIRL's ``f`` (the source kernel's
shaping in it); MaxEnt IRL's reward on the state entered; the source expert's policy"""


def _datasets(
    ctx: StudyContext, demonstrator: torch.Tensor
) -> list[tuple[str, torch.Tensor, object]]:
    """``(label, discounted occupancy, MaxEnt demonstrations)`` per dataset."""
    mdp, cfg = ctx.mdp, ctx.config
    out = []
    for n in cfg.airl_sizes:
        rows = _airl.sample_episodes(mdp, demonstrator, n, seed=cfg.airl_seed)
        out.append(
            (
                f"{n} episodes",
                _airl.empirical_occupancy(mdp, rows),
                _irl.Demonstrations.from_tuples(mdp, rows[:, :4]),
            )
        )
    T = mdp.max_steps
    assert T is not None  # airl_transfer skips an MDP without a time limit
    exact = _irl.occupancy_measure(mdp, demonstrator[None].expand(T, -1, -1))
    out.append(
        (
            "unlimited",
            _airl.discounted_occupancy(mdp, demonstrator),
            _irl.Demonstrations.from_occupancy(exact),
        )
    )
    return out


def _score(mdp: TabularMDP, table: torch.Tensor, own_value: float, uniform: float) -> dict:
    v = float(mdp.initial @ policy_evaluation(mdp, table))
    spread = own_value - uniform  # 0 where no policy does better than chance: undefined
    return {
        "normalised_return": (v - uniform) / spread if spread > 0 else None,
        "success": success_probability(mdp, table),
    }


def _signed(x: float | None) -> str:
    return "n/a" if x is None else f"{x:+.3f}"


def _plans(ctx, target: TabularMDP, fit: _airl.AIRLResult, theta: torch.Tensor) -> dict:
    """The greedy table of each method under ``target``'s kernel."""
    gamma = ctx.config.gamma
    maxent_reward = _irl.linear_reward(theta, _irl.next_state_features(target))
    return {
        "airl_g": _airl.plan(target, fit.g),
        "airl_f": _airl.plan(target, _airl.shaped_reward(ctx.mdp, fit.g, fit.h, gamma)),
        "maxent": _irl.soft_value_iteration(target, maxent_reward).q[0].argmax(dim=-1),
        "source_expert": ctx.expert_table,
    }


def _fit_all(ctx: StudyContext, demonstrator: torch.Tensor) -> list[dict]:
    cfg = ctx.config
    fits = []
    for label, rho, demos in ctx.bar(_datasets(ctx, demonstrator), "airl fits"):
        fit = _airl.airl(ctx.mdp, rho, rounds=cfg.airl_rounds)
        me = _irl.maxent_irl(
            ctx.mdp, demos, _irl.next_state_features(ctx.mdp), steps=cfg.irl_steps, lr=cfg.irl_lr
        )
        fits.append({"label": label, "airl": fit, "theta": me.theta})
    return fits


def _report_fits(ctx: StudyContext, fits: list[dict]) -> None:
    rep, goal = ctx.report, ctx.mdp.goal
    live = ~ctx.mdp.terminal
    for f in fits:
        g = f["airl"].g
        shape = (
            f"g(goal) - max g(live) {float(g[goal].max() - g[live].max()):+.2f}"
            if goal.any()
            else f"g from {float(g.min()):+.2f} to {float(g.max()):+.2f}"
        )
        rep.line(
            f"  {f['label']:<13} AIRL after {ctx.config.airl_rounds} rounds: generator-demonstrator "
            f"occupancy gap {float(f['airl'].occupancy_gap[-1]):.4f}; {shape}"
        )


def _transfer(ctx: StudyContext, fits: list[dict]) -> list[dict]:
    """Every fit's plans scored under the source and each ``--irl-transfer`` kernel."""
    cfg, rep = ctx.config, ctx.report
    rep.line(
        "normalised discounted return under each kernel (uniform policy 0, that kernel's own "
        "optimal policy 1) [exact success]: " + ", ".join(METHODS)
    )
    uniform_policy = torch.full((ctx.S, ctx.A), 1 / ctx.A, dtype=torch.float64)
    rows = []
    for label, target in [("source", ctx.mdp), *transfer_mdps(cfg)]:
        own = greedy(target.backup(value_iteration(target, cfg.vi_iters)[-1]))
        own_value = float(target.initial @ policy_evaluation(target, own))
        uniform = float(target.initial @ policy_evaluation(target, uniform_policy))
        for f in fits:
            plans = _plans(ctx, target, f["airl"], f["theta"])
            row = {
                "target": label,
                "dataset": f["label"],
                "own_success": success_probability(target, own),
            }
            row.update({m: _score(target, plans[m], own_value, uniform) for m in METHODS})
            rows.append(row)
            rep.line(
                f"  {label:<22} {f['label']:<13} "
                + "  ".join(
                    f"{m} {_signed(row[m]['normalised_return'])} [{row[m]['success']:.1%}]"
                    for m in METHODS
                )
                + f"  (own expert [{row['own_success']:.1%}])"
            )
    return rows


def airl_transfer(ctx: StudyContext) -> None:
    """Fits, transfer table and figure (module docstring)."""
    cfg, rep, mdp = ctx.config, ctx.report, ctx.mdp
    rep.section("8b. Beyond cloning: AIRL's reward under changed dynamics, exactly")
    why = (
        f"AIRL needs a discount in (0, 1) and a time limit (gamma {cfg.gamma})"
        if not 0.0 < cfg.gamma < 1.0 or mdp.max_steps is None
        else "the env pays no reward anywhere (no goal can be reached): nothing to recover"
        if not (mdp.r != 0).any()
        else None
    )
    if why is not None:
        rep.line(f"skipped: {why}")
        figures_irl.plot_airl_transfer([], METHODS, ctx.figure("airl_transfer"))
        return
    demonstrator = _airl.boltzmann_policy(mdp, cfg.airl_beta)
    T = mdp.max_steps
    assert T is not None  # refused above (why)
    demo_success = float(
        _irl.time_indexed_state_distributions(mdp, demonstrator[None].expand(T, -1, -1))[-1][
            mdp.goal
        ].sum()
    )
    rep.line(
        f"demonstrator: soft-optimal for {cfg.airl_beta:g} x the env's reward (gamma {cfg.gamma}), "
        f"exact success {demo_success:.2%} (the greedy expert {ctx.exact(ctx.expert_table):.2%}); "
        f"datasets {list(cfg.airl_sizes)} episodes (seed {cfg.airl_seed}) and its exact occupancy"
    )
    fits = _fit_all(ctx, demonstrator)
    _report_fits(ctx, fits)
    rows = _transfer(ctx, fits)
    rep.set(
        "airl",
        {
            "demonstrator_success": demo_success,
            "beta": cfg.airl_beta,
            "fits": [
                {
                    "dataset": f["label"],
                    "g": f["airl"].g.tolist(),
                    "h": f["airl"].h.tolist(),
                    "occupancy_gap": float(f["airl"].occupancy_gap[-1]),
                }
                for f in fits
            ],
            "transfer": rows,
        },
    )
    figures_irl.plot_airl_transfer(rows, METHODS, ctx.figure("airl_transfer"))
