"""Scripted experts for a few gymnasium tasks, written as plain batched functions.

Each function maps a batch of observations ``[..., obs_dim]`` (a torch tensor or a
numpy array) to a batch of actions ``[..., act_dim]`` (or ``[...]`` integer actions
for a discrete env). A torch input gives a torch output on the same device, a numpy
input a numpy output, so every function can be handed to
``imitrl.policies.Expert.from_callable`` or driven directly by a gymnasium loop::

    from imitrl.policies import Expert
    from mypkg import experts

    expert = Expert.from_callable(experts.lunar_lander_continuous)

The arithmetic is done in numpy on a CPU copy of the observation (these experts are
tiny); that also makes the LunarLander ports bit-for-bit identical to gymnasium's
own ``heuristic``, which runs in numpy float32 on float32 observations.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

__all__ = ["lunar_lander", "lunar_lander_continuous", "mountain_car", "reacher"]


def _batched(fn: Callable[[np.ndarray], np.ndarray]) -> Callable:
    """Run ``fn`` on a numpy view of the observation; give back the caller's array type."""

    def wrapper(obs):
        if isinstance(obs, torch.Tensor):
            device = obs.device
            out = fn(_as_float(obs.detach().cpu().numpy()))
            return torch.from_numpy(np.array(out)).to(device)  # (ascontiguousarray makes 0-d 1-d)
        return fn(_as_float(np.asarray(obs)))

    wrapper.__name__ = fn.__name__
    wrapper.__qualname__ = fn.__qualname__
    wrapper.__doc__ = fn.__doc__
    return wrapper


def _as_float(obs: np.ndarray) -> np.ndarray:
    # keep float32/float64 as given (gymnasium's heuristic computes in the obs dtype)
    return obs if np.issubdtype(obs.dtype, np.floating) else obs.astype(np.float32)


# --------------------------------------------------------------------------------------
# MountainCarContinuous-v0: obs = [position, velocity], action in [-1, 1]
# --------------------------------------------------------------------------------------


@_batched
def mountain_car(obs: np.ndarray) -> np.ndarray:
    """Bang-bang energy pumping for ``MountainCarContinuous-v0``.

    Push at full force (exactly +-1.0, the action bounds) in the direction of the
    velocity, which adds energy on every swing until the car crests the right hill.
    At rest (velocity exactly 0, i.e. at reset) it pushes left first: the start is
    near the valley floor, so a first swing to the left builds more height.
    Returns ``float32`` actions of shape ``[..., 1]``.
    """
    velocity = obs[..., 1]
    action = np.where(velocity > 0, 1.0, -1.0).astype(np.float32)
    return action[..., None]


# --------------------------------------------------------------------------------------
# LunarLander-v3 / LunarLanderContinuous-v3: a vectorised port of
# gymnasium.envs.box2d.lunar_lander.heuristic
# obs = [x, y, vx, vy, angle, angular_velocity, leg0_contact, leg1_contact]
# --------------------------------------------------------------------------------------


def _lander_todo(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(hover_todo, angle_todo)`` exactly as gymnasium's heuristic computes them.

    Same operations in the same order and dtype as the reference, so the result is
    bit-identical (e.g. the +-0.4 clamp is a float32 0.4 there too, by NumPy 2's
    scalar promotion rules).
    """
    angle_targ = s[..., 0] * 0.5 + s[..., 2] * 1.0  # angle should point towards center
    angle_targ = np.clip(angle_targ, -0.4, 0.4)  # more than 0.4 rad (22 degrees) is bad
    hover_targ = 0.55 * np.abs(s[..., 0])  # target y proportional to horizontal offset

    angle_todo = (angle_targ - s[..., 4]) * 0.5 - (s[..., 5]) * 1.0
    hover_todo = (hover_targ - s[..., 1]) * 0.5 - (s[..., 3]) * 0.5

    contact = (s[..., 6] != 0) | (s[..., 7] != 0)  # legs have contact
    angle_todo = np.where(contact, np.zeros_like(angle_todo), angle_todo)
    # after contact only reduce the fall speed
    hover_todo = np.where(contact, -(s[..., 3]) * 0.5, hover_todo)
    return hover_todo, angle_todo


@_batched
def lunar_lander_continuous(obs: np.ndarray) -> np.ndarray:
    """gymnasium's ``heuristic`` for ``LunarLanderContinuous-v3``, batched.

    Returns ``[..., 2]`` actions ``[main, lateral]`` in ``[-1, 1]``, in the
    observation's float dtype (float32 for the env's observations).
    """
    hover_todo, angle_todo = _lander_todo(obs)
    action = np.stack([hover_todo * 20 - 1, -angle_todo * 20], axis=-1)
    return np.clip(action, -1, +1)


@_batched
def lunar_lander(obs: np.ndarray) -> np.ndarray:
    """gymnasium's ``heuristic`` for the discrete ``LunarLander-v3``, batched.

    Returns ``int64`` actions of shape ``[...]``: 0 noop, 1 fire left engine,
    2 fire main engine, 3 fire right engine.
    """
    hover_todo, angle_todo = _lander_todo(obs)
    return np.select(
        [
            (hover_todo > np.abs(angle_todo)) & (hover_todo > 0.05),
            angle_todo < -0.05,
            angle_todo > +0.05,
        ],
        [2, 3, 1],
        default=0,
    ).astype(np.int64)


# --------------------------------------------------------------------------------------
# Reacher-v5: obs = [cos q0, cos q1, sin q0, sin q1, target_x, target_y,
#                    dq0, dq1, fingertip_x - target_x, fingertip_y - target_y]
# --------------------------------------------------------------------------------------

REACHER_L0 = 0.1  # base -> elbow (reacher.xml: body1 at x=0.1)
REACHER_L1 = 0.11  # elbow -> fingertip (fingertip body at x=0.11)
REACHER_KP = 0.3  # joint-space PD gains, in action units (joint torque = 200 * action);
REACHER_KD = 0.05  # tuned on seeds 100..129 (not the 0..19 used by measure.py)


@_batched
def reacher(obs: np.ndarray) -> np.ndarray:
    """Inverse kinematics + joint-space PD controller for ``Reacher-v5``.

    The joint angles come from their cos/sin, the target from ``obs[4:6]`` (the
    fingertip - target vector ``obs[8:10]`` is the same information once the forward
    kinematics is known). Two-link IK gives an elbow-up and an elbow-down joint
    target; the one nearer the current joint angles is tracked with
    ``a = KP * (q* - q) - KD * dq``, clipped to the action bounds ``[-1, 1]``. The
    base joint is unlimited, so its error is wrapped to ``(-pi, pi]``. The gains are
    low because the control cost ``|a|^2`` is charged every step: the arm settles
    on the target in about 25 of the 50 steps. Returns ``[..., 2]`` actions in the
    observation's float dtype.
    """
    l0, l1 = REACHER_L0, REACHER_L1
    q = np.arctan2(obs[..., 2:4], obs[..., 0:2])  # joint angles [q0, q1]
    dq = obs[..., 6:8]
    tx, ty = obs[..., 4], obs[..., 5]

    # two-link inverse kinematics: both elbow solutions, [..., 2 solutions]
    cos_q1 = np.clip((tx**2 + ty**2 - l0**2 - l1**2) / (2 * l0 * l1), -1.0, 1.0)
    elbow = np.arccos(cos_q1)[..., None] * np.array([1.0, -1.0])
    base = np.arctan2(ty, tx)[..., None] - np.arctan2(l1 * np.sin(elbow), l0 + l1 * np.cos(elbow))
    err = np.stack([_wrap(base - q[..., :1]), elbow - q[..., 1:]], axis=-1)
    # the solution nearer in joint space, [..., 2 joints]
    nearest = np.argmin((err**2).sum(-1), axis=-1)[..., None, None]
    err = np.take_along_axis(err, nearest, axis=-2)[..., 0, :]

    action = REACHER_KP * err - REACHER_KD * dq
    return np.clip(action, -1.0, 1.0).astype(obs.dtype)


def _wrap(angle: np.ndarray) -> np.ndarray:
    return np.arctan2(np.sin(angle), np.cos(angle))
