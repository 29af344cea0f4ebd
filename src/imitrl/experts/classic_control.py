"""Queryable experts for gymnasium's classic-control tasks, as TensorDict modules.

Each expert is a batched function of the observation (no simulator access), so
DAgger can ask it about any state the learner visits. Returns over 100 episodes
(seeds 0-99) are measured by ``benchmarks/bc_vs_dagger.py`` and checked in
``tests/experts/test_experts.py``:

================= ========================================== ===================
env               expert                                     return (100 eps)
================= ========================================== ===================
CartPole-v1       linear state feedback, push right if K.s>0 500 / 500
MountainCar-v0    push in the direction of the velocity      about -119 / -200
Acrobot-v1        torque against the first link's velocity   about -83 / -500
Pendulum-v1       energy-shaping swing-up + LQR at the top   about -150 (0 best)
================= ========================================== ===================
"""

from __future__ import annotations

import torch
from torch import nn

from imitrl import keys
from imitrl.experts.lqr import dlqr
from imitrl.policies.experts import Expert

__all__ = [
    "CARTPOLE_GAINS",
    "PENDULUM",
    "PendulumSwingUp",
    "acrobot_expert",
    "cartpole_expert",
    "mountaincar_expert",
    "pendulum_expert",
    "pendulum_linearization",
]

CARTPOLE_GAINS = (0.5, 1.0, 10.0, 2.0)
"""state-feedback gains on (x, x_dot, theta, theta_dot): push right when K . obs > 0"""

PENDULUM = {"g": 10.0, "m": 1.0, "l": 1.0, "dt": 0.05, "max_torque": 2.0}
"""gymnasium Pendulum-v1's constants (``g`` is the env's default ``g=10.0``)"""


def _check_dim(obs: torch.Tensor, n: int, name: str) -> None:
    if obs.shape[-1:] != (n,):
        raise ValueError(f"{name} observations have {n} entries, got shape {tuple(obs.shape)}")


def cartpole_expert(*, observation_key=keys.OBSERVATION, gains=CARTPOLE_GAINS) -> Expert:
    """CartPole-v1: linear state feedback, ``a = 1[K . obs > 0]`` (500/500 from any reset).

    Observations ``[..., 4]`` float; writes int64 ``EXPERT_ACTION`` ``[...]``.
    """
    K = torch.tensor(gains, dtype=torch.float32)

    zero = torch.zeros((), dtype=torch.float32)  # a tensor operand: cheaper than 0 per step

    def act(obs: torch.Tensor) -> torch.Tensor:
        _check_dim(obs, 4, "CartPole")
        return ((obs.to(torch.float32) * K).sum(-1) > zero).long()

    return Expert.from_callable(act, observation_key=observation_key)


def mountaincar_expert(*, observation_key=keys.OBSERVATION) -> Expert:
    """MountainCar-v0: accelerate in the direction of the velocity (2 if ``v >= 0`` else 0).

    Pumping energy this way reaches the flag from every reset (about -119 per episode).
    Observations ``[..., 2]`` = (position, velocity); writes int64 ``EXPERT_ACTION`` ``[...]``.
    """

    def act(obs: torch.Tensor) -> torch.Tensor:
        _check_dim(obs, 2, "MountainCar")
        return torch.where(obs[..., 1] >= 0, 2, 0).long()

    return Expert.from_callable(act, observation_key=observation_key)


def acrobot_expert(*, observation_key=keys.OBSERVATION) -> Expert:
    """Acrobot-v1: torque at the elbow against the first link's velocity (0 if ``w1 > 0`` else 2).

    A bang-bang energy pump: about -83 per episode (the time limit gives -500).
    Observations ``[..., 6]`` = (cos t1, sin t1, cos t2, sin t2, w1, w2); writes int64
    ``EXPERT_ACTION`` ``[...]``.
    """

    def act(obs: torch.Tensor) -> torch.Tensor:
        _check_dim(obs, 6, "Acrobot")
        return torch.where(obs[..., 4] > 0, 0, 2).long()

    return Expert.from_callable(act, observation_key=observation_key)


def pendulum_linearization(dt: float = PENDULUM["dt"]) -> tuple[torch.Tensor, torch.Tensor]:
    """``(A, B)`` of Pendulum-v1 linearised at the top, state ``(theta, theta_dot)``.

    The env integrates semi-implicitly, ``w' = w + (a sin(th) + b u) dt``,
    ``th' = th + w' dt`` with ``a = 3g / (2l)``, ``b = 3 / (m l^2)``; with ``sin(th) ~ th``:
    ``A = [[1 + a dt^2, dt], [a dt, 1]]``, ``B = [[b dt^2], [b dt]]`` (float64).
    """
    g, m, length = PENDULUM["g"], PENDULUM["m"], PENDULUM["l"]
    a, b = 3 * g / (2 * length), 3 / (m * length * length)
    A = torch.tensor([[1 + a * dt * dt, dt], [a * dt, 1.0]], dtype=torch.float64)
    B = torch.tensor([[b * dt * dt], [b * dt]], dtype=torch.float64)
    return A, B


class PendulumSwingUp(nn.Module):
    """Pendulum-v1 expert: swing up by energy shaping, balance by LQR near the top.

    With ``E = w^2 / 2 - a (1 - cos th)`` (energy per unit inertia, 0 when resting
    upright, ``a = 3g / 2l``), the swing-up torque is

    * ``"energy"``: ``u = clip(-k w E, -2, 2)``, a smooth pump that vanishes as ``E -> 0``;
    * ``"bang_bang"``: ``u = 2 sign(-w E)``, full torque whichever way pumps energy.

    Inside ``cos th > lqr_cos`` the LQR gain of :func:`pendulum_linearization` under the
    env's own cost (``Q = diag(1, 0.1)``, ``R = 0.001``) takes over. Input
    ``[..., 3]`` = (cos th, sin th, w); output float32 ``[..., 1]`` in ``[-2, 2]``.
    """

    gain: torch.Tensor  # the buffer registered in __init__

    def __init__(
        self, *, swing_up: str = "energy", energy_gain: float = 1.0, lqr_cos: float = 0.9
    ) -> None:
        super().__init__()
        if swing_up not in ("energy", "bang_bang"):
            raise ValueError(f"swing_up must be 'energy' or 'bang_bang', got {swing_up!r}")
        if not -1.0 < lqr_cos < 1.0:
            raise ValueError(f"lqr_cos must be in (-1, 1), got {lqr_cos}")
        self.swing_up, self.energy_gain, self.lqr_cos = swing_up, float(energy_gain), lqr_cos
        A, B = pendulum_linearization()
        K = dlqr(A, B, torch.diag(torch.tensor([1.0, 0.1])), torch.tensor([[0.001]]))
        self.register_buffer("gain", K[0])  # [2]
        self.a = 3 * PENDULUM["g"] / (2 * PENDULUM["l"])
        self.u_max = PENDULUM["max_torque"]
        self._values = {
            "one": 1.0,
            "two": 2.0,
            "a": self.a,
            "-energy_gain": -self.energy_gain,
            "u_max": self.u_max,
            "rest": 1e-3,
            "lqr_cos": self.lqr_cos,
        }
        self._constants: dict[torch.device, dict[str, torch.Tensor]] = {}

    def _constants_on(self, device: torch.device) -> dict[str, torch.Tensor]:
        """The constants as float64 0-d tensors on ``device`` (made once per device)."""
        if device not in self._constants:
            self._constants[device] = {
                n: torch.tensor(v, dtype=torch.float64, device=device)
                for n, v in self._values.items()
            }
        return self._constants[device]

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        _check_dim(obs, 3, "Pendulum")
        # float64 throughout. A rollout labels one state per step, where each torch call
        # costs more than its arithmetic and one with a Python number about twice one
        # with a tensor: the constants are float64 0-d tensors of the same values
        k = self._constants_on(obs.device)
        c, s, w = obs.to(torch.float64).unbind(-1)
        g_th, g_w = self.gain.unbind()
        th = torch.atan2(s, c)
        u_lqr = -(g_th * th + g_w * w)
        energy = w * w / k["two"] - k["a"] * (k["one"] - c)
        if self.swing_up == "energy":
            u_swing = k["-energy_gain"] * w * energy
        else:
            u_swing = k["u_max"] * torch.sign(-w * energy)
        # at rest (w = 0) neither law moves the pendulum: push to start the swing
        u_swing = torch.where(w.abs() < k["rest"], k["u_max"], u_swing)
        u = torch.where(c > k["lqr_cos"], u_lqr, u_swing)
        return u.clamp(-self.u_max, self.u_max).to(torch.float32).unsqueeze(-1)


def pendulum_expert(
    *,
    swing_up: str = "energy",
    energy_gain: float = 1.0,
    lqr_cos: float = 0.9,
    observation_key=keys.OBSERVATION,
) -> Expert:
    """Pendulum-v1: energy-shaping (or bang-bang) swing-up + LQR (about -150 per episode).

    See :class:`PendulumSwingUp`. Writes float32 ``EXPERT_ACTION`` ``[..., 1]``.
    """
    return Expert(
        PendulumSwingUp(swing_up=swing_up, energy_gain=energy_gain, lqr_cos=lqr_cos),
        in_keys=[observation_key],
    )
