"""`make_env`: a TorchRL env for a gymnasium id, single, vectorised or parallel by one switch.

Every env it builds reads ``"observation"`` and writes ``"action"`` (the keys the
policies and experts use), whatever the id:

* discrete action spaces use integer actions (``categorical_action_encoding=True``),
  not TorchRL's default one-hot;
* float64 observations (every MuJoCo env) and float64 action boxes are cast to
  float32 by ``DoubleToFloat``;
* ``num_envs > 1`` steps the copies in this process through
  ``gymnasium.vector.SyncVectorEnv(..., autoreset_mode=DISABLED)`` wrapped by
  ``GymWrapper``. Not ``GymEnv(id, num_envs=N)``: in torchrl 0.14.1 that builds an
  ``AsyncVectorEnv`` (N processes) and records zeros as the final observation of a
  sub-env that ends before the others (measured in
  ``benchmarks/continuous_traps.py``). With ``DISABLED`` TorchRL resets only the
  finished lanes and the true final observation is kept;
* ``pixels=(H, W)`` adds ``"pixels"``, uint8 ``[*batch, H, W, 3]``, beside the state
  ``"observation"``: the gymnasium env renders ``rgb_array`` frames (headless: the
  classic-control envs draw with pygame on an off-screen surface, no display), TorchRL's
  ``PixelRenderTransform`` writes them at every reset and step, resized by
  :class:`ResizeFrame` (torchvision, which TorchRL's ``Resize`` needs, is not a
  dependency; ``ToTensorImage`` would store float CHW, 4x larger: the learner scales
  and permutes inside its network instead);
* a ``Dict`` observation space (robot envs: gym-pusht's ``pixels_agent_pos``) is renamed
  onto the key vocabulary as LeRobot names its entries (:mod:`imitrl.envs.dict_obs`):
  ``agent_pos`` -> ``"observation"`` (float32), ``pixels`` -> ``"pixels"`` (uint8
  ``[H, W, 3]``; a Dict of cameras -> ``("pixels", cam)``), ``environment_state`` ->
  ``"environment_state"``; any other entry is refused, naming it;
* ``parallel=True`` runs each copy in its own process (``torchrl.envs.ParallelEnv``).
  Starting the processes costs seconds (measured in ``benchmarks/continuous_traps.py``):
  it pays only when one env step costs far more than the inter-process round trip.
"""

from __future__ import annotations

import difflib
import inspect
import weakref
from functools import partial
from typing import NamedTuple

import gymnasium
import numpy as np
import torch
from gymnasium.envs.registration import load_env_creator
from torchrl.envs import (
    Compose,
    DoubleToFloat,
    EnvBase,
    GymWrapper,
    ParallelEnv,
    TransformedEnv,
)
from torchrl.record.recorder import PixelRenderTransform

from imitrl import checks, keys
from imitrl.compat import wrapped_gym_env
from imitrl.envs.dict_obs import DictObservation
from imitrl.envs.success import SuccessInfo, reads_success, success_reader
from imitrl.system.imports import import_user_module

__all__ = ["PlainGym", "ResizeFrame", "make_env", "plain_gym"]

METAWORLD_PREFIX = "metaworld/"
"""the ids :mod:`imitrl.envs.metaworld` registers (imported on first use)"""


def _spec(env_id: str) -> gymnasium.envs.registration.EnvSpec:
    if not isinstance(env_id, str):
        raise ValueError(f"env_id must be a gymnasium id string, got {type(env_id).__name__}")
    if env_id.startswith(METAWORLD_PREFIX):  # registered by imitrl.envs.metaworld
        from imitrl.envs import metaworld

        metaworld.task_of(env_id)  # an unknown task named with the list of tasks
    if ":" in env_id:  # "module:Env-v0": importing the module registers the env (gymnasium.make)
        module, env_id = env_id.split(":", 1)
        import_user_module(module, f"env {module}:{env_id} (the module registers {env_id!r})")
    try:
        return gymnasium.spec(env_id)
    except gymnasium.error.Error as err:
        ids = [i for i in gymnasium.registry if i.split("/")[0] not in _JAX_NAMESPACES]
        close = difflib.get_close_matches(env_id, ids, n=3)
        hint = f" (did you mean {', '.join(close)}?)" if close else ""
        raise ValueError(
            f"unknown gymnasium env id {env_id!r}{hint}; register your own env with "
            "gymnasium.register(id=..., entry_point=...) first"
        ) from err


_JAX_NAMESPACES = ("tabular", "phys2d")
"""gymnasium's functional envs, which need jax: never suggested for a mistyped id"""


def _check_kwarg_kinds(env_id: str, env_kwargs: dict) -> None:
    """ValueError for an env argument of another kind than its constructor's default (a
    number given as text: ``--env-kwarg g=abc`` failed inside Pendulum's first step).
    Arguments whose default is None, or constructors that cannot be read, pass as given.
    A Meta-World id's task is its own (``task=`` would swap the env behind the id, and
    the expert the id names would label another task's episodes)."""
    if env_id.startswith(METAWORLD_PREFIX) and "task" in env_kwargs:
        raise ValueError(
            f"--env-kwarg task={env_kwargs['task']!r}: {env_id} names its task; give "
            f"--env {METAWORLD_PREFIX}{env_kwargs['task']} instead"
        )
    try:
        entry = gymnasium.spec(env_id).entry_point
        creator = load_env_creator(entry) if isinstance(entry, str) else entry
        params = inspect.signature(creator).parameters  # type: ignore[arg-type]
    except Exception:
        return
    for name, value in env_kwargs.items():
        default = params[name].default if name in params else None
        kinds = _KINDS.get(type(default))
        if kinds is not None and type(value) not in kinds:
            raise ValueError(
                f"--env-kwarg {name}={value!r}: {env_id}'s {name} defaults to {default!r} "
                f"({type(default).__name__}); give a {type(default).__name__}"
            )


_KINDS: dict[type, tuple[type, ...]] = {
    bool: (bool,),
    int: (int,),
    float: (int, float),
    str: (str,),
}
"""a default's type -> the types a value given for it may have"""


def _refused(env_id: str, env_kwargs: dict | None, err: Exception) -> str:
    """One line: the env refused its ``--env-kwarg`` values (bounded: a value may be long)."""
    shown = ", ".join(f"{k}={v!r}" for k, v in (env_kwargs or {}).items())
    return (
        f"{env_id} refused --env-kwarg {shown[:200]}: {type(err).__name__}: "
        f"{str(err).splitlines()[0][:300] if str(err) else ''}"
    )


def _gym(
    env_id: str,
    max_episode_steps: int | None,
    render: bool = False,
    env_kwargs: dict | None = None,
    success: bool = False,
) -> gymnasium.Env:
    """``gymnasium.make`` with ``env_kwargs`` (rendering ``rgb_array`` frames when
    ``render``), a ``Dict`` observation renamed onto imitrl's keys
    (:class:`DictObservation`), ``info["success"]`` read as a flag when ``success``."""
    extra = {"render_mode": "rgb_array"} if render else {}
    _check_kwarg_kinds(env_id, env_kwargs or {})
    try:
        env = gymnasium.make(
            env_id, max_episode_steps=max_episode_steps, **{**(env_kwargs or {}), **extra}
        )
    except TypeError as err:  # a keyword the env's constructor does not take
        raise ValueError(_refused(env_id, env_kwargs, err)) from err
    except (KeyError, IndexError, ValueError, AssertionError, RuntimeError) as err:
        if not env_kwargs:  # the env's own failure, not about its arguments
            raise
        # a value the constructor cannot use (a hostile review: map_name=16x16 was a
        # KeyError traceback, desc=SFFG "not enough values to unpack")
        raise ValueError(_refused(env_id, env_kwargs, err)) from err
    except gymnasium.error.DependencyNotInstalled as err:
        raise ValueError(
            f"{env_id} needs an optional dependency ({err}); for MuJoCo envs install "
            "the 'mujoco' extra (gymnasium[mujoco]), for classic-control pixels pygame"
        ) from err
    modes = env.metadata.get("render_modes", [])
    if render and ("rgb_array" not in modes or env.render_mode != "rgb_array"):
        env.close()
        raise ValueError(
            f"{env_id} does not render rgb_array frames (render modes {modes}): it cannot "
            "be a pixel env"
        )
    if success and not reads_success(env):
        env = SuccessInfo(env)
    if isinstance(env.observation_space, gymnasium.spaces.Dict):
        try:
            env = DictObservation(env, env_id)
        except ValueError:
            env.close()
            raise
        renamed = env.observation_space
        assert isinstance(renamed, gymnasium.spaces.Dict)  # mapped_space's
        if render and keys.PIXELS in renamed.spaces:
            env.close()
            raise ValueError(
                f"{env_id}: its Dict observation already holds 'pixels'; pixels=(H, W) "
                "would render a second image under the same key (leave pixels=None)"
            )
    return env


def _check_spaces(env: gymnasium.Env, env_id: str) -> tuple[bool, bool]:
    """(discrete action, float64 observation or action); ValueError for spaces the library
    cannot use (a Dict observation was checked and renamed by :class:`DictObservation`)."""
    obs, act = env.observation_space, env.action_space
    if not isinstance(act, (gymnasium.spaces.Box, gymnasium.spaces.Discrete)):
        raise ValueError(
            f"{env_id}: actions must be a Box or Discrete space, got {type(act).__name__}"
        )
    discrete = isinstance(act, gymnasium.spaces.Discrete)
    double_action = not discrete and act.dtype == np.float64
    if isinstance(env, DictObservation):
        return discrete, double_action  # its state entries are float32 already
    if not isinstance(obs, (gymnasium.spaces.Box, gymnasium.spaces.Discrete)):
        raise ValueError(
            f"{env_id}: observations must be a Box or Discrete space (or a Dict of "
            f"imitrl.envs.dict_obs's entries), got {type(obs).__name__}"
        )
    if isinstance(obs, gymnasium.spaces.Box) and len(obs.shape) != 1:
        raise ValueError(
            f"{env_id}: Box observations must be vectors [d], got shape {obs.shape} "
            "(flatten them, e.g. with gymnasium.wrappers.FlattenObservation)"
        )
    return discrete, obs.dtype == np.float64 or double_action


class ResizeFrame:
    """A rendered ``[H0, W0, 3]`` uint8 frame -> uint8 ``[H, W, 3]`` tensor (antialiased
    bilinear; the ``preproc`` of ``PixelRenderTransform``, picklable for workers)."""

    def __init__(self, size: tuple[int, int]) -> None:
        self.size = (int(size[0]), int(size[1]))

    def __call__(self, frame) -> torch.Tensor:
        image = torch.as_tensor(np.ascontiguousarray(frame))
        if image.dtype != torch.uint8 or image.ndim != 3 or image.shape[-1] != 3:
            raise ValueError(
                f"expected a rendered uint8 [H, W, 3] frame, got {image.dtype} {tuple(image.shape)}"
            )
        if tuple(image.shape[:2]) == self.size:
            return image
        x = image.permute(2, 0, 1)[None].to(torch.float32)  # [1, 3, H0, W0]
        x = torch.nn.functional.interpolate(x, size=self.size, mode="bilinear", antialias=True)
        return x[0].round().clamp(0, 255).to(torch.uint8).permute(1, 2, 0).contiguous()


def _check_pixels(pixels) -> tuple[int, int] | None:
    if pixels is None:
        return None
    size = tuple(pixels)
    if len(size) != 2 or any(int(p) != p or p < 1 for p in size):
        raise ValueError(f"pixels must be (H, W) positive integers or None, got {pixels!r}")
    return int(size[0]), int(size[1])


def _single(
    env_id: str,
    frame_skip: int,
    max_episode_steps: int | None,
    seed: int,
    pixels: tuple[int, int] | None = None,
    env_kwargs: dict | None = None,
    success: bool = False,
) -> EnvBase:
    """One seeded TorchRL env (module-level so ``ParallelEnv`` workers can unpickle it)."""
    gym_env = _gym(env_id, max_episode_steps, pixels is not None, env_kwargs, success)
    discrete, double = _check_spaces(gym_env, env_id)
    env = GymWrapper(gym_env, categorical_action_encoding=discrete, frame_skip=frame_skip)
    if reads_success(gym_env):
        env.set_info_dict_reader(success_reader())
    if double:
        env = TransformedEnv(env, DoubleToFloat())
    if pixels is not None:
        render = PixelRenderTransform(out_keys=[keys.PIXELS], preproc=ResizeFrame(pixels))
        env = env.append_transform(render) if double else TransformedEnv(env, render)
    env.set_seed(seed)
    return env


def _reads(env: EnvBase) -> bool:
    """``env`` (built by :func:`_single`) reads ``info["success"]``: an info reader, which
    the direct path does not step."""
    base = env.base_env if isinstance(env, TransformedEnv) else env
    return reads_success(wrapped_gym_env(base))


def _observes_dict(env: EnvBase) -> bool:
    """``env`` (built by :func:`_single`) observes a renamed ``Dict``: the direct path
    (:mod:`imitrl.runtime.fast.env_steps`), which converts one array per step, cannot step it."""
    base = env.base_env if isinstance(env, TransformedEnv) else env
    return isinstance(wrapped_gym_env(base), DictObservation)


def make_env(
    env_id: str,
    *,
    seed: int,
    num_envs: int = 1,
    parallel: bool = False,
    frame_skip: int = 1,
    max_episode_steps: int | None = None,
    pixels: tuple[int, int] | None = None,
    env_kwargs: dict | None = None,
    success: bool = False,
) -> EnvBase:
    """A seeded TorchRL env for a registered gymnasium id.

    Args:
        env_id: a gymnasium id (``"Pendulum-v1"``, ``"InvertedPendulum-v5"``, or your
            own after ``gymnasium.register``). With ``parallel=True`` the workers are
            fresh processes: register your env in an importable module and pass
            ``"module:YourEnv-v0"`` so that each worker imports it (as
            ``gymnasium.make`` does).
        seed: seeds the env; copy ``i`` of a vectorised or parallel env gets ``seed + i``,
            so ``parallel`` does not change the episodes. (A later ``env.set_seed(s)``
            re-seeds in TorchRL's way: ``s + i`` in-process, hashed seeds for workers.)
        num_envs: copies stepped together; the env's batch size is ``[num_envs]``
            (``[]`` for 1 unless ``parallel``).
        parallel: run the copies in worker processes (``ParallelEnv``) instead of in
            this process (``SyncVectorEnv``).
        frame_skip: repeat each action this many steps, summing rewards (TorchRL's
            action repeat). An expert tuned for the env's time step usually fails
            under a repeat: build it for the repeated step (e.g. ``action_repeat=``
            of the MuJoCo experts). Not available for in-process vectorised envs.
        max_episode_steps: override the id's time limit (None keeps it).
        pixels: ``(H, W)``: also give the rendered frame as ``"pixels"``, uint8
            ``[*batch, H, W, 3]`` (the env must render ``rgb_array``); needs
            ``num_envs=1`` or ``parallel=True``.
        env_kwargs: keyword arguments of the env's constructor (``gymnasium.make(env_id,
            **env_kwargs)``), e.g. ``{"obs_type": "pixels_agent_pos"}`` for Meta-World.
        success: read the env's ``info["success"]`` into ``("next", "success")``, a bool
            set from the episode's first success on (:mod:`imitrl.envs.success`), which
            ``evaluate`` reports. An env built as a ``SuccessInfo`` (the ``metaworld/``
            ids, :mod:`imitrl.envs.metaworld`) is read in any case.

    Returns:
        a TorchRL env: ``"observation"`` float32 ``[*batch, d]`` (int64 ``[*batch]``
        for a Discrete space), ``"action"`` int64 ``[*batch]`` (discrete) or float32
        ``[*batch, m]`` bounded by the spec (continuous). A ``Dict`` observation gives
        its entries under LeRobot's keys (:mod:`imitrl.envs.dict_obs`): ``"observation"``
        (``agent_pos``, float32 ``[*batch, d]``; absent when the Dict has none),
        ``"pixels"`` or ``("pixels", cam)`` (uint8 ``[*batch, H, W, 3]``),
        ``"environment_state"`` (float32 ``[*batch, d]``).

    Raises:
        ValueError: unknown id, missing optional dependency, unsupported spaces (a Dict
            entry other than ``agent_pos``, ``pixels``, ``environment_state``, named),
            ``pixels=(H, W)`` for a Dict that holds ``pixels``, bad counts.
    """
    _spec(env_id)
    env_kwargs = _check_kwargs(env_kwargs)
    success = bool(success)
    checks.integer(seed, "seed")  # every copy's seed derives from it: None is a mistake here
    if int(num_envs) != num_envs or num_envs < 1:
        raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
    if int(frame_skip) != frame_skip or frame_skip < 1:
        raise ValueError(f"frame_skip must be a positive integer, got {frame_skip!r}")
    if max_episode_steps is not None and max_episode_steps < 1:
        raise ValueError(f"max_episode_steps must be positive or None, got {max_episode_steps}")
    num_envs, frame_skip, seed = int(num_envs), int(frame_skip), int(seed)
    pixels = _check_pixels(pixels)
    if parallel:
        # Worker i seeds its own copy with seed + i, as SyncVectorEnv does, so the
        # switch changes where the copies run, not the episodes they play.
        # (ParallelEnv.set_seed would derive the workers' seeds by hashing instead.)
        makers = [
            partial(
                _single,
                env_id,
                frame_skip,
                max_episode_steps,
                seed + i,
                pixels,
                env_kwargs,
                success,
            )
            for i in range(num_envs)
        ]
        return ParallelEnv(num_envs, makers)
    if num_envs == 1:
        env = _single(env_id, frame_skip, max_episode_steps, seed, pixels, env_kwargs, success)
        # rollouts step a plain one directly (imitrl.runtime.paths.stepper): same episodes
        plain = pixels is None and frame_skip == 1 and not (_observes_dict(env) or _reads(env))
        return _mark_plain(env) if plain else env
    if pixels is not None:
        raise ValueError("pixels needs num_envs=1 or parallel=True (one renderer per copy)")
    if frame_skip != 1:
        # GymLikeEnv's repeat loop stops when any lane ends, so lanes would
        # repeat their actions a different number of times.
        raise ValueError(
            "frame_skip > 1 needs num_envs=1 or parallel=True (the in-process "
            "vectorised env would stop every lane's repeat when one lane ends)"
        )
    probe = _gym(env_id, max_episode_steps, False, env_kwargs, success)
    discrete, double = _check_spaces(probe, env_id)
    observes_dict, reads = isinstance(probe, DictObservation), reads_success(probe)
    probe.close()
    vec = gymnasium.vector.SyncVectorEnv(
        [
            partial(_gym, env_id, max_episode_steps, False, env_kwargs, success)
            for _ in range(num_envs)
        ],
        autoreset_mode=gymnasium.vector.AutoresetMode.DISABLED,
    )
    env = GymWrapper(vec, categorical_action_encoding=discrete)
    if reads:
        env.set_info_dict_reader(success_reader((num_envs,)))
    if double:
        env = TransformedEnv(env, DoubleToFloat())
    env.set_seed(seed)  # SyncVectorEnv seeds copy i with seed + i
    return env if observes_dict or reads else _mark_plain(env)


_PLAIN_GYM: weakref.WeakSet[EnvBase] = weakref.WeakSet()
"""the envs :func:`make_env` built as a plain GymWrapper (maybe in ``DoubleToFloat``) in
this process"""


def _mark_plain(env: EnvBase) -> EnvBase:
    _PLAIN_GYM.add(env)
    return env


class PlainGym(NamedTuple):
    """What a plain env of :func:`plain_gym` wraps."""

    base: GymWrapper
    """the TorchRL wrapper (``env`` itself, or inside its ``DoubleToFloat``)"""
    inner: gymnasium.Env | gymnasium.vector.VectorEnv
    """the gymnasium env it steps: one env, or a ``SyncVectorEnv`` whose autoreset is
    DISABLED"""


def plain_gym(env: EnvBase) -> PlainGym | None:
    """What ``env`` wraps, where :func:`make_env` built it in this process as a plain
    in-process gymnasium wrapper and it is unchanged since (no pixels, no Dict
    observation, no success reader, no frame skip, no transform but its own
    ``DoubleToFloat``): an env a rollout may step through gymnasium directly
    (:func:`imitrl.runtime.paths.stepper`), with the same episodes; None otherwise."""
    if env not in _PLAIN_GYM:
        return None
    base = env
    if isinstance(env, TransformedEnv):
        parts = list(env.transform) if isinstance(env.transform, Compose) else [env.transform]
        if len(parts) != 1 or type(parts[0]) is not DoubleToFloat:
            return None  # a transform appended since make_env built it
        base = env.base_env
    if not isinstance(base, GymWrapper) or base.wrapper_frame_skip != 1 or base.info_dict_reader:
        return None
    if set(env.observation_spec.keys(True, True)) != {keys.OBSERVATION}:
        return None  # pixels (or another observation) beside the state
    inner = wrapped_gym_env(base)
    if isinstance(inner, gymnasium.vector.VectorEnv):
        if not isinstance(inner, gymnasium.vector.SyncVectorEnv) or (
            inner.autoreset_mode != gymnasium.vector.AutoresetMode.DISABLED
        ):
            return None
    elif not isinstance(inner, gymnasium.Env):
        return None
    return PlainGym(base, inner)


def _check_kwargs(env_kwargs) -> dict:
    """``env_kwargs`` as a dict of keyword names; ValueError for anything else."""
    if env_kwargs is None:
        return {}
    if not isinstance(env_kwargs, dict) or not all(
        isinstance(k, str) and k.isidentifier() for k in env_kwargs
    ):
        raise ValueError(
            f"env_kwargs must be a dict of keyword names to values, got {env_kwargs!r}"
        )
    if {"render_mode", "max_episode_steps"} & set(env_kwargs):
        raise ValueError(
            "env_kwargs cannot set render_mode or max_episode_steps: use pixels= and "
            "max_episode_steps= of make_env"
        )
    return dict(env_kwargs)
