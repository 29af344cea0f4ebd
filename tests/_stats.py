"""Small statistical helpers for tests (no scipy dependency)."""

from __future__ import annotations

import math

import torch


def chi_square_pvalue(observed: torch.Tensor, expected: torch.Tensor) -> float:
    """Upper-tail p-value of Pearson's chi-square statistic with ``k - 1`` degrees of freedom."""
    stat = float(((observed - expected) ** 2 / expected).sum())
    dof = observed.numel() - 1
    if dof == 0:
        return 1.0
    return float(
        torch.special.gammaincc(
            torch.tensor(dof / 2.0, dtype=torch.float64),
            torch.tensor(stat / 2.0, dtype=torch.float64),
        )
    )


def binomial_band(n: int, p: float, z: float = 4.0) -> tuple[float, float]:
    """``n p +- z sqrt(n p (1 - p))``: a band a Binomial(n, p) count leaves with tiny probability."""
    sd = math.sqrt(n * p * (1 - p))
    return n * p - z * sd, n * p + z * sd


def welch_t(a: torch.Tensor, b: torch.Tensor) -> float:
    """Welch's t statistic for mean(a) - mean(b)."""
    a, b = a.double(), b.double()
    va, vb = a.var(unbiased=True) / a.numel(), b.var(unbiased=True) / b.numel()
    return float((a.mean() - b.mean()) / torch.sqrt(va + vb).clamp_min(1e-300))
