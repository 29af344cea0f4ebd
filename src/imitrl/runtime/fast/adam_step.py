"""A fit's optimizer step: ``torch.optim.Adam``'s own arithmetic, without its per-call wrapper.

On a small network on CPU, ``Optimizer.step``'s wrapper (a profiler range, hook checks,
``_init_group`` rebuilding six lists from the state dict each call) costs as much as the
update itself: measured 616 us against 331 us for the same update through
``torch.optim.adam.adam``, the functional form ``Adam.step`` itself calls, on a [32, 32]
MLP with one torch thread. :func:`optimizer_step` returns a step that calls that function
with the optimizer's own state tensors and its group's settings (read every step, so a
learning-rate schedule is seen): the same kernels on the same tensors, so the same bits
(``tests/runtime/fast/test_adam_step.py`` trains side by side). Several optimizers stepped together
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

import itertools
from collections.abc import Callable
from typing import Any

import torch
from torch.optim.adam import adam

from imitrl.compat import foreach_add_, foreach_copy_, optimizer_hooked

__all__ = ["optimizer_step"]

_SETTINGS = (
    "lr", "betas", "eps", "weight_decay", "amsgrad", "maximize", "foreach",
    "decoupled_weight_decay",
)  # fmt: skip
"""the group settings ``adam`` reads: optimizers agreeing on all of them step in one call"""


def _same(a: list, b: list) -> bool:
    return len(a) == len(b) and all(x is y for x, y in zip(a, b))


def optimizer_step(*opts: torch.optim.Optimizer) -> Callable[[], None]:
    """``opt.step()`` for each of ``opts`` in a fit's loop (module docstring): decided once,
    call it per step."""
    adams = [_AdamStep.of(opt) for opt in opts]
    steps: list[Callable[[], Any]] = [a or opt.step for a, opt in zip(adams, opts)]
    flat = [a for a in adams if a is not None]
    params = [p for a in flat for p in a.params]
    if (
        len(flat) == len(opts)
        and len(params) > 1  # one tensor: nothing to lay end to end
        and len({id(p) for p in params}) == len(params)  # a shared parameter steps twice
    ):
        return _FlatStep(opts, flat)
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
            or optimizer_hooked(opt)
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
        groups = self.opt.param_groups
        if (
            len(groups) != 1
            or groups[0] is not self.group
            or not _same(groups[0]["params"], self.params)
        ):
            return None  # a group added or replaced since: Adam's own step reads them
        maybe = [p.grad for p in self.params]
        grads = [g for g in maybe if g is not None and not g.is_sparse]
        if len(grads) != len(maybe) or optimizer_hooked(self.opt):
            return None
        if (
            self.lists
            and self.opt.state.get(self.params[0], {}).get("exp_avg") is not self.lists[0][0]
        ):
            self.lists.clear()  # the state was replaced (load_state_dict): read it again
        if not self.lists:
            found = [self.opt.state.get(p) for p in self.params]
            states = [s for s in found if s]
            if len(states) != len(found):
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
    """The optimizers' parameters stepped by one ``adam`` call on one flat tensor each.

    Adam is elementwise: each parameter's update reads its own gradient, moments and the
    scalars of its step count. Where every group setting and every step count agree, one
    call on each optimizer's parameters, gradients and moments laid end to end computes
    each element as the calls per tensor do, at a tensor's overhead per optimizer (a
    [64, 64] actor-critic's 13 tensors in two optimizers: about 300 us per step through
    ``adam`` per tensor on the CPU, about 150 us here, one thread, load 0.5) -- provided
    an element's bits do not depend on its position in the tensor. Adam's operations are
    multiplies, adds, divides, square roots and their compounds (``lerp``, ``addcmul``,
    ``addcdiv``); a kernel's vectorised loop and its scalar tail could still round a
    compound differently (a fused multiply-add in one of them), so :func:`_flat_agrees`
    checks, once per process and setting, that the flat call gives the per-tensor calls'
    bits on tensors whose sizes leave scalar tails, and the step takes the per-tensor
    calls where it does not.

    Each optimizer's moments live in flat buffers of its own whose views *are* its state
    (``opt.state[p]["exp_avg"]`` and the others), so ``opt.step()``, ``state_dict()`` (one
    optimizer's state saves its own buffers only) and this step read and write the same
    memory; the parameters are gathered into a flat buffer and written back each step,
    the step counts advanced together. Anything else (a gradient missing, settings or step
    counts that differ, mixed dtypes) takes each optimizer's own step, and the buffers are
    laid out anew afterwards; an optimizer whose groups or state were replaced since
    (``load_state_dict``, ``add_param_group``) is read afresh.
    """

    def __init__(self, opts: tuple[torch.optim.Optimizer, ...], parts: list[_AdamStep]) -> None:
        self.opts, self.parts = opts, parts
        self.layouts: list[_Layout] | None = None
        self.arguments: tuple = ()  # each step's lists for adam, made with the layouts

    def __call__(self) -> None:
        if not self._current():
            for opt in self.opts:
                opt.step()  # an optimizer this step no longer replays: its own step
            return
        first = self.parts[0].group
        ready = [s.ready() for s in self.parts]
        grads = [g for g in ready if g is not None]
        if len(grads) != len(ready) or any(
            s.group[k] != first[k] for s in self.parts[1:] for k in _SETTINGS
        ):
            self._each()
            return
        layouts = self.layouts or self._lay_out()
        if layouts is None:
            self._each()
            return
        buffers, lists, others, params, views = self.arguments
        with torch.no_grad():
            for lay, part in zip(layouts, self.parts):
                torch.cat([p.reshape(-1) for p in part.params], out=lay.buffer)
            flat_grads = [torch.cat([g.reshape(-1) for g in gs]) for gs in grads]
            _adam(self.parts[0].opt, first, buffers, flat_grads, lists)
            if others:
                foreach_add_(others, 1)
            foreach_copy_(params, views)

    def _current(self) -> bool:
        """Whether the optimizers are as this step read them (their group and parameters
        the same objects); where they are not, read them again, or False where one no
        longer qualifies. A layout whose state was replaced is dropped."""
        for k, part in enumerate(self.parts):
            groups = part.opt.param_groups
            params = groups[0]["params"] if len(groups) == 1 else []
            if groups[0] is not part.group or not _same(params, part.params):
                fresh = _AdamStep.of(part.opt)
                if fresh is None:
                    return False
                self.parts[k], self.layouts = fresh, None
        if self.layouts is not None and any(
            part.opt.state.get(part.params[0], {}).get("exp_avg") is not lay.views_of[0]
            for lay, part in zip(self.layouts, self.parts)
        ):
            self.layouts = None  # load_state_dict replaced the state: lay it out again
            for part in self.parts:
                part.lists.clear()
        return True

    def _each(self) -> None:
        self.layouts = None  # each optimizer steps on its own: lay out again next time
        for step in self.parts:
            step()

    def _lay_out(self) -> list[_Layout] | None:
        """Each optimizer's flat buffers, its state moved into them; None where one call
        would not compute what the per-tensor calls do."""
        params = [p for part in self.parts for p in part.params]
        states = [s.opt.state[p] for s in self.parts for p in s.params]
        steps = [st["step"] for st in states]
        first = self.parts[0].group
        key = (*(first[k] for k in _SETTINGS if k != "lr"), type(first["lr"]))
        if (
            any(p.dtype != params[0].dtype for p in params)
            or not _flat_agrees(key, first["lr"], params[0].dtype)
            or any(s.dtype != steps[0].dtype for s in steps)
            or len({float(s) for s in steps}) != 1
            or getattr(self.parts[0].opt, "grad_scale", None) is not None
            or getattr(self.parts[0].opt, "found_inf", None) is not None
        ):
            return None
        names = ["exp_avg", "exp_avg_sq"] + (["max_exp_avg_sq"] if first["amsgrad"] else [])
        layouts = [_Layout(part, names) for part in self.parts]
        for part in self.parts:
            part.lists.clear()  # their cached state lists held the tensors just replaced
        moments = [[lay.moments[i] for lay in layouts] for i in range(len(names))]
        if len(moments) == 2:
            moments.append([])  # no max_exp_avg_sq without amsgrad
        self.arguments = (  # what each step passes: made once per layout
            [lay.buffer for lay in layouts],
            [*moments, [lay.steps[0] for lay in layouts]],  # adam advances these counts
            [t for lay in layouts for t in lay.steps[1:]],  # ... and the step these
            params,
            [v for lay in layouts for v in lay.views],
        )
        self.layouts = layouts
        return layouts


class _Layout:
    """One optimizer's parameters and moments laid end to end (:class:`_FlatStep`): the
    moments' flat buffers, whose views replace the tensors of its state."""

    def __init__(self, part: _AdamStep, names: list[str]) -> None:
        params = part.params
        states = [part.opt.state[p] for p in params]
        bounds = list(itertools.accumulate((p.numel() for p in params), initial=0))

        def views(flat: torch.Tensor) -> list[torch.Tensor]:
            return [flat[a:b].view(p.shape) for a, b, p in zip(bounds, bounds[1:], params)]

        self.moments: list[torch.Tensor] = []
        for name in names:
            flat = torch.cat([st[name].reshape(-1) for st in states])
            for st, view in zip(states, views(flat)):
                st[name] = view  # the optimizer's state is now a view of the flat buffer
            self.moments.append(flat)
        self.views_of = [st["exp_avg"] for st in states]  # to notice a replaced state
        self.steps = [st["step"] for st in states]
        self.buffer = torch.empty(bounds[-1], dtype=params[0].dtype)
        self.views = views(self.buffer)


def _flat_agrees(key: tuple, lr, dtype: torch.dtype) -> bool:
    """Whether one ``adam`` call on tensors laid end to end gives, element for element,
    the bits of the calls per tensor, with these group settings (``key``: every one of
    :data:`_SETTINGS` but the learning rate, then its type) and this dtype, on this
    machine: five steps on tensors of 1, 3, 17, 64 and 100 elements (each with a scalar
    tail in a vectorised loop), gradients of several magnitudes. Checked once per key, at
    the first learning rate seen (a rate changes the values, not the kernels)."""
    if (key, dtype) not in _AGREES:
        _AGREES[(key, dtype)] = _check_flat(key, lr, dtype)
    return _AGREES[(key, dtype)]


_AGREES: dict[tuple, bool] = {}


def _check_flat(key: tuple, lr, dtype: torch.dtype) -> bool:
    names = [k for k in _SETTINGS if k != "lr"]
    group = dict(zip(names, key), lr=lr, fused=None)
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
        exp_avgs, exp_avg_sqs, max_exp_avg_sqs, state_steps = lists
        adam(
            params,
            grads,
            exp_avgs,
            exp_avg_sqs,
            max_exp_avg_sqs,
            state_steps,
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
