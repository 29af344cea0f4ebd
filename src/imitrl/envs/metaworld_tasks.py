"""What LeRobot knows of each Meta-World task: its id and its language instruction.

LeRobot's Meta-World env and its ``lerobot/metaworld_mt50`` dataset name every v3 task
by a fixed id (the dataset's ``task_id`` column, int16) and an instruction (the
dataset's task string), both from LeRobot's ``src/lerobot/envs/metaworld_config.json``
(``TASK_NAME_TO_ID``, ``TASK_DESCRIPTIONS``). They are data, copied here so that a
dataset recorded by imitrl carries LeRobot's own values. ``push-v3`` and
``push-back-v3`` share one instruction, which is why ``metaworld_mt50`` has 49 tasks.
"""

from __future__ import annotations

__all__ = ["LEROBOT_TASKS"]

LEROBOT_TASKS: dict[str, tuple[int, str]] = {
    "assembly-v3": (0, "Pick up a nut and place it onto a peg"),
    "basketball-v3": (1, "Dunk the basketball into the basket"),
    "bin-picking-v3": (2, "Grasp the puck from one bin and place it into another bin"),
    "box-close-v3": (3, "Grasp the cover and close the box with it"),
    "button-press-topdown-v3": (4, "Press a button from the top"),
    "button-press-topdown-wall-v3": (5, "Bypass a wall and press a button from the top"),
    "button-press-v3": (6, "Press a button"),
    "button-press-wall-v3": (7, "Bypass a wall and press a button"),
    "coffee-button-v3": (8, "Push a button on the coffee machine"),
    "coffee-pull-v3": (9, "Pull a mug from a coffee machine"),
    "coffee-push-v3": (10, "Push a mug under a coffee machine"),
    "dial-turn-v3": (11, "Rotate a dial 180 degrees"),
    "disassemble-v3": (12, "Pick a nut out of a peg"),
    "door-close-v3": (13, "Close a door with a revolving joint"),
    "door-lock-v3": (14, "Lock the door by rotating the lock clockwise"),
    "door-open-v3": (15, "Open a door with a revolving joint"),
    "door-unlock-v3": (16, "Unlock the door by rotating the lock counter-clockwise"),
    "drawer-close-v3": (17, "Push and close a drawer"),
    "drawer-open-v3": (18, "Open a drawer"),
    "faucet-close-v3": (19, "Rotate the faucet clockwise"),
    "faucet-open-v3": (20, "Rotate the faucet counter-clockwise"),
    "hammer-v3": (21, "Hammer a screw on the wall"),
    "hand-insert-v3": (22, "Insert the gripper into a hole"),
    "handle-press-side-v3": (23, "Press a handle down sideways"),
    "handle-press-v3": (24, "Press a handle down"),
    "handle-pull-side-v3": (25, "Pull a handle up sideways"),
    "handle-pull-v3": (26, "Pull a handle up"),
    "lever-pull-v3": (27, "Pull a lever down 90 degrees"),
    "peg-insert-side-v3": (28, "Insert a peg sideways"),
    "peg-unplug-side-v3": (29, "Unplug a peg sideways"),
    "pick-out-of-hole-v3": (30, "Pick up a puck from a hole"),
    "pick-place-v3": (31, "Pick and place a puck to a goal"),
    "pick-place-wall-v3": (32, "Pick a puck, bypass a wall and place the puck"),
    "plate-slide-back-side-v3": (33, "Get a plate from the cabinet sideways"),
    "plate-slide-back-v3": (34, "Get a plate from the cabinet"),
    "plate-slide-side-v3": (35, "Slide a plate into a cabinet sideways"),
    "plate-slide-v3": (36, "Slide a plate into a cabinet"),
    "push-back-v3": (37, "Push the puck to a goal"),
    "push-v3": (38, "Push the puck to a goal"),
    "push-wall-v3": (39, "Bypass a wall and push a puck to a goal"),
    "reach-v3": (40, "Reach a goal position"),
    "reach-wall-v3": (41, "Bypass a wall and reach a goal"),
    "shelf-place-v3": (42, "Pick and place a puck onto a shelf"),
    "soccer-v3": (43, "Kick a soccer into the goal"),
    "stick-pull-v3": (44, "Grasp a stick and pull a box with the stick"),
    "stick-push-v3": (45, "Grasp a stick and push a box using the stick"),
    "sweep-into-v3": (46, "Sweep a puck into a hole"),
    "sweep-v3": (47, "Sweep a puck off the table"),
    "window-open-v3": (48, "Push and open a window"),
    "window-close-v3": (49, "Push and close a window"),
}
"""task -> (LeRobot's task id, its instruction)"""
