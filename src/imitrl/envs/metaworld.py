"""Meta-World v3 tasks as gymnasium ids: ``make_env("metaworld/pick-place-v3", seed=0)``.

Meta-World (Yu et al., 2019; the ``metaworld`` package, 3.1.1) is 50 Sawyer-arm
manipulation tasks with 39-d state observations (hand, gripper, two objects, the goal),
4-d actions in [-1, 1] (hand displacement and gripper effort) and a success flag in
``info["success"]``. Importing this module registers each task as
``metaworld/<task>-v3`` (:data:`TASKS`; :data:`MT10` and :data:`MT50` name the standard
sets), built by :func:`make_task`:

* **One task, varied per episode.** The task's goal and object positions are drawn at
  every reset from the env's own generator (Meta-World's ``seeded_rand_vec``, as LeRobot's
  Meta-World env draws them), so ``reset(seed=s)`` followed by resets without a seed gives
  the same sequence of variations for the same ``s`` (gymnasium's seeding contract; the
  raw Meta-World env ignores ``reset(seed=)``). TorchRL's ``set_seed`` and ``make_env``'s
  ``seed=`` reach it that way.
* **Success.** Meta-World's evaluation counts an episode a success when ``info["success"]``
  is set at any step (``metaworld/evaluation.py`` turns ``terminate_on_success`` on; so
  does LeRobot's env: ``terminated = done or is_success``). The episode ends at its first
  success (``terminate_on_success=True``, the default), and ``info["success"]`` is made a
  bool that stays set once reached (:class:`~imitrl.envs.success.SuccessInfo`), so the
  flag at an episode's last step is that "at any step" success. ``make_env`` reads it as
  ``("next", "success")`` and :func:`~imitrl.evaluation.evaluate` reports its rate.
* **Observation space.** The raw env declares its goal bounds before the task sets them
  (``[0, 0]``, while observations hold the real goal), which TorchRL's spec checks refuse;
  the space is declared unbounded float64 ``[39]`` instead (``make_env`` casts to float32).
* **Observation types**, LeRobot's names: ``"state"`` (default: the 39-d vector as
  ``"observation"``); ``"environment_state_agent_pos"`` (a Dict: ``agent_pos`` = hand and
  gripper ``[4]``, ``environment_state`` = the 39-d vector); ``"pixels_agent_pos"`` (the
  Dict with ``pixels``, the ``corner2`` camera as LeRobot places and flips it), so rows
  recorded here carry ``lerobot/metaworld_mt50``'s features
  (:mod:`imitrl.datasets.lerobot`, :data:`LEROBOT_FEATURES`).

Install with ``pip install 'imitrl[metaworld]'`` (metaworld 3.1.1 pins mujoco 3.3.0).
Rendering needs an OpenGL backend: ``MUJOCO_GL=egl`` (Mesa's llvmpipe works headless;
set for you when ``MUJOCO_GL`` is unset and there is no display) or ``osmesa``.
"""

from __future__ import annotations

import os
import pickle
from typing import TYPE_CHECKING, Literal, cast

import gymnasium
import numpy as np

from imitrl.compat import random_reset_space
from imitrl.envs.success import SuccessInfo

if TYPE_CHECKING:
    from metaworld.sawyer_xyz_env import SawyerXYZEnv

__all__ = [
    "CAMERA",
    "LEROBOT_FEATURES",
    "MT10",
    "MT50",
    "OBS_TYPES",
    "PREFIX",
    "TASKS",
    "make_task",
    "register",
    "task_of",
]

PREFIX = "metaworld/"
MT10 = (
    "reach-v3",
    "push-v3",
    "pick-place-v3",
    "door-open-v3",
    "drawer-open-v3",
    "drawer-close-v3",
    "button-press-topdown-v3",
    "peg-insert-side-v3",
    "window-open-v3",
    "window-close-v3",
)
"""Meta-World's MT10 (``metaworld.MT10().train_classes``, in its order)"""
MT50 = (
    "assembly-v3", "basketball-v3", "bin-picking-v3", "box-close-v3",
    "button-press-topdown-v3", "button-press-topdown-wall-v3", "button-press-v3",
    "button-press-wall-v3", "coffee-button-v3", "coffee-pull-v3", "coffee-push-v3",
    "dial-turn-v3", "disassemble-v3", "door-close-v3", "door-lock-v3", "door-open-v3",
    "door-unlock-v3", "hand-insert-v3", "drawer-close-v3", "drawer-open-v3",
    "faucet-open-v3", "faucet-close-v3", "hammer-v3", "handle-press-side-v3",
    "handle-press-v3", "handle-pull-side-v3", "handle-pull-v3", "lever-pull-v3",
    "pick-place-wall-v3", "pick-out-of-hole-v3", "pick-place-v3", "plate-slide-v3",
    "plate-slide-side-v3", "plate-slide-back-v3", "plate-slide-back-side-v3",
    "peg-insert-side-v3", "peg-unplug-side-v3", "soccer-v3", "stick-push-v3",
    "stick-pull-v3", "push-v3", "push-wall-v3", "push-back-v3", "reach-v3",
    "reach-wall-v3", "shelf-place-v3", "sweep-into-v3", "sweep-v3", "window-open-v3",
    "window-close-v3",
)  # fmt: skip
"""all 50 v3 tasks (``metaworld.env_dict.ALL_V3_ENVIRONMENTS``, in its order)"""
TASKS = {"MT10": MT10, "MT50": MT50}
"""task sets by name"""
OBS_TYPES = ("state", "environment_state_agent_pos", "pixels_agent_pos")
CAMERA = "corner2"
"""LeRobot's camera, moved to ``cam_pos = [0.75, 0.075, 0.7]`` and its image flipped on
both axes (``lerobot/envs/metaworld.py``)"""
MAX_STEPS = 500
"""the ids' time limit: Meta-World's own ``max_path_length``"""

LEROBOT_FEATURES = {
    "observation.state": ("float32", (4,)),
    "action": ("float32", (4,)),
    "next.reward": ("float32", (1,)),
    "next.success": ("bool", (1,)),
    "observation.environment_state": ("float32", (39,)),
    "observation.image": ("image", (3, 480, 480)),
    "task_id": ("int16", (1,)),
}
"""``lerobot/metaworld_mt50``'s own features (its ``meta/info.json``, codebase v3.0),
besides LeRobot's bookkeeping columns"""


def _import_metaworld():
    try:
        import metaworld
    except ImportError as err:
        raise ValueError(
            "Meta-World envs need the metaworld package: pip install 'imitrl[metaworld]' "
            f"(metaworld 3.1.1 with mujoco 3.3.0); import failed: {err}"
        ) from err
    return metaworld


def task_of(env_id: str) -> str:
    """``"metaworld/pick-place-v3"`` (or ``"pick-place-v3"``) -> ``"pick-place-v3"``;
    ValueError naming the tasks for anything else."""
    task = env_id.removeprefix(PREFIX)
    if task not in MT50:
        raise ValueError(f"unknown Meta-World task {task!r}; the v3 tasks are {', '.join(MT50)}")
    return task


def _sawyer(env: gymnasium.Env) -> SawyerXYZEnv:
    """The raw Meta-World env under ``env`` (gymnasium types ``unwrapped`` as a plain Env)."""
    return cast("SawyerXYZEnv", env.unwrapped)


class _MetaWorldTask(gymnasium.Wrapper):
    """One task, varied per episode by the env's generator (module docstring)."""

    def __init__(self, env: gymnasium.Env, obs_type: str, fast_render: bool) -> None:
        super().__init__(env)
        self.obs_type, self._fast_render = obs_type, fast_render
        state = gymnasium.spaces.Box(-np.inf, np.inf, (39,), np.float64)
        if obs_type == "state":
            self.observation_space = state
        else:
            spaces: dict[str, gymnasium.spaces.Space] = {
                "agent_pos": gymnasium.spaces.Box(-np.inf, np.inf, (4,), np.float64),
                "environment_state": state,
            }
            if obs_type == "pixels_agent_pos":
                h, w = _sawyer(env).height, _sawyer(env).width
                spaces["pixels"] = gymnasium.spaces.Box(0, 255, (h, w, 3), np.uint8)
            self.observation_space = gymnasium.spaces.Dict(spaces)

    def _observe(self, obs: np.ndarray):
        if self.obs_type == "state":
            return obs
        out = {"agent_pos": obs[:4].copy(), "environment_state": obs}
        if self.obs_type == "pixels_agent_pos":
            out["pixels"] = self.render()
        return out

    def reset(self, *, seed: int | None = None, options=None):
        if seed is not None:
            _sawyer(self.env).seed(int(seed))  # the raw env ignores reset(seed=)
        obs, info = self.env.reset(options=options)
        return self._observe(obs), info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return self._observe(obs), reward, terminated, truncated, info

    def render(self):
        if self._fast_render and not _shadows_off(self.env.unwrapped):
            self.env.render()  # the first frame builds the renderer, shadows on: drawn again
            _shadows_off(self.env.unwrapped)
        frame = self.env.render()
        if frame is None:
            return None
        if _sawyer(self.env).camera_name == CAMERA:
            assert isinstance(frame, np.ndarray)  # an rgb_array (or depth_array) frame
            frame = np.ascontiguousarray(np.flip(frame, (0, 1)))  # as LeRobot's env
        return frame


def _shadows_off(raw) -> bool:
    """Shadows and reflections off in the renderer's scene, once built (False before: it
    is built at the first frame): a 480x480 frame on Mesa's llvmpipe from about 160 ms to
    about 25 ms; the geometry is unchanged."""
    import mujoco

    viewer = getattr(raw.mujoco_renderer, "viewer", None)
    if viewer is None or not hasattr(viewer, "scn"):
        return False
    viewer.scn.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
    viewer.scn.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
    return True


MAX_FRAME = 4096
"""largest rendered frame side: MuJoCo's offscreen buffer (a larger one fails inside EGL)"""


def make_task(
    task: str,
    *,
    obs_type: str = "state",
    terminate_on_success: bool = True,
    render_mode: Literal["human", "rgb_array", "depth_array"] | None = None,
    camera_name: str = CAMERA,
    width: int = 480,
    height: int = 480,
    fast_render: bool = False,
) -> gymnasium.Env:
    """One Meta-World v3 task (module docstring); the entry point of ``metaworld/<task>``.

    Args:
        task: a name of :data:`MT50` (``"pick-place-v3"``).
        obs_type: one of :data:`OBS_TYPES`.
        terminate_on_success: end an episode at its first success (Meta-World's and
            LeRobot's evaluation); False: only the time limit ends it (success stays set
            once reached).
        render_mode, camera_name, width, height: the raw env's rendering (``pixels_agent_pos``
            renders ``rgb_array`` frames of ``height x width``).
        fast_render: shadows and reflections off (about 6x faster frames on a CPU renderer,
            but not LeRobot's frames: its env renders them, and frames differ from the
            first step on); off by default, so the frames are LeRobot's byte for byte.
    """
    task = task_of(task)
    if obs_type not in OBS_TYPES:
        raise ValueError(f"obs_type must be one of {OBS_TYPES}, got {obs_type!r}")
    if obs_type == "pixels_agent_pos":
        render_mode = "rgb_array"
    if render_mode is not None and "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY"):
        # headless: MuJoCo's default (glfw) needs a display; EGL renders without one
        os.environ["MUJOCO_GL"] = "egl"
    _import_metaworld()
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS
    from metaworld.types import Task

    for name, size in (("width", width), ("height", height)):
        if isinstance(size, bool) or not isinstance(size, int) or not 1 <= size <= MAX_FRAME:
            raise ValueError(f"{name} must be an integer in [1, {MAX_FRAME}] pixels, got {size!r}")
    cls = ALL_V3_ENVIRONMENTS[task]
    raw = cls(render_mode=render_mode, camera_name=camera_name, width=width, height=height)
    cameras = [raw.model.camera(i).name for i in range(raw.model.ncam)]
    if camera_name not in cameras:  # MuJoCo renders its free camera for an unknown name
        raw.close()
        raise ValueError(f"camera_name {camera_name!r} is not one of {task}'s cameras {cameras}")
    # set_task needs a first placement; every reset draws its own below (seeded_rand_vec),
    # so the middle of the task's range serves (metaworld.MT1 would simulate 50 resets to
    # pick one: 0.7 s an env). The task data is what MT1 builds (its _make_tasks).
    space = random_reset_space(raw)
    assert space is not None  # every v3 task sets its reset range
    first = {
        "env_cls": cls,
        "rand_vec": (space.low + space.high) / 2,
        "partially_observable": False,
    }
    raw.set_task(Task(env_name=task, data=pickle.dumps(first)))
    if camera_name == CAMERA:
        raw.model.cam_pos[2] = [0.75, 0.075, 0.7]  # LeRobot's corner2
    # the time limit is gymnasium's TimeLimit (the id's 500, or make_env's max_episode_steps):
    # the raw env's own stop at max_path_length would raise on the step after it
    raw.max_path_length = np.iinfo(np.int64).max
    raw._freeze_rand_vec = False  # a new variation at every reset ...
    raw.seeded_rand_vec = True  # ... drawn from the env's generator (seeded by reset(seed=))
    env = _MetaWorldTask(raw, obs_type, fast_render)
    return SuccessInfo(env, terminate=terminate_on_success)


def register() -> None:
    """Register ``metaworld/<task>`` for every task (idempotent; importing this module
    does it)."""
    for task in MT50:
        env_id = PREFIX + task
        if env_id not in gymnasium.registry:
            gymnasium.register(
                id=env_id,
                entry_point="imitrl.envs.metaworld:make_task",
                kwargs={"task": task},
                max_episode_steps=MAX_STEPS,
            )


register()
