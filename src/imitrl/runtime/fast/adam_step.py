"""A fit's optimizer step: ``torch.optim.Adam``'s own arithmetic, without its per-call wrapper.

On a small network on CPU, ``Optimizer.step``'s wrapper (a profiler range, hook checks,
``_init_group`` rebuilding six lists from the state dict each call) costs as much as the
update itself: measured 616 us against 331 us for the same update through
``torch.optim.adam.adam``, the functional form ``Adam.step`` itself calls, on a [32, 32]
MLP with one torch thread. :func:`optimizer_step` returns a step that calls that function
with the optimizer's own state tensors and its group's settings (read every step, so a
learning-rate schedule is seen): the same kernels on the same tensors, so the same bits
(``tests/test_optim_step.py`` trains side by side). Several optimizers stepped together
(PPO's policy and value optimizers) are one call over all their parameters while every
group setting agrees: Adam updates each parameter from its own gradient, state and step
count, so one call over the union is the calls one after the other, at one call's
overhead. It falls back to ``opt.step()``
wherever that would do anything else: another optimizer class, a step patched on the
instance, hooks, several parameter groups, fused/capturable/differentiable updates, a
gradient missing or sparse, or state not yet made (the first step of a fresh optimizer
makes it).
"""

from __future__ import annotations

import functools
import itertools
from collections.abc import Callable

import torch
from torch.optim import optimizer as _optimizer
from torch.optim.adam import adam

__all__ = ["optimizer_step"]

_SETTINGS = (
    "lr", "betas", "eps", "weight_decay", "amsgrad", "maximize", "foreach",
    "decoupled_weight_decay",
)  # fmt: skip
"""the group settings ``adam`` reads: optimizers agreeing on all of them step in one call"""


def _hooked(opt: torch.optim.Optimizer) -> bool:
    return bool(
        opt._optimizer_step_pre_hooks
        or opt._optimizer_step_post_hooks
        or _optimizer._global_optimizer_pre_hooks
        or _optimizer._global_optimizer_post_hooks
    )


def optimizer_step(*opts: torch.optim.Optimizer) -> Callable[[], None]:
    """``opt.step()`` for each of ``opts`` in a fit's loop (module docstring): decided once,
    call it per step."""
    steps = [_AdamStep.of(opt) or opt.step for opt in opts]
    if all(isinstance(s, _AdamStep) for s in steps):
        return _FlatStep(steps)
    if len(steps) == 1:
        return steps[0]

    def each() -> None:
        for step in steps:
            step()

    return each


class _AdamStep:
    """One optimizer's step through ``torch.optim.adam.adam``, or ``opt.step()`` where that
    would do anything else."""

    def __init__(self, opt: torch.optim.Optimizer) -> None:
        self.opt, self.group = opt, opt.param_groups[0]
        self.params: list[torch.Tensor] = list(self.group["params"])
        self.lists: list[list[torch.Tensor]] = []  # exp_avg, exp_avg_sq, max_exp_avg_sq, step

    @classmethod
    def of(cls, opt: torch.optim.Optimizer) -> _AdamStep | None:
        if (
            type(opt) is not torch.optim.Adam
            or "step" in vars(opt)  # a step patched on the instance: it is what must run
            or len(opt.param_groups) != 1
            or _hooked(opt)
        ):
            return None
        group = opt.param_groups[0]
        if group["fused"] or group["capturable"] or group["differentiable"]:
            return None
        if any(torch.is_complex(p) or not p.is_cpu for p in group["params"]):
            return None  # off the CPU the per-call wrapper is not the cost: the device's own step
        return cls(opt)

    def ready(self) -> list[torch.Tensor] | None:
        """The gradients, where ``adam`` may step now: every one there and dense, the
        state made (Adam's first step makes it), no hook registered since."""
        grads = [p.grad for p in self.params]
        if any(g is None or g.is_sparse for g in grads) or _hooked(self.opt):
            return None
        if not self.lists:
            states = [self.opt.state.get(p) for p in self.params]
            if not all(states):
                return None
            amsgrad = self.group["amsgrad"]
            self.lists[:] = [
                [s["exp_avg"] for s in states],
                [s["exp_avg_sq"] for s in states],
                [s["max_exp_avg_sq"] for s in states] if amsgrad else [],
                [s["step"] for s in states],
            ]
        return grads

    def __call__(self) -> None:
        grads = self.ready()
        if grads is None:
            self.opt.step()  # Adam's own path for everything this one does not repeat
            return
        _adam(self.opt, self.group, self.params, grads, self.lists)


class _FlatStep:
    """The optimizers' parameters stepped by one ``adam`` call on one flat tensor.

    Adam is elementwise: each parameter's update reads its own gradient, moments and the
    scalars of its step count. Where every group setting and every step count agree, one
    call on the parameters, gradients and moments laid end to end computes each element
    as the calls per tensor do, at one tensor's overhead (a [64, 64] actor-critic's 13
    tensors: about 300 us per step through ``adam`` on the CPU, about 100 us here, one
    thread) -- provided an element's bits do not depend on its position in the tensor.
    Adam's operations are multiplies, adds, divides, square roots and their compounds
    (``lerp``, ``addcmul``, ``addcdiv``); a kernel's vectorised loop and its scalar tail
    could still round a compound differently (a fused multiply-add in one of them), so
    :func:`_flat_agrees` checks, once per process and setting, that the flat call gives
    the per-tensor calls' bits on tensors whose sizes leave scalar tails, and the step
    takes the per-tensor calls where it does not. The moments live in flat buffers whose views *are* the optimizers' state
    (``opt.state[p]["exp_avg"]`` and the others), so ``opt.step()``, ``state_dict()`` and
    this step read and write the same memory; the parameters are gathered into a flat
    buffer and written back each step, the step counts advanced together. Anything else
    (a gradient missing, settings or step counts that differ, mixed dtypes) takes each
    optimizer's own step, and the buffers are laid out anew afterwards.
    """

    def __init__(self, parts: list[_AdamStep]) -> None:
        self.parts = parts
        self.params = [p for s in parts for p in s.params]
        self.flat: tuple | None = None  # parameter buffer, its views, moment buffers, steps

    def __call__(self) -> None:
        first = self.parts[0].group
        grads = [s.ready() for s in self.parts]
        if any(g is None for g in grads) or any(
            s.group[k] != first[k] for s in self.parts[1:] for k in _SETTINGS
        ):
            self._each()
            return
        flat = self.flat or self._lay_out()
        if flat is None:
            self._each()
            return
        buffer, views, moments, steps = flat
        with torch.no_grad():
            torch.cat([p.reshape(-1) for p in self.params], out=buffer)
            grad = torch.cat([g.reshape(-1) for gs in grads for g in gs])
            lists = [[m] for m in moments]
            if len(lists) == 2:
                lists.append([])  # no max_exp_avg_sq without amsgrad
            _adam(self.parts[0].opt, first, [buffer], [grad], [*lists, steps[:1]])
            if len(steps) > 1:
                torch._foreach_add_(steps[1:], 1)
            torch._foreach_copy_(self.params, views)

    def _each(self) -> None:
        self.flat = None  # each optimizer steps on its own: lay out again next time
        for step in self.parts:
            step()

    def _lay_out(self) -> tuple | None:
        """The flat buffers (:class:`_FlatStep`), the state moved into them; None where
        one call would not compute what the per-tensor calls do."""
        params = self.params
        states = [s.opt.state[p] for s in self.parts for p in s.params]
        steps = [st["step"] for st in states]
        first = self.parts[0].group
        if (
            any(p.dtype != params[0].dtype for p in params)
            or not _flat_agrees(tuple(first[k] for k in _SETTINGS), params[0].dtype)
            or any(s.dtype != steps[0].dtype for s in steps)
            or len({float(s) for s in steps}) != 1
            or getattr(self.parts[0].opt, "grad_scale", None) is not None
            or getattr(self.parts[0].opt, "found_inf", None) is not None
        ):
            return None
        names = ["exp_avg", "exp_avg_sq"] + (
            ["max_exp_avg_sq"] if self.parts[0].group["amsgrad"] else []
        )
        bounds = list(itertools.accumulate((p.numel() for p in params), initial=0))

        def views(flat: torch.Tensor) -> list[torch.Tensor]:
            return [flat[a:b].view(p.shape) for a, b, p in zip(bounds, bounds[1:], params)]

        moments = []
        for name in names:
            flat = torch.cat([st[name].reshape(-1) for st in states])
            for st, view in zip(states, views(flat)):
                st[name] = view  # the optimizer's state is now a view of the flat buffer
            moments.append(flat)
        for part in self.parts:
            part.lists.clear()  # their cached state lists held the tensors just replaced
        buffer = torch.empty(bounds[-1], dtype=params[0].dtype)
        self.flat = (buffer, views(buffer), moments, steps)
        return self.flat


@functools.cache
def _flat_agrees(settings: tuple, dtype: torch.dtype) -> bool:
    """Whether one ``adam`` call on tensors laid end to end gives, element for element,
    the bits of the calls per tensor, with these group settings (:data:`_SETTINGS`'
    values) and this dtype, on this machine: five steps on tensors of 1, 3, 17, 64 and
    100 elements (each with a scalar tail in a vectorised loop), gradients of several
    magnitudes."""
    group = dict(zip(_SETTINGS, settings), fused=None)
    g = torch.Generator().manual_seed(0)
    sizes = (1, 3, 17, 64, 100)
    params = [torch.randn(n, generator=g, dtype=dtype) for n in sizes]
    flat = torch.cat(params)
    lists = [[torch.zeros_like(p) for p in params] for _ in range(3)]
    flat_lists = [[torch.zeros_like(flat)] for _ in range(3)]
    if not group["amsgrad"]:
        lists[2], flat_lists[2] = [], []
    steps, flat_step = [torch.zeros(()) for _ in sizes], torch.zeros(())
    for k in range(5):
        grads = [torch.randn(n, generator=g, dtype=dtype) * 10.0 ** (k - 2) for n in sizes]
        _adam(None, group, params, grads, [*lists, steps])
        _adam(None, group, [flat], [torch.cat(grads)], [*flat_lists, [flat_step]])
    return torch.equal(torch.cat(params), flat)


def _adam(opt, group, params, grads, lists) -> None:
    """``Adam.step``'s call of the functional ``adam`` with ``group``'s settings."""
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
