"""The one way to build a learner: :func:`build` ``(name, env, **settings) -> Learner``.

The command line (``--loss``, ``--hidden``, ``--lr``, ``--seed``, ``--device``), the
benchmarks, the FrozenLake study and your own scripts all build their learners here, so
the same name and settings give the same learner, parameter for parameter::

    from imitrl.learners import build

    learner = build("default", env)                  # what `imitrl bc --env ...` trains
    learner = build("mse", env, hidden=(256, 256), seed=3)
    learner = build("for_env", env, head="deterministic", loss="l1")   # for_env's options
    learner = build("diffusion_unet", env, options=UnetDiffusionConfig())  # paper widths
    learner = build("gaussian_nll", env, value=True)  # with a value head (GAIL, AIRL)

``name`` is a registry entry (:func:`imitrl.learners.registry.names`) or ``"default"``,
which names one for the task (:func:`resolve`). ``env`` is a TorchRL env, whose specs are
read (:meth:`TaskSpec.from_env`), or a :class:`TaskSpec` written by hand. ``settings``
are :class:`~imitrl.learners.registry.LearnerConfig`'s fields (``hidden``, ``lr``,
``seed``, ``normalize``, ``device``, ``value``) and the fields of the entry's own options
(``LossEntry.options``: ``for_env``'s head and convolutions, Diffusion Policy's
U-Net); a setting the entry does not have is refused, naming the ones it has.
"""

from __future__ import annotations

import math
import numbers
import warnings
from collections.abc import Mapping
from dataclasses import fields, is_dataclass, replace
from typing import Any

import torch
from torchrl.envs import EnvBase

from imitrl import checks
from imitrl.learners.defaults import default_loss
from imitrl.learners.learner import Learner
from imitrl.learners.registry import DEFAULT, LearnerConfig, get, make
from imitrl.learners.task import IgnoredObservationWarning, TaskSpec
from imitrl.limits import MAX_SEED, check_hidden

__all__ = ["DEFAULT", "FOR_ENV", "build", "resolve"]

FOR_ENV = "for_env"
"""the entry that builds for any env: what ``default`` names where no other entry can"""

_SETTINGS = tuple(f.name for f in fields(LearnerConfig) if f.name != "options")


def resolve(name: str, task: TaskSpec, *, value: bool = False) -> str:
    """``name``, or for ``"default"`` the entry for ``task``'s actions
    (:func:`~imitrl.learners.defaults.default_loss`: ``cross_entropy`` for discrete ones,
    ``mse`` for continuous ones, ``gaussian_nll`` where a value head is asked for: a job
    that needs ``log pi``), or ``for_env`` where the task is not integer states or
    vectors with discrete or ``Bounded`` actions (images; multi-discrete, one-hot or
    unbounded actions)."""
    if name != DEFAULT:
        return name
    if not task.described:
        return FOR_ENV
    return default_loss(task.actions, probabilistic=value)


def build(
    name: str,
    env: EnvBase | TaskSpec,
    *,
    options: Any = None,
    shared: Mapping[str, Any] | None = None,
    **settings: Any,
) -> Learner:
    """The learner of entry ``name`` (or ``"default"``) for ``env``, as ``settings`` say
    (module docstring). The same call gives the same parameters, bit for bit.

    ``shared``: settings a comparison gives every entry, each applied where the entry has
    it (``lr`` unless the entry trains at its recipe's rate, ``hidden`` unless its network
    has no hidden layers: a table, ACT, Diffusion Policy), as the loss benchmark does;
    ``settings`` must all apply.

    Raises:
        ValueError: ``env`` neither a TorchRL env nor a TaskSpec; an unknown name; an
            entry that does not apply to the env; a setting the entry does not have, or
            one it refuses (a rate besides its recipe's, hidden layers of a table, a value
            head it cannot build).
    """
    if not isinstance(env, TaskSpec | EnvBase):
        raise ValueError(
            f"build needs a TorchRL env (imitrl.envs.make_env(id, seed=...), or a gymnasium "
            f"env wrapped in torchrl.envs.GymWrapper) or a TaskSpec, got {type(env).__name__}"
        )
    task = env if isinstance(env, TaskSpec) else TaskSpec.from_env(env)
    _check_settings({k: v for k, v in {**(shared or {}), **settings}.items() if k in _SETTINGS})
    name = resolve(name, task, value=bool(settings.get("value", False)))
    entry = get(name)
    if shared:
        taken = dict(shared)
        if entry.own_lr is not None:
            taken.pop("lr", None)
        if not entry.hidden or (entry.tables and task.num_states is not None):
            taken.pop("hidden", None)
        settings = {**taken, **settings}
    _check_options(name, options, entry.options)
    own = {k: v for k, v in settings.items() if k not in _SETTINGS}
    if own:
        base = options if options is not None else entry.options
        allowed = [f.name for f in fields(base)] if is_dataclass(base) else []
        unknown = sorted(set(own) - set(allowed))
        if unknown:
            raise ValueError(
                f"loss {name} has no setting {', '.join(unknown)}; it takes "
                f"{', '.join([*_SETTINGS, *allowed])}"
            )
        options = replace(base, **own)
    shared = {k: v for k, v in settings.items() if k in _SETTINGS}
    if "hidden" in shared and shared["hidden"] is not None:
        shared["hidden"] = tuple(int(h) for h in shared["hidden"])
    learner = make(name, task, LearnerConfig(**shared, options=options))
    warn_unread(task, learner, name)
    return learner


def _check_options(name: str, options: Any, default: Any) -> None:
    """ValueError unless ``options`` is None or of the entry's options type (a hostile
    review: ``options=3`` surfaced as an AttributeError deep in the builder)."""
    if options is None:
        return
    if default is None or not isinstance(options, type(default)):
        wanted = "none (it has no options)" if default is None else type(default).__name__
        raise ValueError(f"loss {name}'s options must be {wanted}, got {type(options).__name__}")


def _check_settings(shared: dict) -> None:
    """ValueError naming a shared setting of the wrong kind (a hostile review: ``"64"``
    became widths 6 and 4, ``2.7`` a width of 2, ``lr=inf`` NaN losses, ``seed=1.5`` seed 1,
    ``normalize="no"`` true)."""
    check_hidden(shared.get("hidden"), "hidden")
    for flag in ("normalize", "value"):
        if flag in shared:
            checks.boolean(shared[flag], flag)
    device = shared.get("device")
    if device is not None and not isinstance(device, str | torch.device):
        raise ValueError(
            f"device must be a string such as 'cpu' or 'cuda:0' (or a torch.device), got {device!r}"
        )
    lr = shared.get("lr")
    if lr is not None and (
        isinstance(lr, bool) or not isinstance(lr, numbers.Real) or not math.isfinite(lr)
    ):
        raise ValueError(f"lr must be a positive finite number or None, got {lr!r}")
    seed = shared.get("seed", 0)
    if (
        isinstance(seed, bool)
        or not isinstance(seed, numbers.Integral)
        or not 0 <= int(seed) <= MAX_SEED
    ):
        raise ValueError(f"seed must be an integer in [0, {MAX_SEED:_}], got {seed!r}")


def warn_unread(task: TaskSpec, learner: Learner, name: str) -> None:
    """An :class:`~imitrl.learners.task.IgnoredObservationWarning` naming the env's
    observation entries ``learner``'s policy does not read (:meth:`TaskSpec.unread`), and
    how to give them to it."""
    unread = task.unread(list(learner.policy.in_keys))
    if not unread:
        return
    seen = ", ".join(repr(k) for k in learner.policy.in_keys)
    missed = ", ".join(f"{k!r} {v}" for k, v in unread.items())
    warnings.warn(
        f"loss {name}'s policy reads {seen} and not {missed} of the env's observation: "
        "it cannot act on what it does not see (Meta-World's environment_state holds the "
        "objects and the goal). Give the learner one state: for Meta-World the env's "
        "obs_type='state' (--env-kwarg obs_type=state: all 39 numbers as 'observation'); "
        "for another Dict env, gymnasium.wrappers.FlattenObservation before registering it",
        IgnoredObservationWarning,
        stacklevel=3,
    )
