"""Small statistics for reports: Student-t quantiles and intervals over seeds (no scipy)."""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import torch

__all__ = ["student_t_quantile", "t_interval", "t_two_sided_tail"]


def _beta_fraction(a: float, b: float, x: float) -> float:
    """The continued fraction of the regularised incomplete beta function (modified
    Lentz; Press et al., Numerical Recipes, 6.4), for ``x < (a + 1) / (a + b + 2)``."""
    tiny = 1e-300
    c, d = 1.0, 1.0 - (a + b) * x / (a + 1)
    d = 1.0 / (d if abs(d) > tiny else tiny)
    h = d
    for m in range(1, 100_000):
        for aa in (
            m * (b - m) * x / ((a + 2 * m - 1) * (a + 2 * m)),
            -(a + m) * (a + b + m) * x / ((a + 2 * m) * (a + 2 * m + 1)),
        ):
            d = 1.0 + aa * d
            d = 1.0 / (d if abs(d) > tiny else tiny)
            c = 1.0 + aa / c
            c = c if abs(c) > tiny else tiny
            h *= d * c
        if abs(d * c - 1.0) < 1e-16:
            return h
    raise ArithmeticError(f"the incomplete beta fraction did not converge (a={a}, b={b}, x={x})")


def _incomplete_beta(a: float, b: float, x: float, y: float) -> float:
    """``I_x(a, b)``, the regularised incomplete beta function, given ``x`` and ``y = 1 - x``
    each computed without cancellation; to about 1e-15 relative, its small values too (a
    tail of 1e-12 keeps its digits)."""
    if x <= 0.0:
        return 0.0
    if y <= 0.0:
        return 1.0
    log_front = math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b) + a * math.log(x)
    log_front += b * math.log(y)
    if x < (a + 1) / (a + b + 2):
        return math.exp(log_front) * _beta_fraction(a, b, x) / a
    return 1.0 - math.exp(log_front) * _beta_fraction(b, a, y) / b


def t_two_sided_tail(t: float, df: int) -> float:
    """``P(|T| > t)`` for Student's t with ``df`` degrees of freedom, ``t >= 0``:
    ``I_{df / (df + t^2)}(df / 2, 1 / 2)`` (Abramowitz and Stegun 26.7.1), computed
    without cancellation however small it is."""
    if t <= 0.0:
        return 1.0
    if math.isinf(t):
        return 0.0
    return _incomplete_beta(df / 2, 0.5, df / (df + t * t), t * t / (df + t * t))


@functools.lru_cache(maxsize=256)
def student_t_quantile(p: float, df: int) -> float:
    """The ``p`` quantile (``0.5 <= p < 1``) of Student's t with ``df`` degrees of freedom,
    to about 1e-13 relative (the closed forms at 1 and 2 degrees of freedom agree).

    The ``t`` where the two-sided tail :func:`t_two_sided_tail` equals ``2 (1 - p)``, by
    bisection on ``log t``; cached, as an evaluation loop asks again for the same level
    and episode count."""
    if not 0.5 <= p < 1.0 or df < 1:
        raise ValueError(f"need 0.5 <= p < 1 and df >= 1, got p={p}, df={df}")
    tail = 2.0 * (1.0 - p)
    if tail >= 1.0:
        return 0.0
    lo, hi = -40.0, 1.0  # log t; the tail falls from 1 (t = 0) to 0 (t infinite)
    while t_two_sided_tail(math.exp(lo), df) < tail:
        lo *= 2.0  # p within 1e-17 of 0.5
    while t_two_sided_tail(math.exp(hi), df) > tail:
        hi *= 2.0
    while hi - lo > 1e-14:
        mid = (lo + hi) / 2
        if t_two_sided_tail(math.exp(mid), df) > tail:
            lo = mid
        else:
            hi = mid
    return math.exp((lo + hi) / 2)


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
