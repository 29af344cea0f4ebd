"""How much memory a Minari file may make this loader allocate: bounded by its bytes.

A downloaded file declares sizes (an HDF5 dataset's shape, an Arrow record batch's or a
parquet footer's row count, the uncompressed size of a compressed buffer) and the
libraries allocate what it declares before they find out whether the bytes are there: an
80 KB file declaring 5e8 elements took 5.35 GB before any check. Every such size is
checked here first, against the bytes the file holds on disk:

* data stored as it is (an uncompressed HDF5 dataset, an uncompressed Arrow buffer):
  the declared bytes must be stored - ``declared <= stored``;
* data stored compressed or encoded (an HDF5 dataset with filters, a parquet column, a
  compressed Arrow buffer): ``declared <= MAX_EXPANSION * stored``. Deflate (gzip) cannot
  expand past 1032:1, and real demonstrations (floating observations, images) compress
  tens of times at most, so a file declaring more is lying about its size (fill values
  where no chunk was written, run-length runs of one value) or is a bomb;
* below :data:`FLOOR_BYTES` anything goes, for the whole load (one pass over its
  episodes: a :class:`Floor`): a small array costs little whatever it declares, and a
  small all-zero column may legitimately compress far past the ratio, but the arrays
  that declare more than their stored bytes allow may together declare at most
  :data:`FLOOR_BYTES` (each size checked takes its bytes: a parquet file's rows and its
  values are two, the decoded table and the arrays made of it). Per array, twelve
  episodes of arrays each just under it (chunked, never written) made a 41 KB file load
  48 million rows, 5.5 GB.

A refusal is a ValueError naming the file, the episode and the array, the bytes declared
and the bytes stored, raised before anything of the array is read.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["FLOOR_BYTES", "MAX_EXPANSION", "Floor", "check_declared", "step_bytes"]

MAX_EXPANSION = 1100
"""bytes an array may declare per byte its file stores compressed (deflate's ceiling is
1032:1); uncompressed data must store every byte it declares"""

FLOOR_BYTES = 64 << 20
"""bytes the arrays of one load may declare, all together, whatever their files store
(64 MiB)"""


@dataclass
class Floor:
    """What is left of :data:`FLOOR_BYTES` to one load (one pass over its episodes): the
    arrays that declare more than their stored bytes allow take their declared bytes
    from it."""

    left: int = FLOOR_BYTES


def check_declared(
    declared: int, stored: int, *, compressed: bool, where: str, floor: Floor
) -> None:
    """Refuse ``declared`` bytes that ``stored`` bytes on disk cannot hold, unless ``floor``
    (the load's) has them left (module docstring); ``where`` names the file, the episode
    and the array."""
    limit = stored * MAX_EXPANSION if compressed else stored
    if declared <= limit:
        return
    if declared <= floor.left:
        floor.left -= declared
        return
    how = (
        f"compressed or encoded, it may declare at most {MAX_EXPANSION} times those, "
        f"{limit:,} bytes"
        if compressed
        else "stored as they are, it must store every byte it declares"
    )
    used = FLOOR_BYTES - floor.left
    beyond = (
        f", and the arrays read before it took {used:,} of the {FLOOR_BYTES:,} bytes a load "
        "may declare beyond what its files store"
        if used
        else ""
    )
    raise ValueError(
        f"{where}: declares {declared:,} bytes of values, its file stores {stored:,} bytes "
        f"for them ({how}){beyond}; refused before reading it (a damaged or hostile file)"
    )


def step_bytes(space: dict, jpeg: bool = False) -> int:
    """Bytes one step of ``space``'s values takes once loaded (a Minari space as
    :func:`~imitrl.datasets.minari._spaces.parse_space` checked it; a Text space: 0)."""
    kind = space["type"]
    if kind == "Dict":
        return sum(step_bytes(s, jpeg) for s in space["subspaces"].values())
    if kind == "Tuple":
        return sum(step_bytes(s, jpeg) for s in space["subspaces"])
    if kind == "Box":
        return math.prod(space["shape"]) * _itemsize(space.get("dtype", "float32"))
    if kind == "Discrete":
        return 8  # loaded as int64
    if kind == "MultiDiscrete":
        return len(space["nvec"]) * _itemsize(space.get("dtype", "int64"))
    if kind == "MultiBinary":
        n = space["n"]
        return math.prod(n) if isinstance(n, list) else n
    return 0


def _itemsize(dtype: Any) -> int:
    try:
        return np.dtype(dtype).itemsize
    except TypeError:
        return 8
