"""The seam: where imitrl chooses between its reference code and its accelerated paths.

Every accelerated piece is reached through a function of this module, and nothing else
in imitrl imports :mod:`imitrl.runtime.fast` (``tests/test_fast_path.py`` greps for it).
Each piece has a reference on public TorchRL/torch that gives the same digits:

================== ========================================= ==========================================
piece              reference (public API)                    accelerated (:mod:`imitrl.runtime.fast`)
================== ========================================= ==========================================
:func:`stepper`    ``policy(td)``, ``env.step_and_maybe_reset`` ``DirectSteps`` + ``TensorPolicy``
                   (:mod:`imitrl.runtime.reference`)         (plain gymnasium envs, ``TabularEnv``)
:func:`table_      the step loop                             the toy-text stream player: the episodes
returns`                                                     of a fixed state table, without steps
:func:`network`    ``module(x)``                             ``direct_call``: no hook bookkeeping
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
:func:`gae`        ``GAE(batch)``                            ``TensorGAE``: the value net called once,
                                                             on each distinct observation, no vmap
================== ========================================= ==========================================

On a GPU the CPU tricks step aside for the device's own fast forms: ``optimizer_step``
returns ``opt.step`` for parameters off the CPU, and a learner placed on CUDA runs fused
Adam (:meth:`imitrl.learners.Learner.placed`); the policy call crosses devices through
:class:`~imitrl.system.device.OnDevice`, which both steppers run as any module.

The one rollout loop (:func:`imitrl.runtime.loop.play`) runs either stepper.

**Choosing.** Accelerated paths run by default. Inside :func:`reference` (a context
manager, per thread and task) every piece takes its reference path: to check a result
against public TorchRL, or to rule the fast paths out when something looks wrong. A
rollout's ``fast_path=False`` does the same for that rollout's stepper.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator, Sequence
from contextvars import ContextVar
from typing import TYPE_CHECKING

import numpy as np
import torch
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torchrl.envs import EnvBase

if TYPE_CHECKING:  # imported when used: envs and objectives import this module
    from imitrl.runtime.loop import Lanes, Stepper

__all__ = [
    "clip_grad_norm",
    "fast_enabled",
    "gae",
    "gail_loss",
    "loss_chain",
    "network",
    "optimizer_step",
    "ppo_loss",
    "reference",
    "stepper",
    "table_returns",
]

_FAST: ContextVar[bool] = ContextVar("imitrl_fast_paths", default=True)


def fast_enabled() -> bool:
    """Whether accelerated paths run here (False inside :func:`reference`)."""
    return _FAST.get()


@contextlib.contextmanager
def reference() -> Iterator[None]:
    """Within: every piece of this seam takes its reference path (module docstring)."""
    token = _FAST.set(False)
    try:
        yield
    finally:
        _FAST.reset(token)


def stepper(
    env: EnvBase,
    policy: TensorDictModuleBase,
    *,
    record: bool,
    fast_path: bool = True,
    row_keys: tuple | None = None,
    next_observation: bool = False,
) -> Stepper:
    """The stepper of ``env`` driven by ``policy`` for :func:`~imitrl.runtime.loop.play`
    (or :func:`~imitrl.runtime.loop.play_steps`): the accelerated one where it knows the
    env and ``fast_path`` and :func:`fast_enabled` allow, else the reference one. Build it
    inside the rollout's exploration type. ``row_keys``: the root entries a recording
    keeps (None: :data:`~imitrl.runtime.loop.ROW_KEYS`); ``next_observation``: keep
    ``("next", "observation")`` too."""
    from imitrl.runtime.loop import ROW_KEYS

    extra = (ROW_KEYS if row_keys is None else tuple(row_keys), next_observation)
    if fast_path and fast_enabled():
        from imitrl.runtime.fast.env_steps import direct_steps

        direct = direct_steps(env)
        if direct is not None:
            from imitrl.runtime.fast.stepper import DirectStepper

            return DirectStepper(env, direct, policy, record, *extra)
    from imitrl.runtime.reference import TorchRLStepper

    return TorchRLStepper(env, policy, record, *extra)


def table_returns(
    env: EnvBase, policy: TensorDictModuleBase, book: Lanes, *, fast_path: bool = True
) -> tuple[np.ndarray, np.ndarray] | None:
    """Returns and lengths ``[n]`` of ``book``'s episodes by the toy-text stream player
    (:mod:`imitrl.runtime.fast.toy_text`) when ``env`` is a plain gymnasium toy-text env
    with a time limit and ``policy`` a fixed table of states; None (nothing played)
    otherwise, or on the reference path: then the step loop plays them."""
    if not (fast_path and fast_enabled()):
        return None
    from imitrl.runtime.fast.toy_text import table_returns as played

    return played(env, policy, book)


def network(module: nn.Module) -> Callable[..., torch.Tensor]:
    """``module``'s call: without ``nn.Module.__call__``'s hook bookkeeping where it has
    no hooks (the same bits), or ``module`` itself on the reference path."""
    if not fast_enabled():
        return module
    from imitrl.runtime.fast.policy_call import direct_call

    return direct_call(module)


def loss_chain(modules: list[nn.Module] | None):
    """A :class:`~imitrl.runtime.fast.tensor_chain.TensorChain` of ``modules`` (their
    networks run on a batch's tensors), or None where they are not all plain one-key
    modules. A loss asks for it once and uses it while :func:`fast_enabled`."""
    from imitrl.runtime.fast.tensor_chain import TensorChain

    return TensorChain.of(modules)


def ppo_loss(loss, batch=None):
    """A :class:`~imitrl.runtime.fast.ppo_step.TensorPPO` of the ``ClipPPOLoss`` ``loss``
    (its losses on a minibatch's tensors, the same bits), or None on the reference path
    and wherever it would compute anything else (a configuration it does not replay, a
    ``batch`` carrying a loss mask): then call ``loss`` on the TensorDict."""
    if not fast_enabled():
        return None
    from imitrl.runtime.fast.ppo_step import TensorPPO

    return TensorPPO.of(loss, batch)


def gail_loss(loss, batch=None):
    """A :class:`~imitrl.runtime.fast.gail_step.TensorGAILLoss` of the ``GAILLoss``
    ``loss`` (its loss from the four feature tensors, the same bits), or None on the
    reference path and wherever it would compute anything else: then call ``loss``."""
    if not fast_enabled():
        return None
    from imitrl.runtime.fast.gail_step import TensorGAILLoss

    return TensorGAILLoss.of(loss, batch)


def gae(module, batch):
    """``module`` (a TorchRL ``GAE``) as a callable on ``batch``: a
    :class:`~imitrl.runtime.fast.gae_step.TensorGAE` (the same bits) where it replays the
    module's configuration, the module itself on the reference path and elsewhere."""
    if not fast_enabled():
        return module
    from imitrl.runtime.fast.gae_step import TensorGAE

    return TensorGAE.of(module, batch) or module


def optimizer_step(*opts: torch.optim.Optimizer) -> Callable[[], None]:
    """``opt.step()`` of each of ``opts`` for a fit's loop: Adam's functional form with
    the optimizers' own state on the CPU, one call for all of them while their settings
    agree (the same kernels, so the same bits), ``opt.step`` everywhere else and on the
    reference path."""
    if not fast_enabled():
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
    if not fast_enabled():
        return torch.nn.utils.clip_grad_norm_(params, max_norm)
    from imitrl.runtime.fast.clip_grad import clip_grad_norm as fast_clip

    return fast_clip(params, max_norm)
