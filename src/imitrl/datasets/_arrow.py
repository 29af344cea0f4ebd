"""Arrow columns <-> torch tensors, the way LeRobot lays features out in parquet.

LeRobot (through Hugging Face ``datasets``) stores a feature of shape ``(1,)`` as a
plain scalar column, a vector ``(k,)`` as a (fixed-size) list column and an array
``(a, b, ...)`` as nested lists (``datasets.Array2D`` .. ``Array5D``); images are
``struct<bytes: binary, path: string>`` holding PNG bytes. Conversions here check
every list length against the declared shape and refuse nulls, so a malformed column
fails with the file and feature named instead of loading wrong values. A parquet file
is read inside a dataset folder pinned by a descriptor (:func:`parquet_file`: a regular
file, never a link out or a FIFO); an image's header is read before it is decoded, its
size bounded (:func:`decode_images`).
"""

from __future__ import annotations

import ctypes
import io
import json
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
import torch

from imitrl.datasets._common import (
    TORCH_DTYPES,
    WIDEN,
    check_finite,
    exact_cast,
    open_in,
    read_in,
)
from imitrl.fs.reading import OpenedFolder, fd_path

__all__ = [
    "array_shape",
    "check_schema",
    "checked_rows",
    "column_to_tensor",
    "decode_images",
    "encode_images",
    "footer_rows",
    "hf_feature",
    "parquet_file",
    "read_parquet",
    "release_unused_memory",
    "tensor_to_array",
]


def release_unused_memory() -> None:
    """Hand back to the system the memory this process's allocators hold but no longer use:
    pyarrow's pool (mimalloc or jemalloc keeps freed pages for reuse) and, on glibc, the
    malloc heap torch's and numpy's arrays come from (``malloc_trim(0)``: freed blocks of a
    few MB are carved from the heap, not mapped apart, once such arrays have been freed).

    A pass that reads or writes a piece at a time, pieces of varying sizes, otherwise
    sees resident memory creep up piece after piece (measured on a 10M-frame streamed
    load: +100 MB over its 78 pieces; +45 MB over the 11 row groups of a 50k-episode
    table read back). Streamed loads and saves call it after each piece. Values are never
    touched: only memory no array holds is returned."""
    pa.default_memory_pool().release_unused()
    if _MALLOC_TRIM is not None:
        _MALLOC_TRIM(0)


def _malloc_trim():
    try:
        return ctypes.CDLL(None).malloc_trim if os.name == "posix" else None
    except (OSError, AttributeError):  # not glibc (musl, macOS): nothing to trim
        return None


_MALLOC_TRIM = _malloc_trim()


@contextmanager
def parquet_file(
    folder: OpenedFolder, relative: str, *, named_by: str, **options: bool
) -> Iterator[pq.ParquetFile]:
    """The parquet file ``relative`` of ``folder``, opened by descriptor (a regular file
    inside the folder: :meth:`~imitrl.fs.reading.OpenedFolder.open`) for the block;
    ValueError naming it when it is not a readable parquet file (truncated, say).

    Args:
        named_by: who names the file, for messages (``"meta/info.json's data_path"``).
        options: ``memory_map`` or ``pre_buffer`` for ``pyarrow.parquet.ParquetFile``.
    """
    where = folder.root / relative
    fd = open_in(folder, relative, named_by=named_by)
    try:
        try:
            pf = pq.ParquetFile(fd_path(fd), **options)
        except (pa.ArrowException, OSError) as err:
            raise ValueError(
                f"{where}: not a readable parquet file ({_named(err, fd, where)})"
            ) from None
        with pf:
            yield pf
    finally:
        os.close(fd)


def _named(err: Exception, fd: int, where: Path) -> str:
    """pyarrow's message, naming the file instead of the descriptor's path."""
    return str(err).replace(fd_path(fd), str(where))


def checked_rows(pf: pq.ParquetFile, where: Path, expected: int | None = None) -> int:
    """The rows a parquet file's footer declares, once its row groups' rows add up to them
    (a read takes each group's own count: a footer declaring 5 rows over a group of 20
    million would read the 20 million) and, when given, they are the ``expected`` rows;
    ValueError naming the file otherwise, before a value is read. A few hundred KB of
    zstd can declare tens of millions of rows of one value."""
    meta = pf.metadata
    groups = sum(meta.row_group(g).num_rows for g in range(meta.num_row_groups))
    if groups != meta.num_rows:
        raise ValueError(
            f"{where}: its footer declares {meta.num_rows:,} rows, its row groups "
            f"{groups:,}; refused before reading it (a damaged or hostile file)"
        )
    if expected is not None and meta.num_rows != expected:
        raise ValueError(
            f"{where}: its footer declares {meta.num_rows:,} rows, the metadata "
            f"{expected:,}; refused before reading it"
        )
    return meta.num_rows


def footer_rows(folder: OpenedFolder, relative: str, *, named_by: str) -> int:
    """Rows of a parquet file, from its footer (:func:`checked_rows`); ValueError naming
    the file when it is not a readable parquet file (a truncated file is named, not
    blamed on what counts it)."""
    with parquet_file(folder, relative, named_by=named_by) as pf:
        return checked_rows(pf, folder.root / relative)


def read_parquet(
    folder: OpenedFolder,
    relative: str,
    columns: list[str] | None = None,
    *,
    declared: list[str] | None = None,
    rows: int | None = None,
    named_by: str,
) -> pa.Table:
    """Read a parquet file of ``folder`` (:func:`parquet_file`), naming the file (and missing
    columns) in every error.

    Args:
        columns: the columns to read (all when None).
        declared: the columns the file must hold, no more and no fewer (a pandas index
            column aside): a name that differs between a file and its metadata is refused.
        rows: the rows the file must hold, checked on its footer before a value is read
            (:func:`checked_rows`; its row groups' counts are checked whatever ``rows``).
    """
    where = folder.root / relative
    with parquet_file(folder, relative, named_by=named_by) as pf:
        check_schema(where, pf.schema_arrow, columns, declared)
        checked_rows(pf, where, rows)
        try:
            return pf.read(columns=columns)
        except (pa.ArrowException, OSError) as err:
            raise ValueError(f"{where}: cannot read the parquet data ({err})") from None


def check_schema(
    where: Path, schema: pa.Schema, columns: list[str] | None, declared: list[str] | None
) -> None:
    """A parquet file (``where``, its ``schema``) holds ``columns`` and, if given, exactly the
    ``declared`` ones (a pandas index column aside); ValueError naming the file otherwise."""
    missing = [c for c in [*(columns or []), *(declared or [])] if c not in schema.names]
    if missing:
        raise ValueError(
            f"{where}: declared feature(s) {sorted(set(missing))} absent from the file "
            f"(columns present: {schema.names})"
        )
    extra = [
        c
        for c in schema.names
        if declared is not None and c not in declared and not c.startswith("__index_level_")
    ]
    if extra:
        raise ValueError(f"{where}: column(s) {extra} are not declared in meta/info.json")


def _storage(arr: pa.Array) -> pa.Array:
    # datasets registers ArrayND extension types; their storage is nested lists
    return arr.storage if isinstance(arr.type, pa.ExtensionType) else arr


def column_to_tensor(
    col: pa.ChunkedArray | pa.Array, *, shape: tuple[int, ...], dtype: str, where: str
) -> torch.Tensor:
    """``[N]`` column of per-frame values of declared ``shape`` -> tensor ``[N, *shape]``.

    A declared shape ``(1,)`` stored as a scalar column (LeRobot's layout) gives
    ``[N]``; stored as a one-element list it gives ``[N, 1]``.

    Values are cast to the declared dtype only when none changes
    (:func:`~imitrl.datasets._common.exact_cast`); NaN and inf are refused.

    Raises:
        ValueError: nulls, list lengths that contradict ``shape``, a non-numeric column,
            values the declared dtype cannot hold, NaN or inf.
    """
    arr = _storage(col.combine_chunks() if isinstance(col, pa.ChunkedArray) else col)
    n = len(arr)
    dims: list[int] = []
    for expected in shape:
        if not (
            pa.types.is_list(arr.type)
            or pa.types.is_large_list(arr.type)
            or pa.types.is_fixed_size_list(arr.type)
        ):
            if tuple(shape) == (1,) and not dims:
                break  # per-frame scalar, LeRobot's layout for shape (1,)
            raise ValueError(
                f"{where}: holds {arr.type} values, the declared shape {list(shape)} needs "
                f"{len(shape)} nested list level(s)"
            )
        if arr.null_count:
            raise ValueError(f"{where}: contains null entries")
        lengths = pc.list_value_length(arr).to_numpy(zero_copy_only=False)
        if lengths.size and not (lengths == expected).all():
            bad = int(lengths[lengths != expected][0])
            raise ValueError(
                f"{where}: a frame has {bad} entries along dimension {len(dims)}, the declared "
                f"shape is {list(shape)}"
            )
        dims.append(expected)
        arr = _storage(arr.flatten())
    if (
        pa.types.is_list(arr.type)
        or pa.types.is_large_list(arr.type)
        or pa.types.is_fixed_size_list(arr.type)
    ):
        raise ValueError(
            f"{where}: has more nested list levels than the declared shape {list(shape)}"
        )
    if arr.null_count:
        raise ValueError(f"{where}: contains null entries")
    if not (
        pa.types.is_integer(arr.type)
        or pa.types.is_floating(arr.type)
        or pa.types.is_boolean(arr.type)
    ):
        raise ValueError(f"{where}: holds {arr.type} values, expected numbers or booleans")
    target = WIDEN.get(dtype, dtype)
    if target not in TORCH_DTYPES:
        raise ValueError(f"{where}: unsupported dtype {dtype!r}")
    values = exact_cast(np.asarray(arr.to_numpy(zero_copy_only=False)), target, where=where)
    values = values.reshape(n, *dims)
    check_finite(values, where=where)  # per row: "frame i" names the row, not an element
    return torch.from_numpy(values.copy())


MAX_IMAGE_PIXELS = 1 << 25
"""height x width an image feature's frame may have (33.5 million pixels: an 8K frame,
7680 x 4320, fits; about 100 MB a frame in RGB), checked on the image's header before it
is decoded"""

MAX_IMAGE_FILE_BYTES = 256 << 20
"""bytes an image file named by an image feature's ``path`` may hold"""

DEFLATE_MAX_RATIO = 1032
"""the most deflate (PNG's compression) expands its input: a PNG whose header declares
more pixel bytes than its size times this holds less than it declares"""

_PNG = b"\x89PNG\r\n\x1a\n"


class _Refused(ValueError):
    """An image header declaring more than an image may hold (:func:`_header_size`)."""


_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}  # colour type -> samples a pixel


def _header_size(blob: bytes) -> tuple[int, int]:
    """``(height, width)`` an image's header declares, read without decoding it: a PNG's
    IHDR (bytes 16-24), checked against the bytes present (:data:`DEFLATE_MAX_RATIO`),
    else what PIL reads of another format's header."""
    if blob.startswith(_PNG):
        if len(blob) < 33 or blob[12:16] != b"IHDR":
            raise _Refused("a PNG without its IHDR header")
        width, height = int.from_bytes(blob[16:20], "big"), int.from_bytes(blob[20:24], "big")
        _check_pixels(height, width)
        depth, channels = blob[24], _PNG_CHANNELS.get(blob[25], 4)
        pixel_bytes = height * -(-width * channels * depth // 8)
        if pixel_bytes > DEFLATE_MAX_RATIO * len(blob):
            raise _Refused(
                f"its header declares {height}x{width} (height x width), {pixel_bytes:,} bytes "
                f"of pixels, more than its {len(blob):,} bytes can hold (deflate expands at "
                f"most {DEFLATE_MAX_RATIO} times)"
            )
        return height, width
    from PIL import Image  # pillow ships with matplotlib

    with Image.open(io.BytesIO(blob)) as img:  # reads the header only
        _check_pixels(img.height, img.width)
        return img.height, img.width


def _check_pixels(height: int, width: int) -> None:
    if height * width > MAX_IMAGE_PIXELS:
        raise _Refused(
            f"its header declares {height}x{width} (height x width), more than the "
            f"{MAX_IMAGE_PIXELS:,} pixels an image may have (MAX_IMAGE_PIXELS); refused "
            "before decoding it"
        )


def _image_bytes(
    blob: bytes | None, path: str | None, folder: OpenedFolder, where: str, i: int
) -> bytes:
    """An image's bytes: embedded, or the file its ``path`` names inside the folder."""
    if blob is not None:
        return blob
    if path:
        named_by = f"{where}, row {i}"
        return read_in(folder, path, named_by=named_by, limit=MAX_IMAGE_FILE_BYTES)
    raise ValueError(f"{where}: frame {i} has no bytes and no path")


def decode_images(
    col: pa.ChunkedArray, *, shape: tuple[int, ...], folder: OpenedFolder, where: str
) -> torch.Tensor:
    """``struct<bytes, path>`` PNG/JPEG column -> uint8 ``[N, *shape]`` in the declared layout.

    The declared shape is ``(C, H, W)`` or ``(H, W, C)`` (LeRobot accepts both; the
    feature's ``names`` say which); pixels come back as uint8 in that layout. Every
    image's header is read first (no pixel decoded): its size must be the declared one
    and at most :data:`MAX_IMAGE_PIXELS`, and a PNG's must fit the bytes present; only
    then is ``[N, *shape]`` allocated and each image decoded into it. An image named by
    ``path`` is read inside ``folder`` (:meth:`~imitrl.fs.reading.OpenedFolder.read_bytes`).
    """
    from PIL import Image  # pillow ships with matplotlib

    arr = col.combine_chunks() if isinstance(col, pa.ChunkedArray) else col
    if not pa.types.is_struct(arr.type):
        raise ValueError(f"{where}: an image feature must be struct<bytes, path>, got {arr.type}")
    if len(shape) != 3:
        raise ValueError(f"{where}: image features need a 3-d shape, declared {list(shape)}")
    has = {name: arr.type.get_field_index(name) >= 0 for name in ("bytes", "path")}
    blobs = arr.field("bytes").to_pylist() if has["bytes"] else [None] * len(arr)
    paths = arr.field("path").to_pylist() if has["path"] else [None] * len(arr)
    images = []
    for i in range(len(arr)):
        data = _image_bytes(blobs[i], paths[i], folder, where, i)
        try:
            size = _header_size(data)
        except _Refused as err:
            raise ValueError(f"{where}: frame {i}: {err}") from None
        except Exception as err:  # PIL raises assorted errors for broken images
            raise ValueError(f"{where}: frame {i} is not a decodable image ({err})") from err
        if size not in ((shape[0], shape[1]), (shape[1], shape[2])):
            raise ValueError(
                f"{where}: frame {i} is {size[0]}x{size[1]} (height x width), declared "
                f"{list(shape)}"
            )
        images.append(data)
    del blobs
    out = np.empty((len(images), *shape), dtype=np.uint8)
    for i, data in enumerate(images):
        try:
            with Image.open(io.BytesIO(data)) as img:
                pixels = np.asarray(img.convert("RGB") if img.mode not in ("L", "RGB") else img)
        except Exception as err:  # PIL raises assorted errors for broken images
            raise ValueError(f"{where}: frame {i} is not a decodable image ({err})") from err
        if pixels.ndim == 2:
            pixels = pixels[:, :, None]
        if pixels.shape == tuple(shape):  # (H, W, C)
            out[i] = pixels
        elif pixels.transpose(2, 0, 1).shape == tuple(shape):  # (C, H, W)
            out[i] = pixels.transpose(2, 0, 1)
        else:
            raise ValueError(
                f"{where}: frame {i} is {list(pixels.shape)} (H, W, C), declared {list(shape)}"
            )
    return torch.from_numpy(out)


def encode_images(pixels: np.ndarray, frame_index: np.ndarray) -> pa.Array:
    """uint8 ``[N, H, W, C]`` -> ``struct<bytes, path>`` of PNG files, as LeRobot embeds them.

    LeRobot writes each frame to ``frame-{frame_index:06d}.png`` and embeds the bytes with
    the file's base name as ``path`` (``datasets.Image.embed_storage``). PNG is lossless,
    so :func:`decode_images` gives back the same pixels.
    """
    from PIL import Image  # pillow ships with matplotlib

    blobs = []
    for img, i in zip(pixels, frame_index.tolist()):
        buf = io.BytesIO()
        Image.fromarray(img).save(buf, format="PNG")
        blobs.append({"bytes": buf.getvalue(), "path": f"frame-{i:06d}.png"})
    return pa.array(blobs, pa.struct([("bytes", pa.binary()), ("path", pa.string())]))


def tensor_to_array(value: torch.Tensor) -> tuple[pa.Array, tuple[int, ...]]:
    """``[N, *s]`` tensor -> (arrow column, LeRobot feature shape).

    ``[N]`` and ``[N, 1]`` become a scalar column declared ``(1,)`` (LeRobot's layout),
    ``[N, k]`` a ``fixed_size_list[k]`` (``datasets.Sequence(length=k)``), ``[N, a, b, ...]``
    nested lists (``datasets.Array2D`` .. ``Array5D``).
    """
    values = value.detach().cpu().contiguous().numpy()
    trailing = array_shape(tuple(values.shape[1:]))
    if trailing == (1,):
        return pa.array(values.reshape(-1)), (1,)
    if len(trailing) == 1:
        flat = pa.array(values.reshape(-1))
        return pa.FixedSizeListArray.from_arrays(flat, trailing[0]), trailing
    arr = pa.array(values.reshape(-1))
    for size in reversed(trailing):
        offsets = pa.array(np.arange(0, len(arr) + 1, size, dtype=np.int32))
        arr = pa.ListArray.from_arrays(offsets, arr)
    return arr, trailing


def array_shape(trailing: tuple[int, ...]) -> tuple[int, ...]:
    """The LeRobot feature shape of per-row values of shape ``trailing`` (``()`` and ``(1,)``:
    ``(1,)``, a scalar column), as :func:`tensor_to_array` writes them."""
    if trailing in ((), (1,)):
        return (1,)
    if len(trailing) > 5:
        raise ValueError(f"LeRobot features have at most 5 dimensions, got {list(trailing)}")
    return trailing


def hf_feature(dtype: str, shape: tuple[int, ...]) -> dict:
    """The Hugging Face ``datasets`` feature JSON LeRobot derives from (dtype, shape)."""
    if dtype == "image":
        return {"_type": "Image"}
    if shape == (1,):
        return {"dtype": dtype, "_type": "Value"}
    if len(shape) == 1:
        return {"feature": {"dtype": dtype, "_type": "Value"}, "length": shape[0], "_type": "List"}
    return {"shape": list(shape), "dtype": dtype, "_type": f"Array{len(shape)}D"}


def hf_schema_metadata(features: dict[str, dict]) -> dict[bytes, bytes]:
    """Schema metadata ``datasets`` writes next to the columns (``{"info": {"features": ...}}``)."""
    return {b"huggingface": json.dumps({"info": {"features": features}}).encode()}
