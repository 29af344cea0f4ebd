"""GAE on a batch's tensors: ``torchrl.objectives.value.GAE``'s arithmetic, without its vmap.

Accelerated internals of :mod:`imitrl.runtime.paths` (import them from there, nowhere else).

The GAIL/AIRL generator recomputes GAE over its whole round (2048 rows) before every PPO
epoch. Through the ``GAE`` module that costs about 5.5-6 ms on Pendulum's small value
network: ``torch.func.vmap`` of the value module over the stacked ``[observation, next
observation]`` TensorDicts (with the selects and stacks that feed it), then
``generalized_advantage_estimate``'s backward recursion, a few tensor calls per time
step. :class:`TensorGAE` computes what ``GAE.forward`` computes for the configuration
imitrl's generator builds (a plain ``TensorDictModule``/``ValueOperator`` of one input
and one output, no chunked or shifted value calls, no parameters passed in, no
averaging, no auto-reset, no skip-existing, no ``steps_to_next_obs``), in about 2.6 ms,
half of it the value network's own forward:

* the value network called once on the same stacked observations (a batched linear
  layer gives the vmapped call's bits);
* the module's advantage function on the same tensors: ``vec_generalized_advantage_
  estimate`` when the module is vectorised; otherwise ``generalized_advantage_estimate``,
  its recursion run over numpy views (:func:`recursive_gae`: the same float operations in
  the same order) where the values and the reward are ``[*B, T, F]`` CPU tensors of one
  dtype, the function itself elsewhere.

It writes what the module writes: the advantage, the value target, and the value at both
ends of each step. ``tests/test_adversarial_lanes.py`` checks these against the module
and the recursion against the function, bit for bit, and trains GAIL and AIRL on both
paths and compares every weight. A batch whose next observations hold a NaN (what
TorchRL's compact-observation collectors leave at episode ends) goes through the module.
"""

from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, skip_existing
from torchrl.modules import ValueOperator
from torchrl.objectives.value import GAE
from torchrl.objectives.value.functional import (
    generalized_advantage_estimate,
    vec_generalized_advantage_estimate,
)

from imitrl.compat import plain_module
from imitrl.policies.modules import Value
from imitrl.runtime.fast.policy_call import direct_call

__all__ = ["TensorGAE"]


def _plain(gae: GAE) -> bool:
    return not (
        gae.shifted
        or gae.average_gae
        or gae.auto_reset_env
        or gae.differentiable
        or gae.value_chunk_size is not None
        or gae.num_chunks is not None
        or getattr(gae, "group_key", None) is not None
    )


class TensorGAE:
    """``GAE(batch)`` on tensors (module docstring); call it as the module (no grad)."""

    def __init__(self, gae: GAE) -> None:
        value = gae.value_network
        (self.in_key,), (self.value_key,) = value.in_keys, value.out_keys
        self.net = direct_call(value.module)
        self.gae, self.keys = gae, gae.tensor_keys
        self.vectorized = bool(gae.vectorized)

    @classmethod
    def of(cls, gae: GAE, batch: TensorDictBase) -> TensorGAE | None:
        """A :class:`TensorGAE` of ``gae``, or None where it would compute anything else."""
        if type(gae) is not GAE or not _plain(gae) or gae.skip_existing or skip_existing():
            return None  # skip-existing reuses the batch's values from the second epoch on
        value = gae.value_network
        if type(value) not in (TensorDictModule, ValueOperator, Value) or not plain_module(value):
            return None  # a subclass or a sequence may compute anything in its forward
        if value._forward_hooks or value._forward_pre_hooks:
            return None
        if len(value.in_keys) != 1 or len(value.out_keys) != 1:
            return None
        if gae.tensor_keys.steps_to_next_obs in batch.keys(True):
            return None
        return cls(gae)

    def __call__(self, batch: TensorDictBase) -> TensorDictBase:
        obs, nxt = batch.get(self.in_key), batch.get(("next", self.in_key))
        if obs.is_floating_point() and torch.isnan(nxt).any():
            return self.gae(batch)  # the module's NaN substitution
        k = self.keys
        with torch.no_grad():
            both = self.net(torch.stack([obs, nxt], 0))
            value, next_value = both[0], both[1]
            time_dim = _time_dim(self.gae, batch)
            done = batch.get(("next", k.done))
            args = (
                self.gae.gamma,
                self.gae.lmbda,
                value,
                next_value,
                batch.get(("next", k.reward)),
            )
            terminated = batch.get(("next", k.terminated), default=done)
            if self.vectorized:
                adv, target = vec_generalized_advantage_estimate(
                    *args, done=done, terminated=terminated, time_dim=time_dim
                )
            elif _recursion_applies(value, args[4], time_dim, batch.ndim):
                adv, target = recursive_gae(*args, done=done, terminated=terminated)
            else:
                adv, target = generalized_advantage_estimate(
                    *args, done=done, terminated=terminated, time_dim=time_dim
                )
        batch.set(self.value_key, value)
        batch.set(("next", self.value_key), next_value)
        batch.set(k.advantage, adv)
        batch.set(k.value_target, target)
        return batch


def _time_dim(gae: GAE, batch: TensorDictBase) -> int:
    """``GAE._get_time_dim(None, batch)``: the module's ``time_dim``, else the dimension
    named ``"time"``, else the last."""
    if gae.time_dim is not None:
        return gae.time_dim % batch.ndim
    names = list(batch.names)
    return names.index("time") if "time" in names else batch.ndim - 1


def _recursion_applies(
    value: torch.Tensor, reward: torch.Tensor, time_dim: int, batch_dims: int
) -> bool:
    """Values ``[*B, T, F]`` on the CPU, time the batch's last dimension, the reward of
    the values' shape and dtype (anything else: the function, with its own checks)."""
    return (
        value.device.type == "cpu"
        and value.dtype in (torch.float32, torch.float64)
        and reward.dtype == value.dtype
        and reward.shape == value.shape
        and time_dim == batch_dims - 1
        and value.ndim == batch_dims + 1
    )


def recursive_gae(
    gamma: torch.Tensor,
    lmbda: torch.Tensor,
    value: torch.Tensor,
    next_value: torch.Tensor,
    reward: torch.Tensor,
    *,
    done: torch.Tensor,
    terminated: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``generalized_advantage_estimate`` for ``[*B, T, F]`` CPU tensors: its tensors
    built by its own expressions, its backward recursion
    ``A_t = delta_t + A_{t+1} * discount_t`` run over numpy views of them. The same
    IEEE operations in the same order (a multiply, then an add, per element and step),
    so the same bits, at a fifth to a tenth of the time of 2048 steps of tensor calls."""
    not_done = (~done).int()
    not_terminated = (~terminated).int()
    delta = reward + ((gamma * not_terminated) * next_value) - value
    discount = lmbda * gamma * not_done
    d = delta.movedim(-2, 0).numpy()
    c = discount.movedim(-2, 0).numpy()
    out = np.empty_like(d)
    prev = 0
    for t in range(d.shape[0] - 1, -1, -1):
        prev = out[t] = d[t] + prev * c[t]
    advantage = torch.from_numpy(out).movedim(0, -2).contiguous()
    return advantage, advantage + value
