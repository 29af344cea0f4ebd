"""Discrete-time LQR and linear state feedback, the building blocks of the control experts.

``dlqr(A, B, Q, R)`` solves the discrete algebraic Riccati equation

    P = Q + A' P A - A' P B (R + B' P B)^{-1} B' P A

with a doubling iteration (the structure-preserving doubling algorithm of Chu, Fan,
Lin and Wang; each step doubles the horizon, so it converges quadratically) and
returns the gain ``K = (R + B' P B)^{-1} B' P A`` of the control law ``u = -K x`` that minimises ``sum_t x_t' Q x_t + u_t' R u_t`` subject to
``x_{t+1} = A x_t + B u_t`` (Anderson & Moore, *Optimal Control*, ch. 2). All math is
float64.

:class:`LinearFeedback` is the resulting expert as a module: ``u = clip(-K s(obs))``,
with ``s`` mapping an observation to the state the linearisation was made in.
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["LinearFeedback", "dlqr"]


def dlqr(
    A: torch.Tensor,
    B: torch.Tensor,
    Q: torch.Tensor,
    R: torch.Tensor,
    *,
    max_iter: int = 64,
    tol: float = 1e-14,
) -> torch.Tensor:
    """Discrete-time infinite-horizon LQR gain ``K`` ``[m, n]`` (float64).

    Args:
        A: ``[n, n]`` state transition.
        B: ``[n, m]`` control input matrix.
        Q: ``[n, n]`` symmetric positive semi-definite state cost.
        R: ``[m, m]`` symmetric positive definite control cost.
        max_iter: doubling steps before giving up (each doubles the horizon).
        tol: stop when ``max |P_{k+1} - P_k| <= tol * max |P_{k+1}|``.

    Raises:
        ValueError: shapes disagree, or the iteration does not converge (e.g. the
            pair ``(A, B)`` is not stabilisable).
    """
    A, B, Q, R = (torch.as_tensor(x, dtype=torch.float64) for x in (A, B, Q, R))
    n = A.shape[0]
    if A.shape != (n, n) or B.ndim != 2 or B.shape[0] != n:
        raise ValueError(f"need A [n, n] and B [n, m], got {tuple(A.shape)} and {tuple(B.shape)}")
    m = B.shape[1]
    if Q.shape != (n, n) or R.shape != (m, m):
        raise ValueError(
            f"need Q [{n}, {n}] and R [{m}, {m}], got {tuple(Q.shape)} and {tuple(R.shape)}"
        )
    # Doubling: A_k = A^(2^k) in closed loop, G_k -> controllability Gramian-like term,
    # H_k = P of the 2^k-step horizon, converging to the stabilising solution P.
    eye = torch.eye(n, dtype=torch.float64)
    Ak, Gk, Hk = A.clone(), B @ torch.linalg.solve(R, B.T), Q.clone()
    for _ in range(max_iter):
        W = torch.linalg.solve(eye + Gk @ Hk, torch.cat([Ak, Gk], dim=1))  # (I + G H)^-1 [A, G]
        WA, WG = W[:, :n], W[:, n:]
        H_next = Hk + Ak.T @ Hk @ WA
        Gk = Gk + Ak @ WG @ Ak.T
        Ak = Ak @ WA
        H_next = (H_next + H_next.T) / 2
        if not torch.isfinite(H_next).all():
            break
        done = float((H_next - Hk).abs().max()) <= tol * float(H_next.abs().max())
        Hk = H_next
        if done:
            return torch.linalg.solve(R + B.T @ Hk @ B, B.T @ Hk @ A)
    raise ValueError(
        f"the Riccati iteration did not converge in {max_iter} doubling steps: "
        "is (A, B) stabilisable?"
    )


class LinearFeedback(nn.Module):
    """``u = clip(-K (s(obs) - s*), low, high)``: saturated linear state feedback.

    Args:
        gain: ``K`` ``[m, n]``.
        low: ``[m]`` lower action bound.
        high: ``[m]`` upper action bound.
        state: maps observations ``[..., d]`` to states ``[..., n]`` (identity if None).
        setpoint: ``s*`` ``[n]`` (zero if None).

    Input ``[..., d]`` (any float dtype); output float32 ``[..., m]``.
    """

    gain: torch.Tensor  # the buffers registered in __init__
    low: torch.Tensor
    high: torch.Tensor
    setpoint: torch.Tensor

    def __init__(
        self,
        gain: torch.Tensor,
        low: torch.Tensor,
        high: torch.Tensor,
        *,
        state: nn.Module | None = None,
        setpoint: torch.Tensor | None = None,
    ) -> None:
        super().__init__()
        gain = torch.as_tensor(gain, dtype=torch.float64)
        if gain.ndim != 2:
            raise ValueError(f"gain must be [m, n], got shape {tuple(gain.shape)}")
        m, n = gain.shape
        self.register_buffer("gain", gain)
        self.register_buffer("low", torch.as_tensor(low, dtype=torch.float64).reshape(m))
        self.register_buffer("high", torch.as_tensor(high, dtype=torch.float64).reshape(m))
        sp = torch.zeros(n, dtype=torch.float64) if setpoint is None else setpoint
        self.register_buffer("setpoint", torch.as_tensor(sp, dtype=torch.float64).reshape(n))
        self.state = state if state is not None else nn.Identity()

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        s = self.state(obs.to(torch.float64))
        if s.shape[-1:] != self.setpoint.shape:
            raise ValueError(
                f"the state has {self.setpoint.shape[0]} entries, got shape {tuple(s.shape)} "
                f"from an observation of shape {tuple(obs.shape)}"
            )
        u = -(s - self.setpoint) @ self.gain.T
        return torch.minimum(torch.maximum(u, self.low), self.high).to(torch.float32)
