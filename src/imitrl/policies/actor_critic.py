"""`ActorCritic`: a policy head and a value head, each with its own optimizer.

The policy is a TorchRL actor reading ``OBSERVATION`` and writing ``ACTION``
(``ProbabilisticActor`` for the categorical and tanh-normal heads, a plain
``TensorDictModule`` for the deterministic head); the value is a ``ValueOperator``
writing ``STATE_VALUE``. Behaviour cloning trains only the policy; the value head
and its optimizer are carried so that an actor-critic method needs no new class.

Heads:

============== ================================= ===================================
head           policy                            losses it supports
============== ================================= ===================================
categorical    logits -> ``GreedyCategorical``   ``nll`` (cross-entropy)
tanh_normal    loc, scale -> ``TanhNormal``      ``nll``
               within the action bounds
deterministic  ``tanh`` squashed into the bounds ``mse``, ``l1``, ``smooth_l1``
============== ================================= ===================================

Every method takes tensors, numpy arrays or Python scalars. Tensors in give tensors
out (``log_prob`` and ``values`` keep the autograd graph); numpy or scalar inputs
give numpy or Python values out, computed without gradients.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.data import Bounded
from torchrl.data import Categorical as CategoricalSpec
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor, TanhNormal

from imitrl import keys
from imitrl.policies.distributions import GreedyCategorical
from imitrl.policies.modules import Module, Value
from imitrl.rng import rng_from

__all__ = ["HEADS", "HEAD_LOSSES", "ActorCritic"]

HEADS = ("categorical", "tanh_normal", "deterministic")
HEAD_LOSSES = {
    "categorical": ("nll",),
    "tanh_normal": ("nll",),
    "deterministic": ("mse", "l1", "smooth_l1"),
}
"""the ``BehaviorCloningLoss`` types each head can be fitted with (the table above)"""


class _Squash(nn.Module):
    """``low + (high - low) * (tanh(x) + 1) / 2``: a deterministic action inside the bounds."""

    def __init__(self, low: torch.Tensor, high: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("low", low.clone().float())
        self.register_buffer("high", high.clone().float())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.low + (self.high - self.low) * (torch.tanh(x) + 1) / 2


def _mlp(sizes: Sequence[int], activation: type[nn.Module]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(itertools.pairwise(sizes)):
        layers.append(nn.Linear(a, b))
        if i < len(sizes) - 2:
            layers.append(activation())
    return nn.Sequential(*layers)


class ActorCritic(nn.Module):
    """A policy and a value function, each with its own Adam optimizer.

    Use :meth:`tabular` or :meth:`mlp` rather than the constructor.

    Args:
        policy: actor module, ``OBSERVATION -> ACTION`` (TensorDict in, TensorDict out).
        value: ``ValueOperator``, ``OBSERVATION -> STATE_VALUE``.
        head: one of :data:`HEADS`.
        lr: learning rate of both optimizers.
        num_states: number of states for integer observations, or None.
        observation_shape: trailing shape of vector observations, or None.
    """

    def __init__(
        self,
        policy: TensorDictModule,
        value: TensorDictModule,
        *,
        head: str,
        lr: float = 1e-2,
        num_states: int | None = None,
        observation_shape: Sequence[int] | None = None,
    ) -> None:
        super().__init__()
        if head not in HEADS:
            raise ValueError(f"head must be one of {HEADS}, got {head!r}")
        if (num_states is None) == (observation_shape is None):
            raise ValueError(
                "give exactly one of num_states (integer observations) or observation_shape"
            )
        self.policy, self.value, self.head = policy, value, head
        self.num_states = num_states
        self.observation_shape = None if observation_shape is None else tuple(observation_shape)
        self.lr = float(lr)
        self.opt_pi = torch.optim.Adam(policy.parameters(), lr=lr)
        self.opt_v = torch.optim.Adam(value.parameters(), lr=lr)

    # ------------------------------------------------------------ constructors
    @classmethod
    def tabular(cls, num_states: int, num_actions: int, *, lr: float = 0.1) -> ActorCritic:
        """One preference ``theta[s, a]`` per pair: zero-initialised embedding tables.

        At initialisation the policy is exactly uniform and every value is 0.
        """
        if num_states < 1 or num_actions < 1:
            raise ValueError(
                f"need at least one state and one action, got {num_states}, {num_actions}"
            )
        logits_table, value_table = (
            nn.Embedding(num_states, num_actions),
            nn.Embedding(num_states, 1),
        )
        nn.init.zeros_(logits_table.weight)
        nn.init.zeros_(value_table.weight)
        policy = ProbabilisticActor(
            Module(logits_table, in_keys=[keys.OBSERVATION], out_keys=[keys.LOGITS]),
            in_keys=[keys.LOGITS],
            out_keys=[keys.ACTION],
            distribution_class=GreedyCategorical,
            spec=CategoricalSpec(num_actions, dtype=torch.int64),
        )
        value = Value(value_table, in_keys=[keys.OBSERVATION])
        return cls(policy, value, head="categorical", lr=lr, num_states=num_states)

    @classmethod
    def mlp(
        cls,
        observation_dim: int,
        action: int | Bounded,
        *,
        head: str | None = None,
        hidden: Sequence[int] = (64, 64),
        activation: type[nn.Module] = nn.Tanh,
        lr: float = 1e-3,
        seed: int = 0,
    ) -> ActorCritic:
        """MLP policy and value for vector observations ``[..., observation_dim]``.

        Args:
            observation_dim: length of the observation vector.
            action: number of discrete actions, or a ``Bounded`` spec of a continuous
                action (its ``low``/``high`` bound the action).
            head: ``"categorical"`` (default for discrete), ``"tanh_normal"`` (default
                for continuous) or ``"deterministic"``.
            hidden: hidden layer sizes.
            activation: hidden activation.
            lr: learning rate of both optimizers.
            seed: initialisation seed (the global RNG is left untouched).
        """
        if isinstance(action, (int, np.integer)):
            head = head or "categorical"
            if head != "categorical":
                raise ValueError(f"a discrete action space needs head='categorical', got {head!r}")
        elif isinstance(action, Bounded):
            if len(action.shape) != 1:
                raise ValueError(
                    f"a continuous action spec must have shape [action_dim], got {tuple(action.shape)} "
                    "(for a batched env pass env.action_spec_unbatched)"
                )
            head = head or "tanh_normal"
            if head not in ("tanh_normal", "deterministic"):
                raise ValueError(
                    f"a continuous action needs head 'tanh_normal' or 'deterministic', got {head!r}"
                )
        else:
            raise ValueError(
                f"action must be an int (number of actions) or a torchrl Bounded spec, got {action!r}"
            )
        sizes = [int(observation_dim), *[int(h) for h in hidden]]
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            if head == "categorical":
                net = _mlp([*sizes, int(action)], activation)
                policy = ProbabilisticActor(
                    Module(net, in_keys=[keys.OBSERVATION], out_keys=[keys.LOGITS]),
                    in_keys=[keys.LOGITS],
                    out_keys=[keys.ACTION],
                    distribution_class=GreedyCategorical,
                    spec=CategoricalSpec(int(action), dtype=torch.int64),
                )
            else:
                low, high = action.space.low.float(), action.space.high.float()
                (dim,) = action.shape[-1:]
                if head == "tanh_normal":
                    net = nn.Sequential(_mlp([*sizes, 2 * dim], activation), NormalParamExtractor())
                    policy = ProbabilisticActor(
                        Module(net, in_keys=[keys.OBSERVATION], out_keys=[keys.LOC, keys.SCALE]),
                        in_keys=[keys.LOC, keys.SCALE],
                        out_keys=[keys.ACTION],
                        distribution_class=TanhNormal,
                        distribution_kwargs={"low": low, "high": high},
                        spec=action,
                    )
                else:
                    net = nn.Sequential(_mlp([*sizes, dim], activation), _Squash(low, high))
                    policy = Module(net, in_keys=[keys.OBSERVATION], out_keys=[keys.ACTION])
            value = Value(_mlp([*sizes, 1], activation), in_keys=[keys.OBSERVATION])
        return cls(policy, value, head=head, lr=lr, observation_shape=(int(observation_dim),))

    def reset_optimizers(self, lr: float | None = None) -> None:
        """Fresh Adam states (and optionally a new learning rate) for both heads."""
        self.lr = self.lr if lr is None else float(lr)
        self.opt_pi = torch.optim.Adam(self.policy.parameters(), lr=self.lr)
        self.opt_v = torch.optim.Adam(self.value.parameters(), lr=self.lr)

    # ------------------------------------------------------------- TensorDict
    def forward(self, tensordict: TensorDict) -> TensorDict:
        """Run the policy on a tensordict (writes ``ACTION``)."""
        return self.policy(tensordict)

    def get_dist(self, tensordict: TensorDict) -> torch.distributions.Distribution:
        """The action distribution at the tensordict's observations (probabilistic heads)."""
        if self.head == "deterministic":
            raise ValueError(
                "a deterministic head has no action distribution (use loss mse/l1/smooth_l1)"
            )
        return self.policy.get_dist(tensordict)

    def check_observations(self, obs: torch.Tensor) -> None:
        """Raise ``ValueError`` unless ``obs`` fits this policy (integer states in range, or
        vectors of its trailing shape, no NaN)."""
        self._obs(obs)

    # --------------------------------------------------------- array boundary
    def _obs(self, obs: Any) -> tuple[torch.Tensor, str]:
        """Observation tensor and the kind of the input (``tensor``, ``numpy``, ``scalar``)."""
        if isinstance(obs, torch.Tensor):
            kind, t = "tensor", obs
        elif isinstance(obs, np.ndarray):
            kind, t = "numpy", torch.from_numpy(obs)
        elif isinstance(obs, (int, float, np.integer, np.floating, list, tuple)):
            kind, t = ("scalar" if np.ndim(obs) == 0 else "numpy"), torch.as_tensor(np.asarray(obs))
        else:
            raise ValueError(
                f"observations must be a tensor, numpy array or number, got {type(obs).__name__}"
            )
        if self.num_states is not None:
            if t.dtype.is_floating_point or t.dtype == torch.bool:
                raise ValueError(
                    f"this policy expects integer state observations, got dtype {t.dtype}"
                )
            t = t.long()
            if t.numel() and (int(t.min()) < 0 or int(t.max()) >= self.num_states):
                raise ValueError(f"state observation outside [0, {self.num_states})")
        else:
            if t.shape[-1:] != self.observation_shape[-1:]:
                raise ValueError(
                    f"this policy expects observations of trailing shape {self.observation_shape}, "
                    f"got shape {tuple(t.shape)}"
                )
            t = t.to(torch.float32)
            if torch.isnan(t).any():
                raise ValueError("NaN in observations given to the policy")
        return t, kind

    def _batch_shape(self, obs: torch.Tensor) -> torch.Size:
        return obs.shape if self.num_states is not None else obs.shape[:-1]

    def _td(self, obs: torch.Tensor) -> TensorDict:
        return TensorDict({keys.OBSERVATION: obs}, batch_size=self._batch_shape(obs))

    @staticmethod
    def _out(x: torch.Tensor, kind: str) -> Any:
        if kind == "tensor":
            return x
        x = x.detach().cpu().numpy()
        return x.item() if kind == "scalar" and x.ndim == 0 else x

    def act(self, obs: Any, generator: torch.Generator | None = None) -> Any:
        """Sample ``a ~ pi(.|s)`` (``generator`` makes the draw reproducible)."""
        t, kind = self._obs(obs)
        with torch.no_grad():
            if self.head == "deterministic":
                return self._out(self.policy(self._td(t)).get(keys.ACTION), kind)
            dist = self.policy.get_dist(self._td(t))
            with rng_from(generator):
                a = dist.sample()
        return self._out(a, kind)

    def act_greedy(self, obs: Any) -> Any:
        """The deterministic action: argmax of the logits (ties to the lowest), or the mode."""
        t, kind = self._obs(obs)
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            a = self.policy(self._td(t)).get(keys.ACTION)
        return self._out(a, kind)

    def log_prob(self, obs: Any, act: Any) -> Any:
        """``log pi(a|s)`` for a batch of states and the actions taken there."""
        t, kind = self._obs(obs)
        a = act if isinstance(act, torch.Tensor) else torch.as_tensor(np.asarray(act))
        if self.head == "categorical":
            if a.dtype.is_floating_point:
                raise ValueError(f"categorical actions must be integers, got dtype {a.dtype}")
            a = a.long()
            n = int(self.policy.spec[keys.ACTION].space.n)
            if a.numel() and (int(a.min()) < 0 or int(a.max()) >= n):
                raise ValueError(f"categorical actions must lie in [0, {n})")
        elif not torch.isfinite(a).all():
            raise ValueError("actions contain NaN or inf")
        grad = kind == "tensor"
        with torch.set_grad_enabled(grad and torch.is_grad_enabled()):
            lp = self.get_dist(self._td(t)).log_prob(a)
        return self._out(lp, kind)

    def probs(self, obs: Any) -> Any:
        """``pi(.|s)`` of a categorical head, ``[..., A]``."""
        if self.head != "categorical":
            raise ValueError("probs() is defined for the categorical head only")
        t, kind = self._obs(obs)
        with torch.set_grad_enabled(kind == "tensor" and torch.is_grad_enabled()):
            p = self.get_dist(self._td(t)).probs
        return self._out(p, kind)

    def values(self, obs: Any) -> Any:
        """``V(s)`` from the value head, with the trailing singleton removed."""
        t, kind = self._obs(obs)
        with torch.set_grad_enabled(kind == "tensor" and torch.is_grad_enabled()):
            v = self.value(self._td(t)).get(keys.STATE_VALUE).squeeze(-1)
        return self._out(v, kind)

    def greedy_table(self) -> torch.Tensor:
        """``[S]`` greedy action of every state (integer observations only)."""
        if self.num_states is None:
            raise ValueError("greedy_table() needs integer state observations")
        return self.act_greedy(torch.arange(self.num_states))

    def extra_repr(self) -> str:
        space = (
            f"num_states={self.num_states}"
            if self.num_states is not None
            else f"observation_shape={self.observation_shape}"
        )
        return f"head={self.head!r}, {space}, lr={self.lr}"


PolicyFactory = Callable[[], ActorCritic]
