"""Behaviour cloning: fit a policy to the expert's labels by gradient steps on a loss module.

``fit_bc(learner, data, config)`` runs ``config.num_steps`` Adam steps of
``learner.opt_pi`` on a :class:`~imitrl.objectives.BehaviorCloningLoss`:

* full batch (``batch_size=None``): every step sees every row, as the section's
  ``clone`` does; deterministic given the data;
* minibatch: rows are drawn without replacement, epoch after epoch, from a
  permutation seeded by ``config.seed`` (the buffer's TorchRL sampler is not used on
  this hot path: one ``randperm`` per epoch and tensor slicing cost a fraction of a
  ``ReplayBuffer.sample`` call; ``benchmarks/bc_throughput.py`` measures both).

``loss_module=`` replaces the ``BehaviorCloningLoss`` built from ``config.loss_type``
with any loss over the learner's policy (e.g. an entry of
:mod:`imitrl.objectives.registry`); the sum of its ``loss_*`` outputs is minimised.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from tensordict import TensorDictBase
from torchrl.objectives import LossModule
from tqdm.auto import tqdm

from imitrl import keys
from imitrl.data.buffer import DemonstrationBuffer
from imitrl.objectives.bc import LOSS_TYPES, BehaviorCloningLoss
from imitrl.policies.actor_critic import HEAD_LOSSES, ActorCritic

__all__ = ["BCConfig", "FitResult", "fit_bc"]


@dataclass(frozen=True)
class BCConfig:
    """Behaviour-cloning fit."""

    num_steps: int = 200
    """gradient steps of the policy optimizer"""
    batch_size: int | None = None
    """rows per step; None = the full batch every step"""
    loss_type: str = "nll"
    """one of imitrl.objectives.LOSS_TYPES (nll = cross-entropy for discrete actions)"""
    label_key: str = keys.EXPERT_ACTION
    """key of the target action"""
    seed: int = 0
    """seed of the minibatch order"""
    deduplicate: bool | None = None
    """full batch over integer observations and labels: train on the distinct
    (observation, label) pairs weighted by their counts, the same objective at a cost
    that does not grow with the rows; None = whenever it applies"""

    def __post_init__(self) -> None:
        if self.num_steps < 0:
            raise ValueError(f"num_steps must be >= 0, got {self.num_steps}")
        if self.batch_size is not None and self.batch_size < 1:
            raise ValueError(f"batch_size must be positive or None, got {self.batch_size}")
        if self.loss_type not in LOSS_TYPES:
            raise ValueError(f"loss_type must be one of {LOSS_TYPES}, got {self.loss_type!r}")


@dataclass
class FitResult:
    """What a fit measured."""

    losses: torch.Tensor = field(repr=False)
    """``[num_steps]`` loss at each step, before that step's update"""
    final_loss: float
    """the last entry of ``losses`` (nan when num_steps == 0)"""
    num_rows: int
    """rows the fit was trained on"""


def _rows(
    data: DemonstrationBuffer | TensorDictBase, label_key: str, extra: tuple = ()
) -> TensorDictBase:
    td = data.data if isinstance(data, DemonstrationBuffer) else data
    if not isinstance(td, TensorDictBase):
        raise ValueError(
            f"fit_bc needs a DemonstrationBuffer or a TensorDict, got {type(data).__name__}"
        )
    if td.batch_dims != 1 or td.shape[0] == 0:
        raise ValueError(
            f"fit_bc needs a non-empty batch of rows, got batch_size {tuple(td.batch_size)}"
        )
    for key in (keys.OBSERVATION, label_key, *extra):
        if key not in td.keys(include_nested=True):
            raise ValueError(
                f"rows lack {key!r}: need observations, labels and what the loss reads"
            )
    obs = td.get(keys.OBSERVATION)
    if obs.dtype.is_floating_point and torch.isnan(obs).any():
        raise ValueError("NaN in the observations of the training rows")
    return td.select(keys.OBSERVATION, label_key, *extra)


def _distinct_pairs(rows: TensorDictBase, label_key: str) -> TensorDictBase | None:
    """Distinct (observation, label) rows with weights ``count * U / N`` (None if not applicable).

    ``mean_j(w_j l_j)`` over the U distinct pairs then equals ``mean_i l_i`` over the N
    rows: the full-batch objective is unchanged, only summed in another order.
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
    U, N = codes.shape[0], obs.shape[0]
    out = rows.empty(batch_size=[U])
    out.set(keys.OBSERVATION, (codes // base).to(obs.dtype))
    out.set(label_key, (codes % base).to(label.dtype))
    out.set(keys.WEIGHT, counts.to(torch.float32) * (U / N))
    return out


def fit_bc(
    learner: ActorCritic,
    data: DemonstrationBuffer | TensorDictBase,
    config: BCConfig = BCConfig(),
    *,
    loss_module: LossModule | None = None,
    progress: bool = False,
) -> FitResult:
    """Fit ``learner``'s policy to the labels in ``data`` (see the module docstring).

    Args:
        learner: the actor-critic (or any object with ``policy`` and ``opt_pi``); its
            ``opt_pi`` takes the steps.
        data: a demonstration buffer or a TensorDict of rows with ``OBSERVATION`` and
            ``config.label_key``.
        config: steps, batch size, loss, seed.
        loss_module: a loss over ``learner.policy`` reading ``OBSERVATION`` and
            ``config.label_key``, used instead of ``BehaviorCloningLoss(config.loss_type)``
            (``config.loss_type`` and ``deduplicate`` are then unused); the sum of its
            ``loss_*`` outputs is minimised.
        progress: show a progress bar.
    """
    extra = ()
    if loss_module is not None and config.label_key not in loss_module.in_keys:
        raise ValueError(
            f"loss_module reads {list(loss_module.in_keys)}, not the label key "
            f"{config.label_key!r}: remap it with set_keys"
        )
    if loss_module is not None:  # anything else the given loss reads (weights, ...)
        extra = tuple(
            k for k in loss_module.in_keys if k not in (keys.OBSERVATION, config.label_key)
        )
    rows = _rows(data, config.label_key, extra)
    if isinstance(learner, ActorCritic):
        if loss_module is None and config.loss_type not in HEAD_LOSSES[learner.head]:
            raise ValueError(
                f"loss_type {config.loss_type!r} does not fit a {learner.head!r} head; "
                f"it is fitted with {HEAD_LOSSES[learner.head]}"
            )
        learner.check_observations(rows.get(keys.OBSERVATION))
    n = rows.shape[0]
    losses = torch.empty(config.num_steps)
    minibatch = config.batch_size is not None and config.batch_size < n
    default = loss_module is None
    if default:
        loss_module = BehaviorCloningLoss(learner.policy, loss_type=config.loss_type)
        loss_module.set_keys(label=config.label_key)
    if hasattr(loss_module, "check_labels"):
        loss_module.check_labels(rows)  # once, over every row the fit can draw
    if default and not minibatch and config.deduplicate is not False and config.loss_type == "nll":
        distinct = _distinct_pairs(rows, config.label_key)
        if distinct is None and config.deduplicate:
            raise ValueError(
                "deduplicate=True needs integer observations [N] and integer labels [N]"
            )
        if distinct is not None:
            rows = distinct
            loss_module.weighted = True
    objective = getattr(loss_module, "objective", None) or (
        # any TorchRL loss: minimise the sum of its loss_* outputs
        lambda batch: sum(v for k, v in loss_module(batch).items() if k.startswith("loss_"))
    )
    if minibatch:
        generator = torch.Generator().manual_seed(config.seed)
        columns = {key: rows.get(key) for key in rows.keys(include_nested=True, leaves_only=True)}
        perm, cursor = torch.randperm(n, generator=generator), 0
    opt = learner.opt_pi
    steps = tqdm(range(config.num_steps), desc="bc fit", disable=not progress, leave=False)
    for step in steps:
        if minibatch:
            if cursor + config.batch_size > n:  # next epoch (the tail is dropped)
                perm, cursor = torch.randperm(n, generator=generator), 0
            idx = perm[cursor : cursor + config.batch_size]
            cursor += config.batch_size
            batch = rows.empty(batch_size=[idx.numel()])
            for key, column in columns.items():
                batch.set(key, column[idx])
        else:
            batch = rows
        loss = objective(batch)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        losses[step] = loss.detach()
    final = float(losses[-1]) if config.num_steps else float("nan")
    return FitResult(losses=losses, final_loss=final, num_rows=n)
