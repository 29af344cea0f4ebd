"""Exercise 5: a bad expert. BC and DAgger when a fraction of the expert's labels is wrong."""

from __future__ import annotations

import math

import numpy as np
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase

from imitrl import keys
from imitrl.algorithms.dagger import EpisodeSource
from imitrl.experiments.frozenlake import figures
from imitrl.experiments.frozenlake.backends import Block
from imitrl.experiments.frozenlake.context import StudyContext
from imitrl.experiments.frozenlake.replicates import fit_tables, replicated_dagger

__all__ = ["CorruptedSource", "corrupt_labels", "ex_corruption"]


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


class CorruptedSource:
    """An episode source whose expert labels are corrupted (a bad expert on call)."""

    def __init__(
        self, source: EpisodeSource, fraction: float, num_actions: int, generator: torch.Generator
    ) -> None:
        self.source = source
        self.fraction = fraction
        self.A = num_actions
        self.generator = generator

    def check(self, expert, learner) -> None:
        """The wrapped source's checks."""
        self.source.check(expert, learner)

    def state_dict(self) -> dict:
        """The wrapped source's state and the corruption generator's."""
        return {
            "source": self.source.state_dict(),
            "generator": self.generator.get_state().tolist(),
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict`."""
        self.source.load_state_dict(state["source"])
        self.generator.set_state(torch.tensor(state["generator"], dtype=torch.uint8))

    def collect(
        self,
        behaviour: TensorDictModuleBase,
        num_episodes: int,
        *,
        round_index: int,
        first_episode: int,
    ) -> TensorDict:
        rows = self.source.collect(
            behaviour, num_episodes, round_index=round_index, first_episode=first_episode
        )
        return corrupt_labels(rows, self.fraction, self.A, self.generator)


def _dagger_clean_and_corrupted(
    ctx: StudyContext, block: Block, generator: torch.Generator, K: int
) -> tuple[list[TensorDict], list[TensorDict], torch.Tensor, torch.Tensor]:
    """K replicates of: demonstrations, a corrupted copy, DAgger from each (``[K, S]`` tables).

    The corrupted DAgger run relabels with the same bad expert; ``generator`` draws
    every corruption, in stream order.
    """
    cfg = ctx.config

    def bad_expert(source: EpisodeSource) -> EpisodeSource:
        return CorruptedSource(source, cfg.ex_corruption, ctx.A, generator)

    if ctx.backend.vectorised:
        demos = block.demonstrations(cfg.demo_episodes, K)
        bad = [corrupt_labels(d, cfg.ex_corruption, ctx.A, generator) for d in demos]
        clean_tables = replicated_dagger(ctx, block, demos, cfg.ex_fit_steps)[0]
        bad_tables = replicated_dagger(ctx, block, bad, cfg.ex_fit_steps, bad_expert)[0]
        return demos, bad, clean_tables, bad_tables
    demos, bad = [], []
    clean_each: list[torch.Tensor] = []
    bad_each: list[torch.Tensor] = []
    for _ in ctx.bar(range(K), "corruption"):  # stream order: demos, clean DAgger, noisy DAgger
        demos.append(block.demonstrations(cfg.demo_episodes)[0])
        bad.append(corrupt_labels(demos[-1], cfg.ex_corruption, ctx.A, generator))
        clean_each.append(replicated_dagger(ctx, block, demos[-1:], cfg.ex_fit_steps)[0][0])
        bad_each.append(replicated_dagger(ctx, block, bad[-1:], cfg.ex_fit_steps, bad_expert)[0][0])
    return demos, bad, torch.stack(clean_each), torch.stack(bad_each)


def _degrades_more(clean: np.ndarray, bad: np.ndarray, K: int) -> tuple[str, str]:
    """Which method's ``[2, K]`` exact success drops more under corruption ("neither" within 2 se)."""
    paired = (clean[0] - bad[0]) - (clean[1] - bad[1])
    se = paired.std(ddof=1) / math.sqrt(K) if K > 1 else float("inf")
    if abs(paired.mean()) <= 2 * se:
        verdict = f"Neither degrades measurably more (difference of drops {paired.mean():+.3f}, se {se:.3f})"
        return "neither", verdict
    faster = "BC" if paired.mean() > 0 else "DAgger"
    return faster, f"{faster} degrades more (difference of drops {paired.mean():+.3f}, se {se:.3f})"


def ex_corruption(ctx: StudyContext) -> None:
    """Exact success of BC and DAgger with clean and with corrupted expert labels."""
    cfg, rep = ctx.config, ctx.report
    rep.section(f"Exercise 5. A bad expert: {cfg.ex_corruption:.0%} of the labels corrupted")
    block = ctx.backend.block(cfg.ex_seed + 3)
    gen = torch.Generator().manual_seed(cfg.ex_seed + 3)
    K = cfg.ex_datasets
    demos, bad_demos, dagger_clean, dagger_bad = _dagger_clean_and_corrupted(ctx, block, gen, K)
    # the BC fits use no random stream: fitted jointly after the data is drawn
    tables = {
        "bc": (
            fit_tables(ctx, demos, cfg.ex_fit_steps)[0],
            fit_tables(ctx, bad_demos, cfg.ex_fit_steps)[0],
        ),
        "dagger": (dagger_clean, dagger_bad),
    }
    clean = np.array([ctx.exact_each(tables[m][0]) for m in ("bc", "dagger")])  # [2, K]
    bad = np.array([ctx.exact_each(tables[m][1]) for m in ("bc", "dagger")])
    for i, m in enumerate(("BC", "DAgger")):
        drop = clean[i] - bad[i]
        se = drop.std(ddof=1) / math.sqrt(K) if K > 1 else float("nan")  # one seed: no spread
        rep.line(
            f"{m:<6}: exact success clean {clean[i].mean():.3f}, corrupted {bad[i].mean():.3f}, drop {drop.mean():+.3f} (se {se:.3f})"
        )
    faster, verdict = _degrades_more(clean, bad, K)
    changed = [
        float(np.mean([int((c != b).sum()) for c, b in zip(*tables[m])])) for m in ("bc", "dagger")
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
    figures.plot_corruption(["BC", "DAgger"], clean, bad, ctx.figure("ex_corruption"))
