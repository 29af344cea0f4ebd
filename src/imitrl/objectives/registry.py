"""The loss registry: one entry per imitation objective, name -> (policy head, loss module).

An entry says, for a task's observation and action spaces, how to build the policy
that is trained and the TorchRL ``LossModule`` that trains it. Everything that
compares objectives (``benchmarks/loss_functions.py``, your own study) builds
learners through :func:`build` and trains them with
``fit_bc(learner, rows, config)`` (a :class:`~imitrl.policies.Learner` carries its
loss), so adding an objective is one registered function::

    @register("mse_wd", actions="continuous", summary="MSE with an L2 penalty 1e-3")
    def _(task: TaskSpec, config: LearnerConfig) -> Learner:
        ac = mlp(task, config, head="deterministic")
        loss = RegularizedBCLoss(ac.policy, loss_type="mse", l2_coef=1e-3)
        return Learner(ac.policy, loss, ac.opt_pi, normalizer=ac.normalizer)

Built-in entries:

====================== ========== ===================== =====================================
name                   actions    policy                loss
====================== ========== ===================== =====================================
cross_entropy          discrete   categorical           ``-log pi(a*|s)`` (BehaviorCloningLoss nll)
cross_entropy_entropy  discrete   categorical           cross-entropy - 0.01 H(pi(.|s))
advantage_weighted     discrete   categorical           ``-A(s, a*) log pi(a*|s)`` (needs ``task.advantage``)
gaussian_nll           continuous tanh-normal, free std ``-log pi(a*|s)``
mse                    continuous deterministic (tanh)  ``(mu(s) - a*)^2``
l1                     continuous deterministic (tanh)  ``|mu(s) - a*|``
smooth_l1              continuous deterministic (tanh)  Huber(1)
mse_l2                 continuous deterministic (tanh)  MSE + 1e-4 ||W||^2
diffusion              continuous DDPM (DiffusionActor) epsilon-prediction (DiffusionBCLoss), sampled
                                  MLP baseline
diffusion_ddim         continuous the same network      the same loss; sampled by DDIM in 8 steps
flow                   continuous rectified flow        conditional flow matching, 8 Euler steps
====================== ========== ===================== =====================================

``diffusion`` and ``diffusion_ddim`` are MLP baselines (an MLP score network on one
observation, as TorchRL's ``DiffusionActor``); Diffusion Policy as its paper builds it
is ``diffusion_unet`` (:mod:`imitrl.objectives.registry_chunks`).

Chunked entries (``*_chunk``: the learner predicts the expert's next ``H`` actions;
:mod:`imitrl.objectives.registry_chunks`) carry ``LossEntry.horizon``: their rows need
chunk labels (:func:`imitrl.data.chunks.add_chunk_labels`, which ``fit_bc`` adds:
``Learner.horizon``) and their envs ``is_init`` (:func:`imitrl.policies.chunking.chunk_env`);
``LossEntry.history`` says how many past observations a row must carry (``fit_bc`` adds
them too), and ``LossEntry.recipe`` the fit schedule of the loss's recipe
(:func:`fit_config`).

Integer observations (tabular tasks) get a table of logits (``ActorCritic.tabular``),
vector observations an MLP (``ActorCritic.mlp``). Each entry states how its policy
acts when evaluated (``Learner.exploration``): the greedy action or the mode for the
heads above, a sample for diffusion.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields, replace

import torch
from torchrl.data import Bounded
from torchrl.envs.utils import ExplorationType

from imitrl.objectives.advantage_weighted import Advantage, AdvantageWeightedLoss
from imitrl.objectives.base import ImitationLoss
from imitrl.objectives.defaults import learning_rate
from imitrl.objectives.diffusion import DiffusionBehaviorCloningLoss, DiffusionPolicy
from imitrl.objectives.flow import FlowMatchingLoss, FlowPolicy
from imitrl.objectives.regularized import RegularizedBCLoss
from imitrl.policies.actor_critic import ActorCritic
from imitrl.policies.learner import Learner

__all__ = [
    "ACTION_KINDS",
    "Learner",
    "LearnerConfig",
    "LossEntry",
    "TaskSpec",
    "build",
    "entries",
    "fit_config",
    "get",
    "mlp",
    "names",
    "register",
    "unregister",
]

ACTION_KINDS = ("discrete", "continuous")


@dataclass(frozen=True)
class TaskSpec:
    """What a loss entry may know about a task."""

    action: int | Bounded
    """number of discrete actions, or the ``Bounded`` spec ``[m]`` of a continuous action"""
    observation_dim: int | None = None
    """length of vector observations ``[..., d]`` (None for integer states)"""
    num_states: int | None = None
    """number of integer states ``0 .. S-1`` (None for vector observations)"""
    advantage: Advantage | None = field(default=None, compare=False)
    """optional ``A(observation, action) -> [N]`` for advantage-weighted losses"""

    def __post_init__(self) -> None:
        if (self.observation_dim is None) == (self.num_states is None):
            raise ValueError(
                "give exactly one of observation_dim (vectors) or num_states (integers)"
            )
        if isinstance(self.action, bool) or not isinstance(self.action, (int, Bounded)):
            raise ValueError(
                f"action must be a number of actions or a Bounded spec, got {self.action!r}"
            )
        if isinstance(self.action, Bounded) and len(self.action.shape) != 1:
            raise ValueError(
                f"a continuous action spec must have shape [m], got {tuple(self.action.shape)}"
            )

    @property
    def actions(self) -> str:
        """``"discrete"`` or ``"continuous"``."""
        return "discrete" if isinstance(self.action, int) else "continuous"


@dataclass(frozen=True)
class LearnerConfig:
    """Shared by every entry, so that objectives are compared at equal capacity."""

    hidden: tuple[int, ...] = (64, 64)
    """hidden layers of MLP policies (and of the diffusion score network)"""
    lr: float | None = None
    """Adam learning rate of the policy; None: the network's default (a logits table 0.1,
    any other network 1e-3: :mod:`imitrl.objectives.defaults`). Entries with ``own_lr``
    (ACT, diffusion_unet) keep their recipe's. :func:`build` resolves it, so an entry's
    builder always reads a number"""
    seed: int = 0
    """initialisation seed (and the seed of any sampling the learner does)"""
    normalize: bool = True
    """MLP learners: normalise observations by the demonstrations' statistics"""
    device: str | None = None
    """where the learner computes: None (the CPU), ``"auto"``, ``"cpu"``, ``"cuda:N"``
    (:func:`~imitrl.runtime.device.resolve_device`); every entry is built on the CPU with
    its seed, then moved, so every device starts from the same weights"""


@dataclass(frozen=True)
class LossEntry:
    """One registered objective."""

    name: str
    """registry key"""
    actions: str
    """``"discrete"`` or ``"continuous"``: the action spaces it applies to"""
    build: Callable[[TaskSpec, LearnerConfig], Learner]
    """``(task, config) -> Learner``"""
    summary: str
    """one line for tables and ``--help``"""
    requires: tuple[str, ...] = ()
    """``TaskSpec`` fields that must be set (e.g. ``("advantage",)``)"""
    horizon: int | None = None
    """``H`` of a chunked learner: its rows need ``add_chunk_labels(rows, H)`` and its envs
    ``chunk_env(env)``; None: one action per step"""
    batch_size: int | None = None
    """the minibatch the loss's recipe trains on, in place of a benchmark protocol's
    (ACT's transformer: small batches, as its paper); None: the protocol's"""
    history: int | None = None
    """observations a row must carry (``add_observation_history(rows, n)``, which
    ``fit_bc`` adds for the learner: ``Learner.history``); None: the current one"""
    recipe: Callable | None = None
    """``BCConfig -> BCConfig``: the fit schedule of the loss's recipe (Diffusion Policy's
    warm-up and cosine decay), applied by :func:`fit_config`; None: the caller's"""
    own_lr: float | None = None
    """the learning rate of the loss's recipe, which ``LearnerConfig.lr`` does not set
    (ACT's, Diffusion Policy's); None: the entry trains at ``LearnerConfig.lr`` (or its
    default: :func:`imitrl.objectives.defaults.learning_rate`). The CLI
    refuses an ``--lr`` such an entry would not use"""

    def applies_to(self, task: TaskSpec) -> bool:
        """Whether this objective can train a policy for ``task``."""
        return task.actions == self.actions and all(
            getattr(task, name) is not None for name in self.requires
        )


_REGISTRY: dict[str, LossEntry] = {}
_TASK_FIELDS = {f.name for f in fields(TaskSpec)}


def register(
    name: str,
    *,
    actions: str,
    summary: str,
    requires: Sequence[str] = (),
    horizon: int | None = None,
    batch_size: int | None = None,
    history: int | None = None,
    recipe: Callable | None = None,
    own_lr: float | None = None,
) -> Callable[[Callable[[TaskSpec, LearnerConfig], Learner]], Callable]:
    """Decorator: register ``build(task, config) -> Learner`` under ``name``
    (``horizon``: the chunk length of a chunked learner; ``batch_size``: the minibatch of
    its recipe; see :class:`LossEntry`).

    Raises:
        ValueError: the name is taken, ``actions`` is not one of :data:`ACTION_KINDS`,
            or ``requires`` names a field ``TaskSpec`` does not have.
    """
    if actions not in ACTION_KINDS:
        raise ValueError(f"actions must be one of {ACTION_KINDS}, got {actions!r}")
    unknown = set(requires) - _TASK_FIELDS
    if unknown:
        raise ValueError(f"requires names unknown TaskSpec fields {sorted(unknown)}")
    if not name or not isinstance(name, str):
        raise ValueError(f"a loss needs a non-empty string name, got {name!r}")
    if horizon is not None and (int(horizon) != horizon or horizon < 1):
        raise ValueError(f"horizon must be a positive integer or None, got {horizon!r}")
    if batch_size is not None and (int(batch_size) != batch_size or batch_size < 1):
        raise ValueError(f"batch_size must be a positive integer or None, got {batch_size!r}")
    if history is not None and (int(history) != history or history < 1):
        raise ValueError(f"history must be a positive integer or None, got {history!r}")

    def decorator(fn: Callable[[TaskSpec, LearnerConfig], Learner]) -> Callable:
        if name in _REGISTRY:
            raise ValueError(f"a loss named {name!r} is already registered")
        _REGISTRY[name] = LossEntry(
            name, actions, fn, summary, tuple(requires), horizon, batch_size, history, recipe,
            own_lr,
        )  # fmt: skip
        return fn

    return decorator


def unregister(name: str) -> None:
    """Remove an entry (for tests and interactive sessions)."""
    get(name)
    del _REGISTRY[name]


def get(name: str) -> LossEntry:
    """The entry registered under ``name`` (ValueError listing the names otherwise)."""
    if name not in _REGISTRY:
        raise ValueError(f"unknown loss {name!r}; registered: {', '.join(_REGISTRY)}")
    return _REGISTRY[name]


def entries() -> list[LossEntry]:
    """Every entry, in registration order."""
    return list(_REGISTRY.values())


def names(task: TaskSpec | None = None) -> list[str]:
    """Names of the entries that apply to ``task`` (all if None), in registration order."""
    return [e.name for e in _REGISTRY.values() if task is None or e.applies_to(task)]


def build(name: str, task: TaskSpec, config: LearnerConfig = LearnerConfig()) -> Learner:
    """Build entry ``name``'s learner for ``task`` (ValueError if it does not apply)."""
    entry = get(name)
    if not entry.applies_to(task):
        missing = [r for r in entry.requires if getattr(task, r) is None]
        why = f"it needs {', '.join(missing)}" if missing else f"it is for {entry.actions} actions"
        raise ValueError(f"loss {name!r} does not apply to this task: {why}")
    config = replace(config, lr=learning_rate(entry.own_lr, task.num_states, config.lr))
    learner = entry.build(task, config)
    if not isinstance(learner, Learner):
        raise ValueError(f"loss {name!r} built a {type(learner).__name__}, expected a Learner")
    return learner.placed(config.device)


def fit_config(name: str, bc):
    """``bc`` (a :class:`~imitrl.algorithms.BCConfig`) as entry ``name``'s recipe trains:
    its own minibatch (``LossEntry.batch_size``) and schedule (``LossEntry.recipe``)."""
    entry = get(name)
    if entry.batch_size is not None and bc.batch_size is not None:
        bc = replace(bc, batch_size=entry.batch_size)
    return bc if entry.recipe is None else entry.recipe(bc)


# ----------------------------------------------------------------- policy heads
def mlp(
    task: TaskSpec,
    config: LearnerConfig,
    *,
    head: str | None = None,
    loss: str | ImitationLoss | None = None,
) -> ActorCritic:
    """The task's standard learner: a logits table for integer states, else an MLP with
    ``head``, trained with ``loss`` (a loss type of the head, None = its default), at
    ``config.lr`` or the network's default rate (:mod:`imitrl.objectives.defaults`)."""
    lr = learning_rate(None, task.num_states, config.lr)
    if task.num_states is not None:
        if task.actions != "discrete" or head not in (None, "categorical"):
            raise ValueError("integer-state tasks support a categorical policy only")
        if loss not in (None, "nll"):
            raise ValueError("a tabular policy is built with its cross-entropy loss")
        return ActorCritic.tabular(task.num_states, task.action, lr=lr)
    return ActorCritic.mlp(
        task.observation_dim,
        task.action,
        head=head,
        loss=loss,
        hidden=config.hidden,
        lr=lr,
        seed=config.seed,
        normalize=config.normalize,
    )


def _with_loss(ac: ActorCritic, loss: ImitationLoss) -> ActorCritic:
    """``ac`` trained by ``loss`` (a loss over ``ac.policy``) instead of its default: every
    constructor argument carried over (a pixel learner's inputs, the action space)."""
    return ActorCritic(
        ac.policy,
        ac.value,
        head=ac.head,
        loss=loss,
        lr=ac.lr,
        num_states=ac.num_states,
        observation_shape=ac.observation_shape,
        normalizer=ac.normalizer,
        action=ac.action_space,
        pixel_inputs=ac.pixel_inputs,
    )


# ------------------------------------------------------------- built-in entries
ENTROPY_COEF = 0.01
"""weight of the entropy bonus of ``cross_entropy_entropy``"""
L2_COEF = 1e-4
"""weight of the L2 penalty of ``mse_l2``"""
DIFFUSION_STEPS = 50
"""denoising steps of ``diffusion`` (each action costs this many network calls)"""
DDIM_STEPS = 8
"""DDIM sampling steps of ``diffusion_ddim`` (of the ``DIFFUSION_STEPS`` it trains on)"""
FLOW_STEPS = 8
"""Euler steps of ``flow``"""


@register("cross_entropy", actions="discrete", summary="cross-entropy (categorical NLL)")
def _cross_entropy(task: TaskSpec, config: LearnerConfig) -> Learner:
    return mlp(task, config)


@register(
    "cross_entropy_entropy",
    actions="discrete",
    summary=f"cross-entropy - {ENTROPY_COEF} x policy entropy",
)
def _cross_entropy_entropy(task: TaskSpec, config: LearnerConfig) -> Learner:
    ac = mlp(task, config)
    return _with_loss(ac, RegularizedBCLoss(ac.policy, loss_type="nll", entropy_coef=ENTROPY_COEF))


@register(
    "advantage_weighted",
    actions="discrete",
    summary="advantage-weighted cross-entropy (policy_step's objective)",
    requires=("advantage",),
)
def _advantage_weighted(task: TaskSpec, config: LearnerConfig) -> Learner:
    ac = mlp(task, config)
    return _with_loss(ac, AdvantageWeightedLoss(ac.policy, task.advantage))


@register(
    "gaussian_nll",
    actions="continuous",
    summary="tanh-normal NLL with a learned state-independent log-std, acts with tanh(mean)",
)
def _gaussian_nll(task: TaskSpec, config: LearnerConfig) -> Learner:
    """The head chosen by a measured sweep (``benchmarks/README.md``, issue 31): on the
    loss benchmark's continuous tasks (5 seeds, BC / DAgger mean normalised score)
    ``tanh_normal_free`` 0.74 / 0.73, ``normal_free`` 0.63 / 0.68, the state-dependent
    ``tanh_normal`` this entry used before 0.25 / 0.17 and ``normal`` 0.22 / 0.15: a
    likelihood fit that may shrink its scale state by state chases the labels' noise.
    Labels on the bounds are refused, as by every tanh head (``normal_free`` takes them)."""
    return mlp(task, config, head="tanh_normal_free")


def _regression(loss_type: str) -> Callable[[TaskSpec, LearnerConfig], Learner]:
    def build_regression(task: TaskSpec, config: LearnerConfig) -> Learner:
        return mlp(task, config, head="deterministic", loss=loss_type)

    return build_regression


register("mse", actions="continuous", summary="mean squared error")(_regression("mse"))
register("l1", actions="continuous", summary="mean absolute error")(_regression("l1"))
register("smooth_l1", actions="continuous", summary="Huber loss (delta 1)")(
    _regression("smooth_l1")
)


@register("mse_l2", actions="continuous", summary=f"MSE + {L2_COEF} x squared L2 norm of weights")
def _mse_l2(task: TaskSpec, config: LearnerConfig) -> Learner:
    ac = mlp(task, config, head="deterministic")
    return _with_loss(ac, RegularizedBCLoss(ac.policy, loss_type="mse", l2_coef=L2_COEF))


@register(
    "diffusion",
    actions="continuous",
    summary=f"diffusion policy (DDPM, {DIFFUSION_STEPS} steps), samples its actions",
)
def _diffusion(task: TaskSpec, config: LearnerConfig) -> Learner:
    policy = diffusion_policy(task.observation_dim, task.action, config, sampler="ddpm")
    return Learner(
        policy,
        DiffusionBehaviorCloningLoss(policy, seed=config.seed),
        torch.optim.Adam(policy.parameters(), lr=config.lr),
        exploration=ExplorationType.RANDOM,
    )


@register(
    "diffusion_ddim",
    actions="continuous",
    summary=f"diffusion trained as DDPM ({DIFFUSION_STEPS} steps), sampled by DDIM in {DDIM_STEPS}",
)
def _diffusion_ddim(task: TaskSpec, config: LearnerConfig) -> Learner:
    policy = diffusion_policy(task.observation_dim, task.action, config, sampler="ddim")
    return Learner(
        policy,
        DiffusionBehaviorCloningLoss(policy, seed=config.seed),
        torch.optim.Adam(policy.parameters(), lr=config.lr),
        exploration=ExplorationType.RANDOM,
    )


@register(
    "flow",
    actions="continuous",
    summary=f"flow matching (rectified flow), {FLOW_STEPS} Euler steps, samples its actions",
)
def _flow(task: TaskSpec, config: LearnerConfig) -> Learner:
    policy = flow_policy(task.observation_dim, task.action, config)
    return Learner(
        policy,
        FlowMatchingLoss(policy, seed=config.seed),
        torch.optim.Adam(policy.parameters(), lr=config.lr),
        exploration=ExplorationType.RANDOM,
        normalizer=policy.normalizer,
    )


def diffusion_policy(
    observation_dim: int | None, action: Bounded, config: LearnerConfig, *, sampler: str
) -> DiffusionPolicy:
    """The registry's diffusion policy over ``action`` (a task's spec, or a tiled chunk spec)."""
    if observation_dim is None:
        raise ValueError("a diffusion policy needs vector observations")
    return DiffusionPolicy(
        observation_dim,
        action,
        hidden=config.hidden,
        num_steps=DIFFUSION_STEPS,
        seed=config.seed,
        sampler=sampler,
        sample_steps=DDIM_STEPS,
    )


def flow_policy(
    observation_dim: int | None,
    action: Bounded,
    config: LearnerConfig,
    *,
    num_steps: int = FLOW_STEPS,
) -> FlowPolicy:
    """The registry's flow policy over ``action`` (a task's spec, or a tiled chunk spec),
    sampled with ``num_steps`` Euler steps."""
    if observation_dim is None:
        raise ValueError("a flow policy needs vector observations")
    return FlowPolicy(
        observation_dim,
        action,
        hidden=config.hidden,
        num_steps=num_steps,
        normalize=config.normalize,
        seed=config.seed,
    )


import imitrl.objectives.registry_chunks  # noqa: E402, F401  (registers the *_chunk entries)
