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
averaging, no auto-reset, no skip-existing, no ``steps_to_next_obs``), in about 2.2 ms
on Pendulum's 2048 rows:

* the value network called once on the same stacked observations (a batched linear
  layer gives the vmapped call's bits), or, where that gives the same bits, on each
  distinct observation once (:class:`DistinctRows`: a step's next observation is
  mostly the following step's observation: the 150 calls of a Pendulum GAIL run took
  0.44 s stacked, 0.34 s distinct, the network's forward about 1.9 -> 1.0 ms a call,
  one thread, load 0.6-0.8);
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

from imitrl.compat import forward_hooked, plain_module
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
        self.params = tuple(tuple(p.shape) for p in value.module.parameters())
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
        if forward_hooked(value):
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
            time_dim = _time_dim(self.gae, batch)
            value, next_value = self._values(obs, nxt, batch.ndim, time_dim)
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

    def _values(
        self, obs: torch.Tensor, nxt: torch.Tensor, batch_dims: int, time_dim: int
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The value at both ends of every step: the stacked call's, computed on the
        distinct observations where that gives its bits (:class:`DistinctRows`)."""
        rows = DistinctRows.of(obs, nxt, batch_dims, time_dim)
        if rows is None:
            both = self.net(torch.stack([obs, nxt], 0))
            return both[0], both[1]
        key = rows.signature(self.params)
        agrees = _DISTINCT_AGREES.get(key)
        if agrees:
            return rows.values(self.net(rows.inputs))
        both = self.net(torch.stack([obs, nxt], 0))
        if agrees is None:  # once per signature: the distinct call against the stacked one
            value, next_value = rows.values(self.net(rows.inputs))
            _DISTINCT_AGREES[key] = _same_bits(value, both[0]) and _same_bits(next_value, both[1])
        return both[0], both[1]


_DISTINCT_AGREES: dict[tuple, bool] = {}
"""per :meth:`DistinctRows.signature`: whether the value network on the distinct rows gave
the stacked call's bits (checked on the first batch of that signature)"""

_ROW_BLOCK = 64
"""the distinct rows are padded to a multiple of this many"""


def _bits(x: torch.Tensor) -> torch.Tensor:
    """``x``'s bit patterns as integers (float32/float64), ``x`` itself otherwise."""
    if x.dtype == torch.float32:
        return x.view(torch.int32)
    if x.dtype == torch.float64:
        return x.view(torch.int64)
    return x


def _same_bits(a: torch.Tensor, b: torch.Tensor) -> bool:
    return a.shape == b.shape and a.dtype == b.dtype and torch.equal(_bits(a), _bits(b))


class DistinctRows:
    """A round's observations once each: every row of ``obs``, then the next observations
    that are not the following step's observation (an episode's last step, the batch's
    last step), then zero rows up to a multiple of :data:`_ROW_BLOCK`.

    Within a lane, step ``t``'s next observation is step ``t + 1``'s observation unless
    the episode ended at ``t``: the stacked call ``net(stack([obs, next_obs]))`` evaluates
    almost every observation twice. This evaluates each once and gives back the stacked
    call's two tensors. Bits: a matrix product's row and an elementwise operation's
    element can round differently in a kernel's tail block, so a row's value can depend
    on the number of rows in the call; :class:`TensorGAE` compares the two calls on the
    first batch of each :meth:`signature` (shapes, dtype, device, threads) and uses the
    distinct call only where every value agreed to the bit. A next observation counts
    as the following step's only when its bits are equal (``-0.0`` is not ``0.0``).
    """

    def __init__(self, obs: torch.Tensor, nxt: torch.Tensor, carried: torch.Tensor) -> None:
        self.shape = obs.shape[:-1]
        features = obs.shape[-1]
        self.carried = carried  # [*B, T - 1]: next observation t is observation t + 1
        self.own = torch.cat([~carried, carried.new_ones(*carried.shape[:-1], 1)], -1)
        extra = nxt[self.own]  # [E, F], in the batch's order
        self.n_extra = extra.shape[0]
        n = obs[..., 0].numel() + self.n_extra
        pad = obs.new_zeros(-n % _ROW_BLOCK, features)
        self.inputs = torch.cat([obs.reshape(-1, features), extra, pad])

    @classmethod
    def of(
        cls, obs: torch.Tensor, nxt: torch.Tensor, batch_dims: int, time_dim: int
    ) -> DistinctRows | None:
        """The distinct rows of a ``[*B, T, F]`` float batch of vector observations whose
        time is its last batch dimension, or None (anything else: the stacked call)."""
        if not (
            time_dim == batch_dims - 1
            and obs.ndim == batch_dims + 1
            and obs.is_floating_point()
            and obs.shape == nxt.shape
            and obs.dtype == nxt.dtype
            and obs.shape[-2] >= 2
        ):
            return None
        carried = (_bits(nxt[..., :-1, :]) == _bits(obs[..., 1:, :])).all(-1)
        return cls(obs, nxt, carried)

    def signature(self, params: tuple) -> tuple:
        """What decides the kernels of the two calls: shapes, dtype, device, threads."""
        x = self.inputs
        return (params, tuple(self.shape), tuple(x.shape), x.dtype, x.device,
                torch.get_num_threads())  # fmt: skip

    def values(self, out: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(value, next_value)`` of the stacked call, from the values of :attr:`inputs`."""
        n = self.shape.numel()
        value = out[:n].reshape(*self.shape, *out.shape[1:])
        next_value = torch.empty_like(value)
        next_value[self.own] = out[n : n + self.n_extra]
        shifted = next_value[..., :-1, :]
        shifted[self.carried] = value[..., 1:, :][self.carried]
        return value, next_value


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
