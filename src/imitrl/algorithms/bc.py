"""Behaviour cloning: fit a learner's policy to the expert's labels with its own loss.

``fit_bc(learner, data, config)`` runs ``config.num_steps`` steps of
``learner.opt_pi`` on ``learner.loss`` (the loss was chosen when the learner was
built; see :class:`~imitrl.learners.Learner`):

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

The fit reads the keys the loss reads (``learner.loss.in_keys``) and ``OBSERVATION``
when the rows have it (the normaliser's input); a camera-only row has ``PIXELS`` alone.

Memory. A full batch over every row allocates the network's activations for all of
them (about 1 GB per 1e6 rows for a 256-wide MLP), so it is refused, with a message
asking for ``BCConfig(batch_size=...)``, on a disk buffer and beyond
``config.full_batch_max_rows`` rows; distinct pairs are not limited (their number, not
the rows', sets the cost). On a disk buffer (``DemonstrationBuffer(path=...)``) the fit
never holds more than a batch of rows: minibatches index the memory-mapped files (only
the drawn rows are read) in the order of a :class:`~imitrl.data.permutation.LazyPermutation`
(no ``[N]`` permutation in memory); the normaliser is fitted on at most
``CHUNK_BYTES`` of rows (every row when they fit, else a uniform sample drawn with
``config.seed``), and the learner's and the loss's checks run over every row in slices of
that size; distinct pairs are counted slice by slice.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from tensordict import TensorDictBase
from torchrl.record.loggers import Logger
from tqdm.auto import tqdm

from imitrl import keys
from imitrl.configs.bc import PRECISIONS, BCConfig
from imitrl.data.buffer import CHUNK_BYTES, DemonstrationBuffer
from imitrl.data.permutation import LazyPermutation
from imitrl.learners.learner import Learner
from imitrl.runtime import paths
from imitrl.system.device import to_device
from imitrl.system.ranks import DataParallel, sharded, share

__all__ = [
    "FLUSH_SECONDS",
    "PRECISIONS",
    "BCConfig",
    "BCResult",
    "LossStream",
    "distinct_pairs",
    "fit_bc",
]


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
    missing = [k for k in reads if k not in present]
    if missing:
        raise ValueError(f"rows lack {missing}: the learner's loss reads {reads}")
    extra = [keys.OBSERVATION] if keys.OBSERVATION in present else []  # the normaliser's input
    return td.select(*dict.fromkeys([*extra, *reads]))


def distinct_pairs(
    rows: TensorDictBase, label_key=keys.EXPERT_ACTION, *, chunk: int = 1 << 22
) -> tuple[TensorDictBase, torch.Tensor] | None:
    """Distinct (observation, label) rows ``[U]``, sorted by (observation, label), and
    their ``[U]`` int64 counts; None unless both columns are non-negative integers ``[N]``.

    With weights ``count * U / N``, ``mean_j(w_j l_j)`` over the U pairs equals
    ``mean_i l_i`` over the N rows: the full-batch objective is unchanged, only summed
    in another order (the FrozenLake study weights K row sets jointly the same way).
    Rows are read ``chunk`` at a time (a disk buffer's rows are never all in memory);
    the pairs and counts are exact integers, the same for any ``chunk``.
    """
    obs, label = rows.get(keys.OBSERVATION, None), rows.get(label_key)
    if (
        obs is None
        or obs.ndim != 1
        or label.ndim != 1
        or obs.dtype.is_floating_point
        or label.dtype.is_floating_point
    ):
        return None
    n = obs.shape[0]
    parts = [(obs[i : i + chunk].long(), label[i : i + chunk].long()) for i in range(0, n, chunk)]
    if any(int(o.min()) < 0 or int(a.min()) < 0 for o, a in parts):
        return None
    base = max(int(a.max()) for _, a in parts) + 1  # one integer per pair: a 1-D unique
    uniques = [torch.unique(o * base + a, return_counts=True) for o, a in parts]
    codes, counts = torch.cat([c for c, _ in uniques]), torch.cat([k for _, k in uniques])
    if len(parts) > 1:  # merge the slices' pairs, adding their counts
        codes, inverse = torch.unique(codes, return_inverse=True)
        counts = torch.zeros_like(codes).scatter_add_(0, inverse, counts)
    out = rows.empty(batch_size=[codes.shape[0]])
    out.set(keys.OBSERVATION, (codes // base).to(obs.dtype))
    out.set(label_key, (codes % base).to(label.dtype))
    return out, counts


def _with_training_columns(
    learner: Learner, data: DemonstrationBuffer | TensorDictBase
) -> DemonstrationBuffer | TensorDictBase:
    """``data`` with the chunk labels and histories the learner's rows need
    (:meth:`Learner.training_rows`), or ``data`` itself when it needs none."""
    if learner.horizon is None and learner.history is None:
        return data
    if isinstance(data, DemonstrationBuffer):
        if data.path is not None:
            raise ValueError(
                "a learner of chunks or observation histories needs its rows' episodes in "
                "memory to label them: fit it on an in-memory buffer (or rows you labelled "
                "with Learner.training_rows)"
            )
        data = data.data
    return learner.training_rows(data)


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
    """Rows without replacement, epoch after epoch (the tail of an epoch is dropped):
    a ``randperm`` per epoch in memory, a :class:`LazyPermutation` on disk, where each
    batch is read through :meth:`DemonstrationBuffer.rows_at` (only the drawn rows, and
    the pages such reads map are let go regularly)."""

    def __init__(
        self, rows: TensorDictBase | DemonstrationBuffer, reads: list, batch_size: int, seed: int
    ) -> None:
        self.batch_size, self.generator = batch_size, torch.Generator().manual_seed(seed)
        self.part: tuple[int, int] | None = None
        """``(first, count)``: this rank's rows of each global batch (a data-parallel fit)"""
        self.lazy: LazyPermutation | None = None
        if isinstance(rows, DemonstrationBuffer):  # on disk
            self.n, self.buffer, self.reads = len(rows), rows, reads
            self.lazy = LazyPermutation(self.n, self.generator)
            return
        self.rows, self.n = rows, rows.shape[0]
        # plain-tensor views: indexing a column is cheaper than indexing the TensorDict
        self.columns = {
            k: rows.get(k).as_subclass(torch.Tensor)
            for k in rows.keys(include_nested=True, leaves_only=True)
        }
        self.perm, self.cursor = torch.randperm(self.n, generator=self.generator), 0
        # drawn on the CPU (one seed, one order, on every device); rows kept on another
        # device are indexed there
        self.index_device = next(iter(self.columns.values())).device

    def _indices(self) -> torch.Tensor:
        if self.lazy is not None:
            if self.lazy.remaining < self.batch_size:  # next epoch
                self.lazy.new_epoch()
            return self.lazy.take(self.batch_size)
        if self.cursor + self.batch_size > self.n:  # next epoch
            self.perm, self.cursor = torch.randperm(self.n, generator=self.generator), 0
        idx = self.perm[self.cursor : self.cursor + self.batch_size]
        self.cursor += self.batch_size
        return idx

    def next(self) -> TensorDictBase:
        idx = self._indices()
        if self.part is not None:
            idx = idx[self.part[0] : self.part[0] + self.part[1]]
        if self.lazy is not None:
            return self.buffer.rows_at(idx, *self.reads)
        batch = self.rows.empty(batch_size=[idx.numel()])
        if self.index_device.type != "cpu":
            idx = idx.to(self.index_device)
        for key, column in self.columns.items():
            batch.set(key, column.index_select(0, idx))  # = column[idx], without its parsing
        return batch


def _prepare_streaming(
    learner: Learner, buffer: DemonstrationBuffer, reads: list, seed: int
) -> None:
    """``learner.prepare`` and ``loss.check_labels`` over rows that stay on disk: the
    normaliser (if not fitted yet) from at most ``CHUNK_BYTES`` of rows (all of them when
    they fit, else a uniform sample with replacement drawn with ``seed``), then both
    checks over every row, one ``CHUNK_BYTES`` slice at a time (:meth:`~DemonstrationBuffer.chunks`)."""
    n = len(buffer)
    first = buffer.rows_at(torch.zeros(1, dtype=torch.long), *reads)
    row_bytes = sum(v[0].nbytes for v in first.values(include_nested=True, leaves_only=True))
    step = max(1, CHUNK_BYTES // max(1, row_bytes))
    if n <= step:
        first = buffer.rows_at(torch.arange(n), *reads)
    else:
        g = torch.Generator().manual_seed(seed)
        first = buffer.rows_at(torch.randint(n, (step,), generator=g).sort().values, *reads)
    learner.prepare(first)  # fits the normaliser once; later calls only check
    del first
    for part in buffer.chunks(*reads):
        learner.prepare(part)
        learner.loss.check_labels(part)


def _check_full_batch(n: int, on_disk: bool, config: BCConfig) -> None:
    """Refuse a full batch over every row on disk or beyond ``full_batch_max_rows``."""
    limit = config.full_batch_max_rows
    if on_disk or (limit is not None and n > limit):
        where = "a disk buffer" if on_disk else f"more than full_batch_max_rows = {limit:,}"
        raise ValueError(
            f"a full-batch fit (batch_size=None) over {n:,} rows of {where} would hold every "
            "row and its activations in memory at each step: pass BCConfig(batch_size=...) "
            "(e.g. 256)" + ("" if on_disk else ", or raise full_batch_max_rows")
        )


class _Cosine:
    """One fit's schedule over ``opt``'s own learning rates (``BCConfig.lr_schedule`` and
    ``warmup_steps``): a linear warm-up from 0, then constant or the cosine decay over the
    remaining steps (diffusers' ``get_cosine_schedule_with_warmup``)."""

    def __init__(
        self, opt: torch.optim.Optimizer, num_steps: int, warmup: int = 0, kind: str = "cosine"
    ) -> None:
        # a warm-up longer than the fit is cut at its end (the fit stays in its warm-up)
        self.opt, self.num_steps = opt, max(int(num_steps), 1)
        self.warmup = min(int(warmup), self.num_steps)
        self.cosine = kind == "cosine"
        self.base = [group["lr"] for group in opt.param_groups]

    def scale(self, step: int) -> float:
        """The factor on the optimizer's rate at ``step``."""
        if step < self.warmup:
            return step / self.warmup
        if not self.cosine:
            return 1.0
        progress = (step - self.warmup) / max(1, self.num_steps - self.warmup)
        return 0.5 * (1.0 + math.cos(math.pi * progress))

    def at(self, step: int) -> None:
        scale = self.scale(step)
        for group, lr in zip(self.opt.param_groups, self.base):
            group["lr"] = lr * scale

    def restore(self) -> None:
        for group, lr in zip(self.opt.param_groups, self.base):
            group["lr"] = lr


def _bf16(objective: Callable, device: torch.device) -> Callable:
    """``objective`` computed under ``torch.autocast`` in bfloat16, returned in float32."""

    def forward(*args) -> torch.Tensor:
        with torch.autocast(device.type, dtype=torch.bfloat16):
            return objective(*args).float()

    return forward


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
        learner: any :class:`~imitrl.learners.Learner` (``ActorCritic``, a registry
            learner); its ``opt_pi`` takes the steps.
        data: a demonstration buffer or a TensorDict of rows with what the loss reads.
        config: steps, batch size, seed.
        progress: show a progress bar (on stderr).
        logger: a TorchRL logger; the loss of every step is logged as ``log_name`` at
            steps ``log_step, log_step + 1, ...``, while the fit runs (:class:`LossStream`:
            a long fit's curve grows, and the progress bar shows the latest loss).
    """
    if not isinstance(learner, Learner):
        raise ValueError(
            f"fit_bc takes an imitrl Learner (ActorCritic, a registry learner), got "
            f"{type(learner).__name__}"
        )
    data = _with_training_columns(learner, data)
    rows = _rows(data, list(learner.loss.in_keys))
    on_disk = isinstance(data, DemonstrationBuffer) and data.path is not None
    if on_disk:
        # no view of the mapped files is held through the fit: the pages it reads go
        reads, n = list(rows.keys(include_nested=True, leaves_only=True)), rows.shape[0]
        del rows
        _prepare_streaming(learner, data, reads, config.seed)
    else:
        learner.prepare(rows)
        learner.loss.check_labels(rows)  # once, over every row the fit can draw
        n = rows.shape[0]
    dp = DataParallel.of(learner.opt_pi)  # None in a single process
    feed = _feed(learner, data, None if on_disk else rows, n, reads if on_disk else [], config, dp)
    minibatch, rows, weights = feed.batches is not None, feed.rows, feed.weights
    objective, opt = learner.loss.objective, learner.opt_pi
    zero_grad = paths.zero_grad(opt)  # the seam's: its assignment without the method's range
    if config.compile:
        objective = torch.compile(objective)
    opt_step = paths.optimizer_step(opt)  # on the CPU: Adam's update without its wrapper
    device, cross = _placement(opt)
    if cross and not minibatch:  # the full batch crosses to the learner's device once
        rows = to_device(rows, device)
        weights = None if weights is None else to_device(weights, device)
    losses = torch.empty(config.num_steps, device=device)  # recording never waits for it
    steps = tqdm(range(config.num_steps), desc="bc fit", disable=not progress, leave=False)
    stream = LossStream(losses, logger, log_name, log_step, steps if progress else None)
    schedule = None
    if config.lr_schedule == "cosine" or config.warmup_steps:
        schedule = _Cosine(opt, config.num_steps, config.warmup_steps, config.lr_schedule)
    ema = learner.ema
    if config.precision == "bf16":  # the forward in bfloat16; backward and the step float32
        objective = _bf16(objective, device)
    shard = contextlib.nullcontext() if dp is None else sharded(feed.first, feed.total)
    try:
        # e.g. its networks without nn.Module.__call__; an EMA learner's trained weights
        with learner.loss.fitting(), learner.fitting_weights(), shard:
            for step in steps:
                batch = feed.batches.next() if feed.batches is not None else rows
                if cross and minibatch:  # pinned, without blocking: runtime.device
                    batch = to_device(batch, device)
                loss = objective(batch) if weights is None else objective(batch, weights)
                zero_grad()
                loss.backward()
                if dp is not None:  # the global batch's gradients and loss, on every rank
                    loss = dp.reduce(loss, feed.count, feed.total)
                if schedule is not None:
                    schedule.at(step)
                opt_step()
                if ema is not None:
                    ema.update()
                losses[step] = loss.detach()
                if stream.on and stream.due():
                    stream.flush(step + 1)
    finally:
        if schedule is not None:
            schedule.restore()
    stream.flush(config.num_steps)
    final = float(losses[-1]) if losses.numel() else float("nan")
    return BCResult(losses=losses.cpu(), final_loss=final, num_rows=n)


@dataclass
class _Feed:
    """Each step's batch: minibatches, or the full batch (and its distinct pairs'
    weights); in a data-parallel fit this rank's ``count`` rows from ``first`` of each
    global batch of ``total``."""

    batches: _Minibatches | None
    rows: TensorDictBase | None
    weights: torch.Tensor | None
    first: int
    count: int
    total: int


def _feed(
    learner: Learner,
    data: DemonstrationBuffer | TensorDictBase,
    rows: TensorDictBase | None,
    n: int,
    reads: list,
    config: BCConfig,
    dp: DataParallel | None,
) -> _Feed:
    """The fit's batches over ``n`` rows (``rows`` in memory; None on disk, where a batch
    reads the columns ``reads`` of the drawn rows only): minibatches of
    ``config.batch_size`` per rank when that is below ``n`` (the global batch: the batch
    times the ranks), else the full batch, on distinct pairs where the loss allows (one
    process only)."""
    world = 1 if dp is None else dp.world
    weights, batches = None, None
    if config.batch_size is not None and config.batch_size * world < n:
        total = config.batch_size * world  # the global batch: each rank computes its share
        batches = _Minibatches(data if rows is None else rows, reads, total, config.seed)
    else:
        on_disk = rows is None
        if rows is None:
            rows = _rows(data, list(learner.loss.in_keys))  # distinct pairs may be few
        if dp is None:
            rows, weights = _dedup(learner, rows, config)
        if weights is None and config.batch_size is None:  # a batch_size at or above n
            _check_full_batch(n, on_disk, config)  # already bounds what a step holds
        total = rows.shape[0]
    first, count = (0, total) if dp is None else share(total, dp.rank, dp.world)
    if batches is not None:
        batches.part = None if dp is None else (first, count)
    elif dp is not None and rows is not None:
        rows = rows[first : first + count]
    return _Feed(batches, rows, weights, first, count, total)


def _placement(opt: torch.optim.Optimizer) -> tuple[torch.device, bool]:
    """``(device, cross)``: the parameters' device, and whether batches cross to it (rows
    stay on the CPU or disk; a minibatch crosses each step, pinned and without blocking)."""
    device = next((p.device for g in opt.param_groups for p in g["params"]), torch.device("cpu"))
    return device, device.type != "cpu"


FLUSH_SECONDS = 1.0
"""how often a fit hands its losses to the logger and the progress bar"""


class LossStream:
    """A fit's losses to the logger and the progress bar while it runs: the steps since
    the last flush, every :data:`FLUSH_SECONDS` (one read of the losses from their
    device each time), and the rest when the fit ends. What is logged (each step's loss
    at its step) does not depend on when it is flushed; without a logger or a bar
    nothing is read until the end (:attr:`on`)."""

    def __init__(self, losses: torch.Tensor, logger: Logger | None, name: str, first: int,
                 bar: tqdm | None) -> None:  # fmt: skip
        self.losses, self.logger, self.name, self.first, self.bar = losses, logger, name, first, bar
        self.on = logger is not None or bar is not None
        """whether anything reads the losses while the fit runs"""
        self.done, self.next = 0, time.monotonic() + FLUSH_SECONDS

    def due(self) -> bool:
        """Whether :data:`FLUSH_SECONDS` have passed since the last flush."""
        return time.monotonic() >= self.next

    def flush(self, upto: int) -> None:
        """Log the losses of steps ``done .. upto - 1`` and show the last on the bar."""
        values = self.losses[self.done : upto].tolist() if self.on else []
        if self.logger is not None:
            for i, value in enumerate(values, start=self.first + self.done):
                self.logger.log_scalar(self.name, value, step=i)
        if self.bar is not None and values:
            self.bar.set_postfix(loss=f"{values[-1]:.4g}", refresh=False)
        self.done, self.next = upto, time.monotonic() + FLUSH_SECONDS
