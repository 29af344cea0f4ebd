"""Meta-World demonstrations written as ``lerobot/metaworld_mt50`` holds them.

``lerobot/metaworld_mt50`` (LeRobot's Meta-World dataset, codebase v3.0, 80 fps) has
these features besides LeRobot's bookkeeping (:data:`~imitrl.envs.metaworld.
LEROBOT_FEATURES`): ``observation.state`` float32 [4] (the hand's ``agent_pos``),
``observation.environment_state`` float32 [39] (the full Meta-World state),
``observation.image`` a [3, 480, 480] image (the ``corner2`` camera, placed and flipped as
LeRobot's env does), ``action`` float32 [4], ``next.reward`` float32 [1], ``next.success``
bool [1], ``task_id`` int16 [1] (LeRobot's task id); its task strings are LeRobot's
instructions (:data:`~imitrl.envs.metaworld_tasks.LEROBOT_TASKS`).

Rows recorded in ``make_env("metaworld/<task>-v3", env_kwargs={"obs_type":
"pixels_agent_pos"})`` carry every one of these under imitrl's keys
(``"observation"``, ``"environment_state"``, ``"pixels"``, ``"expert_action"``,
``("next", "reward")``, ``("next", "success")``); :func:`save_metaworld_lerobot` adds the
task id and writes exactly that feature set. ``load_lerobot`` reads such a dataset (or
LeRobot's own) back into the same keys, so a learner trained on it acts in the same env
without a key mapping.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import torch
from tensordict import TensorDict, TensorDictBase

from imitrl import keys
from imitrl.datasets.lerobot._write import save_lerobot
from imitrl.envs.metaworld import LEROBOT_FEATURES, task_of
from imitrl.envs.metaworld_tasks import LEROBOT_TASKS

__all__ = ["FPS", "save_metaworld_lerobot"]

FPS = 80
"""``lerobot/metaworld_mt50``'s frame rate (LeRobot's Meta-World env config)"""
_NAMES = {"action": {"axes": ["x", "y", "z", "gripper"]}}
"""the dataset's per-entry ``names`` (its ``observation.environment_state`` is named
``["keypoints"]``, one name for 39 entries, which LeRobot's own writer would refuse: left
None here)"""

_SOURCE = {
    keys.OBSERVATION: (torch.float32, (4,)),
    keys.ENVIRONMENT_STATE: (torch.float32, (39,)),
    keys.EXPERT_ACTION: (torch.float32, (4,)),
    (keys.NEXT, keys.REWARD): (torch.float32, (1,)),
    (keys.NEXT, "success"): (torch.bool, None),
}
"""the row keys a recording needs, with their dtype and per-frame shape (None: [] or [1])"""


def _check(task: str, rows: TensorDictBase) -> None:
    present = rows.keys(include_nested=True)
    for key, (dtype, shape) in {**_SOURCE, keys.PIXELS: (torch.uint8, None)}.items():
        if key not in present:
            raise ValueError(
                f"{task}: rows lack {key!r}; record them in make_env('metaworld/{task}', "
                "env_kwargs={'obs_type': 'pixels_agent_pos'}) with metaworld_expert(task, "
                "observation_key='environment_state')"
            )
        value = rows.get(key)
        frame = tuple(value.shape[1:])
        ok = frame == shape if shape is not None else frame in ((), (1,))
        if key == keys.PIXELS:
            ok = frame == (480, 480, 3)
        if value.dtype != dtype or not ok:
            raise ValueError(
                f"{task}: {key!r} is {value.dtype} {list(frame)}, lerobot/metaworld_mt50 "
                f"holds {dtype} {list(shape or (480, 480, 3) if key == keys.PIXELS else [1])}"
            )


def _as_lerobot(task: str, rows: TensorDictBase, first_episode: int, task_index: int) -> TensorDict:
    """One task's rows under the dataset's keys and layouts (episodes renumbered)."""
    n = rows.shape[0]
    task_id, _ = LEROBOT_TASKS[task]
    episodes = rows.get(keys.EPISODE)
    _, dense = torch.unique(episodes, return_inverse=True)  # 0..E-1 in episode-id order
    return TensorDict(
        {
            **{k: rows.get(k) for k in _SOURCE},
            (keys.NEXT, "success"): rows.get((keys.NEXT, "success")).reshape(n, 1),
            keys.PIXELS: rows.get(keys.PIXELS).permute(0, 3, 1, 2),  # [3, 480, 480]
            "task_id": torch.full((n, 1), task_id, dtype=torch.int16),
            "task_index": torch.full((n,), task_index, dtype=torch.int64),
            keys.EPISODE: dense + first_episode,
            keys.STEP: rows.get(keys.STEP),
        },
        batch_size=[n],
    )


def save_metaworld_lerobot(
    recordings: Mapping[str, TensorDictBase], path: str | Path, *, overwrite: bool = False
) -> Path:
    """Write Meta-World recordings as a LeRobot v3.0 dataset with exactly
    ``lerobot/metaworld_mt50``'s features (module docstring).

    Args:
        recordings: task (``"pick-place-v3"`` or ``"metaworld/pick-place-v3"``) -> its
            rows (``rollout_episodes`` in that task's env with ``obs_type=
            "pixels_agent_pos"``, 480 x 480 frames); the tasks' episodes follow each
            other in this order.
        path, overwrite: as in :func:`~imitrl.datasets.save_lerobot`.

    Returns:
        the dataset directory.
    """
    if not recordings:
        raise ValueError("recordings must map at least one Meta-World task to its rows")
    parts, instructions, first = [], [], 0
    for name, rows in recordings.items():
        task = task_of(name)
        _check(task, rows)
        instruction = LEROBOT_TASKS[task][1]
        if instruction not in instructions:  # push and push-back share theirs
            instructions.append(instruction)
        part = _as_lerobot(task, rows, first, instructions.index(instruction))
        first = int(part.get(keys.EPISODE).max()) + 1
        parts.append(part)
    rows = torch.cat(parts)
    return save_lerobot(
        rows,
        path,
        fps=FPS,
        tasks=instructions,
        robot_type="metaworld",
        names=_NAMES,
        overwrite=overwrite,
        features=tuple(LEROBOT_FEATURES),
    )
