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

from imitrl.compat import foreach_lerp_

__all__ = ["EMA"]


class EMA(nn.Module):
    """The moving average of ``model``'s weights (module docstring).

    Args:
        model: the network being trained (its weights are read, never written, except
            inside :meth:`trained_weights`).
        power, inv_gamma, min_decay, max_decay, update_after_step: the decay's schedule.

    The average is a copy of ``model`` (:attr:`averaged`), and so are the weights being
    trained while the model acts with the average (:attr:`trained`, see
    :meth:`trained_weights`); both are saved with the learner's state dict, and ``step`` counts
    the updates (a buffer): checkpoints and DAgger's resume carry all three.
    """

    step: torch.Tensor
    _model: nn.Module

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
        self.trained = copy.deepcopy(model).requires_grad_(False)
        self.power, self.inv_gamma = float(power), float(inv_gamma)
        self.min_decay, self.max_decay = float(min_decay), float(max_decay)
        self.update_after_step = int(update_after_step)
        self.register_buffer("step", torch.zeros((), dtype=torch.long))
        # the count as a Python int too: reading the buffer each update would wait for
        # the device; a loaded state dict sets both
        self._updates = 0
        self.register_load_state_dict_post_hook(EMA._after_load)
        object.__setattr__(self, "_model", model)  # not a submodule: the learner owns it

    @staticmethod
    def _after_load(module: EMA, _incompatible) -> None:
        module._updates = int(module.step)

    def decay(self, step: int | None = None) -> float:
        """``decay(n)`` at update ``n`` (default: the next update's)."""
        n = self._updates if step is None else int(step)
        s = max(0, n - self.update_after_step - 1)
        if s <= 0:
            return 0.0
        value = 1 - (1 + s / self.inv_gamma) ** -self.power
        return max(self.min_decay, min(value, self.max_decay))

    @torch.no_grad()
    def update(self) -> None:
        """Average the model's current weights in (after an optimiser step)."""
        d = self.decay()
        avgs: list[torch.Tensor] = []
        ws: list[torch.Tensor] = []
        for avg, w in zip(self.averaged.parameters(), self._model.parameters(), strict=True):
            if avg.is_floating_point() and avg.dtype == w.dtype:
                avgs.append(avg)
                ws.append(w.detach())
            else:
                avg.copy_(w)
        if avgs:  # ema + (1 - d) (w - ema) = d ema + (1 - d) w, in one pass over the list
            foreach_lerp_(avgs, ws, 1.0 - d)
        for ba, b in zip(self.averaged.buffers(), self._model.buffers(), strict=True):
            ba.copy_(b)
        self.step += 1
        self._updates += 1

    @contextlib.contextmanager
    def trained_weights(self) -> Iterator[None]:
        """Within: the model holds the weights being trained (an optimiser's steps, each
        followed by :meth:`update`); on exit they are kept in :attr:`trained` and the
        model holds the average again, to act, to be evaluated and to be saved.

        Outside this context a learner with an EMA acts with its averaged weights, as
        Diffusion Policy evaluates; the trained weights (and the optimiser's moments,
        which belong to the same parameter objects) carry over to the next fit: DAgger's
        warm start continues training, not averaging. Buffers (a normaliser's
        statistics) are not averaged: all three copies take the model's on exit. Weights
        set on the model directly since the last fit (not through the learner's
        ``load_state_dict``, which restores all three copies) are taken as the trained
        weights and the average restarts from them.
        """
        with torch.no_grad():
            pairs = list(zip(self._model.parameters(), self.averaged.parameters(), strict=True))
            if not all(torch.equal(p, avg) for p, avg in pairs):
                # weights set on the model since (a policy's own load_state_dict, an
                # edit): they become the trained weights and the average starts there
                for (p, avg), w in zip(pairs, self.trained.parameters(), strict=True):
                    w.copy_(p)
                    avg.copy_(p)
            for p, w in zip(self._model.parameters(), self.trained.parameters(), strict=True):
                p.copy_(w)
        try:
            yield
        finally:
            with torch.no_grad():
                for p, w, avg in zip(
                    self._model.parameters(),
                    self.trained.parameters(),
                    self.averaged.parameters(),
                    strict=True,
                ):
                    w.copy_(p)
                    p.copy_(avg)
                for b, bt, ba in zip(
                    self._model.buffers(), self.trained.buffers(), self.averaged.buffers(),
                    strict=True,
                ):  # fmt: skip
                    bt.copy_(b)
                    ba.copy_(b)
