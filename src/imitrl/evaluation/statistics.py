"""Small statistics for reports: Student-t quantiles and intervals over seeds (no scipy)."""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import torch

__all__ = ["student_t_quantile", "t_interval"]


def _t_cdf(t: float, df: int) -> float:
    """``P(T <= t)`` for ``t >= 0`` by Simpson's rule on the density (error < 1e-10 here)."""
    n = 4000  # even number of panels
    x = torch.linspace(0.0, t, n + 1, dtype=torch.float64)
    log_norm = math.lgamma((df + 1) / 2) - math.lgamma(df / 2) - 0.5 * math.log(df * math.pi)
    pdf = torch.exp(log_norm - (df + 1) / 2 * torch.log1p(x * x / df))
    w = torch.ones(n + 1, dtype=torch.float64)
    w[1:-1:2], w[2:-1:2] = 4.0, 2.0
    return 0.5 + float((w * pdf).sum()) * (t / n) / 3


@functools.lru_cache(maxsize=256)
def student_t_quantile(p: float, df: int) -> float:
    """The ``p`` quantile (``0.5 <= p < 1``) of Student's t with ``df`` degrees of freedom.

    Cached: a bisection over 4000-panel integrals costs about 13 ms, and an evaluation
    loop asks again for the same level and episode count."""
    if not 0.5 <= p < 1.0 or df < 1:
        raise ValueError(f"need 0.5 <= p < 1 and df >= 1, got p={p}, df={df}")
    lo, hi = 0.0, 1.0
    while _t_cdf(hi, df) < p:
        hi *= 2.0
    for _ in range(60):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if _t_cdf(mid, df) < p else (lo, mid)
    return (lo + hi) / 2


def t_interval(
    values: Sequence[float | None], confidence: float = 0.95
) -> tuple[float, float, float]:
    """Mean and Student-t interval ``mean +- t_{(1+c)/2, n-1} s / sqrt(n)`` over seeds.

    ``None`` entries are dropped; no values give NaNs, one value gives NaN bounds.
    """
    x = torch.tensor([v for v in values if v is not None], dtype=torch.float64)
    if x.numel() == 0:
        return math.nan, math.nan, math.nan
    mean = float(x.mean())
    if x.numel() == 1:
        return mean, math.nan, math.nan
    half = (
        student_t_quantile(0.5 + confidence / 2, x.numel() - 1)
        * float(x.std(unbiased=True))
        / math.sqrt(x.numel())
    )
    return mean, mean - half, mean + half
