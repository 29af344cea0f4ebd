"""The seam: where imitrl chooses between its reference code and its accelerated paths.

Every accelerated piece is reached through a function of this module, and nothing else
in imitrl imports :mod:`imitrl.runtime.fast` (``tests/runtime/test_paths.py`` greps for it).
Each piece has a reference on public TorchRL/torch that gives the same digits:

================== ========================================= ==========================================
piece              reference (public API)                    accelerated (:mod:`imitrl.runtime.fast`)
================== ========================================= ==========================================
:func:`stepper`    ``policy(td)``, ``env.step_and_maybe_reset`` ``DirectSteps`` + ``TensorPolicy``
                   (:mod:`imitrl.runtime.reference`)         (plain gymnasium envs, ``TabularEnv``)
:func:`table_      the step loop                             the toy-text stream player: the episodes
returns`                                                     of a fixed state table, without steps
:func:`loss_chain` the actor on a TensorDict                 its plain modules' networks on tensors
:func:`optimizer_  ``opt.step``                              Adam's functional form on the CPU (its
step`                                                        wrapper costs as much as a small update),
                                                             several optimizers as one flat call
:func:`clip_grad_  ``torch.nn.utils.clip_grad_norm_``        its four foreach calls, no wrapper
norm`
:func:`ppo_loss`   ``ClipPPOLoss(minibatch)``                ``TensorPPO``: its arithmetic on tensors,
                                                             a tanh-normal's or categorical's log-
                                                             probability without the distribution
:func:`gail_loss`  ``GAILLoss(batch)``                       ``TensorGAILLoss``: its arithmetic on the
                                                             four feature tensors
================== ========================================= ==========================================

On a GPU the CPU tricks step aside for the device's own fast forms: ``optimizer_step``
returns ``opt.step`` for parameters off the CPU, and a learner placed on CUDA runs fused
Adam (:meth:`imitrl.learners.Learner.placed`); the policy call crosses devices through
:class:`~imitrl.system.device.OnDevice`, which both steppers run as any module.

The one rollout loop (:func:`imitrl.runtime.loop.play`) runs either stepper.

**Choosing: one switch.** Accelerated paths run by default. Inside :func:`reference` (a
context manager, per thread and task) every piece, or the pieces named, takes its
reference path: to check a result against public TorchRL, or to rule the fast paths out
when something looks wrong. ``IMITRL_REFERENCE`` (``all``, or a comma-separated list of
:data:`PIECES`) does the same for a whole process: what ``benchmarks/seam.py`` measures
each piece's gain with.

Each piece is kept because it buys at least 5% of a whole process on a benchmark it
serves (``benchmarks/seam.py``'s table in ``benchmarks/README.md``); ``network`` (a bare
module call, no caller left) and ``gae`` (GAE replayed on tensors: +1.8% / +4.6% on the
GAIL commands) bought less and were deleted (issue 43).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextvars import ContextVar
from typing import TYPE_CHECKING, Union

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torchrl.envs import EnvBase
from torchrl.objectives import LossModule

from imitrl.runtime.losses import GAILReference, PPOReference

if TYPE_CHECKING:  # imported when used: envs and objectives import this module
    from imitrl.runtime.fast.gail_step import TensorGAILLoss
    from imitrl.runtime.fast.ppo_step import TensorPPO
    from imitrl.runtime.loop import Lanes, Stepper

PPOLossPiece = Union["TensorPPO", PPOReference]
"""what :func:`ppo_loss` returns: either path, the same methods"""
GAILLossPiece = Union["TensorGAILLoss", GAILReference]
"""what :func:`gail_loss` returns: either path, the same methods"""

__all__ = [
    "PIECES",
    "clip_grad_norm",
    "fast_enabled",
    "gail_loss",
    "loss_chain",
    "optimizer_step",
    "ppo_loss",
    "reference",
    "stepper",
    "table_returns",
    "zero_grad",
]

PIECES = (
    "stepper",
    "table_returns",
    "loss_chain",
    "optimizer_step",
    "zero_grad",
    "clip_grad_norm",
    "ppo_loss",
    "gail_loss",
)
"""every accelerated piece, by the name :func:`reference` and ``IMITRL_REFERENCE`` take"""


def _pieces(names: Iterable[str], where: str) -> frozenset[str]:
    names = [n.strip() for n in names if n.strip()]
    if names == ["all"]:
        return frozenset(PIECES)
    unknown = sorted(set(names) - set(PIECES))
    if unknown:
        raise ValueError(
            f"{where}: no accelerated piece {unknown}; the pieces: {', '.join(PIECES)}"
        )
    return frozenset(names)


_FROM_ENVIRONMENT = _pieces(os.environ.get("IMITRL_REFERENCE", "").split(","), "IMITRL_REFERENCE")
_REFERENCE: ContextVar[frozenset[str]] = ContextVar(
    "imitrl_reference_pieces", default=_FROM_ENVIRONMENT
)
"""the pieces on their reference path here: :func:`reference`'s, or the environment's
``IMITRL_REFERENCE`` (``all``, or a comma-separated list of :data:`PIECES`: how a whole
process is measured without one piece, ``benchmarks/seam.py``)"""


def fast_enabled(piece: str | None = None) -> bool:
    """Whether the accelerated path of ``piece`` (None: of every piece) runs here (False
    inside :func:`reference` of it)."""
    off = _REFERENCE.get()
    return not off if piece is None else piece not in off


@contextlib.contextmanager
def reference(*pieces: str) -> Iterator[None]:
    """Within: the named pieces (none named: every piece, :data:`PIECES`) take their
    reference path (module docstring); the one switch, for a check against public TorchRL
    or to rule an accelerated piece out."""
    names = frozenset(PIECES) if not pieces else _pieces(pieces, "paths.reference")
    token = _REFERENCE.set(_REFERENCE.get() | names)
    try:
        yield
    finally:
        _REFERENCE.reset(token)


def stepper(
    env: EnvBase,
    policy: TensorDictModuleBase,
    *,
    record: bool,
    row_keys: tuple | None = None,
    next_observation: bool = False,
) -> Stepper:
    """The stepper of ``env`` driven by ``policy`` for :func:`~imitrl.runtime.loop.play`
    (or :func:`~imitrl.runtime.loop.play_steps`): the accelerated one where it knows the
    env (outside :func:`reference`), else the reference one. Build it
    inside the rollout's exploration type. ``row_keys``: the root entries a recording
    keeps (None: :data:`~imitrl.runtime.loop.ROW_KEYS`); ``next_observation``: keep
    ``("next", "observation")`` too."""
    from imitrl.runtime.loop import ROW_KEYS

    extra = (ROW_KEYS if row_keys is None else tuple(row_keys), next_observation)
    if fast_enabled("stepper"):
        from imitrl.runtime.fast.env_steps import direct_steps

        direct = direct_steps(env)
        if direct is not None:
            from imitrl.runtime.fast.stepper import DirectStepper

            return DirectStepper(env, direct, policy, record, *extra)
    from imitrl.runtime.reference import TorchRLStepper

    return TorchRLStepper(env, policy, record, *extra)


def table_returns(
    env: EnvBase, policy: TensorDictModuleBase, book: Lanes
) -> tuple[np.ndarray, np.ndarray] | None:
    """Returns and lengths ``[n]`` of ``book``'s episodes by the toy-text stream player
    (:mod:`imitrl.runtime.fast.toy_text`) when ``env`` is a plain gymnasium toy-text env
    with a time limit and ``policy`` a fixed table of states; None (nothing played)
    otherwise, or on the reference path: then the step loop plays them."""
    if not fast_enabled("table_returns"):
        return None
    from imitrl.runtime.fast.toy_text import table_returns as played

    return played(env, policy, book)


def loss_chain(modules: list[nn.Module] | None):
    """A :class:`~imitrl.runtime.fast.tensor_chain.TensorChain` of ``modules`` (their
    networks run on a batch's tensors), or None where they are not all plain one-key
    modules. A loss asks for it once and uses it while :func:`fast_enabled`."""
    from imitrl.runtime.fast.tensor_chain import TensorChain

    return TensorChain.of(modules)


def ppo_loss(loss: LossModule, batch: TensorDictBase | None = None) -> PPOLossPiece:
    """The ``ClipPPOLoss`` ``loss`` on a minibatch's rows (``prepare(flat)`` once per
    epoch, ``on_rows(prepared, rows)`` per minibatch): a
    :class:`~imitrl.runtime.fast.ppo_step.TensorPPO` (its arithmetic on the batch's
    tensors, the same bits) where it replays ``loss``, else, and on the reference path,
    :class:`~imitrl.runtime.losses.PPOReference` (the module on the rows). ``batch``: one
    the loss will see (a loss mask in it keeps the module)."""
    if fast_enabled("ppo_loss"):
        from imitrl.runtime.fast.ppo_step import TensorPPO

        fast = TensorPPO.of(loss, batch)
        if fast is not None:
            return fast
    return PPOReference(loss)


def gail_loss(loss: LossModule, batch: TensorDictBase | None = None) -> GAILLossPiece:
    """The ``GAILLoss`` ``loss`` (``loss_and_penalty(batch, sides)``) and its
    discriminator's output on each side (``logits(sides, key)``): a
    :class:`~imitrl.runtime.fast.gail_step.TensorGAILLoss` (its arithmetic on the four
    feature tensors, the same bits) where it replays ``loss``, else, and on the reference
    path, :class:`~imitrl.runtime.losses.GAILReference` (the modules as they are)."""
    if fast_enabled("gail_loss"):
        from imitrl.runtime.fast.gail_step import TensorGAILLoss

        fast = TensorGAILLoss.of(loss, batch)
        if fast is not None:
            return fast
    return GAILReference(loss, loss.discriminator_network)


def optimizer_step(*opts: torch.optim.Optimizer) -> Callable[[], None]:
    """``opt.step()`` of each of ``opts`` for a fit's loop: Adam's functional form with
    the optimizers' own state on the CPU, one call for all of them while their settings
    agree (the same kernels, so the same bits), ``opt.step`` everywhere else and on the
    reference path."""
    if not fast_enabled("optimizer_step"):
        if len(opts) == 1:
            return opts[0].step

        def each() -> None:
            for opt in opts:
                opt.step()

        return each
    from imitrl.runtime.fast.adam_step import optimizer_step as fast_step

    return fast_step(*opts)


def clip_grad_norm(params: Sequence[torch.Tensor], max_norm: float) -> torch.Tensor:
    """``torch.nn.utils.clip_grad_norm_(params, max_norm)``: its four calls without its
    wrapper where it would take its foreach path on the CPU (the same bits), the function
    itself elsewhere and on the reference path."""
    if not fast_enabled("clip_grad_norm"):
        return torch.nn.utils.clip_grad_norm_(params, max_norm)
    from imitrl.runtime.fast.clip_grad import clip_grad_norm as fast_clip

    return fast_clip(params, max_norm)


def zero_grad(*opts: torch.optim.Optimizer) -> Callable[[], None]:
    """``opt.zero_grad(set_to_none=True)`` of each of ``opts`` as a function of no
    argument: for torch's own ``Optimizer.zero_grad`` (not overridden) that method's
    assignment, ``p.grad = None`` for every parameter, without the profiler range the
    method opens at each call; the method itself elsewhere and on the reference path."""
    if not fast_enabled("zero_grad") or any(
        type(o).zero_grad is not torch.optim.Optimizer.zero_grad for o in opts
    ):

        def each() -> None:
            for opt in opts:
                opt.zero_grad(set_to_none=True)

        return each
    params = [p for opt in opts for group in opt.param_groups for p in group["params"]]

    def assign() -> None:
        for p in params:
            p.grad = None

    return assign
