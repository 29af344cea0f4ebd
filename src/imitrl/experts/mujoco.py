"""LQR experts for gymnasium's MuJoCo balancing tasks (needs the ``mujoco`` extra).

At construction the simulator is linearised about the upright equilibrium by
central finite differences of one env step (``frame_skip`` MuJoCo steps with the
action held), ``x_{t+1} ~ A x_t + B u_t`` with ``x = (qpos, qvel)``, and
:func:`~imitrl.experts.lqr.dlqr` gives the gain. The expert is then a plain
function of the observation, ``u = clip(-K x(obs))``, so DAgger can query it at any
state. Returns over 100 episodes (``benchmarks/bc_vs_dagger.py``,
``tests/experts/test_experts.py``): InvertedPendulum-v5 1000 / 1000, InvertedDoublePendulum-v5
about 9360 / 9360.

The gain is tuned for the env's time step. An action repeat (TorchRL's
``frame_skip``) holds each action for several steps and breaks it; build the expert
with ``action_repeat`` equal to the repeat to re-identify the model at that step.
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium
import numpy as np
import torch
from gymnasium.error import DependencyNotInstalled
from torch import nn

from imitrl import keys
from imitrl.experts.lqr import LinearFeedback, dlqr
from imitrl.policies.experts import Expert

__all__ = [
    "Linearization",
    "inverted_double_pendulum_expert",
    "inverted_pendulum_expert",
    "linearize_mujoco",
]


@dataclass(frozen=True)
class Linearization:
    """One env step of a MuJoCo env, linearised about ``(x0, u0 = 0)`` (see ``drift``)."""

    A: torch.Tensor
    """``[n, n]`` float64, ``n = nq + nv``"""
    B: torch.Tensor
    """``[n, m]`` float64, ``m = nu``"""
    x0: torch.Tensor
    """``[n]`` the state linearised about, ``(init_qpos, init_qvel)`` (``u0 = 0``)"""
    drift: torch.Tensor
    """``[n]`` ``f(x0, u0) - x0``: non-zero where ``x0`` is not an exact equilibrium
    (InvertedPendulum-v5's pole is modelled 1 mm off vertical), so
    ``f(x, u) ~ x0 + drift + A (x - x0) + B (u - u0)``"""
    dt: float
    """seconds per linearised step (env ``dt`` x ``action_repeat``)"""
    action_low: torch.Tensor
    """``[m]`` lower action bound of the env"""
    action_high: torch.Tensor
    """``[m]`` upper action bound of the env"""


def linearize_mujoco(env_id: str, *, action_repeat: int = 1, eps: float = 1e-6) -> Linearization:
    """Central finite differences of ``action_repeat`` env steps at ``(init_qpos, init_qvel)``, ``u = 0``.

    The experts measure their state from ``x0`` (zero for both balancing envs).

    Raises:
        ValueError: ``gymnasium[mujoco]`` is missing, or ``env_id`` is not a MuJoCo env.
    """
    if int(action_repeat) != action_repeat or action_repeat < 1:
        raise ValueError(f"action_repeat must be a positive integer, got {action_repeat!r}")
    try:
        from gymnasium.envs.mujoco.mujoco_env import MujocoEnv

        env = gymnasium.make(env_id).unwrapped
    except (ImportError, DependencyNotInstalled) as err:  # pragma: no cover - install-dependent
        # gymnasium raises DependencyNotInstalled (not an ImportError) without mujoco
        raise ValueError(
            f"{env_id} needs MuJoCo: pip install 'imitrl[mujoco]' (gymnasium[mujoco])"
        ) from err
    except gymnasium.error.Error as err:
        raise ValueError(f"unknown or unbuildable gymnasium env id {env_id!r}: {err}") from err
    if not isinstance(env, MujocoEnv):
        raise ValueError(f"{env_id} is not a MuJoCo env ({type(env).__name__})")
    env.reset(seed=0)
    nq, nv, nu = env.model.nq, env.model.nv, env.model.nu
    x0 = np.concatenate([env.init_qpos, env.init_qvel]).astype(np.float64)
    u0 = np.zeros(nu)

    def step(x: np.ndarray, u: np.ndarray) -> np.ndarray:
        env.set_state(x[:nq].copy(), x[nq:].copy())
        env.do_simulation(u, env.frame_skip * int(action_repeat))
        return np.concatenate([env.data.qpos, env.data.qvel]).copy()

    A = np.zeros((nq + nv, nq + nv))
    B = np.zeros((nq + nv, nu))
    for i in range(nq + nv):
        d = np.zeros(nq + nv)
        d[i] = eps
        A[:, i] = (step(x0 + d, u0) - step(x0 - d, u0)) / (2 * eps)
    for j in range(nu):
        d = np.zeros(nu)
        d[j] = eps
        B[:, j] = (step(x0, u0 + d) - step(x0, u0 - d)) / (2 * eps)
    drift = step(x0, u0) - x0
    space = env.action_space
    assert isinstance(space, gymnasium.spaces.Box)  # a MuJoCo env's: the actuators' ctrlrange
    low, high = space.low, space.high
    dt = float(env.dt) * int(action_repeat)
    env.close()
    return Linearization(
        A=torch.from_numpy(A),
        B=torch.from_numpy(B),
        x0=torch.from_numpy(x0),
        drift=torch.from_numpy(drift),
        dt=dt,
        action_low=torch.as_tensor(low, dtype=torch.float64),
        action_high=torch.as_tensor(high, dtype=torch.float64),
    )


class _DoublePendulumState(nn.Module):
    """InvertedDoublePendulum-v5 observation ``[..., 9]`` -> state ``[..., 6]``.

    The observation is ``(x, sin t1, sin t2, cos t1, cos t2, v, w1, w2, f)``
    (velocities clipped to +-10, ``f`` a constraint force); the state is
    ``(x, t1, t2, v, w1, w2)``.
    """

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        if obs.shape[-1:] != (9,):
            raise ValueError(
                f"InvertedDoublePendulum observations have 9 entries, got {tuple(obs.shape)}"
            )
        angles = torch.atan2(obs[..., 1:3], obs[..., 3:5])
        return torch.cat([obs[..., :1], angles, obs[..., 5:8]], dim=-1)


class _Check(nn.Module):
    def __init__(self, n: int, name: str) -> None:
        super().__init__()
        self.n, self.name = n, name

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        if obs.shape[-1:] != (self.n,):
            raise ValueError(
                f"{self.name} observations have {self.n} entries, got {tuple(obs.shape)}"
            )
        return obs


def _lqr_expert(
    env_id: str,
    state: nn.Module,
    Q: torch.Tensor | None,
    R: torch.Tensor | None,
    action_repeat: int,
    observation_key,
) -> Expert:
    lin = linearize_mujoco(env_id, action_repeat=action_repeat)
    n, m = lin.B.shape
    Q = torch.eye(n, dtype=torch.float64) if Q is None else torch.as_tensor(Q)
    R = torch.eye(m, dtype=torch.float64) if R is None else torch.as_tensor(R)
    K = dlqr(lin.A, lin.B, Q, R)
    return Expert(
        LinearFeedback(K, lin.action_low, lin.action_high, state=state, setpoint=lin.x0),
        in_keys=[observation_key],
    )


def inverted_pendulum_expert(
    *,
    Q: torch.Tensor | None = None,
    R: torch.Tensor | None = None,
    action_repeat: int = 1,
    observation_key=keys.OBSERVATION,
) -> Expert:
    """InvertedPendulum-v5: LQR on the identified linearisation (1000 / 1000).

    Args:
        Q: ``[4, 4]`` state cost on ``(x, theta, v, w)`` (identity if None).
        R: ``[1, 1]`` action cost (identity if None).
        action_repeat: steps each action is held (match the env's ``frame_skip``).
        observation_key: where the observation ``[..., 4]`` is read.

    Writes float32 ``EXPERT_ACTION`` ``[..., 1]`` in ``[-3, 3]``.
    """
    return _lqr_expert(
        "InvertedPendulum-v5",
        _Check(4, "InvertedPendulum"),
        Q,
        R,
        action_repeat,
        observation_key,
    )


def inverted_double_pendulum_expert(
    *,
    Q: torch.Tensor | None = None,
    R: torch.Tensor | None = None,
    action_repeat: int = 1,
    observation_key=keys.OBSERVATION,
) -> Expert:
    """InvertedDoublePendulum-v5: LQR on the identified linearisation (about 9360).

    Args:
        Q: ``[6, 6]`` state cost on ``(x, t1, t2, v, w1, w2)`` (identity if None).
        R: ``[1, 1]`` action cost (identity if None).
        action_repeat: steps each action is held (match the env's ``frame_skip``).
        observation_key: where the observation ``[..., 9]`` is read.

    Writes float32 ``EXPERT_ACTION`` ``[..., 1]`` in ``[-1, 1]``.
    """
    return _lqr_expert(
        "InvertedDoublePendulum-v5",
        _DoublePendulumState(),
        Q,
        R,
        action_repeat,
        observation_key,
    )
