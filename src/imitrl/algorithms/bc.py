"""Behaviour cloning: fit a learner's policy to the expert's labels with its own loss.

``fit_bc(learner, data, config)`` runs ``config.num_steps`` steps of
``learner.opt_pi`` on ``learner.loss`` (the loss was chosen when the learner was
built; see :class:`~imitrl.policies.Learner`):

* full batch (``batch_size=None``): every step sees every row, as the section's
  ``clone`` does; deterministic given the data;
* minibatch: rows are drawn without replacement, epoch after epoch, from a
  permutation seeded by ``config.seed`` (the buffer's TorchRL sampler is not used on
  this hot path: one ``randperm`` per epoch and tensor slicing cost a fraction of a
  ``ReplayBuffer.sample`` call; ``benchmarks/bc_throughput.py`` measures both).

Before the first step the learner validates the rows and fits its observation
normaliser (``learner.prepare``), and the loss validates every label a step can draw
(``learner.loss.check_labels``). Full-batch fits of a loss that takes per-row weights
(``supports_weights``) and reads only observations and labels train on the distinct
(observation, label) pairs weighted by their counts (:func:`distinct_pairs`): the
same objective, at a cost that does not grow with repeated rows.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from tensordict import TensorDictBase
from torchrl.record.loggers import Logger
from tqdm.auto import tqdm

from imitrl import keys
from imitrl.data.buffer import DemonstrationBuffer
from imitrl.policies.learner import Learner

__all__ = ["BCConfig", "BCResult", "distinct_pairs", "fit_bc"]


@dataclass(frozen=True)
class BCConfig:
    """Behaviour-cloning fit (the loss belongs to the learner, not to this config)."""

    num_steps: int = 200
    """gradient steps of the policy optimizer"""
    batch_size: int | None = None
    """rows per step; None = the full batch every step"""
    seed: int = 0
    """seed of the minibatch order"""
    deduplicate: bool | None = None
    """full batch over integer observations and labels: train on the distinct
    (observation, label) pairs weighted by their counts, the same objective at a cost
    that does not grow with the rows; None = whenever it applies"""

    def __post_init__(self) -> None:
        if int(self.num_steps) != self.num_steps or self.num_steps < 0:
            raise ValueError(f"num_steps must be an integer >= 0, got {self.num_steps!r}")
        if self.batch_size is not None and self.batch_size < 1:
            raise ValueError(f"batch_size must be positive or None, got {self.batch_size}")


@dataclass
class BCResult:
    """What a behaviour-cloning fit measured."""

    losses: torch.Tensor = field(repr=False)
    """``[num_steps]`` loss at each step, before that step's update"""
    final_loss: float
    """the last entry of ``losses`` (nan when num_steps == 0)"""
    num_rows: int
    """rows the fit was trained on"""


def _rows(data: DemonstrationBuffer | TensorDictBase, reads: list) -> TensorDictBase:
    td = data.data if isinstance(data, DemonstrationBuffer) else data
    if not isinstance(td, TensorDictBase):
        raise ValueError(
            f"fit_bc needs a DemonstrationBuffer or a TensorDict, got {type(data).__name__}"
        )
    if td.batch_dims != 1 or td.shape[0] == 0:
        raise ValueError(
            f"fit_bc needs a non-empty batch of rows, got batch_size {tuple(td.batch_size)}"
        )
    present = set(td.keys(include_nested=True))
    missing = [k for k in (keys.OBSERVATION, *reads) if k not in present]
    if missing:
        raise ValueError(f"rows lack {missing}: the learner's loss reads {reads}")
    return td.select(*dict.fromkeys([keys.OBSERVATION, *reads]))


def distinct_pairs(
    rows: TensorDictBase, label_key=keys.EXPERT_ACTION
) -> tuple[TensorDictBase, torch.Tensor] | None:
    """Distinct (observation, label) rows ``[U]``, sorted by (observation, label), and
    their ``[U]`` int64 counts; None unless both columns are non-negative integers ``[N]``.

    With weights ``count * U / N``, ``mean_j(w_j l_j)`` over the U pairs equals
    ``mean_i l_i`` over the N rows: the full-batch objective is unchanged, only summed
    in another order (the FrozenLake study weights K row sets jointly the same way).
    """
    obs, label = rows.get(keys.OBSERVATION), rows.get(label_key)
    if (
        obs.ndim != 1
        or label.ndim != 1
        or obs.dtype.is_floating_point
        or label.dtype.is_floating_point
    ):
        return None
    o, a = obs.long(), label.long()
    if int(a.min()) < 0 or int(o.min()) < 0:
        return None
    base = int(a.max()) + 1  # one integer per pair: a 1-D unique is far cheaper than dim=0
    codes, counts = torch.unique(o * base + a, return_counts=True)
    out = rows.empty(batch_size=[codes.shape[0]])
    out.set(keys.OBSERVATION, (codes // base).to(obs.dtype))
    out.set(label_key, (codes % base).to(label.dtype))
    return out, counts


def _dedup(learner: Learner, rows: TensorDictBase, config: BCConfig):
    """``(rows, weights)`` of the full-batch fit: distinct pairs where they apply."""
    loss = learner.loss
    plain = set(loss.in_keys) <= {keys.OBSERVATION, loss.label_key}
    if config.deduplicate is False or not (loss.supports_weights and plain):
        if config.deduplicate:
            raise ValueError("deduplicate=True needs a loss that takes per-row weights")
        return rows, None
    distinct = distinct_pairs(rows, loss.label_key)
    if distinct is None:
        if config.deduplicate:
            raise ValueError(
                "deduplicate=True needs integer observations [N] and integer labels [N]"
            )
        return rows, None
    pairs, counts = distinct
    return pairs, counts.to(torch.float32) * (pairs.shape[0] / rows.shape[0])


class _Minibatches:
    """Rows without replacement, epoch after epoch (the tail of an epoch is dropped)."""

    def __init__(self, rows: TensorDictBase, batch_size: int, seed: int) -> None:
        self.rows, self.batch_size, self.n = rows, batch_size, rows.shape[0]
        self.columns = {k: rows.get(k) for k in rows.keys(include_nested=True, leaves_only=True)}
        self.generator = torch.Generator().manual_seed(seed)
        self.perm, self.cursor = torch.randperm(self.n, generator=self.generator), 0

    def next(self) -> TensorDictBase:
        if self.cursor + self.batch_size > self.n:  # next epoch
            self.perm, self.cursor = torch.randperm(self.n, generator=self.generator), 0
        idx = self.perm[self.cursor : self.cursor + self.batch_size]
        self.cursor += self.batch_size
        batch = self.rows.empty(batch_size=[idx.numel()])
        for key, column in self.columns.items():
            batch.set(key, column[idx])
        return batch


def fit_bc(
    learner: Learner,
    data: DemonstrationBuffer | TensorDictBase,
    config: BCConfig = BCConfig(),
    *,
    progress: bool = False,
    logger: Logger | None = None,
    log_name: str = "bc/loss",
    log_step: int = 0,
) -> BCResult:
    """Fit ``learner``'s policy to the labels in ``data`` with ``learner.loss``.

    Args:
        learner: any :class:`~imitrl.policies.Learner` (``ActorCritic``, a registry
            learner); its ``opt_pi`` takes the steps.
        data: a demonstration buffer or a TensorDict of rows with what the loss reads.
        config: steps, batch size, seed.
        progress: show a progress bar (on stderr).
        logger: a TorchRL logger; the loss of every step is logged as ``log_name`` at
            steps ``log_step, log_step + 1, ...``.
    """
    if not isinstance(learner, Learner):
        raise ValueError(
            f"fit_bc takes an imitrl Learner (ActorCritic, a registry learner), got "
            f"{type(learner).__name__}"
        )
    rows = _rows(data, list(learner.loss.in_keys))
    learner.prepare(rows)
    learner.loss.check_labels(rows)  # once, over every row the fit can draw
    n = rows.shape[0]
    minibatch = config.batch_size is not None and config.batch_size < n
    weights = None
    if minibatch:
        batches = _Minibatches(rows, config.batch_size, config.seed)
    else:
        rows, weights = _dedup(learner, rows, config)
    objective, opt = learner.loss.objective, learner.opt_pi
    losses = torch.empty(config.num_steps)
    steps = tqdm(range(config.num_steps), desc="bc fit", disable=not progress, leave=False)
    for step in steps:
        batch = batches.next() if minibatch else rows
        loss = objective(batch) if weights is None else objective(batch, weights)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        losses[step] = loss.detach()
    if logger is not None:
        for step, value in enumerate(losses.tolist()):
            logger.log_scalar(log_name, value, step=log_step + step)
    final = float(losses[-1]) if config.num_steps else float("nan")
    return BCResult(losses=losses, final_loss=final, num_rows=n)
