"""Input checks shared by the tabular modules: one row tolerance, one message per mistake.

The lowest tabular module (it imports only numpy and torch), so that the MDP,
the gymnasium model reader and the policy tables check probabilities alike.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

__all__ = ["ROW_TOL", "as_float64", "check_gamma", "check_probabilities"]

ROW_TOL = 1e-9
"""How far from 1 a probability row (kernel, initial distribution, policy) may sum."""


def check_gamma(gamma: float) -> None:
    """Raise ``ValueError`` unless ``gamma`` is a number in ``[0, 1]``."""
    if not (isinstance(gamma, (int, float)) and 0.0 <= gamma <= 1.0):
        raise ValueError(f"gamma must be a number in [0, 1], got {gamma!r}")


def as_float64(x: Any, name: str) -> np.ndarray:
    """``x`` (array-like or tensor) as a finite float64 numpy array named ``name`` in errors."""
    arr = x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
    if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
        raise ValueError(f"{name} must be a real numeric array, got dtype {arr.dtype}")
    arr = arr.astype(np.float64)
    if not np.isfinite(arr).all():
        raise ValueError(
            f"{name} must be finite, found {int((~np.isfinite(arr)).sum())} NaN/inf entries"
        )
    return arr


def check_probabilities(p: np.ndarray, name: str, axis: int) -> None:
    """Raise ``ValueError`` unless ``p`` is non-negative and sums to 1 (within ``ROW_TOL``) along ``axis``."""
    if (p < 0).any():
        idx = tuple(int(i) for i in np.argwhere(p < 0)[0])
        raise ValueError(f"{name} has a negative probability {p[idx]:.3g} at index {idx}")
    sums = p.sum(axis=axis)
    bad = np.abs(sums - 1.0) > ROW_TOL
    if np.any(bad):
        idx = tuple(int(i) for i in np.argwhere(np.atleast_1d(bad))[0])
        total = np.atleast_1d(sums)[idx]
        raise ValueError(
            f"{name} rows must sum to 1 (tolerance {ROW_TOL}); row {idx} sums to {total:.12g}"
        )
