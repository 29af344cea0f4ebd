"""`ActorCritic`: the section's container, a policy and (when a job needs one) a value head,
as a :class:`Learner`.

The policy is a TorchRL actor reading ``OBSERVATION`` and writing ``ACTION`` (see
:mod:`imitrl.policies.heads` for the heads and the losses each takes); the value, when
asked for (``value=True``: GAIL's and AIRL's PPO generator), is a ``ValueOperator``
writing ``STATE_VALUE`` with its own optimizer ``opt_v``. Behaviour cloning trains only
the policy (``opt_pi``, on the learner's ``loss``) and builds no value head.

The constructors :meth:`ActorCritic.tabular` (the section's zero-initialised table),
:meth:`ActorCritic.mlp` (any observation and action spec), :meth:`ActorCritic.pixels`
(a CNN over uint8 images under a pixel key, and optionally the state:
:mod:`imitrl.policies.pixel_learner` holds what it reads and builds) and
:meth:`ActorCritic.for_specs` (the specs of an env) are the registry's building blocks:
a learner is built by :func:`imitrl.learners.build`, which names them by entry
(``cross_entropy``, ``mse``, ``for_env``, ...). MLP learners normalise observations
with the demonstrations' mean and standard deviation by default
(:class:`~imitrl.policies.normalization.ObservationNormalizer`, inside the networks).

Every method takes tensors, numpy arrays or Python scalars. Tensors in give tensors
out (``log_prob`` and ``values`` keep the autograd graph); numpy or scalar inputs
give numpy or Python values out, computed without gradients.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, cast

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import Categorical as CategoricalSpec
from torchrl.data import Composite, TensorSpec
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor

from imitrl import keys
from imitrl.learners.defaults import HIDDEN, NETWORK_LR, PIXEL_CHANNELS, PIXEL_HIDDEN, TABLE_LR
from imitrl.learners.learner import Learner
from imitrl.objectives.base import ImitationLoss
from imitrl.objectives.bc import BehaviorCloningLoss
from imitrl.policies.distributions import GreedyCategorical
from imitrl.policies.heads import HEAD_LOSSES, HEADS, OneHotInput, build_head, check_head, mlp
from imitrl.policies.modules import Module, Value
from imitrl.policies.normalization import ObservationNormalizer
from imitrl.policies.observations import read_observations
from imitrl.policies.pixel_learner import PixelInputs, pixel_networks, spec_pixel_inputs
from imitrl.policies.specs import (
    ActionSpace,
    action_space,
    check_same_actions,
    observation_space,
)
from imitrl.rng import rng_from
from imitrl.system.device import to_device

if TYPE_CHECKING:
    from torch import distributions as D

__all__ = ["HEADS", "HEAD_LOSSES", "ActorCritic"]


def _loss(policy: TensorDictModule, head: str, loss: str | ImitationLoss | None) -> ImitationLoss:
    """The learner's loss: given, or a ``BehaviorCloningLoss`` of the head's (default) type."""
    if isinstance(loss, ImitationLoss):
        return loss
    loss_type = loss or HEAD_LOSSES[head][0]
    if loss_type not in HEAD_LOSSES[head]:
        raise ValueError(
            f"loss {loss_type!r} does not fit a {head!r} head; it is fitted with {HEAD_LOSSES[head]}"
        )
    return BehaviorCloningLoss(policy, loss_type=loss_type)


def _adam(module: nn.Module, lr: float) -> torch.optim.Adam:
    """Adam on ``module``'s parameters; with more than two tensors its multi-tensor update
    (``foreach``: the same arithmetic and bits on CPU, ~15% of a small MLP's step), else
    the per-tensor loop (faster for a table: measured 12% on one tensor)."""
    params = list(module.parameters())
    return torch.optim.Adam(params, lr=lr, foreach=len(params) > 2)


class ActorCritic(Learner):
    """A policy (and, when asked for, a value function), each with its own Adam optimizer,
    and the policy's loss.

    Build one with :func:`imitrl.learners.build` rather than the constructor.

    Args:
        policy: actor module, ``OBSERVATION -> ACTION`` (TensorDict in, TensorDict out).
        value: ``ValueOperator``, ``OBSERVATION -> STATE_VALUE``, or None (no value head).
        head: one of :data:`HEADS`.
        loss: a loss type of the head (:data:`HEAD_LOSSES`; None = its default) or an
            ``ImitationLoss`` over ``policy``.
        lr: learning rate of both optimizers.
        num_states: number of states for integer observations, or None.
        observation_shape: trailing shape of vector observations (the state a pixel
            learner reads beside its images), or None.
        normalizer: the observation normaliser inside both networks, or None.
        action: the action space the policy writes (checked against envs), or None.
        pixel_inputs: what a pixel learner reads (image key and shape, state shape), or None.
    """

    def __init__(
        self,
        policy: TensorDictModule,
        value: TensorDictModule | None,
        *,
        head: str,
        loss: str | ImitationLoss | None = None,
        lr: float = NETWORK_LR,
        num_states: int | None = None,
        observation_shape: Sequence[int] | None = None,
        normalizer: ObservationNormalizer | None = None,
        action: ActionSpace | None = None,
        pixel_inputs: PixelInputs | None = None,
    ) -> None:
        if head not in HEADS:
            raise ValueError(f"head must be one of {HEADS}, got {head!r}")
        if pixel_inputs is None and (num_states is None) == (observation_shape is None):
            raise ValueError(
                "give exactly one of num_states (integer observations) or observation_shape"
            )
        super().__init__(
            policy,
            _loss(policy, head, loss),
            _adam(policy, lr),
            normalizer=normalizer,
        )
        self.value, self.head = value, head
        self.num_states = num_states
        self.observation_shape = None if observation_shape is None else tuple(observation_shape)
        self.pixel_inputs = pixel_inputs
        self.lr = float(lr)
        self.opt_v = None if value is None else _adam(value, lr)
        self.action_space = action

    # ------------------------------------------------------------ constructors
    @classmethod
    def tabular(
        cls,
        num_states: int,
        num_actions: int,
        *,
        lr: float = TABLE_LR,
        value: bool = False,
        device: str | torch.device | None = None,
    ) -> ActorCritic:
        """One preference ``theta[s, a]`` per pair: zero-initialised embedding tables.

        At initialisation the policy is exactly uniform and every value is 0; the loss
        is the cross-entropy. ``value``: a value table beside it (zeros too);
        ``device``: where it computes (None: the CPU; see
        :meth:`~imitrl.learners.Learner.placed`).
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
        return cls(
            policy,
            Value(value_table, in_keys=[keys.OBSERVATION]) if value else None,
            head="categorical",
            lr=lr,
            num_states=num_states,
            action=action_space(num_actions),
        ).placed(device)

    @classmethod
    def mlp(
        cls,
        observation: int | TensorSpec,
        action: int | TensorSpec,
        *,
        head: str | None = None,
        loss: str | ImitationLoss | None = None,
        hidden: Sequence[int] = HIDDEN,
        activation: type[nn.Module] = nn.Tanh,
        lr: float = NETWORK_LR,
        seed: int = 0,
        normalize: bool = True,
        value: bool = False,
        device: str | torch.device | None = None,
    ) -> ActorCritic:
        """MLP policy (and, with ``value``, a value network) over any observation and
        action spec.

        Args:
            observation: width of vector observations, or the env's (unbatched)
                observation spec: ``Bounded``/``Unbounded`` ``[d]``, or ``Categorical``
                integer states (fed to the MLP one-hot).
            action: number of discrete actions, or the env's (unbatched) action spec:
                ``Categorical``, ``OneHot``, ``MultiCategorical``, ``Bounded`` or
                ``Unbounded`` (see :mod:`imitrl.policies.heads`).
            head: one of :data:`HEADS` that fits the action (None = its default:
                categorical, multi, or deterministic for continuous actions).
            loss: the head's loss type (None = its default) or an ``ImitationLoss``.
            hidden: hidden layer sizes.
            activation: hidden activation.
            lr: learning rate of both optimizers.
            seed: initialisation seed (the global RNG is left untouched).
            normalize: normalise vector observations by the demonstrations' mean and
                standard deviation (fitted at the first ``fit_bc``).
            value: build a value network beside the policy (its weights drawn after the
                policy's, so the policy is the same with or without it).
            device: where the learner computes (None: the CPU; ``"auto"``, ``"cuda:N"``:
                :func:`~imitrl.system.device.resolve_device`); initialised on the CPU
                with ``seed`` first, so every device starts from the same weights.
        """
        obs, space = observation_space(observation), action_space(action)
        head = check_head(space, head)
        if obs.kind == "states":
            assert obs.num_states is not None  # a "states" space has its count
            first: nn.Module = OneHotInput(obs.num_states)
            width, normalizer, shape = obs.num_states, None, None
        else:
            assert obs.shape is not None  # a "vector" space has its shape
            (width,) = obs.shape
            normalizer = ObservationNormalizer(obs.shape) if normalize else None
            first, shape = normalizer or nn.Identity(), obs.shape
        sizes = [int(width), *[int(h) for h in hidden]]
        body_width = sizes[-1]
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            trunk = [first, *mlp(sizes, activation), activation()] if hidden else [first]
            policy = build_head(trunk, body_width, space, head)
            critic = None
            if value:
                value_trunk = [first, *mlp(sizes, activation), activation()] if hidden else [first]
                critic = Value(
                    nn.Sequential(*value_trunk, nn.Linear(body_width, 1)),
                    in_keys=[keys.OBSERVATION],
                )
        return cls(
            policy,
            critic,
            head=head,
            loss=loss,
            lr=lr,
            num_states=obs.num_states,
            observation_shape=shape,
            normalizer=normalizer,
            action=space,
        ).placed(device)

    @classmethod
    def pixels(
        cls,
        pixels: Sequence[int] | TensorSpec,
        action: int | TensorSpec,
        *,
        state: int | TensorSpec | None = None,
        frames: int = 1,
        head: str | None = None,
        loss: str | ImitationLoss | None = None,
        channels: Sequence[int] = PIXEL_CHANNELS,
        kernels: Sequence[int] | None = None,
        strides: Sequence[int] | None = None,
        hidden: Sequence[int] = PIXEL_HIDDEN,
        activation: type[nn.Module] = nn.ReLU,
        lr: float = NETWORK_LR,
        seed: int = 0,
        normalize: bool = True,
        pixel_key: NestedKey = keys.PIXELS,
        value: bool = False,
        device: str | torch.device | None = None,
    ) -> ActorCritic:
        """CNN policy (and, with ``value``, a value network) over uint8 images ``[H, W, C * frames]`` under ``pixel_key``,
        any head (:mod:`imitrl.policies.encoders`: layout, scaling, conv defaults).

        ``pixels``: ``(H, W, C)`` of one frame or the env's unbatched uint8 pixel spec;
        ``pixel_key``: where the images are (``"pixels"``, or a nested camera key such
        as ``("pixels", "top")``), read by the policy, the value and the loss alike;
        ``state``: also read ``OBSERVATION`` (a width or a ``[d]`` spec; normalised when
        ``normalize``, concatenated to the CNN features), None: the image alone;
        ``frames``: frames stacked on the channel axis; ``channels``/``kernels``/
        ``strides``: the conv layers; ``hidden``: the MLP after them; ``activation``
        follows every layer; the rest (``device`` too) as in :meth:`mlp`.
        """
        net = pixel_networks(
            pixels, action, pixel_key=pixel_key, state=state, frames=frames, head=head,
            channels=channels, kernels=kernels, strides=strides, hidden=hidden,
            activation=activation, seed=seed, normalize=normalize, value=value,
        )  # fmt: skip
        return cls(
            net.policy, net.value, head=net.head, loss=loss, lr=lr, normalizer=net.normalizer,
            action=net.space, observation_shape=net.inputs.state_shape, pixel_inputs=net.inputs,
        ).placed(device)  # fmt: skip

    @classmethod
    def for_specs(
        cls,
        observation_spec: Composite,
        action_spec: TensorSpec,
        *,
        head: str | None = None,
        loss: str | ImitationLoss | None = None,
        hidden: Sequence[int] | None = None,
        activation: type[nn.Module] | None = None,
        lr: float = NETWORK_LR,
        seed: int = 0,
        normalize: bool = True,
        state: bool = False,
        channels: Sequence[int] = PIXEL_CHANNELS,
        pixel_key: NestedKey | None = None,
        value: bool = False,
        device: str | torch.device | None = None,
    ) -> ActorCritic:
        """:meth:`mlp` over an env's (unbatched) observation and action specs; :meth:`pixels`
        when the observations hold ``PIXELS`` or ``pixel_key`` names an image (reading the
        state beside it only when ``state``: by default the state is the privileged
        expert's). ``hidden``/``activation`` None: each builder's default; ``device``:
        where the learner computes."""
        if pixel_key is not None or keys.PIXELS in observation_spec.keys():
            pixels, state_spec, pixel_key = spec_pixel_inputs(
                observation_spec, pixel_key, state=state
            )
            return cls.pixels(
                pixels, action_spec, head=head, loss=loss, state=state_spec,
                channels=channels, hidden=PIXEL_HIDDEN if hidden is None else hidden,
                activation=activation or nn.ReLU, lr=lr, seed=seed, normalize=normalize,
                pixel_key=pixel_key, value=value, device=device,
            )  # fmt: skip
        if keys.OBSERVATION not in observation_spec.keys():
            raise ValueError(
                f"the env has no {keys.OBSERVATION!r} observation (keys "
                f"{list(observation_spec.keys())})"
            )
        return cls.mlp(
            observation_spec[keys.OBSERVATION],
            action_spec,
            head=head,
            loss=loss,
            hidden=HIDDEN if hidden is None else hidden,
            activation=activation or nn.Tanh,
            lr=lr,
            seed=seed,
            normalize=normalize,
            value=value,
            device=device,
        )

    def check_env(self, env: EnvBase) -> None:
        """Raise ``ValueError``, naming both, unless this learner reads the env's observations
        and writes actions of the env's kind and size (checked before any step)."""
        if self.pixel_inputs is not None:
            return self.pixel_inputs.check_env(env, self.action_space)
        obs_spec = env.observation_spec_unbatched.get(keys.OBSERVATION, None)
        if obs_spec is None:
            raise ValueError(f"the env has no {keys.OBSERVATION!r} observation for the learner")
        try:
            obs = observation_space(obs_spec)
        except ValueError as err:
            raise ValueError(f"the env's observations do not fit an imitrl learner: {err}") from err
        mine = f"{self.num_states} states" if self.num_states else f"shape {self.observation_shape}"
        theirs = f"{obs.num_states} states" if obs.num_states else f"shape {obs.shape}"
        if (obs.num_states, obs.shape) != (self.num_states, self.observation_shape):
            raise ValueError(f"the learner reads observations of {mine}; the env gives {theirs}")
        if self.action_space is not None:
            check_same_actions(self.action_space, action_space(env.action_spec_unbatched))

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        """``opt_pi`` (the policy's) and, with a value head, ``opt_v`` (its)."""
        if self.opt_v is None:
            return {"opt_pi": self.opt_pi}
        return {"opt_pi": self.opt_pi, "opt_v": self.opt_v}

    def migrated_state(self, states: dict[str, dict]) -> dict[str, dict]:
        """A checkpoint of imitrl up to d6e5639, when every ``ActorCritic`` carried a value
        head, holds ``value.*`` weights and ``opt_v``: a learner built without a value head
        (no job of it needs one) drops them; everything else loads as saved."""
        states = super().migrated_state(states)
        if self.value is not None:
            return states
        out = {k: v for k, v in states.items() if k != "opt_v"}
        if "learner" in out:
            out["learner"] = {k: v for k, v in out["learner"].items() if not k.startswith("value.")}
        return out

    @property
    def loss_type(self) -> str | None:
        """The ``BehaviorCloningLoss`` type of the learner's loss (None for another loss)."""
        return self.loss.loss_type if isinstance(self.loss, BehaviorCloningLoss) else None

    def get_dist(self, tensordict: TensorDict) -> torch.distributions.Distribution:
        """The action distribution at the tensordict's observations (probabilistic heads)."""
        if self.head == "deterministic":
            raise ValueError(
                "a deterministic head has no action distribution (use loss mse/l1/smooth_l1)"
            )
        return self.policy.get_dist(tensordict)

    @property
    def pixel_shape(self) -> tuple[int, int, int] | None:
        """``(H, W, C)`` of the images a pixel learner reads (None: not a pixel learner)."""
        return None if self.pixel_inputs is None else self.pixel_inputs.shape

    @property
    def pixel_key(self) -> NestedKey | None:
        """The key of the images a pixel learner reads (None: not a pixel learner)."""
        return None if self.pixel_inputs is None else self.pixel_inputs.key

    def check_observations(self, obs: Any) -> None:
        """Raise ``ValueError`` unless ``obs`` fits this policy (integer states in range, or
        vectors of its trailing shape, no NaN; a pixel learner's: a TensorDict or dict with
        uint8 images of its shape under its pixel key, and the state when it reads it)."""
        self._obs(obs)

    def prepare(self, rows: TensorDictBase) -> None:
        """:meth:`Learner.prepare`; a pixel learner checks the rows' images (and the state,
        only when it reads it: rows of images alone are fine) first."""
        if self.pixel_inputs is None:
            return super().prepare(rows)
        self.check_observations(rows.select(*self.pixel_inputs.in_keys, strict=False))
        if self.normalizer is not None and not self.normalizer.is_fitted:
            self.normalizer.fit(rows.get(keys.OBSERVATION).reshape(-1, *self.normalizer.shape))

    # --------------------------------------------------------- array boundary
    def _obs(self, obs: Any) -> tuple[torch.Tensor | TensorDict, str]:
        """Observation tensor and the kind of the input (``tensor``, ``numpy``, ``scalar``);
        for a pixel learner a TensorDict of what it reads (:meth:`PixelInputs.read`)."""
        if self.pixel_inputs is not None:
            return self.pixel_inputs.read(obs)
        return read_observations(obs, num_states=self.num_states, shape=self.observation_shape)

    def _batch_shape(self, obs: torch.Tensor) -> torch.Size:
        return obs.shape if self.num_states is not None else obs.shape[:-1]

    def _td(self, obs: torch.Tensor | TensorDict) -> TensorDict:
        """The policy's input on the learner's device (outputs come back through
        :meth:`_out`, on the CPU for numpy and scalars, on the learner's device as tensors)."""
        if not isinstance(obs, TensorDict):
            obs = TensorDict({keys.OBSERVATION: obs}, batch_size=self._batch_shape(obs))
        return to_device(obs, self.device)

    @staticmethod
    def _out(x: torch.Tensor, kind: str) -> Any:
        if kind == "tensor":
            return x
        arr = x.detach().cpu().numpy()
        return arr.item() if kind == "scalar" and arr.ndim == 0 else arr

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
            # get_dist gives a Distribution; a categorical head's is a (one-hot) Categorical
            dist = cast("D.Categorical | D.OneHotCategorical", self.get_dist(self._td(t)))
            p = dist.probs
        return self._out(p, kind)

    def values(self, obs: Any) -> Any:
        """``V(s)`` from the value head, with the trailing singleton removed (ValueError
        for a learner built without one)."""
        if self.value is None:
            raise ValueError("this learner has no value head (build it with value=True)")
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
        if self.pixel_inputs is not None:
            space = f"pixel_key={self.pixel_key!r}, pixel_shape={self.pixel_shape}, {space}"
        return f"head={self.head!r}, {space}, lr={self.lr}"
