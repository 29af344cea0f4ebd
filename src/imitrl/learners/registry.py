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
is ``diffusion_unet`` (:mod:`imitrl.learners.catalogue`).

Chunked entries (``*_chunk``: the learner predicts the expert's next ``H`` actions;
:mod:`imitrl.learners.catalogue`) carry ``LossEntry.horizon``: their rows need
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

from torchrl.data import Bounded

from imitrl.learners.defaults import learning_rate
from imitrl.learners.learner import Learner
from imitrl.objectives.advantage_weighted import Advantage

__all__ = [
    "ACTION_KINDS",
    "LearnerConfig",
    "LossEntry",
    "TaskSpec",
    "build",
    "entries",
    "fit_config",
    "get",
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
    any other network 1e-3: :mod:`imitrl.learners.defaults`). Entries with ``own_lr``
    (ACT, diffusion_unet) keep their recipe's. :func:`build` resolves it, so an entry's
    builder always reads a number"""
    seed: int = 0
    """initialisation seed (and the seed of any sampling the learner does)"""
    normalize: bool = True
    """MLP learners: normalise observations by the demonstrations' statistics"""
    device: str | None = None
    """where the learner computes: None (the CPU), ``"auto"``, ``"cpu"``, ``"cuda:N"``
    (:func:`~imitrl.system.device.resolve_device`); every entry is built on the CPU with
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
    default: :func:`imitrl.learners.defaults.learning_rate`). The CLI
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
