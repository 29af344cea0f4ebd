"""A behaviour-cloning fit's settings, each declared once (:class:`BCConfig`).

This module imports no torch: ``imitrl bc`` and ``imitrl dagger`` extend
:class:`BCConfig` (:mod:`imitrl.jobs.configs`), so the command line's fit flags
(``--steps``, ``--batch-size``, ``--lr-schedule``, ...) are these fields, with their
docstrings as help and their limits as ranges, and a fit from Python has the same
defaults as one from the command line: 1000 steps of 256 rows.
"""

from __future__ import annotations

from dataclasses import dataclass

from imitrl import checks
from imitrl.limits import MAX_BATCH, MAX_SEED, MAX_STEPS, bounded, check_bounds

__all__ = ["LR_SCHEDULES", "PRECISIONS", "BCConfig"]


LR_SCHEDULES = ("constant", "cosine")
"""the learning-rate schedules of a fit (:attr:`BCConfig.lr_schedule`)"""
PRECISIONS = ("fp32", "bf16")
"""the arithmetic of a fit's forward pass (:attr:`BCConfig.precision`)"""


@dataclass(frozen=True)
class BCConfig:
    """Behaviour-cloning fit (the loss belongs to the learner, not to this config)."""

    num_steps: int = bounded(1000, 0, MAX_STEPS, flag="--steps")
    """gradient steps of the policy optimizer (of every round's fit for dagger)"""
    batch_size: int | None = bounded(256, 1, MAX_BATCH, none_ok=True)
    """rows per gradient step, drawn without replacement epoch after epoch; None = the
    full batch every step (the section's clone; a full batch holds every row's
    activations at once)"""
    seed: int = bounded(0, 0, MAX_SEED)
    """seed of the minibatch order"""
    deduplicate: bool | None = None
    """full batch over integer observations and labels: train on the distinct
    (observation, label) pairs weighted by their counts, the same objective at a cost
    that does not grow with the rows; None = whenever it applies"""

    lr_schedule: str = "constant"
    """``"constant"``: the optimizer's learning rate every step; ``"cosine"``: decayed from
    it to 0 over the fit, ``lr * (1 + cos(pi * step / num_steps)) / 2`` (the closed form
    of ``torch.optim.lr_scheduler.CosineAnnealingLR``); every fit starts again from the
    optimizer's own rate, which the fit restores when it ends"""

    warmup_steps: int = bounded(0, 0, MAX_STEPS)
    """steps of a linear warm-up of the learning rate from 0 at the start of every fit
    (before ``lr_schedule``'s constant rate or cosine decay, which then runs over the
    remaining steps; Diffusion Policy warms up over 500)"""

    full_batch_max_rows: int | None = bounded(1 << 20, 1, none_ok=True)
    """the most rows a full-batch fit (``batch_size=None``) runs on before it is refused
    (activations for every row every step; distinct pairs are not limited); None = no
    limit. A disk buffer always needs a ``batch_size``"""

    precision: str = "fp32"
    """``"fp32"``; ``"bf16"``: each step's loss computed under ``torch.autocast`` in
    bfloat16 on the learner's device (weights, gradients and the optimizer stay
    float32). Off by default: on a 2-core CPU it ran the MLP fit at 0.74x and the CNN fit
    at 1.27x float32's speed, final loss within 1.4% on one seed
    (``benchmarks/fit_options.py``); not on by default for pixels until a multi-seed
    accuracy comparison and a GPU measurement back it"""

    compile: bool = False
    """run the loss through ``torch.compile`` (compiled at the fit's first step: tens
    of seconds on a 2-core CPU). Off by default: 0.84x (MLP) and 0.78x (CNN) the eager
    fit's speed on a 2-core CPU, the same losses (``benchmarks/fit_options.py``); no GPU
    measurement yet"""

    def __post_init__(self) -> None:
        check_bounds(self, name=lambda field: f"BCConfig.{field}")
        checks.boolean(self.deduplicate, "BCConfig.deduplicate", none_ok=True)
        if self.lr_schedule not in LR_SCHEDULES:
            raise ValueError(f"lr_schedule must be one of {LR_SCHEDULES}, got {self.lr_schedule!r}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS}, got {self.precision!r}")
        checks.boolean(self.compile, "BCConfig.compile")
