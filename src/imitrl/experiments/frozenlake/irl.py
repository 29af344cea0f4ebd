"""Section 8: beyond cloning. Maximum-entropy IRL from the same demonstrations, exactly.

Behaviour cloning reads only the demonstrated (state, action) pairs and throws the
transition kernel away. Maximum-causal-entropy IRL (:mod:`imitrl.tabular.maxent_irl`)
uses it: it infers a reward on the state entered, ``R(s, a, s') = theta[s']``, under
which the demonstrated actions are softly optimal (the exact causal likelihood,
maximised with its exact gradient), then plans against that reward. Everything here is
exact: the fitted reward, its soft-optimal and greedy policies' success probabilities,
and the same for every dataset of the sweep and every transfer target.

* the fit from section 1's demonstrations, and what it does on the states the
  demonstrations never visited (the clone's blind spots);
* redrawn datasets of each size: IRL, BC and DAgger from the same datasets;
* reward transfer: the reward recovered under the study's dynamics, planned against
  under other dynamics (``--irl-transfer``: constructor arguments of the env), scored
  against that dynamics' own expert.
"""

from __future__ import annotations

import ast
import importlib
import inspect
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
import torch

from imitrl import keys
from imitrl.experiments.frozenlake import figures_irl
from imitrl.experiments.frozenlake.config import StudyConfig
from imitrl.experiments.frozenlake.context import StudyContext
from imitrl.experiments.frozenlake.replicates import fit_tables, replicated_dagger
from imitrl.tabular.dp import greedy, value_iteration
from imitrl.tabular.finite_horizon import (
    reachable_states,
    state_distributions,
    success_probability,
)
from imitrl.tabular.mdp import TabularMDP

if TYPE_CHECKING:
    from imitrl.tabular.maxent_irl import IRLResult

# the module, not the function of the same name that imitrl.tabular re-exports
_irl = importlib.import_module("imitrl.tabular.maxent_irl")

__all__ = ["irl", "transfer_mdps"]

# what --irl-transfer means when not given: these constructor arguments, where the env takes them
_DEFAULT_TRANSFER = (("is_slippery", "False"), ("success_rate", "0.5"), ("success_rate", "0.9"))


def _env_arguments(env_id: str) -> set[str] | None:
    """Names the env's constructor takes (None: unknown, e.g. a function entry point)."""
    entry = gym.spec(env_id).entry_point
    if entry is None:
        return None  # no entry point to read
    if not isinstance(entry, str):
        entry_obj = entry
    else:
        module, _, name = entry.partition(":")
        entry_obj = getattr(importlib.import_module(module), name)
    try:
        return set(inspect.signature(entry_obj).parameters)
    except (TypeError, ValueError):
        return None


def transfer_mdps(config: StudyConfig) -> list[tuple[str, TabularMDP]]:
    """``(label, MDP)`` of each transfer target; refuses what the env cannot build.

    ``config.irl_transfer`` None: the default targets the env's constructor accepts.
    """
    pairs = config.irl_transfer
    if pairs is None:
        accepted = _env_arguments(config.env_id) or set()
        pairs = tuple(p for p in _DEFAULT_TRANSFER if p[0] in accepted)
    out = []
    for name, text in pairs:
        try:
            value = ast.literal_eval(text)
        except (ValueError, SyntaxError):
            value = text  # a bare word: a string argument
        kwargs = {**config.make_kwargs, name: value}
        try:
            mdp = TabularMDP.from_gym(
                config.env_id, config.gamma, make_kwargs=kwargs, max_steps=config.max_steps
            )
        except Exception as err:  # gym.make's own errors are of many types
            raise ValueError(
                f"--irl-transfer {name}:{text}: {config.env_id} cannot be built with "
                f"{name}={value!r} ({type(err).__name__}: {err})"
            ) from err
        out.append((f"{name}={value!r}", mdp))
    return out


def _fit(ctx: StudyContext, rows: list) -> IRLResult:
    """IRL on each row set at once (a batch of fits, each its own)."""
    mdp, cfg = ctx.mdp, ctx.config
    demos = _irl.Demonstrations.stack([_irl.Demonstrations.from_rows(mdp, r) for r in rows])
    phi = _irl.next_state_features(mdp)
    return _irl.maxent_irl(mdp, demos, phi, steps=cfg.irl_steps, lr=cfg.irl_lr)


def _soft_success(mdp: TabularMDP, policy: torch.Tensor) -> float:
    """Exact success within the time limit of the time-indexed soft policy ``[T, S, A]``."""
    return float(_irl.time_indexed_state_distributions(mdp, policy)[-1][mdp.goal].sum())


def _main_fit(ctx: StudyContext) -> IRLResult:
    """The fit from section 1's demonstrations, reported next to the expert and the clone."""
    mdp, rep = ctx.mdp, ctx.report
    assert ctx.demos is not None  # section 1 set them
    res = _fit(ctx, [ctx.demos])
    theta, table = res.theta[0], res.greedy()[0]
    uniform = -float(ctx.demos.shape[0]) / ctx.config.demo_episodes * np.log(ctx.A)
    ll = float(res.log_likelihood[0, -1])
    exact: dict[str, float | None] = {
        "expert": ctx.exact(ctx.expert_table),
        "irl": ctx.exact(table),
    }
    exact["clone"] = ctx.exact(ctx.clone_table) if ctx.clone_table is not None else None
    soft = _soft_success(mdp, res.policy[0])
    rep.line(
        f"reward on the state entered, fitted to the {ctx.config.demo_episodes} demonstrations "
        f"by exact causal likelihood ({ctx.config.irl_steps} Adam steps, lr {ctx.config.irl_lr}): "
        f"log-likelihood per episode {ll:.4f} (uniform policy {uniform:.4f})"
    )
    clone = f", the clone {exact['clone']:.2%}" if exact["clone"] is not None else ""
    rep.line(
        f"planning against it: greedy policy {exact['irl']:.2%} exact success, soft-optimal "
        f"policy {soft:.2%} (the expert {exact['expert']:.2%}{clone})"
    )
    reachable = reachable_states(mdp) & ~mdp.terminal
    seen = set(ctx.demos.get(keys.OBSERVATION).tolist())
    unseen = [s for s in torch.nonzero(reachable).view(-1).tolist() if s not in seen]
    match = {s: bool(table[s] == ctx.expert_table[s]) for s in unseen}
    clone_match = (
        {s: bool(ctx.clone_table[s] == ctx.expert_table[s]) for s in unseen}
        if ctx.clone_table is not None
        else {}
    )
    rep.line(
        f"on the {len(unseen)} reachable states the demonstrations never visited {unseen}: "
        f"IRL's greedy action is the expert's on {sum(match.values())}"
        + (f", the clone's on {sum(clone_match.values())}" if clone_match else "")
    )
    rep.set(
        "irl.fit",
        {
            "log_likelihood": ll,
            "uniform_log_likelihood": uniform,
            "theta": theta.tolist(),
            "policy": table.tolist(),
            "exact_success_greedy": exact["irl"],
            "exact_success_soft": soft,
            "unseen_states": unseen,
            "unseen_match_expert": [match[s] for s in unseen],
            "demonstrations_argmax": _argmax_fraction(ctx, res),
        },
    )
    return res


def _argmax_fraction(ctx: StudyContext, res: IRLResult) -> float:
    """Fraction of demonstrated decisions that are a most likely action of the soft-optimal
    policy (ties included)."""
    assert ctx.demos is not None  # section 1 set them
    t = ctx.demos.get(keys.STEP).long()
    s = ctx.demos.get(keys.OBSERVATION).long()
    a = ctx.demos.get(keys.EXPERT_ACTION).long()
    probs = res.policy[0][t, s]  # [N, A]
    chosen = probs.gather(-1, a.unsqueeze(-1)).squeeze(-1)
    # a tie is a most likely action too (argmax would pick the lowest index among them)
    best = torch.isclose(chosen, probs.max(dim=-1).values, rtol=1e-9, atol=1e-12)
    return float(best.double().mean())


def _sweep(ctx: StudyContext) -> dict[int, dict[str, np.ndarray]]:
    """IRL, BC and DAgger from the same redrawn datasets of each size; exact success."""
    cfg, rep = ctx.config, ctx.report
    block = ctx.backend.block(cfg.irl_seed)
    rep.line(f"redrawn datasets ({cfg.irl_datasets} per size), exact success: median [worst]")
    out: dict[int, dict[str, np.ndarray]] = {}
    for n in cfg.irl_sizes:
        rows = (
            block.demonstrations(n, cfg.irl_datasets)
            if ctx.backend.vectorised
            else [
                block.demonstrations(n)[0] for _ in ctx.bar(range(cfg.irl_datasets), f"irl {n} ep")
            ]
        )
        scores = {
            "irl": ctx.exact_each(_fit(ctx, rows).greedy()),
            "bc": ctx.exact_each(fit_tables(ctx, rows, cfg.sweep_fit_steps)[0]),
            "dagger": ctx.exact_each(replicated_dagger(ctx, block, rows, cfg.fit_steps)[0]),
        }
        rep.line(
            f"{n:>3} episodes: "
            + ", ".join(
                f"{k.upper() if k != 'dagger' else 'DAgger'} {np.median(v):.1%} [{v.min():.1%}]"
                for k, v in scores.items()
            )
        )
        rep.set(f"irl.sweep.{n}", {k: np.sort(v).tolist() for k, v in scores.items()})
        out[n] = scores
    return out


def _transfer(ctx: StudyContext, res: IRLResult) -> list[dict]:
    """The recovered reward planned against under each target's dynamics."""
    cfg, rep = ctx.config, ctx.report
    rows: list[dict[str, Any]] = []
    targets = transfer_mdps(cfg)
    if not targets:
        rep.line("reward transfer: no target dynamics for this env (--irl-transfer)")
        return rows
    rep.line(
        "reward transfer, exact success under the target dynamics: IRL's reward planned "
        "there | the source expert's policy | the target's own expert; where the plan "
        "spends its steps"
    )
    for label, mdp in targets:
        reward = _irl.linear_reward(res.theta[0], _irl.next_state_features(mdp))
        planned = _irl.soft_value_iteration(mdp, reward).q[0].argmax(dim=-1)
        own = greedy(mdp.backup(value_iteration(mdp, cfg.vi_iters)[-1]))
        visits = state_distributions(mdp, planned)[:-1].sum(0) * (~mdp.terminal)  # [S]
        most = int(visits.argmax())
        row = {
            "target": label,
            "irl": success_probability(mdp, planned),
            "source_expert": success_probability(mdp, ctx.expert_table),
            "target_expert": success_probability(mdp, own),
            "most_visited": most,
            "most_visited_steps": float(visits[most]),
        }
        rep.line(
            f"  {label:<22} {row['irl']:.2%} | {row['source_expert']:.2%} | "
            f"{row['target_expert']:.2%}; {row['most_visited_steps']:.1f} expected steps in "
            f"state {most} (reward {float(res.theta[0, most]):+.2f} per entry)"
        )
        rows.append(row)
    if any(r["irl"] < r["source_expert"] - 1e-9 for r in rows):
        rep.line(
            "  a reward on the state entered is identified only up to shaping: what explains "
            "the demonstrations under one dynamics may pay the plan to loiter under another"
        )
    rep.set("irl.transfer", rows)
    return rows


def irl(ctx: StudyContext) -> None:
    """Fit, sweep and transfer (module docstring); figures of the reward and the sweep."""
    ctx.report.section("8. Beyond cloning: maximum-entropy IRL, exactly")
    res = _main_fit(ctx)
    scores = _sweep(ctx)
    _transfer(ctx, res)
    figures_irl.plot_reward(
        ctx.mdp.desc, res.theta[0].numpy(), res.greedy()[0].numpy(), ctx.figure("irl_reward")
    )
    figures_irl.plot_irl_sweep(scores, ctx.exact(ctx.expert_table), ctx.figure("irl_sweep"))
