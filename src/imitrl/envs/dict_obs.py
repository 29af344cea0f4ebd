"""A gymnasium ``Dict`` observation, renamed onto imitrl's key vocabulary as LeRobot names it.

Robot envs (gym-pusht's ``pixels_agent_pos`` and ``environment_state_agent_pos``,
gym-aloha, most manipulation suites) observe a ``Dict``. LeRobot evaluates a policy in
such an env by renaming its entries to the dataset's features
(``lerobot/envs/utils.py``, ``preprocess_observation``); :class:`DictObservation` renames
them to the buffer keys :func:`~imitrl.datasets.load_lerobot` gives those features, so a
policy trained on a LeRobot dataset reads the same keys in the matching env:

* ``agent_pos`` (LeRobot's ``observation.state``) -> ``"observation"``, float32 ``[d]``;
* ``pixels``, one image (``observation.image``) -> ``"pixels"``, uint8 ``[H, W, 3]``;
* ``pixels``, a ``Dict`` of cameras (``observation.images.<cam>``) -> ``("pixels", cam)``,
  uint8 ``[H, W, 3]`` each;
* ``environment_state`` (``observation.environment_state``) -> ``"environment_state"``,
  float32 ``[d]``.

``environment_state`` has no key of its own in :mod:`imitrl.keys`, and ``load_lerobot``
loads ``observation.environment_state`` beside ``observation.state`` only when asked:
``key_map={"observation.environment_state": "environment_state"}`` gives the key this
env writes (:data:`ENVIRONMENT_STATE`). Any other entry is refused, naming it and what is
accepted: drop it (``gymnasium.wrappers.FilterObservation``) or flatten the whole
observation (``FlattenObservation``) before ``gymnasium.register``. The state entries
are cast to float32 (as LeRobot does, ``.float()``); images stay uint8 height x width x
channels (LeRobot's own layout on disk; a pixel learner scales them in its network).
"""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np
from gymnasium.spaces import Box, Dict, Space

from imitrl import keys

__all__ = ["ENTRY_KEYS", "ENVIRONMENT_STATE", "DictObservation"]

ENVIRONMENT_STATE = keys.ENVIRONMENT_STATE
"""the key of a Dict env's ``environment_state`` entry (float32 ``[*batch, d]``)"""

ENTRY_KEYS: dict[str, str] = {
    "agent_pos": keys.OBSERVATION,
    "pixels": keys.PIXELS,
    "environment_state": ENVIRONMENT_STATE,
}
"""Dict entry -> the key :class:`DictObservation` writes it under (cameras nest under ``PIXELS``)"""


def _state_box(space: Any, entry: str, where: str) -> Box:
    """A state entry's space as a float32 vector Box; ValueError unless a numeric ``[d]`` Box."""
    if not isinstance(space, Box) or len(space.shape) != 1 or space.dtype.kind not in "fiub":
        raise ValueError(
            f"{where}: Dict entry {entry!r} must be a numeric vector Box [d], got {space}"
        )
    return Box(space.low.astype(np.float32), space.high.astype(np.float32), dtype=np.float32)


def _image_box(space: Any, entry: str, where: str) -> Box:
    """A camera's space, checked: a uint8 ``[H, W, 3]`` Box."""
    if not (
        isinstance(space, Box)
        and space.dtype == np.uint8
        and len(space.shape) == 3
        and space.shape[-1] == 3
    ):
        raise ValueError(
            f"{where}: Dict entry {entry!r} must be a uint8 image Box [H, W, 3], got {space}"
        )
    return space


def _pixels_space(space: Any, where: str) -> Box | Dict:
    """The ``pixels`` entry: one image, or a Dict of named cameras (one level, plain names)."""
    if not isinstance(space, Dict):
        return _image_box(space, "pixels", where)
    if not space.spaces:
        raise ValueError(f"{where}: Dict entry 'pixels' holds no camera")
    cameras: dict[str, Space] = {}
    for cam, sub in space.spaces.items():
        if not isinstance(cam, str) or not cam or "." in cam or "/" in cam:
            raise ValueError(
                f"{where}: camera name {cam!r} under 'pixels' must be a non-empty string "
                "without '.' or '/' (LeRobot's observation.images.<cam> splits names at '.')"
            )
        cameras[cam] = _image_box(sub, f"pixels/{cam}", where)
    return Dict(cameras)


def mapped_space(space: Dict, where: str) -> Dict:
    """The renamed observation space of a Dict env (module docstring), checked.

    Raises:
        ValueError: an entry other than :data:`ENTRY_KEYS` (naming it and the accepted
            ones), an entry of the wrong kind, or neither ``agent_pos`` nor ``pixels``.
    """
    other = sorted(str(k) for k in space.spaces if k not in ENTRY_KEYS)
    if other:
        raise ValueError(
            f"{where}: Dict observation entries {other} have no imitrl key; accepted entries "
            f"(LeRobot's names) are {sorted(ENTRY_KEYS)} -> "
            f"{[ENTRY_KEYS[k] for k in sorted(ENTRY_KEYS)]}. Drop the others with "
            "gymnasium.wrappers.FilterObservation, or flatten the observation with "
            "gymnasium.wrappers.FlattenObservation"
        )
    if "agent_pos" not in space.spaces and "pixels" not in space.spaces:
        raise ValueError(
            f"{where}: a Dict observation needs 'agent_pos' (the state a learner reads as "
            f"{keys.OBSERVATION!r}) or 'pixels' (a camera); got {sorted(space.spaces)}"
        )
    out: dict[str, gymnasium.Space] = {}
    for entry, sub in space.spaces.items():
        if entry == "pixels":
            out[keys.PIXELS] = _pixels_space(sub, where)
        else:
            out[ENTRY_KEYS[entry]] = _state_box(sub, entry, where)
    return Dict(out)


class DictObservation(gymnasium.ObservationWrapper):
    """A gymnasium env with a ``Dict`` observation, its entries renamed onto imitrl's keys
    (module docstring): ``{"agent_pos": ..., "pixels": ...}`` -> ``{"observation":
    float32 [d], "pixels": uint8 [H, W, 3]}``. TorchRL's ``GymWrapper`` then gives each
    as a key of the same name (a Dict of cameras as nested keys ``("pixels", cam)``).

    Raises:
        ValueError: the observation space is not a ``Dict``, or holds what
            :func:`mapped_space` refuses.
    """

    def __init__(self, env: gymnasium.Env, where: str) -> None:
        super().__init__(env)
        if not isinstance(env.observation_space, Dict):
            raise ValueError(f"{where}: expected a Dict observation space")
        self.observation_space = mapped_space(env.observation_space, where)

    def observation(self, observation: dict[str, Any]) -> dict[str, Any]:
        """The env's Dict observation under imitrl's keys (state entries as float32)."""
        out: dict[str, Any] = {}
        for entry, value in observation.items():
            key = ENTRY_KEYS[entry]
            out[key] = value if key == keys.PIXELS else np.asarray(value, dtype=np.float32)
        return out
