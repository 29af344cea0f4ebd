"""K replicates of one experiment: K datasets, K clones, K DAgger runs.

The batched backend runs the K replicates as one experiment on the ``K``-fold product
MDP (replicate ``k`` owns states ``k * S + s``): one rollout, one joint fit, one
evaluation. The faithful backend runs them one after another on the block's stream, in
the section's order. A joint fit of K row sets equals K separate fits (see
:func:`fit_tables`), so row sets that touch no random stream are always fitted jointly.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from tensordict import TensorDict

from imitrl import keys
from imitrl.algorithms.bc import BCConfig, distinct_pairs, fit_bc
from imitrl.algorithms.dagger import EpisodeSource, dagger
from imitrl.experiments.frozenlake.backends import Block, _BatchedBlock
from imitrl.experiments.frozenlake.context import StudyContext
from imitrl.learners.actor_critic import ActorCritic
from imitrl.learners.learner import Learner
from imitrl.objectives.bc import BehaviorCloningLoss
from imitrl.policies.experts import Expert
from imitrl.tabular.finite_horizon import expected_episode_length

__all__ = [
    "demos_with_budget",
    "fit_tables",
    "product_rows",
    "replicated_clones",
    "replicated_dagger",
]


def _joint_pairs(rows: list[TensorDict], S: int) -> TensorDict:
    """The K row sets as distinct (product state ``k * S + s``, label) pairs, weighted.

    Weight ``count * U / N_k`` (U distinct pairs, N_k rows in the pair's own set): the
    weighted mean over the U pairs is ``sum_k mean_k``, the sum of the K fits' objectives.
    """
    obs = torch.cat([r.get(keys.OBSERVATION) + k * S for k, r in enumerate(rows)])
    label = torch.cat([r.get(keys.EXPERT_ACTION) for r in rows])
    union = TensorDict({keys.OBSERVATION: obs, keys.EXPERT_ACTION: label}, [obs.shape[0]])
    distinct = distinct_pairs(union)
    assert distinct is not None  # integer states and actions
    pairs, counts = distinct
    per_copy = torch.tensor([r.shape[0] for r in rows], dtype=torch.float32)
    state = pairs.get(keys.OBSERVATION)
    pairs.set(keys.WEIGHT, counts.float() * pairs.shape[0] / per_copy[state // S])
    return pairs


def fit_tables(
    ctx: StudyContext, rows: list[TensorDict], steps: int
) -> tuple[torch.Tensor, list[float]]:
    """Fit one zero-initialised tabular clone per row set; ``[K, S]`` greedy tables.

    K > 1 row sets are fitted as one ``K * S``-row table on the product states
    (``k * S + s``), over the distinct (state, label) pairs weighted so that the
    objective is ``sum_k mean_k``: copies touch disjoint rows of the table, so each
    copy's gradient, and hence its Adam step, is the one its own fit would take.
    """
    S, K = ctx.S, len(rows)
    if K == 1:
        clone = ctx.learner()
        fit = fit_bc(clone, rows[0], BCConfig(num_steps=steps, batch_size=None))
        return clone.greedy_table()[None], [fit.final_loss]
    union = _joint_pairs(rows, S)
    table = ctx.learner(K)
    # the same table trained on the weighted pairs (the WEIGHT column is read as data)
    weighted = BehaviorCloningLoss(table.policy, loss_type="nll", weighted=True)
    learner = Learner(table.policy, weighted, table.opt_pi)
    fit = fit_bc(learner, union, BCConfig(num_steps=steps, batch_size=None))
    return table.greedy_table().reshape(K, S), [fit.final_loss] * K


def replicated_clones(
    ctx: StudyContext,
    block: Block,
    K: int,
    n_demos: int,
    fit_steps: int,
    eval_episodes: int,
    desc: str,
) -> tuple[torch.Tensor, torch.Tensor | None, list[TensorDict]]:
    """K datasets of ``n_demos`` expert episodes -> K clones -> (optionally) K success rates.

    Returns the ``[K, S]`` greedy tables, the ``[K]`` success rates (None when
    ``eval_episodes`` is 0) and the K row sets.

    Faithful: replicate after replicate on the block's stream (demos, fit, evaluation).
    Batched: all K datasets in one rollout, one joint fit, one evaluation run.
    """
    if ctx.backend.vectorised:
        rows = block.demonstrations(n_demos, K)
        tables, _ = fit_tables(ctx, rows, fit_steps)
        rates = block.evaluate(tables, eval_episodes) if eval_episodes else None
        return tables, rates, rows
    if not eval_episodes:
        # nothing but the demonstrations touches the stream: draw them in order, fit jointly
        rows = [block.demonstrations(n_demos)[0] for _ in ctx.bar(range(K), desc)]
        return fit_tables(ctx, rows, fit_steps)[0], None, rows
    each_table: list[torch.Tensor] = []
    each_rate: list[torch.Tensor] = []
    rows = []
    for _ in ctx.bar(range(K), desc):  # each evaluation reads the stream the next demos use
        r = block.demonstrations(n_demos)[0]
        t = fit_tables(ctx, [r], fit_steps)[0][0]
        each_rate.append(block.evaluate(t[None], eval_episodes)[0])
        each_table.append(t)
        rows.append(r)
    return torch.stack(each_table), torch.stack(each_rate), rows


def product_rows(rows: list[TensorDict], S: int) -> TensorDict:
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


def replicated_dagger(
    ctx: StudyContext,
    block: Block,
    demos: list[TensorDict],
    fit_steps: int,
    wrap_source: Callable[[EpisodeSource], EpisodeSource] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """DAgger from each demonstration set; returns final ``[K, S]`` tables and ``[K]`` label counts.

    ``wrap_source`` (e.g. a labeller that corrupts the expert's labels) wraps every
    episode source the relabel rounds are collected from.
    """
    cfg = ctx.config
    K, S = len(demos), ctx.S
    # on the product MDP one round collects every copy's episodes (lanes pinned to copies)
    episodes = cfg.dagger_episodes * (K if ctx.backend.vectorised else 1)
    dcfg = ctx.dagger_config(episodes, fit_steps)

    def wrap(source: EpisodeSource) -> EpisodeSource:
        return source if wrap_source is None else wrap_source(source)

    if ctx.backend.vectorised:
        assert isinstance(block, _BatchedBlock)  # the batched backend's
        buf = ctx.buffer(product_rows(demos, S), num_states=K * S)
        source = wrap(block.source(K, cfg.dagger_episodes))
        res = dagger(
            source, Expert.from_table(ctx.expert_table.repeat(K)), lambda: ctx.learner(K), buf, dcfg
        )
        copy = buf.data.get(keys.OBSERVATION) // S
        budgets = torch.bincount(copy, minlength=K)
        assert isinstance(res.learner, ActorCritic)  # ctx.learner's table
        return res.learner.greedy_table().reshape(K, S), budgets
    tables: list[torch.Tensor] = []
    counts: list[int] = []
    for d in demos:
        buf = ctx.buffer(d)
        res = dagger(
            wrap(block.source()), Expert.from_table(ctx.expert_table), ctx.learner, buf, dcfg
        )
        assert isinstance(res.learner, ActorCritic)  # ctx.learner's table
        tables.append(res.learner.greedy_table())
        counts.append(len(buf))
    return torch.stack(tables), torch.tensor(counts)


def demos_with_budget(ctx: StudyContext, block: Block, budgets: torch.Tensor) -> list[TensorDict]:
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
