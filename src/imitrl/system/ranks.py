"""Data-parallel ranks on ``torch.distributed``: who this process is, and a fit's step
shared among the ranks.

imitrl trains data-parallel on torch's own collectives (gloo on CPUs, NCCL on GPUs), in
processes that ``torchrun`` (or ``imitrl ... --nproc N``, which launches them the same
way, through torch's elastic launcher) starts with ``RANK`` and ``WORLD_SIZE`` set. Every
rank holds the same demonstrations (the same seeds give the same rows), and each step of
``fit_bc`` splits its global batch among the ranks (:class:`DataParallel`): rank ``r``
computes the loss of its contiguous share of rows, the gradients and the loss are summed
across ranks weighted by each rank's share of the rows (one all-reduce of one flat
buffer a step), and every rank takes the same optimizer step. N ranks at batch ``B`` are
one process at batch ``N B``: the same rows, the same per-row draws
(:func:`rows_drawn`), the same masked means (:func:`masked_mean`), the same parameters up
to float summation order. A loss whose draws happen inside TorchRL's own modules
(``act``'s CVAE latent, ``diffusion``'s noise, an entropy estimate) draws on each rank
from its own generator: a valid data-parallel fit, not bit for bit one process's.
GAIL's and AIRL's discriminator and PPO steps average their gradients the same way
(:meth:`DataParallel.mean`), each rank playing its own lanes
(:mod:`imitrl.algorithms.adversarial.loop`); :func:`gathered` and :func:`summed` put
every rank's rows or counts together.

Why ``torch.distributed`` and not TorchRL's Ray learner backend or Ray Train: a fit is
one loop over one buffer that every rank already holds; the collectives are all it
needs, and ``torchrun`` is the launcher people already use for LeRobot's and torch's
own data-parallel training, on one machine or many (``--nnodes``, ``--rdzv-endpoint``).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from contextvars import ContextVar
from typing import TypeVar

import torch

__all__ = [
    "DataParallel",
    "barrier",
    "check_same",
    "from_lead",
    "gathered",
    "masked_mean",
    "rank_and_world",
    "rows_drawn",
    "sharded",
    "share",
    "summed",
]

T = TypeVar("T")

_SHARD: ContextVar[tuple[int, int] | None] = ContextVar("imitrl_shard", default=None)
"""``(first, total)``: this rank's rows start at ``first`` of a global batch of ``total``"""


@contextlib.contextmanager
def sharded(first: int, total: int) -> Iterator[None]:
    """Within: the batch a loss sees is rows ``first ..`` of a global batch of ``total``
    rows (a data-parallel fit's share, set by ``fit_bc``): :func:`rows_drawn` draws for
    all of them, :func:`masked_mean` divides by the global batch's weight."""
    token = _SHARD.set((int(first), int(total)))
    try:
        yield
    finally:
        _SHARD.reset(token)


def rows_drawn(draw: Callable[[int], torch.Tensor], n: int) -> torch.Tensor:
    """``draw(m)``, random values ``[m, ...]`` for ``m`` rows, for a batch of ``n`` rows:
    ``draw(n)``, or within :func:`sharded` the whole global batch's draws, of which this
    rank keeps its ``n``: the ranks' generators stay in step, and N ranks draw what one
    process at N times the batch draws."""
    shard = _SHARD.get()
    if shard is None:
        return draw(n)
    first, total = shard
    return draw(total)[first : first + n]


def masked_mean(values: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """``(values * weight).sum() / weight.sum()`` (at least 1) of a batch ``[n, ...]``.
    Within :func:`sharded`, the mean over the global batch as :class:`DataParallel`
    sums it: this rank's weighted sum over the global weight (one all-reduce), times
    ``total / n`` (undone by the ranks' ``n / total`` weights)."""
    numerator, denominator = (values * weight).sum(), weight.sum()
    shard = _SHARD.get()
    if shard is None:
        return numerator / denominator.clamp_min(1.0)
    import torch.distributed as dist

    denominator = denominator.detach().clone()
    dist.all_reduce(denominator)
    return numerator / denominator.clamp_min(1.0) * (shard[1] / values.shape[0])


def rank_and_world() -> tuple[int, int]:
    """``(rank, world size)`` of the default process group, ``(0, 1)`` without one."""
    import torch.distributed as dist

    if not (dist.is_available() and dist.is_initialized()):
        return 0, 1
    return dist.get_rank(), dist.get_world_size()


def share(total: int, rank: int, world: int) -> tuple[int, int]:
    """``(first, count)``: rank ``rank``'s contiguous rows of ``total`` split among
    ``world`` ranks (the first ``total % world`` ranks hold one row more)."""
    base, extra = divmod(int(total), int(world))
    first = rank * base + min(rank, extra)
    return first, base + (1 if rank < extra else 0)


def gathered(values: torch.Tensor) -> torch.Tensor:
    """Every rank's ``values`` (the same shape on each), concatenated along the first
    dimension in rank order (``values`` itself in a single process): what one process
    holding every rank's rows holds."""
    if rank_and_world()[1] == 1:
        return values
    import torch.distributed as dist

    parts = [torch.empty_like(values) for _ in range(rank_and_world()[1])]
    dist.all_gather(parts, values.contiguous())
    return torch.cat(parts)


def from_lead(value: T) -> T:
    """Rank 0's ``value`` (any picklable object) on every rank (``value`` itself in a
    single process); the other ranks' ``value`` is ignored."""
    if rank_and_world()[1] == 1:
        return value
    import torch.distributed as dist

    box = [value]
    dist.broadcast_object_list(box, src=0)
    return box[0]


def barrier() -> None:
    """Wait until every rank reaches here (nothing in a single process)."""
    if rank_and_world()[1] == 1:
        return
    import torch.distributed as dist

    dist.barrier()


def check_same(value: object, what: str) -> None:
    """ValueError on a rank whose ``value`` (picklable, comparable) differs from rank 0's:
    what every rank must hold alike (nothing in a single process)."""
    if rank_and_world()[1] == 1:
        return
    lead = from_lead(value)
    if lead != value:
        raise ValueError(
            f"rank {rank_and_world()[0]}'s {what} differ from rank 0's ({value} against "
            f"{lead}): every rank must hold the same"
        )


def summed(values: torch.Tensor) -> torch.Tensor:
    """The sum of ``values`` over the ranks (``values`` itself in a single process)."""
    if rank_and_world()[1] == 1:
        return values
    import torch.distributed as dist

    out = values.detach().clone()
    dist.all_reduce(out)
    return out


class DataParallel:
    """One fit's gradients shared among the ranks of the default process group.

    :meth:`reduce`, after the backward of a rank's loss over its ``count`` of ``total``
    rows: every gradient and the loss become the sums over ranks of ``count / total``
    times their own (the gradient and the loss of the mean over all ``total`` rows, for a
    loss that is a mean over its rows), in one all-reduce of one flat buffer.
    """

    def __init__(self, params: list[torch.nn.Parameter]) -> None:
        self.rank, self.world = rank_and_world()
        self.params = params

    @classmethod
    def of(cls, *opts: torch.optim.Optimizer) -> DataParallel | None:
        """The sharing of the parameters ``opts`` step, or None in a single process."""
        if rank_and_world()[1] == 1:
            return None
        return cls([p for opt in opts for group in opt.param_groups for p in group["params"]])

    def reduce(self, loss: torch.Tensor, count: int, total: int) -> torch.Tensor:
        """Weight this rank's gradients and ``loss`` by ``count / total`` and sum them over
        the ranks; returns the global loss (every rank holds the same gradients after)."""
        import torch.distributed as dist

        grads = [p.grad for p in self.params if p.grad is not None]
        flat = torch.cat([g.reshape(-1) for g in grads] + [loss.detach().reshape(1)])
        flat.mul_(count / total)
        dist.all_reduce(flat)
        offset = 0
        for g in grads:
            g.copy_(flat[offset : offset + g.numel()].view_as(g))
            offset += g.numel()
        return flat[-1]

    def mean(self, loss: torch.Tensor) -> torch.Tensor:
        """:meth:`reduce` where every rank's ``loss`` is a mean over as many rows as any
        other's: the ranks' gradients and losses averaged."""
        return self.reduce(loss, 1, self.world)
