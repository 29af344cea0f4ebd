"""The compounding-error chain: an imitator that never recovers vs one that always does.

On a chain where the expert earns 1 per step, an imitator errs independently with
probability ``eps`` at each step. The *cloned* imitator earns nothing after its first
error (it never saw an off-chain state); the *recovering* one loses only the step it
fumbled. Lost return over horizon ``T``:

    cloned:      T - sum_{t=1}^{T} (1 - eps)^t      (<= eps T^2 / 2, Theta(eps T^2))
    recovering:  eps T
"""

from __future__ import annotations

import numpy as np

__all__ = ["chain_exact", "chain_monte_carlo"]


def chain_monte_carlo(
    eps: float, horizon: int, samples: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """``[T]`` lost return of the cloned and the recovering imitator, T = 1 .. horizon.

    Draws ``rng.random((samples, horizon)) < eps`` once and reads every horizon off it.
    """
    wrong = rng.random((samples, horizon)) < eps  # [samples, T]
    T = np.arange(1, horizon + 1)
    gap_cloned = T - np.cumprod(~wrong, axis=1).cumsum(axis=1).mean(axis=0)
    gap_recovering = T - (~wrong).cumsum(axis=1).mean(axis=0)
    return gap_cloned, gap_recovering


def chain_exact(eps: float, horizon: int) -> tuple[np.ndarray, np.ndarray]:
    """Expected lost returns ``[T]`` (closed forms in the module docstring)."""
    T = np.arange(1, horizon + 1)
    gap_cloned = T - np.cumsum((1.0 - eps) ** T)
    gap_recovering = eps * T.astype(np.float64)
    return gap_cloned, gap_recovering
