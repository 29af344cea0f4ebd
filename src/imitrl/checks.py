"""Checks of config fields at the boundary, each failing with a message that names the
field, what was expected and what was given (``BCConfig(batch_size=2.5)`` says so,
instead of a ``TypeError`` deep inside a fit).

Integers are Python or numpy integers, never floats or bools (``2.0`` steps is a
mistake caught here, not a step count); numbers are finite reals.
"""

from __future__ import annotations

import math
import numbers
from typing import Any

__all__ = ["boolean", "finite_at_least", "integer", "number", "whole"]


def integer(value: Any, name: str, *, minimum: int | None = None, none_ok: bool = False) -> None:
    """``value`` is an integer (>= ``minimum``), or None when ``none_ok``; ValueError."""
    if value is None and none_ok:
        return
    ok = isinstance(value, numbers.Integral) and not isinstance(value, bool)
    if not ok or (minimum is not None and value < minimum):
        expected = "an integer" + (f" >= {minimum}" if minimum is not None else "")
        expected += " or None" if none_ok else ""
        raise ValueError(f"{name} must be {expected}, got {value!r} ({type(value).__name__})")


def number(value: Any, name: str, *, positive: bool = False, none_ok: bool = False) -> None:
    """``value`` is a finite real number (> 0 when ``positive``), or None when ``none_ok``."""
    if value is None and none_ok:
        return
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool)
    ok = ok and math.isfinite(value) and (not positive or value > 0)
    if not ok:
        expected = "a finite number" + (" > 0" if positive else "")
        expected += " or None" if none_ok else ""
        raise ValueError(f"{name} must be {expected}, got {value!r} ({type(value).__name__})")


def boolean(value: Any, name: str, *, none_ok: bool = False) -> None:
    """``value`` is True or False (or None when ``none_ok``)."""
    if (value is None and none_ok) or isinstance(value, bool):
        return
    expected = "True or False" + (" or None" if none_ok else "")
    raise ValueError(f"{name} must be {expected}, got {value!r} ({type(value).__name__})")


def whole(value: Any, low: int) -> bool:
    """Whether ``value`` is an integer (Python or numpy, not a bool, not a float such as
    ``2.5`` or ``inf``) of at least ``low``: for checks that word their own message."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool) and int(value) >= low


def finite_at_least(value: Any, low: float) -> bool:
    """Whether ``value`` is a finite real number (not a bool) of at least ``low``."""
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool)
    return ok and math.isfinite(value) and value >= low
