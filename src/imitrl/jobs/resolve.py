"""Names on the command line -> objects: experts, learners, datasets, time limits.

Every function here fails with a ``ValueError`` that names the flag and what was
expected, before any work is done; the CLI turns it into one line on stderr and
exit status 2.

* ``--expert``: a built-in name (:data:`EXPERTS`) or ``module:function``. What the
  function is, is stated by ``--expert-kind``, never guessed: ``builder`` =
  ``function()`` returns an expert module (a TensorDictModule writing
  ``expert_action``, e.g. ``Expert.from_callable(...)``); ``callable`` =
  ``function(obs [N, d]) -> action [N] or [N, m]``, a batched policy wrapped with
  :meth:`~imitrl.policies.Expert.from_callable`. A builder's return value is checked
  once, when it is built.
* ``--loss``: a name of the loss registry (:mod:`imitrl.learners.registry`), built by
  the one builder of learners (:func:`imitrl.learners.build`); ``default`` is resolved
  to one for the env (:func:`resolve_loss`: ``cross_entropy`` for discrete actions,
  ``mse`` for continuous ones, ``gaussian_nll`` where the job needs ``log pi``, and
  ``for_env`` where no other entry describes the env: image observations).
* ``--dataset``: a directory; its files say its format (``meta/info.json``: LeRobot;
  ``main_data.hdf5`` / ``metadata.json``, or a ``data/`` folder holding them: Minari).
"""

from __future__ import annotations

import inspect
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

from imitrl import experts, keys
from imitrl.configs.bc import BCConfig
from imitrl.data.buffer import OBSERVATION_KEYS, REQUIRED_KEYS
from imitrl.data.interventions import intervention_segments
from imitrl.envs.make import METAWORLD_PREFIX
from imitrl.jobs.names import EXPERT_ENVS, EXPERT_KINDS, TABULAR_ENVS, VALUE_ITERATION
from imitrl.learners import FOR_ENV, Learner, TaskSpec, build, registry, resolve
from imitrl.policies import Expert
from imitrl.system.imports import import_user_module

__all__ = [
    "AUTO",
    "EXPERTS",
    "EXPERT_ENVS",
    "EXPERT_KINDS",
    "FOR_ENV",
    "LEGACY_DEFAULT",
    "LearnerChoice",
    "check_expert_fits",
    "choose_learner",
    "dataset_format",
    "expert_for_env",
    "learner_factory",
    "load_dataset",
    "make_expert",
    "played_limit",
    "registered_loss",
    "resolve_loss",
    "resolved_expert",
    "time_limit",
]

EXPERTS: dict[str, Callable[[], TensorDictModuleBase]] = {
    "cartpole": experts.cartpole_expert,
    "mountaincar": experts.mountaincar_expert,
    "acrobot": experts.acrobot_expert,
    "pendulum": experts.pendulum_expert,
    "inverted_pendulum": experts.inverted_pendulum_expert,
    "inverted_double_pendulum": experts.inverted_double_pendulum_expert,
}
"""built-in expert name -> builder (CartPole-v1, MountainCar-v0, Acrobot-v1, Pendulum-v1,
InvertedPendulum-v5, InvertedDoublePendulum-v5; the MuJoCo ones need the mujoco extra)"""


AUTO = "auto"
"""``--expert auto``: the built-in expert of ``--env`` (:func:`expert_for_env`)"""


# the keys a rollout writes (imitrl.runtime.rollout_episodes): loaded rows keep only these,
# so that DAgger's rollouts can extend the same buffer
PROVENANCE_KEYS = (keys.BETA, keys.POLICY_VERSION)
"""a DAgger dataset's per-frame provenance (:mod:`imitrl.data.provenance`), kept when present"""
ROW_KEYS = (
    *REQUIRED_KEYS,
    *OBSERVATION_KEYS,  # the state, the camera(s) (a nested "pixels" keeps every camera)
    *[(keys.NEXT, k) for k in (keys.REWARD, keys.DONE, keys.TERMINATED, keys.TRUNCATED)],
)


def _import(spec: str) -> object:
    """``"module:attribute"`` -> the attribute."""
    module_name, _, attr = spec.partition(":")
    if not module_name or not attr:
        raise ValueError(f"--expert {spec!r}: expected module:function")
    module = import_user_module(module_name, f"--expert {spec!r}")
    if not hasattr(module, attr):
        raise ValueError(f"--expert {spec!r}: module {module_name!r} has no {attr!r}")
    return getattr(module, attr)


METAWORLD = "metaworld"
"""``--expert metaworld``: the scripted policy of ``--env metaworld/<task>-v3``"""


def expert_for_env(spec: str | None, env_id: str) -> str | None:
    """``--expert`` as given, or for ``auto`` the built-in expert that acts in ``env_id``
    (None when there is none: a job that needs an expert then says what to pass)."""
    if spec != AUTO:
        return spec
    plain = env_id.split(":", 1)[-1]
    if plain.startswith(METAWORLD_PREFIX):
        return METAWORLD
    if plain in TABULAR_ENVS:
        return VALUE_ITERATION
    return next((name for name, env in EXPERT_ENVS.items() if env == plain), None)


def no_expert_message(env_id: str) -> str:
    """What to pass when ``--env`` has no built-in expert."""
    return (
        f"--env {env_id} has no built-in expert (built-in: "
        + ", ".join(f"{n} for {e}" for n, e in EXPERT_ENVS.items())
        + f", {METAWORLD} for {METAWORLD_PREFIX}<task>-v3, {VALUE_ITERATION} for a toy-text "
        "env such as FrozenLake-v1); pass --expert module:function (with --expert-kind "
        "callable for a batched obs -> action function) or --dataset DIR"
    )


def check_expert_fits(expert: TensorDictModuleBase, spec: str, env_id: str, env: EnvBase) -> None:
    """``expert`` labels ``env``'s observations; a ValueError naming ``--expert`` (and the
    built-in expert of ``env_id``, if any) otherwise."""
    try:
        expert(env.fake_tensordict().select(*expert.in_keys))
    except (Exception, SystemExit) as err:  # a user's function may raise anything: one line
        mine = expert_for_env(AUTO, env_id)
        hint = f"use --expert {mine}" if mine else no_expert_message(env_id).split("; ", 1)[1]
        raise ValueError(
            f"--expert {spec} cannot label {env_id}'s observations ({type(err).__name__}: "
            f"{err}); {hint}"
        ) from err


def make_expert(
    spec: str,
    kind: str = "builder",
    *,
    env_id: str | None = None,
    env: EnvBase | None = None,
    env_kwargs: Mapping[str, Any] | None = None,
) -> TensorDictModuleBase:
    """The expert named by ``spec`` (a built-in name or ``module:function``), built.

    ``env_id``, ``env`` and ``env_kwargs``: the env it acts in (``metaworld`` needs the id
    and the env: the task's scripted policy, reading the 39-d state where the env gives
    it; ``value_iteration`` the id and the keyword arguments: the model of that map).

    With ``env_id`` and ``env``, the expert is bound to the env's action spec
    (:meth:`~imitrl.policies.Expert.bind`) and labels one of the env's observations first
    (:func:`check_expert_fits`: a failure is one line naming ``--expert``), as every
    command that builds one (bc, dagger, gail, airl, eval, compare) needs.

    Returns a TensorDictModule reading ``observation`` and writing ``expert_action``.
    """
    expert = _build_expert(spec, kind, env_id=env_id, env=env, env_kwargs=env_kwargs)
    if env_id is not None and env is not None:
        if isinstance(expert, Expert):  # its labels cast and checked as a rollout's are
            expert.bind(env.action_spec_unbatched)
        check_expert_fits(expert, spec, env_id, env)
    return expert


def resolved_expert(
    spec: str,
    kind: str,
    *,
    env_id: str,
    env: EnvBase,
    env_kwargs: Mapping[str, Any] | None,
    where: str = "",
) -> TensorDictModuleBase:
    """``--expert`` as eval and compare take it, which need one: ``auto`` resolved against
    ``env_id`` (:func:`expert_for_env`; an env without a built-in expert is refused, the
    message after ``where``), then :func:`make_expert`."""
    name = expert_for_env(spec, env_id)
    if name is None:
        raise ValueError(f"{where}{no_expert_message(env_id)}")
    return make_expert(name, kind, env_id=env_id, env=env, env_kwargs=env_kwargs)


def _build_expert(
    spec: str,
    kind: str,
    *,
    env_id: str | None,
    env: EnvBase | None,
    env_kwargs: Mapping[str, Any] | None,
) -> TensorDictModuleBase:
    """:func:`make_expert`'s expert, unchecked."""
    if kind not in EXPERT_KINDS:
        raise ValueError(f"--expert-kind must be one of {EXPERT_KINDS}, got {kind!r}")
    if spec == AUTO:
        raise ValueError("--expert auto is resolved against --env first (expert_for_env)")
    if spec == METAWORLD:
        return _metaworld_expert(env_id, env)
    if spec == VALUE_ITERATION:
        if env_id is None:
            raise ValueError(f"--expert {VALUE_ITERATION} solves the model of --env: pass one")
        return experts.value_iteration_expert(env_id.split(":", 1)[-1], env_kwargs)
    if ":" not in spec:
        if spec not in EXPERTS:
            raise ValueError(
                f"unknown expert {spec!r}; built-in: "
                f"{', '.join([*EXPERTS, METAWORLD, VALUE_ITERATION])}, "
                "or module:function (see --expert-kind)"
            )
        return EXPERTS[spec]()
    fn = _import(spec)
    if not callable(fn):
        raise ValueError(f"--expert {spec!r} is a {type(fn).__name__}, not a function")
    if kind == "callable":
        if env is not None and keys.OBSERVATION in env.observation_spec_unbatched.keys():
            event = len(env.observation_spec_unbatched[keys.OBSERVATION].shape)
            return Expert.from_callable(_BatchedCall(fn, event))
        return Expert.from_callable(fn)
    needs = _required_arguments(fn)
    if needs:
        raise ValueError(
            f"--expert {spec} takes argument(s) {needs}: it looks like a batched function "
            "obs -> action; pass --expert-kind callable (the default, builder, calls it "
            "with no arguments to build an expert module)"
        )
    try:
        expert = fn()
    except TypeError as err:
        raise ValueError(
            f"--expert {spec}: calling it with no arguments failed ({err}); for a batched "
            "function obs -> action pass --expert-kind callable"
        ) from err
    except (Exception, SystemExit) as err:  # the user's code may raise anything: one line
        raise ValueError(
            f"--expert {spec}: building it raised {type(err).__name__}: {err}"[:500]
        ) from None
    if not isinstance(expert, TensorDictModuleBase) or keys.EXPERT_ACTION not in expert.out_keys:
        raise ValueError(
            f"--expert {spec!r}: the builder returned a {type(expert).__name__}, expected a "
            f"TensorDictModule writing {keys.EXPERT_ACTION!r} (for a batched function "
            "obs -> action, pass --expert-kind callable)"
        )
    return expert


class _BatchedCall:
    """An ``--expert-kind callable`` function called as its flag promises, on a batch
    ``obs [N, *event]``: one env's observation ``[*event]`` (one lane, where TorchRL
    steps it unbatched) goes in as a batch of one and its label comes back out."""

    def __init__(self, fn: Callable, event_dims: int) -> None:
        self.fn, self.event_dims = fn, event_dims

    def __call__(self, obs: torch.Tensor) -> object:
        if obs.dim() > self.event_dims:
            return self.fn(obs)
        out = torch.as_tensor(self.fn(obs.unsqueeze(0)))
        return out[0] if out.dim() > 0 and out.shape[0] == 1 else out


def _metaworld_expert(env_id: str | None, env: EnvBase | None) -> Expert:
    plain = (env_id or "").split(":", 1)[-1]
    if not plain.startswith(METAWORLD_PREFIX):
        raise ValueError(
            f"--expert {METAWORLD} labels Meta-World tasks: pass --env "
            f"{METAWORLD_PREFIX}<task>-v3 (got --env {env_id})"
        )
    observes = env.observation_spec.keys() if env is not None else ()
    key = keys.ENVIRONMENT_STATE if keys.ENVIRONMENT_STATE in observes else keys.OBSERVATION
    return experts.metaworld_expert(plain, observation_key=key)


def _required_arguments(fn: Callable) -> list[str]:
    """The parameters ``fn`` cannot be called without (none when its signature is unknown)."""
    try:
        params = inspect.signature(fn).parameters.values()
    except (TypeError, ValueError):
        return []
    kinds = (inspect.Parameter.POSITIONAL_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
    return [p.name for p in params if p.kind in kinds and p.default is inspect.Parameter.empty]


def played_limit(env_id: str, override: int | None) -> int | None:
    """:func:`time_limit`, or None for an env registered without one: what a report
    records of the episodes it played."""
    try:
        return time_limit(env_id, override)
    except ValueError:
        return None


def time_limit(env_id: str, override: int | None) -> int:
    """Steps per episode: ``override``, else the gymnasium spec's ``max_episode_steps``."""
    if override is not None:
        return int(override)
    limit = gymnasium.spec(env_id.split(":", 1)[-1]).max_episode_steps
    if limit is None:
        raise ValueError(f"{env_id} is registered without a time limit: pass --max-episode-steps")
    return int(limit)


LEGACY_DEFAULT = "default"
"""the loss name checkpoints saved before ``default`` was resolved to a registry entry
record: their learner was ``for_env``'s"""


def registered_loss(spec: str) -> str:
    """``--loss`` as a registry name: ``spec`` itself, or for ``module:name`` (your own
    loss) ``name`` after importing ``module``, which registers it
    (:func:`imitrl.learners.registry.register`): code you named on the command line, as
    ``--env module:Env-v0`` and ``--expert module:function`` are.

    Raises:
        ValueError: a module that does not import, or registers no loss ``name``.
    """
    if ":" not in spec:
        return spec
    module, _, name = spec.partition(":")
    if not module or not name:
        raise ValueError(f"--loss {spec!r}: expected a registered name or module:name")
    import_user_module(module, f"--loss {spec!r}")
    builder = registry.get(name).build if name in registry.names() else None
    if builder is None or getattr(builder, "__module__", "").startswith("imitrl."):
        own = f" ({name!r} is imitrl's own loss: --loss {name})" if builder is not None else ""
        raise ValueError(
            f"--loss {spec!r}: importing {module!r} registered no loss {name!r}{own} (register "
            f"it with @imitrl.learners.registry.register({name!r}, ...)); registered: "
            f"{', '.join(registry.names())}"
        )
    return name


def resolve_loss(loss: str, env: EnvBase | TaskSpec, *, probabilistic: bool = False) -> str:
    """``--loss`` as the registry entry it names for ``env``
    (:func:`imitrl.learners.resolve`: ``default`` is ``cross_entropy``, ``mse``, or
    ``gaussian_nll`` where the job needs ``log pi``; ``for_env`` on images); what a run
    records and a checkpoint rebuilds."""
    task = env if isinstance(env, TaskSpec) else TaskSpec.from_env(env)
    return resolve(loss, task, value=probabilistic)


def learner_factory(
    loss: str,
    env: EnvBase | TaskSpec,
    *,
    hidden: tuple[int, ...] | None,
    lr: float | None,
    seed: int,
    device: str | None = None,
    value: bool = False,
) -> Callable[[], Learner]:
    """``() -> Learner``: a fresh :func:`imitrl.learners.build` ``(loss, env, ...)`` each
    call, the same initialisation each time, from the flags (``hidden``, ``lr`` None: the
    entry's own; ``value``: a value head, for GAIL and AIRL). Builds one learner right
    away, so that an unknown loss or a flag the loss refuses fails here, naming the flag."""
    settings: dict = {"seed": seed, "device": device, "value": value}
    if hidden is not None:
        settings["hidden"] = tuple(hidden)
    if lr is not None:
        settings["lr"] = lr

    def make() -> Learner:
        return build(loss, env, **settings)

    try:
        make()
    except ValueError as err:  # the library's words for the flags: --loss, --lr, --hidden
        text = str(err).replace(f"loss {loss} ", f"--loss {loss} ", 1)
        text = re.sub(r"(\bnot lr\b|\bleave lr\b|\bleave hidden\b|^hidden\b)", _flag, text)
        text = text.replace("; registered:", "; choose default or one of:")
        raise ValueError(text) from None
    return make


@dataclass(frozen=True)
class LearnerChoice:
    """What ``--loss`` (with ``--hidden``, ``--lr``, ``--seed``, ``--device``) chose for an env."""

    loss: str
    """the registry entry ``--loss`` resolved to (:func:`resolve_loss`): what the run
    records and a checkpoint rebuilds"""
    make: Callable[[], Learner]
    """a fresh learner, same initialisation each call (:func:`learner_factory`)"""
    recipe: Callable[[BCConfig], BCConfig] | None
    """the entry's fit schedule (``LossEntry.recipe``), None for ``for_env`` or an entry
    without one"""


def choose_learner(
    loss: str,
    env: EnvBase | TaskSpec,
    *,
    hidden: tuple[int, ...] | None,
    lr: float | None,
    seed: int,
    device: str | None = None,
    probabilistic: bool = False,
) -> LearnerChoice:
    """``--loss`` and its settings for ``env``, in one visit of :mod:`imitrl.learners`:
    the learner factory (one learner built at once, so that a bad flag fails here, naming
    it), the entry ``default`` resolves to, and that entry's fit recipe.
    ``probabilistic``: the job needs ``log pi`` and a value head (GAIL, AIRL). A loss of
    your own, ``module:name`` (:func:`registered_loss`), is recorded as given, so that
    ``imitrl eval`` knows which module to ask you to name."""
    plain = registered_loss(loss)
    make = learner_factory(
        plain, env, hidden=hidden, lr=lr, seed=seed, device=device, value=probabilistic
    )
    name = resolve_loss(plain, env, probabilistic=probabilistic)
    recipe = registry.get(name).recipe if name in registry.names() else None
    return LearnerChoice(loss if plain != loss else name, make, recipe)


def _flag(match: re.Match) -> str:
    words = match.group(0).split(" ")
    words[-1] = "--" + words[-1]
    return " ".join(words)


def dataset_format(path: Path) -> str:
    """``"lerobot"`` or ``"minari"``, read off the files in ``path``; a ``path`` that is
    no folder but a Hub ``repo_id`` (``<org>/<name>``) names a LeRobot dataset, which
    :func:`load_dataset` finds in the local caches or downloads (``imitrl[hub]``)."""
    if not path.is_dir():
        if not path.exists() and re.fullmatch(r"[\w.-]+/[\w.-]+", str(path)):
            return "lerobot"
        raise ValueError(
            f"--dataset {path}: no such directory (nor a Hub repo_id <org>/<name> of a "
            "LeRobot dataset)"
        )
    if (path / "meta" / "info.json").is_file():
        return "lerobot"
    for folder in (path, path / "data"):
        if (folder / "main_data.hdf5").is_file() or (folder / "metadata.json").is_file():
            return "minari"
    raise ValueError(
        f"--dataset {path}: neither a LeRobot dataset (meta/info.json) nor a Minari one "
        "(main_data.hdf5 or metadata.json, possibly under data/)"
    )


def load_dataset(
    path: Path, env: EnvBase | None, frames: str = "all", *, successors: bool = False
) -> TensorDictBase:
    """Demonstration rows ``[N]`` of the dataset at ``path``, conformed to ``env``'s specs
    (None: as recorded, for a run on the dataset alone).

    ``path`` is a folder or a LeRobot dataset's Hub ``repo_id`` (:func:`dataset_format`).
    Only the keys a rollout writes are kept (:data:`ROW_KEYS`), so DAgger's rounds
    can extend the same buffer, and a DAgger dataset's provenance (``BETA`` and
    ``POLICY_VERSION``, which DAgger's rounds then carry too). ``frames="interventions"``
    keeps the frames whose ``intervention`` is True, each streak an episode
    (:func:`~imitrl.data.interventions.intervention_segments`; ``--dataset-frames``).
    ``successors``: keep each row's recorded next observation too (``("next",
    OBSERVATION)``, as Minari records it), which adversarial imitation reads for the last
    row of an episode a time limit cut
    (:func:`~imitrl.algorithms.adversarial.transitions.expert_transitions`).
    """
    from imitrl.datasets import load_lerobot, load_minari  # needs the datasets extra

    fmt = dataset_format(path)
    if fmt == "lerobot":  # a repo_id goes as a str: resolved locally or downloaded
        loaded = load_lerobot(path if path.is_dir() else str(path), env=env)
    else:
        loaded = load_minari(path, env=env, next_observation=successors)
    present = set(loaded.rows.keys(include_nested=True))
    kept = [*ROW_KEYS, *(PROVENANCE_KEYS if set(PROVENANCE_KEYS) <= present else ())]
    if successors:
        kept.append((keys.NEXT, keys.OBSERVATION))
    rows = loaded.rows.select(*[k for k in kept if k in present])
    if frames == "interventions":
        if keys.EXPERT_EXECUTED not in loaded.loaded.values():
            raise ValueError(
                f"--dataset-frames interventions: --dataset {path} has no intervention column "
                f"(features loaded: {sorted(loaded.loaded)})"
            )
        rows = intervention_segments(rows, first_episode=0)
        if rows.shape[0] == 0:
            raise ValueError(
                f"--dataset-frames interventions: no frame of --dataset {path} is an intervention"
            )
    return rows
