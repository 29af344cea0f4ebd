"""Gymnasium spaces as Minari writes them, and demonstration values checked against them.

:func:`serialize_space` gives Minari 0.5's JSON (``minari/serialization.py``, the text
:mod:`._spaces` parses back): ``Box`` (``dtype``, ``shape``, ``low``, ``high``),
``Discrete`` (``dtype`` ``"int64"``, ``start``, ``n``), ``MultiDiscrete``, ``MultiBinary``
and the nested ``Dict``. :func:`space_values` turns one episode's tensors into the numpy
arrays written for a space: one array per leaf (a nested dict for a ``Dict``), each in
the space's dtype when that changes no value, of the space's per-step shape, finite and
inside the space (Box bounds, Discrete ranges) - what ``space.contains`` asks of every
step, checked for the whole episode at once.
"""

from __future__ import annotations

import json
from typing import Any

import gymnasium
import numpy as np
import torch
from gymnasium.spaces import Box, Dict, Discrete, MultiBinary, MultiDiscrete
from tensordict import TensorDictBase

from imitrl.datasets._common import check_finite, exact_cast

__all__ = ["check_space", "serialize_space", "space_values"]

_LEAVES = (Box, Discrete, MultiDiscrete, MultiBinary)


def check_space(space: Any, what: str) -> None:
    """ValueError unless ``space`` is a space :func:`serialize_space` writes (and
    :func:`~imitrl.datasets.load_minari` reads back into tensors)."""
    if isinstance(space, Dict):
        for name, sub in space.spaces.items():
            if not isinstance(name, str) or not name or "/" in name:
                raise ValueError(f"{what}: Dict entry {name!r} must be a name without '/'")
            check_space(sub, f"{what}[{name!r}]")
    elif not isinstance(space, _LEAVES):
        raise ValueError(
            f"{what} must be a gymnasium Box, Discrete, MultiDiscrete, MultiBinary or Dict "
            f"of them, got {type(space).__name__}"
        )


def _serialized(space: gymnasium.Space) -> dict[str, Any]:
    if isinstance(space, Box):
        return {
            "type": "Box",
            "dtype": str(space.dtype),
            "shape": list(space.shape),
            "low": space.low.tolist(),
            "high": space.high.tolist(),
        }
    if isinstance(space, Discrete):
        return {"type": "Discrete", "dtype": "int64", "start": int(space.start), "n": int(space.n)}
    if isinstance(space, MultiDiscrete):
        return {
            "type": "MultiDiscrete",
            "dtype": str(space.dtype),
            "nvec": space.nvec.tolist(),
            "start": space.start.tolist(),
        }
    if isinstance(space, MultiBinary):
        n = space.n
        return {"type": "MultiBinary", "n": n.tolist() if isinstance(n, np.ndarray) else n}
    assert isinstance(space, Dict)  # the last kind check_space lets through
    return {"type": "Dict", "subspaces": {k: _serialized(s) for k, s in space.spaces.items()}}


def serialize_space(space: gymnasium.Space) -> str:
    """Minari 0.5's JSON text of ``space`` (``minari.serialization.serialize_space``)."""
    return json.dumps(_serialized(space))


def _leaf_dtype(space: gymnasium.Space) -> np.dtype:
    if isinstance(space, Discrete):
        return np.dtype(np.int64)
    return np.dtype(space.dtype)


def _inside(values: np.ndarray, space: gymnasium.Space, where: str) -> None:
    """Every value lies inside the leaf ``space`` (what ``space.contains`` checks)."""
    if isinstance(space, Box):
        outside = (values < space.low) | (values > space.high)
    elif isinstance(space, Discrete):
        outside = (values < space.start) | (values >= space.start + space.n)
    elif isinstance(space, MultiDiscrete):
        outside = (values < space.start) | (values >= space.start + space.nvec)
    else:  # MultiBinary
        outside = (values != 0) & (values != 1)
    if outside.any():
        step = int(np.flatnonzero(outside.reshape(len(values), -1).any(axis=1))[0])
        bad = values[step][outside[step]].ravel()[0].item()
        raise ValueError(f"{where}: step {step} holds {bad!r}, outside the space {space}")


def space_values(value: Any, space: gymnasium.Space, where: str) -> Any:
    """An episode's ``[T, ...]`` tensor (a TensorDict for a ``Dict`` space) as the numpy
    arrays written for ``space``; ValueError naming ``where`` when a value does not fit.

    Shapes: a leaf's per-step shape must be the space's (``[T]`` for ``Discrete``); dtypes:
    cast to the space's when no value changes (:func:`exact_cast`: float data is never
    truncated to integers), then checked finite and inside the space."""
    if isinstance(space, Dict):
        if not isinstance(value, TensorDictBase):
            raise ValueError(f"{where}: a Dict space needs a TensorDict of entries, got a tensor")
        names, held = set(space.spaces), set(value.keys())
        if names != held:
            raise ValueError(
                f"{where}: the Dict space has entries {sorted(names)}, the rows hold {sorted(held)}"
            )
        return {k: space_values(value.get(k), s, f"{where}/{k}") for k, s in space.spaces.items()}
    if not isinstance(value, torch.Tensor):
        raise ValueError(f"{where}: a {type(space).__name__} space needs a tensor, got entries")
    array = value.detach().cpu().numpy()
    shape = space.shape
    assert shape is not None  # a leaf space (check_space): each has a shape
    if tuple(array.shape[1:]) != tuple(shape):
        raise ValueError(
            f"{where}: per-step shape {list(array.shape[1:])}, the space {space} declares "
            f"{list(shape)}"
        )
    check_finite(array, where=where)
    dtype = _leaf_dtype(space)
    if array.dtype.kind == "f" and dtype.kind != "f":
        raise ValueError(
            f"{where}: {array.dtype} values for the {dtype} space {space} (refusing to "
            "truncate floating data)"
        )
    array = exact_cast(array, dtype.name, where=where)
    _inside(array, space, where)
    return np.ascontiguousarray(array)
