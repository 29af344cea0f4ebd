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
* ``--loss``: a name of the loss registry (:mod:`imitrl.learners.registry`), the
  one builder of learners; ``default`` is resolved to one for the env
  (:func:`resolve_loss`: ``cross_entropy`` for discrete actions, ``mse`` for
  continuous ones, ``gaussian_nll`` where the job needs ``log pi``), or to
  :data:`FOR_ENV` where the registry builds nothing (image observations).
* ``--dataset``: a directory; its files say its format (``meta/info.json``: LeRobot;
  ``main_data.hdf5`` / ``metadata.json``, or a ``data/`` folder holding them: Minari).
"""

from __future__ import annotations

import importlib
import inspect
import re
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import gymnasium
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Bounded, Categorical, MultiCategorical
from torchrl.envs import EnvBase

from imitrl import experts, keys
from imitrl.data.buffer import OBSERVATION_KEYS, REQUIRED_KEYS
from imitrl.envs.make import METAWORLD_PREFIX
from imitrl.jobs.names import EXPERT_ENVS, EXPERT_KINDS
from imitrl.learners import ActorCritic, Learner, defaults, registry
from imitrl.learners.registry import LearnerConfig, TaskSpec
from imitrl.policies import Expert

__all__ = [
    "AUTO",
    "EXPERTS",
    "EXPERT_ENVS",
    "EXPERT_KINDS",
    "FOR_ENV",
    "LEGACY_DEFAULT",
    "builds_table",
    "check_expert_fits",
    "dataset_format",
    "expert_for_env",
    "learner_factory",
    "load_dataset",
    "make_expert",
    "resolve_loss",
    "task_spec",
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


# the keys a rollout writes (imitrl.data.rollout_episodes): loaded rows keep only these,
# so that DAgger's rollouts can extend the same buffer
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
    try:
        module = importlib.import_module(module_name)
    except ImportError as err:
        raise ValueError(f"--expert {spec!r}: cannot import {module_name!r} ({err})") from err
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
    return next((name for name, env in EXPERT_ENVS.items() if env == plain), None)


def no_expert_message(env_id: str) -> str:
    """What to pass when ``--env`` has no built-in expert."""
    return (
        f"--env {env_id} has no built-in expert (built-in: "
        + ", ".join(f"{n} for {e}" for n, e in EXPERT_ENVS.items())
        + f", {METAWORLD} for {METAWORLD_PREFIX}<task>-v3); pass --expert module:function (with --expert-kind callable for a batched "
        "obs -> action function) or --dataset DIR"
    )


def check_expert_fits(expert: TensorDictModuleBase, spec: str, env_id: str, env: EnvBase) -> None:
    """``expert`` labels ``env``'s observations; a ValueError naming ``--expert`` (and the
    built-in expert of ``env_id``, if any) otherwise."""
    try:
        expert(env.fake_tensordict().select(*expert.in_keys))
    except (ValueError, RuntimeError, KeyError, TypeError, IndexError) as err:
        mine = expert_for_env(AUTO, env_id)
        hint = f"--expert {mine}" if mine else no_expert_message(env_id).split("; ", 1)[1]
        raise ValueError(
            f"--expert {spec} cannot label {env_id}'s observations ({type(err).__name__}: "
            f"{err}); use {hint}"
        ) from err


def make_expert(
    spec: str, kind: str = "builder", *, env_id: str | None = None, env: EnvBase | None = None
) -> TensorDictModuleBase:
    """The expert named by ``spec`` (a built-in name or ``module:function``), built.

    ``env_id`` and ``env``: the env it acts in (``metaworld`` needs them: the task's
    scripted policy, reading the 39-d state where the env gives it).

    Returns a TensorDictModule reading ``observation`` and writing ``expert_action``.
    """
    if kind not in EXPERT_KINDS:
        raise ValueError(f"--expert-kind must be one of {EXPERT_KINDS}, got {kind!r}")
    if spec == AUTO:
        raise ValueError("--expert auto is resolved against --env first (expert_for_env)")
    if spec == METAWORLD:
        return _metaworld_expert(env_id, env)
    if ":" not in spec:
        if spec not in EXPERTS:
            raise ValueError(
                f"unknown expert {spec!r}; built-in: {', '.join([*EXPERTS, METAWORLD])}, "
                "or module:function (see --expert-kind)"
            )
        return EXPERTS[spec]()
    fn = _import(spec)
    if not callable(fn):
        raise ValueError(f"--expert {spec!r} is a {type(fn).__name__}, not a function")
    if kind == "callable":
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
    if not isinstance(expert, TensorDictModuleBase) or keys.EXPERT_ACTION not in expert.out_keys:
        raise ValueError(
            f"--expert {spec!r}: the builder returned a {type(expert).__name__}, expected a "
            f"TensorDictModule writing {keys.EXPERT_ACTION!r} (for a batched function "
            "obs -> action, pass --expert-kind callable)"
        )
    return expert


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


def time_limit(env_id: str, override: int | None) -> int:
    """Steps per episode: ``override``, else the gymnasium spec's ``max_episode_steps``."""
    if override is not None:
        return int(override)
    limit = gymnasium.spec(env_id.split(":", 1)[-1]).max_episode_steps
    if limit is None:
        raise ValueError(f"{env_id} is registered without a time limit: pass --max-episode-steps")
    return int(limit)


def task_spec(env: EnvBase) -> TaskSpec:
    """The registry's view of ``env``: action count or ``Bounded`` spec, observation size."""
    spec = env.observation_spec_unbatched
    if keys.OBSERVATION not in spec.keys():
        raise ValueError(
            f"the loss registry needs an {keys.OBSERVATION!r} observation, got keys "
            f"{list(spec.keys())}"
        )
    obs = spec[keys.OBSERVATION]
    action = env.action_spec_unbatched
    if isinstance(action, Categorical) and not isinstance(action, MultiCategorical):
        act: int | Bounded = int(action.space.n)
    elif isinstance(action, Bounded):
        act = action
    else:
        raise ValueError(
            f"the loss registry needs Categorical or Bounded actions, got {type(action).__name__}"
        )
    if isinstance(obs, Categorical):
        return TaskSpec(action=act, num_states=int(obs.space.n))
    if len(obs.shape) != 1:
        raise ValueError(f"the loss registry needs vector observations [d], got {tuple(obs.shape)}")
    return TaskSpec(action=act, observation_dim=int(obs.shape[0]))


FOR_ENV = "for_env"
"""``--loss for_env``: the network :meth:`ActorCritic.for_env` builds for the env (a
one-hot MLP on integer states, a CNN on images), with its default head. What ``--loss
default`` resolves to where the registry builds nothing (image observations;
multi-discrete, one-hot or unbounded actions), and what a checkpoint saved when
``default`` meant ``for_env`` everywhere is rebuilt as (:data:`LEGACY_DEFAULT`)."""
LEGACY_DEFAULT = "default"
"""the loss name checkpoints saved before ``default`` was resolved to a registry entry
record: their learner was ``for_env``'s"""


def resolve_loss(loss: str, env: EnvBase, *, probabilistic: bool = False) -> str:
    """``--loss`` as a name :func:`learner_factory` builds: ``default`` becomes the
    registry entry for the env's actions (:func:`imitrl.learners.defaults.default_loss`;
    ``probabilistic``: the job needs ``log pi``), or :data:`FOR_ENV` where the registry
    cannot describe the env (image observations, with or without a state beside them;
    specs :func:`task_spec` refuses); any other name is kept."""
    if loss != "default":
        return loss
    if keys.PIXELS in env.observation_spec_unbatched.keys():
        return FOR_ENV  # images (with or without a state): for_env's CNN reads them
    try:
        task = task_spec(env)
    except ValueError:
        return FOR_ENV
    return defaults.default_loss(task.actions, probabilistic=probabilistic)


def builds_table(loss: str, env: EnvBase) -> bool:
    """Whether ``loss`` (resolved for ``env``) builds a logits table: a registry entry on
    integer states, which has no hidden layers (``learner_factory`` refuses ``hidden``)."""
    loss = resolve_loss(loss, env)
    return loss in registry.names() and task_spec(env).num_states is not None


def learner_factory(
    loss: str,
    env: EnvBase,
    *,
    hidden: tuple[int, ...] | None,
    lr: float | None,
    seed: int,
    device: str | None = None,
) -> Callable[[], Learner]:
    """``() -> Learner``: a fresh learner for ``env`` trained by ``loss``, same init each call.

    ``loss``: a registry name, :data:`FOR_ENV`, or ``default`` (:func:`resolve_loss`).
    ``lr`` None: the learner's own default (:mod:`imitrl.learners.defaults`: a table's,
    a network's, or the recipe's rate of an entry with ``own_lr``); a rate an entry with
    ``own_lr`` would not use is refused. ``hidden`` None: the network's own layers; given
    for a logits table (a registry entry on integer states), it is refused. Builds one
    learner right away, so that an unknown loss, or a loss for the other kind of action,
    fails here.
    """
    loss = resolve_loss(loss, env)
    if loss == FOR_ENV:
        rate = defaults.learning_rate(None, None, lr)

        def make() -> Learner:
            return ActorCritic.for_env(env, hidden=hidden, lr=rate, seed=seed, device=device)

        make()
        return make

    if loss not in registry.names():
        raise ValueError(
            f"unknown loss {loss!r}; choose default, {FOR_ENV} or one of: "
            f"{', '.join(registry.names())}"
        )
    own = registry.get(loss).own_lr
    if lr is not None and own is not None and lr != own:
        raise ValueError(
            f"--loss {loss} trains at its recipe's learning rate {own:g}, not --lr {lr:g}: "
            "leave --lr out (the rate is the loss's, see imitrl.learners.registry)"
        )
    task = task_spec(env)
    if hidden is not None and task.num_states is not None:
        raise ValueError(
            f"--hidden {','.join(map(str, hidden))}: --loss {loss} on {task.num_states} "
            f"integer states builds a logits table, which has no hidden layers; leave "
            f"--hidden out, or take --loss {FOR_ENV} (an MLP on one-hot states)"
        )
    config = LearnerConfig(lr=lr, seed=seed, device=device)
    if hidden is not None:
        config = replace(config, hidden=tuple(hidden))

    def make() -> Learner:
        return registry.build(loss, task, config)

    make()
    return make


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


def load_dataset(path: Path, env: EnvBase) -> TensorDictBase:
    """Demonstration rows ``[N]`` of the dataset at ``path``, conformed to ``env``'s specs.

    ``path`` is a folder or a LeRobot dataset's Hub ``repo_id`` (:func:`dataset_format`).
    Only the keys a rollout writes are kept (:data:`ROW_KEYS`), so DAgger's rounds
    can extend the same buffer.
    """
    from imitrl.datasets import load_lerobot, load_minari  # needs the datasets extra

    fmt = dataset_format(path)
    if fmt == "lerobot":  # a repo_id goes as a str: resolved locally or downloaded
        loaded = load_lerobot(path if path.is_dir() else str(path), env=env)
    else:
        loaded = load_minari(path, env=env)
    present = set(loaded.rows.keys(include_nested=True))
    return loaded.rows.select(*[k for k in ROW_KEYS if k in present])
