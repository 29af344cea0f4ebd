"""Every use of a private attribute of TorchRL or tensordict, in one module.

imitrl reaches past the public API of TorchRL/tensordict only here, each time for a
reason written next to it, and ``tests/test_compat.py`` checks that the public path
gives the same digits. Written against tensordict 0.14.3 and torchrl 0.14.1 (the
pins in ``pyproject.toml``): on an upgrade, read this file and run that test first.

=================================== ==========================================================
private attribute                   used by
=================================== ==========================================================
``TensorDictModule._write_to_       :class:`DirectWriteMixin` (``imitrl.policies.modules``)
tensordict`` (overridden)
``RoundRobinWriter._cursor``        :func:`writer_cursor`, :func:`set_writer_cursor`
                                    (``imitrl.data.buffer.DemonstrationBuffer.extend``)
``LazyTensorStorage._storage``      :func:`grow_tensor_storage`
                                    (``imitrl.data.buffer.GrowingTensorStorage.reserve``)
``LazyTensorStorage._storage``,     :func:`replace_storage_contents`
``LazyTensorStorage._len``          (``imitrl.data.disk.GrowingMemmapStorage``);
                                    :func:`forget_rows_after` (a failed extend)
``TensorDictSequential._select_     :func:`plain_sequence`, :func:`plain_module`,
before_return``, ``TensorDictModule :func:`plain_sampler` (``imitrl.runtime.fast.
._kwargs``/``_get_kwargs``,          policy_call.TensorPolicy``, a rollout's policy call)
``ProbabilisticTensorDictModule.
_generator``/``_generator_key``,
``ProbabilisticTensorDictSequential
._requires_sample`` (read)
``ClipPPOLoss._clip_bounds``,       :func:`plain_clip_ppo`, :func:`ppo_clip_bounds`
``._asymmetric_clip``,              (``imitrl.runtime.fast.ppo_step.TensorPPO``, PPO's
``LossModule._loss_mask_keys()``    loss on tensors)
``torchrl.weight_update._ray.       :func:`raise_ray_weight_sync_wait`
_DIST_TIMEOUT``                     (``imitrl.algorithms.ray_source.RaySource``)
``torch.distributions.utils.        :func:`standard_normal`, :func:`safe_tanh`
_standard_normal``, torchrl's       (``imitrl.runtime.fast.tanh_normal``, a tanh-normal
``safetanh_noeps`` (undocumented)   actor's action without its distribution)
``torch.distributions.utils.        :func:`sum_rightmost`, :func:`safe_atanh`
_sum_rightmost``, torchrl's         (``imitrl.runtime.fast.tanh_normal.TanhNormalLogProb``,
``_SafeTanhNoEps``/``_SafeaTanhNoEps PPO's log-probability of a tanh-normal), :func:`safe_tanh`
.forward``
``Distribution._validate_args``     :func:`validates_args` (``imitrl.runtime.fast.tanh_normal``)
``nn.Module._forward_hooks``,       :func:`forward_hooked`, :func:`hooked`,
``_forward_pre_hooks``,             :func:`global_module_hooks` (the seam's direct calls of a
``_backward_hooks``,                module: ``imitrl.runtime.fast``)
``_backward_pre_hooks``, torch's
``_global_*_hooks``
``Optimizer._optimizer_step_pre_    :func:`optimizer_hooked` (``imitrl.runtime.fast.adam_step``)
hooks``/``post_hooks``, torch's
``_global_optimizer_*_hooks``
``torch._foreach_add_``, ``_copy_``, :data:`foreach_add_`, :data:`foreach_copy_`,
``_norm``, ``_mul_``, ``_lerp_``    :data:`foreach_norm`, :data:`foreach_mul_`,
                                    :data:`foreach_lerp_` (Adam's flat step, the gradient
                                    clip, the EMA)
``LossModule._loss_mask_keys()``    :func:`loss_mask_keys` (``imitrl.runtime.fast.gail_step``)
Meta-World's ``SawyerXYZEnv.        :func:`random_reset_space` (``imitrl.envs.metaworld``)
_random_reset_space``
``torchrl.modules.models.act.       :func:`act_latent_noise` (``imitrl.learners.act.loss``:
_reparameterise``                   the CVAE latent's noise drawn per row, so that
                                    data-parallel ranks draw one process's)
=================================== ==========================================================
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any, cast

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import LazyTensorStorage, ReplayBuffer

if TYPE_CHECKING:  # the mixin's partner in the bases, for its attributes and ``super()``
    from tensordict.nn import TensorDictModule as _WriteBase
else:
    _WriteBase = object

__all__ = [
    "DirectWriteMixin",
    "act_latent_noise",
    "foreach_add_",
    "foreach_copy_",
    "foreach_lerp_",
    "foreach_mul_",
    "foreach_norm",
    "forward_hooked",
    "global_module_hooks",
    "grow_tensor_storage",
    "hooked",
    "loss_mask_keys",
    "optimizer_hooked",
    "plain_module",
    "plain_sampler",
    "plain_sequence",
    "quiet_torchrl_info",
    "raise_ray_weight_sync_wait",
    "random_reset_space",
    "replace_storage_contents",
    "set_writer_cursor",
    "validates_args",
    "wrapped_gym_env",
    "writer_cursor",
]


class DirectWriteMixin(_WriteBase):
    """Mixin for ``TensorDictModule`` subclasses: tensor outputs are set directly.

    Why: tensordict 0.14.3 writes every output of a ``TensorDictModule`` in its
    private ``_write_to_tensordict`` through ``TensorDict.from_any``, which calls
    ``importlib.util.find_spec("pandas")`` on each call (about 0.1 ms with a few
    entries on ``sys.path``), even when the output is a plain tensor. On a tabular or
    small-MLP policy that is most of the step, and tensordict has no public switch to
    skip it. This override handles the common case (write in place into a
    ``TensorDictBase``, every output a tensor) with ``TensorDictBase.set``, which
    stores the same tensor object ``from_any`` returns for a tensor, and defers to
    tensordict for everything else (``inplace`` False or ``"empty"``, an explicit
    ``tensordict_out``, non-tensor outputs).

    Put it first in the bases: ``class Module(DirectWriteMixin, TensorDictModule)``.
    """

    def _write_to_tensordict(
        self,
        tensordict: TensorDictBase,
        tensors: Sequence[torch.Tensor],
        tensordict_out: TensorDictBase | None = None,
        out_keys: Iterable[NestedKey] | None = None,
    ) -> TensorDictBase:
        if (
            tensordict_out is None
            and self.inplace is True
            and isinstance(tensordict, TensorDictBase)
            and all(isinstance(t, torch.Tensor) for t in tensors)
        ):
            # tensordict types out_keys as an Iterable, yet takes its len() as we do (a
            # string: this is the per-step path, and cast evaluates its first argument)
            written = cast(
                "Sequence[NestedKey]", self.out_keys_source if out_keys is None else out_keys
            )
            if len(tensors) != len(written):
                raise RuntimeError(f"{len(tensors)} outputs for out_keys {written}")
            for key, value in zip(written, tensors):
                if key != "_":  # tensordict's placeholder for an output to drop
                    tensordict.set(key, value)
            return tensordict
        return super()._write_to_tensordict(tensordict, tensors, tensordict_out, out_keys)


def writer_cursor(rb: ReplayBuffer) -> int:
    """The row where ``rb``'s round-robin writer puts its next ``extend``.

    Why: torchrl has no public getter. ``RoundRobinWriter._cursor`` is
    ``len(rb) % max_size`` as long as the storage never wraps; the public
    ``rb.writer.state_dict()["_cursor"]`` holds the same number but builds a dict.
    """
    return int(rb.writer._cursor)


def set_writer_cursor(rb: ReplayBuffer, value: int) -> None:
    """Make ``rb``'s round-robin writer put its next ``extend`` at row ``value``.

    Why: a storage that grows (``imitrl.data.buffer.GrowingTensorStorage``) must
    continue writing at its end, but the writer computes its cursor modulo the
    capacity it had at the last write: after exactly filling a capacity of ``n`` it
    points at row 0 and would overwrite the oldest rows. torchrl has no public
    setter; ``rb.writer.load_state_dict({"_cursor": value})`` does the same through
    the same private name, spelled as a state-dict key.
    """
    rb.writer._cursor = int(value)


def grow_tensor_storage(storage: LazyTensorStorage, new_size: int) -> None:
    """Give ``storage`` room for ``new_size`` rows, keeping the rows it holds.

    Why: a ``LazyTensorStorage`` preallocates one tensordict of ``max_size`` rows at
    its first write and keeps it in the private ``_storage``; torchrl has no public
    way to enlarge it. Raising ``max_size`` alone is silently wrong: the tensordict keeps
    its old size, writes past it land on the first rows and ``len`` counts rows that do
    not exist (seen on torchrl 0.14.1). The demonstration buffer must grow instead of
    wrapping, so this reallocates that tensordict at ``new_size`` rows and copies the
    first ``len(storage)`` rows over.
    ``tests/data/test_buffer_properties.py`` checks that a buffer grown this way holds the
    same rows as a ``LazyTensorStorage`` allocated large enough from the start.
    """
    if new_size < len(storage):
        raise ValueError(f"cannot shrink a storage of {len(storage)} rows to {new_size}")
    if storage.initialized:
        old = storage._storage
        rows = len(storage)
        grown = torch.empty_like(old[:1].expand(new_size, *old.shape[1:]))
        grown[:rows] = old[:rows]
        storage._storage = grown
    storage.max_size = int(new_size)


from torchrl.envs import GymWrapper  # noqa: E402  (appended with wrapped_gym_env)


def wrapped_gym_env(env: GymWrapper) -> object:
    """The gymnasium env (or vector env) inside a TorchRL ``GymWrapper``/``GymEnv``.

    Why: ``imitrl.envs.limits.episode_limit`` reads the wrapped env's time limit
    (``spec.max_episode_steps``). torchrl keeps the wrapped env in the private
    ``_EnvWrapper._env``; its only public route is ``_EnvWrapper.__getattr__``, which
    forwards any attribute the TorchRL env lacks (``env.spec`` reaches the gymnasium
    env's ``spec``) - an implicit fallthrough that an attribute added to ``EnvBase``
    would silently shadow. ``tests/envs/test_limits.py`` checks that both give the
    same spec.
    """
    if not isinstance(env, GymWrapper):
        raise ValueError(f"expected a TorchRL GymWrapper or GymEnv, got {type(env).__name__}")
    return env._env


def replace_storage_contents(
    storage: LazyTensorStorage, contents: TensorDictBase, rows: int
) -> None:
    """Make ``contents`` (a TensorDict ``[capacity]``) the rows of ``storage``, of which
    the first ``rows`` count as written.

    Why: ``imitrl.data.disk.GrowingMemmapStorage`` grows its memory-mapped files in place
    (lengthen each file, map it again at the new size: no row is copied) and reopens a
    disk buffer a previous process wrote; both hand the storage tensors it did not
    allocate. torchrl keeps them in the private ``_storage`` and its row count in the
    private ``_len`` (a property over a shared ``mp.Value``), with no public setter; its
    ``load_state_dict`` would copy every row. ``tests/data/test_disk.py`` checks that a
    disk buffer grown this way holds the same rows as an in-memory buffer fed the same rows.
    """
    if not 0 <= rows <= contents.shape[0]:
        raise ValueError(f"{rows} written rows do not fit a capacity of {contents.shape[0]}")
    storage._storage = contents
    storage.max_size = int(contents.shape[0])
    storage.initialized = True
    storage._len = int(rows)


def forget_rows_after(rb: ReplayBuffer, rows: int) -> None:
    """Count only the first ``rows`` of ``rb``'s storage as written, and write next at
    ``rows``: what a failed ``extend`` must leave (the demonstration buffer rolls back).

    Why: torchrl's storage counts a write's rows before every column is set, so a write
    that fails part-way (a column of another dtype) leaves ``len`` past the rows that
    exist; the count is the private ``_len`` and the cursor ``_cursor``
    (:func:`set_writer_cursor`), with no public setter.
    ``tests/data/test_disk_resume.py`` checks that a failed extend leaves the count as it was.
    """
    if int(rows) > len(rb.storage):
        raise ValueError(f"cannot keep {rows} rows of a storage holding {len(rb.storage)}")
    rb.storage._len = int(rows)
    set_writer_cursor(rb, rows)


def plain_sequence(seq) -> bool:
    """Whether ``seq(td)`` (a ``TensorDictSequential``) runs its modules in order on ``td``
    itself and returns it, so that its call can be replayed module by module.

    Why: ``imitrl.runtime.fast.policy_call.TensorPolicy`` runs a rollout's policy on a dict of
    tensors instead of a TensorDict, and must refuse a sequence that selects its outputs
    (``selected_out_keys``/``select_out_keys``), which tensordict records only in the
    private ``_select_before_return``. ``tests/runtime/test_paths.py`` checks that the dict
    call gives the same digits as the TensorDict call.
    """
    # inplace None also returns `td` itself (no out-tensordict is made)
    return (
        seq.inplace in (True, None) and not seq.partial_tolerant and not seq._select_before_return
    )


def plain_module(module) -> bool:
    """Whether ``module(td)`` (a ``TensorDictModule``) is ``module.module(*td[in_keys])``
    written in place to ``out_keys``: in-keys passed by position, no extra ``get`` options.

    Why: as :func:`plain_sequence`; a dict of in-keys (keyword arguments) and ``get``
    options are kept only in the private ``_kwargs`` and ``_get_kwargs``.
    """
    return module.inplace is True and module._kwargs is None and not module._get_kwargs


def plain_sampler(module, sequence=None) -> bool:
    """Whether a ``ProbabilisticTensorDictModule`` (the last module of ``sequence``, a
    ``ProbabilisticTensorDictSequential``) only builds its distribution and writes one
    sample: no log-probability, no ``num_samples``, no generator of its own, and (in the
    sequence) a sample requested.

    Why: as :func:`plain_sequence`; the generator settings live in the private
    ``_generator``/``_generator_key``, whether the sequence samples in ``_requires_sample``.
    """
    if module.return_log_prob or module.num_samples is not None:
        return False
    if module._generator is not None or module._generator_key is not None:
        return False
    if sequence is not None and (
        not sequence._requires_sample or sequence.return_composite or not plain_sequence(sequence)
    ):
        return False
    return True


def plain_call(node, sequence: bool = False, module: bool = False) -> bool:
    """One answer for a rollout's policy call (``imitrl.runtime.fast.policy_call.
    TensorPolicy``): whether ``node`` may be replayed from its public settings. Never with a
    forward hook of its own; a ``TensorDictSequential`` (``sequence``) when
    :func:`plain_sequence`; a ``TensorDictModule`` (``module``) when :func:`plain_module`; a
    ``ProbabilisticActor`` when its last module is hookless and :func:`plain_sampler`
    (where its last module is a ``ProbabilisticTensorDictModule``); any other node when
    hookless.

    Why: the private attributes each of those reads (see them), asked in one place.
    """
    from tensordict.nn import ProbabilisticTensorDictModule
    from torchrl.modules import ProbabilisticActor

    if forward_hooked(node):
        return False
    if sequence:
        return plain_sequence(node)
    if module:
        return plain_module(node)
    if type(node) is ProbabilisticActor:
        last = list(node.module)[-1]
        if isinstance(last, ProbabilisticTensorDictModule):
            return not forward_hooked(last) and plain_sampler(last, node)
    return True


@contextmanager
def quiet_torchrl_info() -> Iterator[None]:
    """TorchRL's INFO lines off for the block (its public ``"torchrl"`` logger).

    Why: torchrl 0.14.1 logs "Initialized LazyTensorStorage ..." at INFO, coloured, on
    stdout (its own handler), the first time a storage is written; a library call must
    not print before its caller's first line. Only the buffer's first write is wrapped:
    anything else TorchRL logs is left as the user set it.
    """
    log = logging.getLogger("torchrl")
    level = log.level
    if level > logging.INFO or log.disabled:
        yield
        return
    log.setLevel(logging.WARNING)
    try:
        yield
    finally:
        log.setLevel(level)


def raise_ray_weight_sync_wait(seconds: float) -> None:
    """Let the driver wait at least ``seconds`` for Ray workers to join the weight sync.

    Why: TorchRL's Ray weight sync (``torchrl.weight_update._ray``) waits a fixed 60 s
    (its module constant ``_DIST_TIMEOUT``, no argument sets it) for every worker to join
    its process group; on a loaded 2-core machine a worker can take longer to start, and
    the round fails with ``DistStoreError: wait timeout``. The constant is read when the
    group is built, so raising it before the collectors start is enough.
    """
    from datetime import timedelta

    import torchrl.weight_update._ray as ray_sync

    ray_sync._DIST_TIMEOUT = max(ray_sync._DIST_TIMEOUT, timedelta(seconds=seconds))


def plain_clip_ppo(loss, batch: TensorDictBase | None = None) -> bool:
    """Whether a ``ClipPPOLoss`` computes only the clipped objective and a smooth-L1
    critic, averaged (no entropy bonus, value clipping, delayed actor, importance-ratio
    cap, asymmetric clip or advantage scaling beyond standardisation), and ``batch``
    holds none of the entries it reads as a loss mask.

    Why: ``TensorPPO`` replays exactly that arithmetic on tensors; whether the clip is
    asymmetric and which batch entries mask the loss live in the private
    ``_asymmetric_clip`` and ``_loss_mask_keys()``.
    """
    if loss.functional or loss.delay_actor or getattr(loss, "_asymmetric_clip", False):
        return False
    if batch is not None and any(k in batch.keys(True) for k in loss_mask_keys(loss)):
        return False
    return not (
        loss.entropy_bonus
        or loss.clip_value
        or not loss.normalize_advantage
        or loss.normalize_advantage_exclude_dims
        or getattr(loss, "advantage_norm", None) is not None
        or getattr(loss, "max_importance_ratio", None) is not None
        or loss.loss_critic_type != "smooth_l1"
        or loss.reduction != "mean"
        or loss.separate_losses
        or loss.critic_coeff is None
    )


def ppo_clip_bounds(loss) -> tuple[torch.Tensor, torch.Tensor]:
    """``ClipPPOLoss``'s log-ratio bounds ``(log1p(-eps), log1p(eps))``, the same tensors
    its forward clamps with. Why: they are the private ``_clip_bounds`` property."""
    return loss._clip_bounds


def standard_normal(shape: torch.Size, like: torch.Tensor) -> torch.Tensor:
    """The noise ``torch.distributions.Normal.rsample`` draws for a sample of ``shape``
    (``dtype`` and device of ``like``), from the global RNG. Why: it is the private
    ``torch.distributions.utils._standard_normal``; calling it draws exactly what the
    distribution would."""
    from torch.distributions.utils import _standard_normal

    return _standard_normal(shape, dtype=like.dtype, device=like.device)


def safe_tanh(x: torch.Tensor) -> torch.Tensor:
    """TorchRL's ``SafeTanhTransform`` forward (``tanh`` clamped one resolution inside
    +-1). Why: ``torchrl.modules.distributions.utils.safetanh_noeps`` is undocumented.
    Without a gradient to record (acting), its ``autograd.Function``'s forward runs as
    it is: the same two calls, without ``Function.apply``'s argument binding (about 17 us
    a call on 8 lanes, most of a tanh-normal action's squashing)."""
    from torchrl.modules.distributions.utils import _SafeTanhNoEps, safetanh_noeps

    if torch.is_grad_enabled() and x.requires_grad:
        return safetanh_noeps(x)
    return _SafeTanhNoEps.forward(x)


def safe_atanh(y: torch.Tensor) -> torch.Tensor:
    """TorchRL's ``SafeTanhTransform`` inverse (``atanh`` of ``y`` clamped one resolution
    inside +-1), for a ``y`` that records no gradient (an action). Why: it is the forward
    of the private ``_SafeaTanhNoEps`` (``safeatanh_noeps``, undocumented), run as it is:
    ``Function.apply``'s argument binding costs more than the two calls."""
    from torchrl.modules.distributions.utils import _SafeaTanhNoEps, safeatanh_noeps

    if torch.is_grad_enabled() and y.requires_grad:
        return safeatanh_noeps(y)
    return _SafeaTanhNoEps.forward(y)


def sum_rightmost(value: torch.Tensor, dim: int) -> torch.Tensor:
    """``value`` with its ``dim`` rightmost dimensions summed out, as the distributions sum
    a log-density over event dimensions. Why: it is the private
    ``torch.distributions.utils._sum_rightmost``; calling it sums as they do."""
    from torch.distributions.utils import _sum_rightmost

    return _sum_rightmost(value, dim)


def loss_mask_keys(loss) -> list[NestedKey]:
    """The batch entries a TorchRL ``LossModule`` reads as a loss mask. Why: the list is
    the private ``_loss_mask_keys()``; a replay of the loss on tensors computes something
    else where the batch holds one, so it steps aside."""
    return list(loss._loss_mask_keys())


def validates_args(dist: torch.distributions.Distribution) -> bool:
    """Whether ``dist`` checks its arguments and samples (``validate_args``). Why: the
    instance's setting is the private ``_validate_args``; a replay that skips the
    distribution must not skip a check it would have made."""
    return bool(dist._validate_args)


def forward_hooked(*modules: nn.Module) -> bool:
    """Whether any of ``modules`` has a forward or forward-pre hook of its own. Why:
    torch keeps them in the private ``_forward_hooks`` and ``_forward_pre_hooks`` and has
    no public query; a direct call of ``forward`` would skip them."""
    return any(m._forward_hooks or m._forward_pre_hooks for m in modules)


def hooked(module: nn.Module) -> bool:
    """Whether ``module`` has a hook of its own (forward, forward-pre, backward or
    backward-pre; the private dicts, as :func:`forward_hooked`)."""
    return forward_hooked(module) or bool(module._backward_hooks or module._backward_pre_hooks)


def global_module_hooks() -> bool:
    """Whether a global module hook is registered (``register_module_forward_hook`` and
    kin). Why: torch keeps them in ``torch.nn.modules.module``'s private
    ``_global_*_hooks``; a direct call of ``forward`` would skip them."""
    from torch.nn.modules import module as torch_module

    names = ("forward_hooks", "forward_pre_hooks", "backward_hooks", "backward_pre_hooks")
    return any(getattr(torch_module, f"_global_{n}", None) for n in names)


def optimizer_hooked(opt: torch.optim.Optimizer) -> bool:
    """Whether ``opt.step`` would run a step hook (its own or a global one). Why: torch
    keeps them in the private ``_optimizer_step_pre_hooks``/``_post_hooks`` and
    ``torch.optim.optimizer._global_optimizer_*_hooks``; Adam's functional step skips them."""
    from torch.optim import optimizer as torch_optimizer

    return bool(
        opt._optimizer_step_pre_hooks
        or opt._optimizer_step_post_hooks
        or torch_optimizer._global_optimizer_pre_hooks
        or torch_optimizer._global_optimizer_post_hooks
    )


foreach_add_ = torch._foreach_add_
"""``torch._foreach_add_``: one kernel over a list of tensors (what ``torch.optim`` and
``clip_grad_norm_`` call on the CPU; private by name, used throughout torch itself)"""
foreach_copy_ = torch._foreach_copy_
"""``torch._foreach_copy_`` (as :data:`foreach_add_`)"""
foreach_norm = torch._foreach_norm
"""``torch._foreach_norm`` (as :data:`foreach_add_`)"""
foreach_mul_ = torch._foreach_mul_
"""``torch._foreach_mul_`` (as :data:`foreach_add_`)"""
foreach_lerp_ = torch._foreach_lerp_
"""``torch._foreach_lerp_`` (as :data:`foreach_add_`; what ``AveragedModel``'s EMA calls)"""


def random_reset_space(env: object) -> Any:
    """A Meta-World v3 env's box of task placements (``rand_vec``'s bounds). Why: it is
    the private ``_random_reset_space`` of ``SawyerXYZEnv``; ``metaworld.MT1`` reads it the
    same way to build its tasks."""
    return env._random_reset_space  # type: ignore[attr-defined]


@contextmanager
def act_latent_noise(noise: torch.Tensor) -> Iterator[None]:
    """Within: TorchRL's ``ACTModel`` samples its CVAE latent as ``mu + std * noise``
    (``noise`` ``[B, latent]``, given) instead of drawing ``torch.randn_like(std)`` from
    the global RNG inside its module-level ``_reparameterise``. The loss draws ``noise``
    itself, per row, from the same generator state (the same numbers one process drew
    before), so a data-parallel rank can keep its rows' (:mod:`imitrl.system.ranks`);
    TorchRL offers no argument for it."""
    import torchrl.modules.models.act as act

    original = act._reparameterise

    def given(mu: torch.Tensor, log_var: torch.Tensor) -> torch.Tensor:
        return mu + (0.5 * log_var).exp() * noise.to(mu.device, mu.dtype)

    act._reparameterise = given
    try:
        yield
    finally:
        act._reparameterise = original
