"""A fit's optimizer step: ``torch.optim.Adam``'s own arithmetic, without its per-call wrapper.

On a small network on CPU, ``Optimizer.step``'s wrapper (a profiler range, hook checks,
``_init_group`` rebuilding six lists from the state dict each call) costs as much as the
update itself: measured 616 us against 331 us for the same update through
``torch.optim.adam.adam``, the functional form ``Adam.step`` itself calls, on a [32, 32]
MLP with one torch thread. :func:`optimizer_step` returns a step that calls that function
with the optimizer's own state tensors and its group's settings (read every step, so a
learning-rate schedule is seen): the same kernels on the same tensors, so the same bits
(``tests/test_optim_step.py`` trains side by side). It falls back to ``opt.step()``
wherever that would do anything else: another optimizer class, a step patched on the
instance, hooks, several parameter groups, fused/capturable/differentiable updates, a
gradient missing or sparse, or state not yet made (the first step of a fresh optimizer
makes it).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch.optim import optimizer as _optimizer
from torch.optim.adam import adam

__all__ = ["optimizer_step"]


def _hooked(opt: torch.optim.Optimizer) -> bool:
    return bool(
        opt._optimizer_step_pre_hooks
        or opt._optimizer_step_post_hooks
        or _optimizer._global_optimizer_pre_hooks
        or _optimizer._global_optimizer_post_hooks
    )


def optimizer_step(opt: torch.optim.Optimizer) -> Callable[[], None]:
    """``opt.step`` for a fit's loop (module docstring): decided once, call it per step."""
    if (
        type(opt) is not torch.optim.Adam
        or "step" in vars(opt)  # a step patched on the instance: it is what must run
        or len(opt.param_groups) != 1
        or _hooked(opt)
    ):
        return opt.step
    group = opt.param_groups[0]
    if group["fused"] or group["capturable"] or group["differentiable"]:
        return opt.step
    params: list[torch.Tensor] = list(group["params"])
    if any(torch.is_complex(p) or not p.is_cpu for p in params):
        return opt.step  # off the CPU the per-call wrapper is not the cost: the device's own step
    lists: list[list[torch.Tensor]] = []  # exp_avg, exp_avg_sq, max_exp_avg_sq, step

    def state_lists() -> bool:
        states = [opt.state.get(p) for p in params]
        if not all(states):
            return False
        amsgrad = group["amsgrad"]
        lists[:] = [
            [s["exp_avg"] for s in states],
            [s["exp_avg_sq"] for s in states],
            [s["max_exp_avg_sq"] for s in states] if amsgrad else [],
            [s["step"] for s in states],
        ]
        return True

    def step() -> None:
        grads = [p.grad for p in params]
        if (
            any(g is None or g.is_sparse for g in grads)
            or (not lists and not state_lists())
            or _hooked(opt)
        ):
            opt.step()  # Adam's own path for everything this one does not repeat
            return
        beta1, beta2 = group["betas"]
        with torch.no_grad():
            adam(
                params,
                grads,
                *lists,
                amsgrad=group["amsgrad"],
                has_complex=False,
                beta1=beta1,
                beta2=beta2,
                lr=group["lr"],
                weight_decay=group["weight_decay"],
                eps=group["eps"],
                maximize=group["maximize"],
                foreach=group["foreach"],
                capturable=False,
                differentiable=False,
                fused=group["fused"],
                grad_scale=getattr(opt, "grad_scale", None),
                found_inf=getattr(opt, "found_inf", None),
                decoupled_weight_decay=group["decoupled_weight_decay"],
            )

    return step
