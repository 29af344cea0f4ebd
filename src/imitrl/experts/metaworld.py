"""Meta-World's scripted experts, batched over lanes: ``metaworld_expert("pick-place-v3")``.

Every Meta-World v3 task ships a closed-loop scripted policy
(``metaworld.policies.ENV_POLICY_MAP``) that maps one 39-d observation to a 4-d action.
The policies keep no state, so they label any state a learner visits: a queryable
expert for DAgger. :func:`metaworld_expert` calls the task's policy on each lane's
observation.

The scripted policies return actions outside the action bounds [-1, 1] (up to about 25
in magnitude) and rely on the env, which clips every action it executes
(``np.clip(action, -1, 1)`` in ``SawyerXYZEnv.set_xyz_action``). The expert clips its
labels the same way (``Expert.from_callable(..., clip=True)``): the label is the action
the env executes, the one a learner bounded by the action spec can imitate.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
import torch
from torchrl.data import Bounded

from imitrl import keys
from imitrl.policies.experts import Expert

if TYPE_CHECKING:
    from metaworld.policies.policy import Policy

__all__ = ["metaworld_expert"]


STATE_DIM = 39
"""the width of Meta-World's state (hand, gripper, two objects, the goal)"""


class _LanePolicy:
    """The task's scripted policy on ``[*B, 39]`` observations (a loop over lanes)."""

    def __init__(self, task: str, key: str) -> None:
        from imitrl.envs.metaworld import _import_metaworld, task_of

        _import_metaworld()
        from metaworld.policies import ENV_POLICY_MAP

        self.task, self.key = task_of(task), key
        # each a concrete policy class: mypy reads the map as of the abstract Policy
        make: Callable[[], Policy] = ENV_POLICY_MAP[self.task]
        self.policy = make()
        # its move() warns at every call whose gain exceeds the bounds: the labels are
        # clipped on purpose (module docstring)
        warnings.filterwarnings(
            "ignore", message=r"Constant\(s\) may be too high", category=UserWarning
        )

    def __call__(self, obs: torch.Tensor) -> torch.Tensor:
        if obs.shape[-1] != STATE_DIM:
            other = keys.ENVIRONMENT_STATE if self.key == keys.OBSERVATION else keys.OBSERVATION
            raise ValueError(
                f"metaworld_expert({self.task!r}) reads Meta-World's {STATE_DIM}-d state from "
                f"{self.key!r}, which holds {obs.shape[-1]} numbers: with the LeRobot "
                f"observation types (obs_type='environment_state_agent_pos' or "
                f"'pixels_agent_pos') the state is {keys.ENVIRONMENT_STATE!r}: pass "
                f"observation_key={other!r}"
            )
        flat = obs.detach().cpu().reshape(-1, obs.shape[-1]).to(torch.float64).numpy()
        actions = np.stack([self.policy.get_action(o) for o in flat]).astype(np.float32)
        return torch.from_numpy(actions).reshape(*obs.shape[:-1], actions.shape[-1])


def metaworld_expert(task: str, *, observation_key=None) -> Expert:
    """The scripted policy of Meta-World task ``task`` (``"pick-place-v3"`` or
    ``"metaworld/pick-place-v3"``) as an :class:`Expert` with clipped labels.

    Args:
        observation_key: the key of the 39-d state: None picks ``"observation"``
            (``obs_type="state"``, the default env); pass ``"environment_state"`` for
            the LeRobot observation types, where ``"observation"`` is the hand's 4-d
            ``agent_pos``.
    """
    key = keys.OBSERVATION if observation_key is None else observation_key
    # every task's action space (so the labels are clipped wherever the expert acts,
    # before any env binds it: as_actor(expert), a DAgger relabel)
    spec = Bounded(low=-1.0, high=1.0, shape=(4,), dtype=torch.float32)
    return Expert.from_callable(
        _LanePolicy(task, key), action_spec=spec, observation_key=key, clip=True
    )
