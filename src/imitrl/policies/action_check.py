"""Does an action fit an action spec: the one check, and the one exact cast.

:func:`check_action` is the library's single answer to "does this action fit this
spec": the spec's dtype, the shape ``(*batch_shape, *spec.shape)`` and, on request,
the spec's range. The rollouts check the first action a policy writes with it (envs
do not: a gymnasium env may silently read the first entry of a longer action).

:func:`cast_action` turns what an expert's function returned (a torch tensor, a
numpy array, a python number) into the spec's dtype and shape when, and only when,
nothing is lost: float64 values that float32 holds to a relative ``1e-6``, whole
numbers into an integer action, a missing trailing action dimension of size 1.
Anything else is refused with what was returned and what the spec needs.

``spec`` is always ONE lane's spec (``env.action_spec_unbatched``); the batch a
value carries is passed as ``batch_shape``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torchrl.data import Bounded, Categorical, TensorSpec

__all__ = ["cast_action", "check_action"]


def _needs(spec: TensorSpec, batch_shape: Sequence[int]) -> str:
    return f"dtype {spec.dtype}, shape {(*batch_shape, *spec.shape)}"


def check_action(
    action: torch.Tensor,
    spec: TensorSpec,
    *,
    batch_shape: Sequence[int] = (),
    name: str = "action",
    in_range: bool = False,
) -> None:
    """Raise ``ValueError`` unless ``action`` fits ``spec``.

    Args:
        action: ``[*batch_shape, *spec.shape]``.
        spec: one lane's action spec (``env.action_spec_unbatched``).
        batch_shape: the leading dimensions ``action`` carries (an env's batch size,
            ``(N,)`` for N rows of a buffer).
        name: how the error names ``action`` (a key, "the policy's action", ...).
        in_range: also check the values: ``[0, n)`` for a ``Categorical``, the bounds
            of a ``Bounded``, ``spec.is_in`` for any other spec.
    """
    want = (*batch_shape, *spec.shape)
    if action.dtype != spec.dtype or tuple(action.shape) != want:
        raise ValueError(
            f"{name} has dtype {action.dtype}, shape {tuple(action.shape)}; "
            f"the action spec needs {_needs(spec, batch_shape)}"
        )
    if not in_range or action.numel() == 0:
        return
    if isinstance(spec, Categorical):
        n = spec.space.n
        lo, hi = int(action.min()), int(action.max())
        if lo < 0 or hi >= n:
            raise ValueError(f"{name} holds action {lo if lo < 0 else hi}, outside [0, {n})")
    elif isinstance(spec, Bounded):
        low, high = spec.space.low, spec.space.high  # [*spec.shape], broadcast over the batch
        if bool((action < low).any() or (action > high).any()):
            raise ValueError(
                f"{name} holds actions outside the bounds [{low.tolist()}, {high.tolist()}]"
            )
    elif not spec.expand(*want).is_in(action):
        raise ValueError(f"{name} holds actions outside {spec}")


def _as_tensor(value: object, source: str) -> torch.Tensor:
    if isinstance(value, torch.Tensor):
        return value
    array = np.array(value)  # a contiguous copy; python ints -> int64, floats -> float64
    try:
        return torch.from_numpy(array)
    except TypeError as err:
        raise ValueError(
            f"{source} returned {type(value).__name__} of numpy dtype {array.dtype}, "
            "not a numeric tensor or array"
        ) from err


def _exact(value: torch.Tensor, cast: torch.Tensor, rtol: float) -> bool:
    """Whether ``cast`` (``value`` in another dtype) holds the same numbers."""
    if cast.dtype.is_floating_point:
        # float64 -> float32 rounds by at most 6e-8 relative; overflow (1e300 -> inf)
        # is refused; below the smallest normal number (1.2e-38) the absolute error
        # is at most that number, and the value is kept
        atol = torch.finfo(cast.dtype).tiny
        return bool(
            torch.isclose(cast.double(), value.double(), rtol=rtol, atol=atol, equal_nan=True).all()
        )
    if value.dtype.is_floating_point and not bool(torch.isfinite(value).all()):
        return False
    return bool((cast.to(value.dtype) == value).all())  # 0.5 -> 0 -> 0.0 != 0.5


def cast_action(
    value: object,
    spec: TensorSpec,
    *,
    batch_shape: Sequence[int] = (),
    rtol: float = 1e-6,
    source: str = "the expert",
) -> torch.Tensor:
    """``value`` in ``spec``'s dtype and shape ``(*batch_shape, *spec.shape)``, cast only when exact.

    Accepted: a tensor or array already in the spec's dtype and shape; another dtype
    whose values the spec's dtype holds exactly (floats to a relative ``rtol``; ints,
    bools and whole-number floats into an integer action); a value missing a
    trailing action dimension of size 1 (``(8,)`` for ``(8, 1)``).

    Raises:
        ValueError: naming what ``source`` returned (dtype, shape) and what the spec
            needs, when no exact cast exists (a value out of float32's range, 0.5 into
            an integer action, a width 2 action for a width 1 spec, ...).
    """
    x = _as_tensor(value, source)
    returned = (x.dtype, tuple(x.shape))
    want = (*batch_shape, *spec.shape)
    if tuple(x.shape) != want:
        if tuple(spec.shape[-1:]) == (1,) and tuple(x.shape) == want[:-1]:
            x = x.unsqueeze(-1)
        else:
            raise _refused(source, returned, spec, batch_shape, "the shapes differ")
    if x.dtype == spec.dtype:
        return x
    if x.dtype.is_complex or spec.dtype.is_complex:
        raise _refused(source, returned, spec, batch_shape, "no exact cast between these dtypes")
    cast = x.to(spec.dtype)
    if not _exact(x, cast, rtol):
        raise _refused(
            source, returned, spec, batch_shape, f"its values do not fit {spec.dtype} exactly"
        )
    return cast


def _refused(
    source: str, returned: tuple, spec: TensorSpec, batch_shape: Sequence[int], why: str
) -> ValueError:
    dtype, shape = returned
    return ValueError(
        f"{source} returned dtype {dtype}, shape {shape}; the action spec needs "
        f"{_needs(spec, batch_shape)} ({why})"
    )
