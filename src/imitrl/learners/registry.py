"""The loss registry: one entry per imitation objective, name -> (policy head, loss module).

An entry says, for a task's observation and action spaces, how to build the policy
that is trained and the TorchRL ``LossModule`` that trains it. Everything that
compares objectives (``benchmarks/loss_functions.py``, your own study) builds
learners through :func:`build` and trains them with
``fit_bc(learner, rows, config)`` (a :class:`~imitrl.learners.Learner` carries its
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
from dataclasses import dataclass, fields, replace
from typing import Any

from imitrl.learners.defaults import HIDDEN, learning_rate
from imitrl.learners.learner import Learner
from imitrl.learners.task import ACTION_KINDS, TaskSpec

DEFAULT = "default"
"""the name that resolves to an entry for the task (:func:`imitrl.learners.build.resolve`),
which no entry may take"""

__all__ = [
    "DEFAULT",
    "LearnerConfig",
    "LossEntry",
    "entries",
    "fit_config",
    "get",
    "make",
    "names",
    "register",
    "unregister",
]


@dataclass(frozen=True)
class LearnerConfig:
    """What :func:`imitrl.learners.build` hands an entry's builder: the settings every
    entry shares (so that objectives are compared at equal capacity), and the entry's own
    (``options``)."""

    hidden: tuple[int, ...] | None = None
    """hidden layers of MLP policies (and of the diffusion and flow networks); None: the
    network's default (:data:`~imitrl.learners.defaults.HIDDEN`). An entry whose network
    has no hidden layers (a logits table, ACT's transformer, Diffusion Policy's U-Net)
    refuses a given one"""
    lr: float | None = None
    """Adam learning rate of the policy; None: the network's default (a logits table 0.1,
    any other network 1e-3: :mod:`imitrl.learners.defaults`). An entry with ``own_lr``
    (ACT, diffusion_unet) trains at its recipe's and refuses another. The registry
    resolves it, so an entry's builder always reads a number"""
    seed: int = 0
    """initialisation seed (and the seed of any sampling the learner does)"""
    normalize: bool = True
    """MLP learners: normalise observations by the demonstrations' statistics"""
    device: str | None = None
    """where the learner computes: None (the CPU), ``"auto"``, ``"cpu"``, ``"cuda:N"``
    (:func:`~imitrl.system.device.resolve_device`); every entry is built on the CPU with
    its seed, then moved, so every device starts from the same weights"""
    value: bool = False
    """a value head beside the policy (GAIL's and AIRL's PPO generator need one): only the
    table, MLP and CNN entries (:class:`~imitrl.learners.ActorCritic`) build one"""
    options: Any = None
    """the entry's own settings (``LossEntry.options``' type: ``for_env``'s head and
    convolutions, Diffusion Policy's U-Net); None: the entry's defaults"""

    @property
    def width(self) -> tuple[int, ...]:
        """``hidden``, or the default widths when it is None."""
        return HIDDEN if self.hidden is None else self.hidden


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
    default: :func:`imitrl.learners.defaults.learning_rate`). :func:`make` refuses a rate
    such an entry would not use"""
    options: Any = None
    """the entry's own settings, a frozen dataclass with its defaults (None: it has none);
    ``build(name, env, field=value)`` replaces a field, ``build(..., options=...)`` all"""
    hidden: bool = True
    """whether ``LearnerConfig.hidden`` shapes its network (False: a given one is refused)"""
    value: bool = False
    """whether it builds a value head when ``LearnerConfig.value`` asks for one"""
    tables: bool = True
    """whether it builds a logits table on integer states, which trains at a table's
    default rate (False: ``for_env``'s one-hot MLP, at a network's)"""
    pixels: bool = False
    """whether it reads an env's image beside the state (``diffusion_unet``'s camera
    encoder); the other entries apply to envs without images only"""

    def applies_to(self, task: TaskSpec) -> bool:
        """Whether this objective can train a policy for ``task``."""
        if self.actions == "any":
            return True
        return (
            (task.observes if self.pixels else task.described)
            and task.actions == self.actions
            and all(getattr(task, name) is not None for name in self.requires)
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
    options: Any = None,
    hidden: bool = True,
    value: bool = False,
    tables: bool = True,
    pixels: bool = False,
) -> Callable[[Callable[[TaskSpec, LearnerConfig], Learner]], Callable]:
    """Decorator: register ``build(task, config) -> Learner`` under ``name``
    (``horizon``: the chunk length of a chunked learner; ``batch_size``: the minibatch of
    its recipe; see :class:`LossEntry`).

    Raises:
        ValueError: the name is taken, ``actions`` is not one of :data:`ACTION_KINDS`,
            or ``requires`` names a field ``TaskSpec`` does not have.
    """
    if actions not in (*ACTION_KINDS, "any"):
        raise ValueError(f"actions must be one of {(*ACTION_KINDS, 'any')}, got {actions!r}")
    unknown = set(requires) - _TASK_FIELDS
    if unknown:
        raise ValueError(f"requires names unknown TaskSpec fields {sorted(unknown)}")
    if not isinstance(name, str) or not name or any(c.isspace() for c in name):
        raise ValueError(f"a loss needs a name without spaces, got {name!r}")
    if name == DEFAULT:
        raise ValueError(f"{DEFAULT!r} names the entry build chooses for a task: pick another")
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
            own_lr, options, hidden, value, tables, pixels,
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


def make(name: str, task: TaskSpec, config: LearnerConfig) -> Learner:
    """Entry ``name``'s learner for ``task`` as ``config`` says, on ``config.device``;
    what :func:`imitrl.learners.build` calls once it has resolved the name and the
    settings. ValueError, naming the entry, when it does not apply to ``task``, or
    ``config`` asks for what it does not have (a rate besides its recipe's, hidden layers,
    a value head)."""
    entry = get(name)
    if not entry.applies_to(task):
        missing = [r for r in entry.requires if getattr(task, r) is None]
        if missing:
            why = f"it needs {', '.join(missing)}"
        elif not task.described:
            why = "its observations or actions are not integer states or vectors with "
            why += "discrete or Bounded actions (images: loss for_env builds a CNN)"
        else:
            why = f"it is for {entry.actions} actions"
        raise ValueError(f"loss {name!r} does not apply to this task: {why}")
    if config.value and not entry.value:
        raise ValueError(
            f"loss {name} builds no value head: GAIL and AIRL need one (take default, "
            "cross_entropy, gaussian_nll or for_env)"
        )
    if config.lr is not None and entry.own_lr is not None and config.lr != entry.own_lr:
        raise ValueError(
            f"loss {name} trains at its recipe's learning rate {entry.own_lr:g}, not lr "
            f"{config.lr:g}: leave lr out"
        )
    if config.hidden is not None and not entry.hidden:
        raise ValueError(f"loss {name} has no hidden layers to set: leave hidden out")
    states = task.num_states if entry.tables else None
    config = replace(config, lr=learning_rate(entry.own_lr, states, config.lr))
    learner = entry.build(task, config)
    if not isinstance(learner, Learner):
        raise ValueError(f"loss {name!r} built a {type(learner).__name__}, expected a Learner")
    if not _horizon_kept(entry.horizon, learner.horizon, config.options is not None):
        raise ValueError(
            f"loss {name!r} is registered with horizon {entry.horizon} but built a learner "
            f"of horizon {learner.horizon}: register it with the horizon its learner predicts"
        )
    return learner.placed(config.device)


def _horizon_kept(declared: int | None, built: int | None, options: bool) -> bool:
    """Whether a learner of chunk horizon ``built`` is what an entry declaring
    ``declared`` may build: the same horizon, or (``options`` given: a chunk length is one
    of Diffusion Policy's settings) another chunk length, never a one-step learner for a
    chunked entry or the reverse (the CLI says whether a loss plays chunks by its entry)."""
    if options:
        return (declared is None) == (built is None)
    return declared == built


def fit_config(name: str, bc):
    """``bc`` (a :class:`~imitrl.algorithms.BCConfig`) as entry ``name``'s recipe trains:
    its own minibatch (``LossEntry.batch_size``) and schedule (``LossEntry.recipe``)."""
    entry = get(name)
    if entry.batch_size is not None and bc.batch_size is not None:
        bc = replace(bc, batch_size=entry.batch_size)
    return bc if entry.recipe is None else entry.recipe(bc)
