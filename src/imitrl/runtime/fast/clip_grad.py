"""Gradient-norm clipping: ``torch.nn.utils.clip_grad_norm_``'s arithmetic, without its wrapper.

Accelerated internals of :mod:`imitrl.runtime.paths` (import them from there, nowhere else).

On PPO's small networks a ``clip_grad_norm_`` call costs about 0.2 ms, most of it the
wrapper: a ``no_grad`` context per inner function, the gradients grouped by device and
dtype on every call, the foreach support checked per group. The arithmetic is four
calls: the norm of each gradient (``torch._foreach_norm``), the norm of their stack, the
coefficient ``max_norm / (total + 1e-6)`` clamped at 1, and every gradient multiplied by
it (``torch._foreach_mul_``). :func:`clip_grad_norm` runs those calls, in that order, where
``clip_grad_norm_`` would group every gradient into one group and take its foreach path
(dense CPU gradients of one floating dtype, the 2-norm): the same kernels on the same
tensors, so the same bits (``tests/runtime/fast/test_adam_step.py``); anywhere else it calls
``clip_grad_norm_`` itself.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from imitrl.compat import foreach_mul_, foreach_norm

__all__ = ["clip_grad_norm"]


def clip_grad_norm(params: Sequence[torch.Tensor], max_norm: float) -> torch.Tensor:
    """``torch.nn.utils.clip_grad_norm_(params, max_norm)`` (module docstring): the total
    2-norm of the gradients before clipping; the gradients scaled in place."""
    grads = [p.grad for p in params if p.grad is not None]
    if not grads or not _one_foreach_group(grads):
        return torch.nn.utils.clip_grad_norm_(params, max_norm)
    with torch.no_grad():
        total = torch.linalg.vector_norm(torch.stack(foreach_norm(grads, 2.0)), 2.0)
        coef = torch.clamp(float(max_norm) / (total + 1e-6), max=1.0)
        foreach_mul_(grads, coef)
    return total


def _one_foreach_group(grads: list[torch.Tensor]) -> bool:
    dtype = grads[0].dtype
    return dtype.is_floating_point and all(
        type(g) is torch.Tensor and g.is_cpu and not g.is_sparse and g.dtype is dtype for g in grads
    )
