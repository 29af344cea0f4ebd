"""Minari's serialized spaces, and a dataset's step arrays checked against them.

A space is Minari's JSON (``minari/serialization.py``): ``{"type": "Box", "dtype",
"shape", "low", "high"}``, ``Discrete`` (``n``, ``start``), ``MultiDiscrete`` (``nvec``),
``MultiBinary`` (``n``), ``Text``, and the nested ``Dict`` / ``Tuple``. :func:`decode`
walks a space over one storage's nodes (an HDF5 group, an arrow struct column: the
``Storage`` says how to reach a child and read a leaf) and checks every leaf the same
way whatever the storage: its per-step shape, a dtype cast that changes no value (an
``int64`` Box over float data, float actions in a ``Discrete`` space: refused), actions
inside a ``Discrete`` space's range, no NaN or inf. A space's JSON is parsed with
:func:`~imitrl.fs.reading.parse_json` (too deep a nesting is refused by name) and may
nest Dict/Tuple spaces :data:`MAX_SPACE_DEPTH` deep; an encoded image's size is read
from its header and checked against the space before it is decoded.
"""

from __future__ import annotations

import io
import math
from collections.abc import Iterable
from typing import Any, Protocol

import numpy as np

from imitrl.datasets._common import check_finite, exact_cast
from imitrl.fs.reading import parse_json

__all__ = ["MAX_SPACE_DEPTH", "Storage", "decode", "is_image", "parse_space", "space_shape"]

MAX_SPACE_DEPTH = 32
"""Dict/Tuple spaces nested deeper than this are refused (Minari's own are a level or two)"""


class Storage(Protocol):
    """How one storage format holds the values of a space."""

    def child(self, node: Any, name: str, kind: str, where: str) -> Any:
        """The node of subspace ``name`` (``_index_<i>`` of a Tuple) of a Dict/Tuple node;
        ValueError when it is missing."""

    def leaf(self, node: Any, space: dict, jpeg: bool, where: str) -> Any:
        """A leaf node's ``[T, ...]`` values as numpy (encoded images: an iterable of
        bytes, one image at a time)."""


def parse_space(text: Any, where: str) -> dict:
    """A space from ``metadata.json`` (a JSON string, or already a mapping), checked."""
    if isinstance(text, bytes | str):
        text = parse_json(text, where=f"{where} (the serialized space)")
    _check_space(text, where)
    return text


def _sizes(value: Any) -> bool:
    """A flat list of non-negative integers."""
    return isinstance(value, list) and all(
        isinstance(d, int) and not isinstance(d, bool) and d >= 0 for d in value
    )


def _check_space(space: Any, where: str, depth: int = 0) -> None:
    """What :func:`decode` reads of a space is there and well-formed."""
    if depth > MAX_SPACE_DEPTH:
        raise ValueError(f"{where}: spaces nested more than {MAX_SPACE_DEPTH} deep; refused")
    if not isinstance(space, dict) or "type" not in space:
        raise ValueError(f"{where}: not a Minari space description: {space!r}")
    kind = space["type"]
    if kind == "Box" and not _sizes(space.get("shape")):
        raise ValueError(f"{where}: a Box space needs a 'shape' list of sizes, got {space!r}")
    if kind in ("Box", "MultiDiscrete") and "dtype" in space:
        try:
            ok = np.dtype(space["dtype"]).kind in "fiub"
        except Exception:  # numpy parses dtype strings: TypeError, SyntaxError (","), ...
            ok = False
        if not ok:
            raise ValueError(f"{where}: unsupported dtype {space['dtype']!r}")
    if kind == "Discrete":
        n, start = space.get("n"), space.get("start", 0)
        if not (
            isinstance(n, int)
            and not isinstance(n, bool)
            and isinstance(start, int)
            and not isinstance(start, bool)
            and n >= 1
        ):
            raise ValueError(f"{where}: a Discrete space needs integers n >= 1 and start")
    if kind == "MultiDiscrete" and not _sizes(space.get("nvec")):
        raise ValueError(f"{where}: a MultiDiscrete space needs an 'nvec' list of sizes")
    if kind == "MultiBinary" and not _sizes(
        [space.get("n")] if isinstance(space.get("n"), int) else space.get("n")
    ):
        raise ValueError(f"{where}: a MultiBinary space needs 'n' (a size or list of sizes)")
    if kind == "Dict":
        if not isinstance(space.get("subspaces"), dict):
            raise ValueError(f"{where}: a Dict space needs a 'subspaces' mapping, got {space!r}")
        for name, sub in space["subspaces"].items():
            _check_space(sub, f"{where}[{name!r}]", depth + 1)
    elif kind == "Tuple":
        if not isinstance(space.get("subspaces"), list):
            raise ValueError(f"{where}: a Tuple space needs a 'subspaces' list, got {space!r}")
        for i, sub in enumerate(space["subspaces"]):
            _check_space(sub, f"{where}[{i}]", depth + 1)


def space_shape(space: dict) -> tuple[int, ...]:
    """The per-step shape of a leaf space's values."""
    kind = space["type"]
    if kind == "Box":
        return tuple(space["shape"])
    if kind == "MultiDiscrete":
        return (len(space["nvec"]),)
    if kind == "MultiBinary":
        return tuple(space["n"]) if isinstance(space["n"], list) else (space["n"],)
    return ()


def is_image(space: dict) -> bool:
    """``minari.dataset.minari_storage.is_image_space``: JPEG-encoded when ``jpeg_encoding``."""
    bounds: np.bool_ | bool
    try:
        bounds = np.all(np.asarray(space.get("low")) == 0) and np.all(
            np.asarray(space.get("high")) == 255
        )
    except (TypeError, ValueError):
        bounds = False
    return (
        space["type"] == "Box"
        and space.get("dtype") == "uint8"
        and len(space["shape"]) in (2, 3)
        and space["shape"][0] >= 32
        and space["shape"][1] >= 32
        and bool(bounds)
    )


def _jpeg_frames(blobs: Iterable[Any], space: dict, here: str) -> np.ndarray:
    """Each encoded image decoded, once its header says it has the space's width and
    height (so a small file declaring a huge image is refused before it is decoded)."""
    from PIL import Image

    shape = space["shape"]
    frames = []
    for i, blob in enumerate(blobs):
        try:
            image = Image.open(io.BytesIO(bytes(blob)))  # reads the header only
        except Exception as err:  # PIL raises assorted errors for broken images
            raise ValueError(f"{here}: step {i} is not a decodable JPEG image ({err})") from err
        if image.size != (shape[1], shape[0]):  # PIL: (width, height)
            raise ValueError(
                f"{here}: step {i} is a {image.size[0]}x{image.size[1]} image; the space's "
                f"shape is {shape}, so an image does not hold the space's shape"
            )
        try:
            frames.append(np.asarray(image))
        except Exception as err:
            raise ValueError(f"{here}: step {i} is not a decodable JPEG image ({err})") from err
    want = math.prod(shape)
    if any(f.size != want or f.dtype != np.uint8 for f in frames):
        raise ValueError(f"{here}: an image does not hold the space's shape {shape}")
    if not frames:
        return np.empty((0, *space["shape"]), dtype=np.uint8)
    return np.stack(frames).reshape(len(frames), *space["shape"])


def _leaf_values(raw: Any, space: dict, jpeg: bool, here: str) -> np.ndarray:
    """One leaf's ``[T, ...]`` values checked against its space (module docstring)."""
    kind = space["type"]
    if jpeg and is_image(space):
        return _jpeg_frames(raw, space, here)
    values = np.asarray(raw)
    want = space_shape(space)
    if tuple(values.shape[1:]) != want or values.ndim == 0:
        raise ValueError(
            f"{here} has shape {list(values.shape[1:])} per step, the {kind} space declares "
            f"{list(want)}"
        )
    if kind == "Box":
        values = exact_cast(values, space.get("dtype", values.dtype.name), where=here)
    elif kind in ("Discrete", "MultiDiscrete", "MultiBinary"):
        if values.dtype.kind not in ("iub" if kind == "MultiBinary" else "iu"):
            raise ValueError(
                f"{here}: a {kind} space holds integers, the dataset stores {values.dtype} "
                "(refusing to truncate or reinterpret)"
            )
        dtypes = {"Discrete": "int64", "MultiDiscrete": space.get("dtype", "int64")}
        values = exact_cast(values, dtypes.get(kind, "int8"), where=here)
        low = space.get("start", 0) if kind == "Discrete" else 0
        high = low + space["n"] if kind == "Discrete" else None
        if kind == "MultiDiscrete":
            high = np.asarray(space["nvec"]) + np.asarray(space.get("start", 0))
        elif kind == "MultiBinary":
            high = 2
        outside = (values < low) | (values >= high)
        if outside.any():
            bad = values[outside].ravel()[0].item()
            raise ValueError(f"{here}: value {bad} lies outside the {kind} space")
    else:
        raise ValueError(f"{here}: space type {kind!r} is not supported")
    check_finite(values, where=here)
    return values


def decode(
    node: Any,
    space: dict,
    path: str,
    *,
    storage: Storage,
    jpeg: bool,
    skipped: dict[str, str],
    where: str,
) -> Any:
    """A storage node + its space -> checked numpy ``[T, ...]`` or a nested dict of them
    (None for what cannot be a tensor, listed in ``skipped``)."""
    kind = space["type"]
    here = f"{where}: {path}"
    if kind in ("Dict", "Tuple"):
        subs = space["subspaces"]
        items = subs.items() if kind == "Dict" else ((f"_index_{i}", s) for i, s in enumerate(subs))
        out = {}
        for name, sub in items:
            child = storage.child(node, name, kind, f"{here}/{name}")
            value = decode(
                child,
                sub,
                f"{path}/{name}",
                storage=storage,
                jpeg=jpeg,
                skipped=skipped,
                where=where,
            )
            if value is not None:
                out[name] = value
        return out
    if kind == "Text":
        skipped[path] = "Text space: strings cannot go into a tensor"
        return None
    return _leaf_values(storage.leaf(node, space, jpeg, here), space, jpeg, here)
