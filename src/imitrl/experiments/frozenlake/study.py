"""The FrozenLake study: every experiment of the section, then its exercises.

``run_study(config)`` is a function of its config: same config, same digits. It
prints the report, writes ``report.txt``, ``results.json`` and the figures to
``config.out``, and returns the results dict. Every Monte Carlo rate is printed next
to the exact finite-horizon value of the same policy.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np
import torch
from tensordict import TensorDict
from torchrl.data import Categorical
from tqdm.auto import tqdm

from imitrl import keys
from imitrl.algorithms.bc import BCConfig, fit_bc
from imitrl.algorithms.dagger import DAggerConfig, dagger
from imitrl.data.buffer import DemonstrationBuffer
from imitrl.evaluation.evaluate import wilson_interval
from imitrl.experiments.frozenlake import figures
from imitrl.experiments.frozenlake.backends import BatchedBackend, FaithfulBackend
from imitrl.experiments.frozenlake.chain import chain_exact, chain_monte_carlo
from imitrl.experiments.frozenlake.config import StudyConfig
from imitrl.experiments.frozenlake.report import Report
from imitrl.objectives.bc import BehaviorCloningLoss
from imitrl.policies.actor_critic import ActorCritic
from imitrl.policies.experts import Expert
from imitrl.tabular.dp import greedy, value_iteration
from imitrl.tabular.finite_horizon import (
    expected_episode_length,
    reachable_states,
    state_distributions,
    success_probability,
    total_variation,
)
from imitrl.tabular.mdp import TabularMDP

__all__ = ["run_study"]


@dataclass
class _Context:
    config: StudyConfig
    mdp: TabularMDP
    expert_table: torch.Tensor
    backend: FaithfulBackend | BatchedBackend
    report: Report
    demos: TensorDict | None = None
    clone: ActorCritic | None = None
    clone_table: torch.Tensor | None = None
    _exact: dict = field(default_factory=dict)

    @property
    def S(self) -> int:
        return self.mdp.num_states

    @property
    def A(self) -> int:
        return self.mdp.num_actions

    def exact(self, table: torch.Tensor) -> float:
        key = tuple(table.tolist())  # replicates often share a table: price each once
        if key not in self._exact:
            self._exact[key] = success_probability(self.mdp, table)
        return self._exact[key]

    def buffer(
        self, rows: TensorDict | None = None, num_states: int | None = None
    ) -> DemonstrationBuffer:
        buf = DemonstrationBuffer(num_states=num_states or self.S, action_spec=Categorical(self.A))
        if rows is not None:
            buf.extend(rows)
        return buf

    def learner(self, copies: int = 1) -> ActorCritic:
        return ActorCritic.tabular(self.S * copies, self.A, lr=self.config.lr)

    def bar(self, iterable, desc: str, total: int | None = None):
        return tqdm(iterable, desc=desc, total=total, disable=not self.config.progress, leave=False)


# --------------------------------------------------------------------- helpers
def _fit_tables(
    ctx: _Context, rows: list[TensorDict], steps: int
) -> tuple[torch.Tensor, list[float]]:
    """Fit one zero-initialised tabular clone per row set; ``[K, S]`` greedy tables.

    K > 1 row sets are fitted as one ``K * S``-row table on the product states
    (``k * S + s``), over the distinct (state, label) pairs weighted so that the
    objective is ``sum_k mean_k``: copies touch disjoint rows of the table, so each
    copy's gradient, and hence its Adam step, is the one its own fit would take.
    """
    S, K = ctx.S, len(rows)
    if K == 1:
        learner = ctx.learner()
        fit = fit_bc(learner, rows[0], BCConfig(num_steps=steps))
        return learner.greedy_table()[None], [fit.final_loss]
    obs = torch.cat([r.get(keys.OBSERVATION) + k * S for k, r in enumerate(rows)])
    label = torch.cat([r.get(keys.EXPERT_ACTION) for r in rows])
    codes, counts = torch.unique(obs * ctx.A + label, return_counts=True)
    state, action = codes // ctx.A, codes % ctx.A
    per_copy = torch.tensor([r.shape[0] for r in rows], dtype=torch.float32)
    weight = counts.float() * codes.numel() / per_copy[state // S]
    union = TensorDict(
        {keys.OBSERVATION: state, keys.EXPERT_ACTION: action, keys.WEIGHT: weight},
        batch_size=[codes.numel()],
    )
    learner = ctx.learner(K)
    loss = BehaviorCloningLoss(learner.policy, loss_type="nll", weighted=True)
    fit = fit_bc(learner, union, BCConfig(num_steps=steps), loss_module=loss)
    return learner.greedy_table().reshape(K, S), [fit.final_loss] * K


def _replicated_clones(
    ctx: _Context, block, K: int, n_demos: int, fit_steps: int, eval_episodes: int, desc: str
) -> tuple[torch.Tensor, torch.Tensor | None, list[TensorDict]]:
    """K datasets of ``n_demos`` expert episodes -> K clones -> (optionally) K success rates.

    Faithful: replicate after replicate on the block's stream (demos, fit, evaluation).
    Batched: all K datasets in one rollout, one joint fit, one evaluation run.
    """
    if ctx.backend.vectorised:
        rows = block.demonstrations(n_demos, K)
        tables, _ = _fit_tables(ctx, rows, fit_steps)
        rates = block.evaluate(tables, eval_episodes) if eval_episodes else None
        return tables, rates, rows
    if not eval_episodes:
        # nothing but the demonstrations touches the stream: draw them in order, fit jointly
        rows = [block.demonstrations(n_demos)[0] for _ in ctx.bar(range(K), desc)]
        return _fit_tables(ctx, rows, fit_steps)[0], None, rows
    tables, rates, rows = [], [], []
    for _ in ctx.bar(range(K), desc):  # each evaluation reads the stream the next demos use
        r = block.demonstrations(n_demos)[0]
        t = _fit_tables(ctx, [r], fit_steps)[0][0]
        rates.append(block.evaluate(t[None], eval_episodes)[0])
        tables.append(t)
        rows.append(r)
    return torch.stack(tables), torch.stack(rates), rows


def corrupt_labels(
    rows: TensorDict, fraction: float, num_actions: int, generator: torch.Generator
) -> TensorDict:
    """A copy of ``rows`` with ``round(fraction * n)`` expert labels replaced by a different action."""
    rows = rows.clone()
    n = rows.shape[0]
    m = round(fraction * n)
    if m == 0:
        return rows
    idx = torch.randperm(n, generator=generator)[:m]
    label = rows.get(keys.EXPERT_ACTION)
    label[idx] = (
        label[idx] + torch.randint(1, num_actions, (m,), generator=generator)
    ) % num_actions
    return rows


class _CorruptedSource:
    """An episode source whose expert labels are corrupted (a bad expert on call)."""

    def __init__(
        self, source, fraction: float, num_actions: int, generator: torch.Generator
    ) -> None:
        self.source, self.fraction, self.A, self.generator = (
            source,
            fraction,
            num_actions,
            generator,
        )

    def collect(
        self, behaviour, num_episodes: int, *, round_index: int, first_episode: int
    ) -> TensorDict:
        rows = self.source.collect(
            behaviour, num_episodes, round_index=round_index, first_episode=first_episode
        )
        return corrupt_labels(rows, self.fraction, self.A, self.generator)


def _product_rows(rows: list[TensorDict], S: int) -> TensorDict:
    """Row sets of K copies as one row set on the product MDP (states and episode ids shifted)."""
    parts, next_episode = [], 0
    for k, r in enumerate(rows):
        r = r.clone()
        r.set(keys.OBSERVATION, r.get(keys.OBSERVATION) + k * S)
        ep = r.get(keys.EPISODE)
        r.set(keys.EPISODE, ep - ep.min() + next_episode)
        next_episode = int(r.get(keys.EPISODE).max()) + 1
        parts.append(r)
    return torch.cat(parts)


def _replicated_dagger(
    ctx: _Context,
    block,
    demos: list[TensorDict],
    fit_steps: int,
    corruption: tuple[float, torch.Generator] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """DAgger from each demonstration set; returns final ``[K, S]`` tables and ``[K]`` label counts."""
    cfg = ctx.config
    K, S = len(demos), ctx.S
    # on the product MDP one round collects every copy's episodes (lanes pinned to copies)
    episodes = cfg.dagger_episodes * (K if ctx.backend.vectorised else 1)
    dcfg = DAggerConfig(
        rounds=cfg.dagger_rounds, episodes_per_round=episodes, fit=BCConfig(num_steps=fit_steps)
    )

    def wrap(source):
        return (
            source
            if corruption is None
            else _CorruptedSource(source, corruption[0], ctx.A, corruption[1])
        )

    if ctx.backend.vectorised:
        buf = ctx.buffer(_product_rows(demos, S), num_states=K * S)
        source = wrap(block.source(K, cfg.dagger_episodes))
        res = dagger(
            source, Expert.from_table(ctx.expert_table.repeat(K)), lambda: ctx.learner(K), buf, dcfg
        )
        copy = buf.data.get(keys.OBSERVATION) // S
        budgets = torch.bincount(copy, minlength=K)
        return res.learner.greedy_table().reshape(K, S), budgets
    tables, budgets = [], []
    for d in demos:
        buf = ctx.buffer(d)
        res = dagger(
            wrap(block.source()), Expert.from_table(ctx.expert_table), ctx.learner, buf, dcfg
        )
        tables.append(res.learner.greedy_table())
        budgets.append(len(buf))
    return torch.stack(tables), torch.tensor(budgets)


def _demos_with_budget(ctx: _Context, block, budgets: torch.Tensor) -> list[TensorDict]:
    """Expert demonstrations cut to exactly ``budgets[k]`` pairs for each replicate."""
    mean_len = expected_episode_length(ctx.mdp, ctx.expert_table)
    K = budgets.numel()
    have: list[list[TensorDict]] = [[] for _ in range(K)]
    counts = torch.zeros(K, dtype=torch.int64)
    while (counts < budgets).any():
        missing = (budgets - counts).clamp_min(0)
        n = max(1, math.ceil(float(missing.max()) / (1 + mean_len) * 1.2))
        if ctx.backend.vectorised:
            new = block.demonstrations(n, K)
        else:
            # one replicate's demonstrations at a time (the caller interleaves replicates)
            new = [block.demonstrations(n)[0] if missing[k] > 0 else None for k in range(K)]
        for k in range(K):
            if missing[k] > 0 and new[k] is not None:
                have[k].append(new[k])
                counts[k] += new[k].shape[0]
    return [torch.cat(h)[: int(b)] for h, b in zip(have, budgets)]


def _decision_distribution(mdp: TabularMDP, table: torch.Tensor) -> torch.Tensor:
    """``[S]`` where the policy takes its decisions: mean of d_0 .. d_{T-1} over live states."""
    d = state_distributions(mdp, table)[:-1]
    live = d * (~mdp.terminal).double()
    total = live.sum()
    return live.sum(0) / total


# ---------------------------------------------------------------------- study
def run_study(config: StudyConfig, *, echo: bool = True) -> dict:
    """Run the whole study (see the module docstring); returns the results dict."""
    t0 = time.perf_counter()
    timing: dict[str, float] = {}
    out = config.out
    out.mkdir(parents=True, exist_ok=True)
    rep = Report(out, echo=echo)
    mdp = TabularMDP.from_gym(
        config.env_id, config.gamma, make_kwargs=config.make_kwargs, max_steps=config.max_steps
    )
    V = value_iteration(mdp, config.vi_iters)[-1]
    expert_table = greedy(mdp.backup(V))
    backend = (
        FaithfulBackend(mdp, expert_table)
        if config.protocol == "faithful"
        else BatchedBackend(mdp, expert_table, config.eval_scale)
    )
    ctx = _Context(config, mdp, expert_table, backend, rep)
    rep.set(
        "config", {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(config).items()}
    )
    rep.set("protocol", config.protocol)
    if mdp.max_steps is None:
        raise ValueError(
            f"{mdp.name!r} is registered without a time limit: give one with --max-steps "
            "(StudyConfig.max_steps); every success rate here is within a horizon"
        )
    bad = [s for s in config.probe_states if not 0 <= s < mdp.num_states]
    if bad:
        raise ValueError(
            f"--probe-states {bad} outside the {mdp.num_states} states of {mdp.name!r}"
        )
    starts = int((mdp.initial > 0).sum())
    if config.protocol == "batched" and starts != 1:
        raise ValueError(
            f"--protocol batched pins each lane to one start state, and {mdp.name!r} has "
            f"{starts}: run it with --protocol faithful"
        )
    stochastic = bool((mdp.P.amax(-1) < 1).any())
    limit = "no time limit" if mdp.max_steps is None else f"time limit {mdp.max_steps}"
    rep.line(
        f"imitrl frozenlake: {mdp.name}, {'stochastic' if stochastic else 'deterministic'} "
        f"transitions, {limit}, protocol {config.protocol}"
    )
    if config.protocol == "batched":
        rep.line(
            f"(batched: independent TabularEnv lanes, {config.eval_scale}x the evaluation episodes; numbers differ from the section's)"
        )

    sections: list[tuple[str, Callable[[_Context], None]]] = [
        ("expert", _expert_and_demos),
        ("bc", _behaviour_cloning),
        ("evaluation", _evaluation),
        ("sweep", _sweep),
        ("chain", _chain),
        ("divergence", _divergence),
        ("dagger", _dagger),
    ]
    if config.exercises:
        sections += [
            ("ex_demo_counts", _ex_demo_counts),
            ("ex_state_errors", _ex_state_errors),
            ("ex_budget", _ex_budget),
            ("ex_corruption", _ex_corruption),
        ]
    sections.append(("prose", _prose_checks))
    for name, fn in sections:
        ts = time.perf_counter()
        fn(ctx)
        timing[name] = time.perf_counter() - ts
    timing["total"] = time.perf_counter() - t0
    rep.set("timing", timing)
    rep.section("Outputs")
    text, data = rep.write()
    rep.line(f"report: {text}")
    rep.line(f"results: {data}")
    rep.line(f"figures: {', '.join(sorted(p.name for p in out.glob('*.png')))}")
    rep.line(f"wall time: {timing['total']:.1f} s")
    rep.write()
    return rep.results


# ------------------------------------------------------------------- sections
def _expert_and_demos(ctx: _Context) -> None:
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


def _behaviour_cloning(ctx: _Context) -> None:
    cfg, rep = ctx.config, ctx.report
    rep.section("2. Behaviour cloning")
    buffer = ctx.buffer(ctx.demos)
    clone = ctx.learner()
    fit = fit_bc(clone, buffer, BCConfig(num_steps=cfg.fit_steps))
    ctx.clone = clone
    rep.line(f"cross-entropy on the demonstrations after the fit: {fit.final_loss:.3f}")
    rep.set("bc.cross_entropy", fit.final_loss)
    for s in cfg.probe_states:
        probs = clone.probs(np.int64(s)).astype(np.float32)
        rep.line(f"clone pi(.|s={s}): {np.round(probs, 3)}")
        rep.set(f"bc.probs.{s}", probs.astype(float).tolist())


def _evaluation(ctx: _Context) -> None:
    cfg, rep = ctx.config, ctx.report
    rep.section("3. Acting on its own")
    clone_table = ctx.clone.greedy_table()
    ctx.clone_table = clone_table
    demos = ctx.demos
    mistakes = int(
        (clone_table[demos.get(keys.OBSERVATION)] != demos.get(keys.EXPERT_ACTION)).sum()
    )
    n = cfg.eval_episodes * ctx.backend.eval_scale
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


def _sweep(ctx: _Context) -> None:
    cfg, rep = ctx.config, ctx.report
    rep.section("4. How typical was the dataset: redrawn datasets")
    block = ctx.backend.block(cfg.sweep_seed)
    n_eval = cfg.sweep_eval_episodes * ctx.backend.eval_scale
    all_rates, all_exact = [], []
    for n in cfg.sweep_sizes:
        tables, rates, _ = _replicated_clones(
            ctx, block, cfg.sweep_datasets, n, cfg.sweep_fit_steps, n_eval, f"sweep {n} ep"
        )
        rates = rates.double().numpy()
        exact = np.array([ctx.exact(t) for t in tables])
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
        cfg.sweep_sizes, all_rates, all_exact, ctx.exact(ctx.expert_table), cfg.out / "sweep.png"
    )


def _chain(ctx: _Context) -> None:
    cfg, rep = ctx.config, ctx.report
    rep.section("5. Compounding error on the chain")
    panels = []
    for eps, T in cfg.chain_panels:
        rng = np.random.default_rng(cfg.chain_seed)
        gap_bc, gap_rec = chain_monte_carlo(eps, T, cfg.chain_samples, rng)
        ex_bc, ex_rec = chain_exact(eps, T)
        rep.line(
            f"lost return at T={T}: cloned {gap_bc[-1]:.2f} (eps T^2/2 = {eps * T**2 / 2:.2f}), "
            f"recovering {gap_rec[-1]:.2f} (eps T = {eps * T:.2f})"
        )
        rep.line(
            f"  eps={eps}: exact expectations cloned {ex_bc[-1]:.3f}, recovering {ex_rec[-1]:.3f}; "
            f"ratio measured {gap_bc[-1] / gap_rec[-1]:.1f}x, exact {ex_bc[-1] / ex_rec[-1]:.1f}x"
        )
        panels.append(
            {
                "eps": eps,
                "T": T,
                "cloned": gap_bc,
                "recovering": gap_rec,
                "cloned_exact": ex_bc,
                "recovering_exact": ex_rec,
                "ratio": float(gap_bc[-1] / gap_rec[-1]),
                "ratio_exact": float(ex_bc[-1] / ex_rec[-1]),
            }
        )
    rep.set("chain.panels", panels)
    figures.plot_chain(panels, cfg.out / "chain.png")


def _divergence(ctx: _Context) -> None:
    cfg, mdp, rep = ctx.config, ctx.mdp, ctx.report
    rep.section("6. The divergence of the state distributions (exact kernel evolution)")
    H = max(cfg.tv_steps)
    d_exp = state_distributions(mdp, ctx.expert_table, H)
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
    occ_exp, occ_clo = d_exp[1:].mean(0), d_clo[1:].mean(0)
    rep.set("divergence.occupancy", {"expert": occ_exp, "clone": occ_clo, "steps": H})
    figures.plot_occupancy(
        mdp.desc,
        [occ_exp.numpy(), occ_clo.numpy()],
        [ctx.expert_table.numpy(), ctx.clone_table.numpy()],
        ["expert occupancy", "clone occupancy"],
        cfg.out / "occupancy.png",
    )


def _dagger(ctx: _Context) -> None:
    cfg, rep = ctx.config, ctx.report
    rep.section("7. DAgger: relabel the learner's states, aggregate, refit")
    block = ctx.backend.block(cfg.dagger_seed)
    n = cfg.eval_episodes * ctx.backend.eval_scale
    buffer = ctx.buffer(ctx.demos.clone())
    rounds: list[dict] = []

    def on_fit(k: int, learner: ActorCritic) -> None:
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

    source = block.source() if not ctx.backend.vectorised else block.source(1, cfg.dagger_episodes)
    dagger(
        source,
        Expert.from_table(ctx.expert_table),
        ctx.learner,
        buffer,
        DAggerConfig(
            rounds=cfg.dagger_rounds,
            episodes_per_round=cfg.dagger_episodes,
            fit=BCConfig(num_steps=cfg.fit_steps),
        ),
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
        cfg.out / "dagger.png",
    )


# ------------------------------------------------------------------ exercises
def _ex_demo_counts(ctx: _Context) -> None:
    cfg, mdp, rep = ctx.config, ctx.mdp, ctx.report
    rep.section("Exercise 2. How many demonstrations")
    block = ctx.backend.block(cfg.ex_seed)
    expert_states = _decision_distribution(mdp, ctx.expert_table)
    expert_success = ctx.exact(ctx.expert_table)
    success = np.zeros((len(cfg.ex_demo_counts), cfg.ex_datasets))
    agree = np.zeros_like(success)
    own_error = np.zeros_like(success)
    rep.line(
        f"{cfg.ex_datasets} datasets per N, {cfg.ex_fit_steps} fit steps; exact values (expert success {expert_success:.2%})"
    )
    rep.line(
        "     N | success mean [min, max]   | agreement on expert's states | error on own states | clones matching on expert's states"
    )
    for i, N in enumerate(cfg.ex_demo_counts):
        tables, _, _ = _replicated_clones(
            ctx, block, cfg.ex_datasets, N, cfg.ex_fit_steps, 0, f"N={N}"
        )
        for k, t in enumerate(tables):
            success[i, k] = ctx.exact(t)
            agree[i, k] = float((expert_states * (t == ctx.expert_table).double()).sum())
            own = _decision_distribution(mdp, t)
            own_error[i, k] = float((own * (t != ctx.expert_table).double()).sum())
        matching = agree[i] >= 0.999
        lost = (expert_success - success[i][matching]).mean() if matching.any() else float("nan")
        rep.line(
            f"{N:>6} | {success[i].mean():.3f} [{success[i].min():.3f}, {success[i].max():.3f}] "
            f"| {agree[i].mean():>27.4f} | {own_error[i].mean():>18.4f} | {int(matching.sum())}/{cfg.ex_datasets}"
            + (f", losing {lost:.4f} success on average" if matching.any() else "")
        )
        rep.set(
            f"exercises.demo_counts.{N}",
            {
                "success": success[i],
                "agreement_expert_states": agree[i],
                "error_own_states": own_error[i],
            },
        )
    gap = expert_success - success
    near = [
        (N, float(gap[i][agree[i] >= 0.99].mean()))
        for i, N in enumerate(cfg.ex_demo_counts)
        if (agree[i] >= 0.99).any()
    ]
    losing = [(N, g) for N, g in near if g > 1e-3]
    if losing:
        rep.line(
            f"answer: at N = {losing[0][0]} clones already agree with the expert on >= 99% of the expert's state mass "
            f"yet lose {losing[0][1]:.2%} success on average: the remaining disagreements sit on rarely visited states "
            "from which the clone's own mistakes compound"
        )
    rep.set("exercises.demo_counts.answer", losing[0][0] if losing else None)
    figures.plot_demo_counts(
        list(cfg.ex_demo_counts), success, agree, expert_success, cfg.out / "ex_demo_counts.png"
    )


def _ex_state_errors(ctx: _Context) -> None:
    cfg, mdp, rep = ctx.config, ctx.mdp, ctx.report
    rep.section("Exercise 3. Where the errors are")
    block = ctx.backend.block(cfg.ex_seed + 1)
    tables, _, rows = _replicated_clones(
        ctx, block, cfg.ex_error_datasets, cfg.demo_episodes, cfg.ex_fit_steps, 0, "state errors"
    )
    live = torch.nonzero(reachable_states(mdp) & ~mdp.terminal).view(-1)
    visit = _decision_distribution(mdp, ctx.expert_table)
    error = (tables != ctx.expert_table).double().mean(0)
    coverage = torch.zeros(ctx.S, dtype=torch.float64)
    for r in rows:
        seen = torch.zeros(ctx.S, dtype=torch.bool)
        seen[r.get(keys.OBSERVATION)] = True
        coverage += seen.double()
    coverage /= len(rows)
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
        visit[live].numpy(), error[live].numpy(), live.tolist(), cfg.out / "ex_state_errors.png"
    )


def _ex_budget(ctx: _Context) -> None:
    cfg, rep = ctx.config, ctx.report
    rep.section("Exercise 4. DAgger's budget: BC and DAgger at an equal number of expert queries")
    block = ctx.backend.block(cfg.ex_seed + 2)
    K = cfg.ex_datasets
    if ctx.backend.vectorised:
        demos = block.demonstrations(cfg.demo_episodes, K)
        dagger_tables, budgets = _replicated_dagger(ctx, block, demos, cfg.ex_fit_steps)
        bc_rows = _demos_with_budget(ctx, block, budgets)
    else:
        demos, dagger_tables, budgets, bc_rows = [], [], [], []
        for _ in ctx.bar(range(K), "budget"):
            d = block.demonstrations(cfg.demo_episodes)[0]
            t, b = _replicated_dagger(ctx, block, [d], cfg.ex_fit_steps)
            bc_rows += _demos_with_budget(ctx, block, b)
            demos.append(d)
            dagger_tables.append(t[0])
            budgets.append(b[0])
        dagger_tables, budgets = torch.stack(dagger_tables), torch.stack(budgets)
    bc_tables, _ = _fit_tables(ctx, bc_rows, cfg.ex_fit_steps)
    demo_tables, _ = _fit_tables(ctx, demos, cfg.ex_fit_steps)
    dg = np.array([ctx.exact(t) for t in dagger_tables])
    bc = np.array([ctx.exact(t) for t in bc_tables])
    bc0 = np.array([ctx.exact(t) for t in demo_tables])
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
        budgets.numpy(), dg, bc, bc0, ctx.exact(ctx.expert_table), cfg.out / "ex_budget.png"
    )


def _ex_corruption(ctx: _Context) -> None:
    cfg, rep = ctx.config, ctx.report
    rep.section(f"Exercise 5. A bad expert: {cfg.ex_corruption:.0%} of the labels corrupted")
    block = ctx.backend.block(cfg.ex_seed + 3)
    gen = torch.Generator().manual_seed(cfg.ex_seed + 3)
    K = cfg.ex_datasets
    noise = (cfg.ex_corruption, gen)
    results = {"bc": [[], []], "dagger": [[], []]}
    if ctx.backend.vectorised:
        demos = block.demonstrations(cfg.demo_episodes, K)
        bad = [corrupt_labels(d, cfg.ex_corruption, ctx.A, gen) for d in demos]
        results["dagger"][0] = _replicated_dagger(ctx, block, demos, cfg.ex_fit_steps)[0]
        results["dagger"][1] = _replicated_dagger(ctx, block, bad, cfg.ex_fit_steps, noise)[0]
    else:
        demos, bad = [], []
        for _ in ctx.bar(range(K), "corruption"):  # stream order: demos, clean DAgger, noisy DAgger
            demos.append(block.demonstrations(cfg.demo_episodes)[0])
            bad.append(corrupt_labels(demos[-1], cfg.ex_corruption, ctx.A, gen))
            results["dagger"][0].append(
                _replicated_dagger(ctx, block, demos[-1:], cfg.ex_fit_steps)[0][0]
            )
            results["dagger"][1].append(
                _replicated_dagger(ctx, block, bad[-1:], cfg.ex_fit_steps, noise)[0][0]
            )
    # the BC fits use no random stream: fitted jointly after the data is drawn
    results["bc"][0] = _fit_tables(ctx, demos, cfg.ex_fit_steps)[0]
    results["bc"][1] = _fit_tables(ctx, bad, cfg.ex_fit_steps)[0]
    clean = np.array([[ctx.exact(t) for t in results[m][0]] for m in ("bc", "dagger")])
    bad = np.array([[ctx.exact(t) for t in results[m][1]] for m in ("bc", "dagger")])
    for i, m in enumerate(("BC", "DAgger")):
        drop = clean[i] - bad[i]
        rep.line(
            f"{m:<6}: exact success clean {clean[i].mean():.3f}, corrupted {bad[i].mean():.3f}, drop {drop.mean():+.3f} (se {drop.std(ddof=1) / math.sqrt(K):.3f})"
        )
    paired = (clean[0] - bad[0]) - (clean[1] - bad[1])
    se = paired.std(ddof=1) / math.sqrt(K) if K > 1 else float("inf")
    if abs(paired.mean()) <= 2 * se:
        faster = "neither"
        verdict = f"Neither degrades measurably more (difference of drops {paired.mean():+.3f}, se {se:.3f})"
    else:
        faster = "BC" if paired.mean() > 0 else "DAgger"
        verdict = f"{faster} degrades more (difference of drops {paired.mean():+.3f}, se {se:.3f})"
    changed = [
        float(np.mean([int((c != b).sum()) for c, b in zip(results[m][0], results[m][1])]))
        for m in ("bc", "dagger")
    ]
    rep.line(
        f"{verdict}. Corruption changed the greedy action on {changed[0]:.1f} states per BC clone and "
        f"{changed[1]:.1f} per DAgger learner: a tabular clone acts on the majority label of each state, so a "
        "corrupted label wins only where a state holds one or two labels"
    )
    rep.set(
        "exercises.corruption",
        {
            "fraction": cfg.ex_corruption,
            "bc_clean": clean[0],
            "bc_corrupted": bad[0],
            "dagger_clean": clean[1],
            "dagger_corrupted": bad[1],
            "degrades_more": faster,
            "states_changed": {"bc": changed[0], "dagger": changed[1]},
        },
    )
    figures.plot_corruption(["BC", "DAgger"], clean, bad, cfg.out / "ex_corruption.png")


# ---------------------------------------------------------------- prose check
def _prose_checks(ctx: _Context) -> None:
    """Where the section's prose and the exact numbers agree or not."""
    r, rep = ctx.report.results, ctx.report
    rep.section("Prose vs exact values")
    checks = []

    def check(claim: str, printed: float, exact: float, agrees: bool, note: str = "") -> None:
        verdict = "agrees" if agrees else "DISAGREES"
        rep.line(
            f"- {claim}: measured {printed:.4g}, exact {exact:.4g} -> {verdict}{'; ' + note if note else ''}"
        )
        checks.append(
            {
                "claim": claim,
                "measured": printed,
                "exact": exact,
                "agrees": bool(agrees),
                "note": note,
            }
        )

    faithful = ctx.config.protocol == "faithful"
    if not faithful:
        rep.line(
            "(the batched protocol draws other datasets: only the draw-independent claims are checked)"
        )
    ev = r.get("evaluation", {}) if faithful else {}
    for name in ("expert", "clone"):
        if name in ev:
            e = ev[name]
            inside = e["ci"][0] <= e["exact"] <= e["ci"][1]
            check(
                f"{name} success rate {e['rate']:.1%}",
                e["rate"],
                e["exact"],
                inside,
                "exact value inside the 95% interval"
                if inside
                else "exact value outside the 95% interval",
            )
    if (
        "expert" in ev
        and "clone" in ev
        and min(1 - ev["expert"]["rate"], 1 - ev["expert"]["exact"]) <= 0
    ):
        rep.line(
            "- the clone fails three times as often as the expert: undefined, the expert never fails"
        )
    elif "expert" in ev and "clone" in ev:
        fail_ratio = (1 - ev["clone"]["rate"]) / (1 - ev["expert"]["rate"])
        fail_exact = (1 - ev["clone"]["exact"]) / (1 - ev["expert"]["exact"])
        check(
            "the clone fails three times as often as the expert",
            fail_ratio,
            fail_exact,
            abs(fail_exact - 3) < 0.5,
        )
    claims = {
        (0.05, 10): (
            "cloned and recovering already five times apart at T = 10",
            lambda x: abs(x - 5.0) < 0.5,
        ),
        (0.01, 64): (
            "at T = 64 the gap between the rates has grown past thirtyfold",
            lambda x: x > 30.0,
        ),
    }
    for c in r.get("chain", {}).get("panels", []):
        if (c["eps"], c["T"]) in claims:
            claim, holds = claims[(c["eps"], c["T"])]
            check(
                claim,
                c["ratio"],
                c["ratio_exact"],
                holds(c["ratio_exact"]),
                "ratio of lost returns, cloned / recovering",
            )
    div = r.get("divergence", {}) if faithful else {}
    if "worst_hole" in div:
        h = str(div["worst_hole"])
        mass = div["hole_mass"][h]["clone"]
        check(
            f"the clone parks 22 percent of its mass in hole {h} by step 20",
            mass,
            mass,
            abs(mass - 0.22) < 0.01,
            "exact kernel evolution",
        )
    dg = r.get("dagger", {}).get("rounds", []) if faithful else []
    if len(dg) > 1:
        e = r["expert"]["exact_success"]
        check(
            "one DAgger round later the clone matches the expert",
            dg[1]["rate"],
            dg[1]["exact"],
            abs(dg[1]["exact"] - e) < 0.01,
            f"expert exact {e:.4f}",
        )
    rep.set("prose_checks", checks)
