"""An exponential moving average of a network's weights, with Diffusion Policy's warm-up.

Diffusion Policy (Chi et al. 2023) acts with an EMA of its weights; its ``EMAModel``
(after ``diffusers``) uses a decay that grows with the optimisation step ``n``:

    decay(n) = clamp(1 - (1 + s / inv_gamma) ** -power, min_decay, max_decay),
    s = max(0, n - update_after_step - 1),   decay = 0 while s == 0,

so the average follows the weights closely at first and averages over more and more
steps later (``power`` 0.75, ``inv_gamma`` 1, ``max_decay`` 0.9999 in the paper's
configs). Each :meth:`EMA.update` then sets ``ema <- decay * ema + (1 - decay) * w`` for
every floating parameter and copies the buffers (GroupNorm's have none; a running mean
would be copied as it is).
"""

from __future__ import annotations

import contextlib
import copy
from collections.abc import Iterator

import torch
from torch import nn

__all__ = ["EMA"]


class EMA(nn.Module):
    """The moving average of ``model``'s weights (module docstring).

    Args:
        model: the network being trained (its weights are read, never written, except
            inside :meth:`swapped_in`).
        power, inv_gamma, min_decay, max_decay, update_after_step: the decay's schedule.

    The average is a copy of ``model`` (:attr:`averaged`), saved with the learner's state
    dict; ``step`` counts the updates (a buffer: checkpoints and resumes carry it).
    """

    def __init__(
        self,
        model: nn.Module,
        *,
        power: float = 0.75,
        inv_gamma: float = 1.0,
        min_decay: float = 0.0,
        max_decay: float = 0.9999,
        update_after_step: int = 0,
    ) -> None:
        super().__init__()
        if not 0.0 <= min_decay <= max_decay < 1.0:
            raise ValueError(f"need 0 <= min_decay <= max_decay < 1, got {min_decay}, {max_decay}")
        if power <= 0 or inv_gamma <= 0:
            raise ValueError(f"power and inv_gamma must be positive, got {power}, {inv_gamma}")
        self.averaged = copy.deepcopy(model).requires_grad_(False)
        self.power, self.inv_gamma = float(power), float(inv_gamma)
        self.min_decay, self.max_decay = float(min_decay), float(max_decay)
        self.update_after_step = int(update_after_step)
        self.register_buffer("step", torch.zeros((), dtype=torch.long))
        object.__setattr__(self, "_model", model)  # not a submodule: the learner owns it

    def decay(self, step: int | None = None) -> float:
        """``decay(n)`` at update ``n`` (default: the next update's)."""
        n = int(self.step) if step is None else int(step)
        s = max(0, n - self.update_after_step - 1)
        if s <= 0:
            return 0.0
        value = 1 - (1 + s / self.inv_gamma) ** -self.power
        return max(self.min_decay, min(value, self.max_decay))

    @torch.no_grad()
    def update(self) -> None:
        """Average the model's current weights in (after an optimiser step)."""
        d = self.decay()
        for avg, w in zip(self.averaged.parameters(), self._model.parameters(), strict=True):
            if avg.is_floating_point():
                avg.mul_(d).add_(w.detach().to(avg.dtype), alpha=1 - d)
            else:
                avg.copy_(w)
        for avg, b in zip(self.averaged.buffers(), self._model.buffers(), strict=True):
            avg.copy_(b)
        self.step += 1

    @contextlib.contextmanager
    def swapped_in(self) -> Iterator[None]:
        """Within: the model holds the averaged weights (to act or evaluate); its own
        weights come back on exit."""
        saved = [p.detach().clone() for p in self._model.parameters()]
        with torch.no_grad():
            for p, avg in zip(self._model.parameters(), self.averaged.parameters(), strict=True):
                p.copy_(avg)
        try:
            yield
        finally:
            with torch.no_grad():
                for p, w in zip(self._model.parameters(), saved, strict=True):
                    p.copy_(w)
