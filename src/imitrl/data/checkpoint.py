"""The demonstration buffer's checkpoint: files listed in a manifest with sizes and SHA-256.

Layout of a checkpoint at ``path`` (:meth:`~imitrl.data.DemonstrationBuffer.save`)::

    path/
      manifest.json     {"format": ..., "content": {..., "files": {name: {"bytes", "sha256"}}},
                         "content_sha256": sha256 of the canonical JSON of "content"}
      <name>            every file "content.files" lists, and nothing else

What the files hold: one raw file per key of the rows (:func:`encode_rows` /
:func:`decode_rows`: the rows only, never the storage's spare capacity), the learner's
and its optimizers' state dicts (:func:`learner_components`, :func:`restore_learner`),
and a JSON state (:func:`state_json`). The rest of this module knows nothing of that.

Writing (:func:`write_checkpoint`) goes through :func:`imitrl.fs.publish.publishing`:
the files go to a hidden temporary sibling ``.<name>.imitrl-tmp-<hex>``, each is
fsynced, then the directory is moved into place under the path's exclusive lock (of
several savers of one path, one writes and the others are refused). An existing
``path`` is replaced only with ``overwrite=True``, and only when it is a checkpoint of
the same format holding nothing but its listed files (or empty); the swap is one
``renameat2(RENAME_EXCHANGE)`` on Linux, so ``path`` always holds the old or the new
checkpoint, whole, even under ``kill -9``. (Where the exchange is unsupported the old
checkpoint is moved aside to ``.<name>.imitrl-old-<hex>`` for the instant between two
renames; a load that finds ``path`` missing names that folder.) Leftovers of killed
saves are sorted out by the next save to the same path.

Reading (:func:`read_checkpoint`) checks everything before interpreting any byte:
the manifest's format and its own checksum, that the directory holds exactly the
listed files, each file's size and SHA-256. Any mismatch is a ``ValueError`` that names
the file. Reading opens files read-only and writes nothing. The folder is pinned once and
each file opened once, by descriptor, inside it (:mod:`imitrl.fs.reading`): a load that
meets a saver's exchange reads the new checkpoint whole, or says the folder was replaced
while it was read, never that the data is damaged. :func:`decode_rows` holds the rows the
manifest declares to the bytes present (no row count or shape asks for memory the files
do not hold).
"""

from __future__ import annotations

import copy
import hashlib
import io
import json
import math
import os
import re
import sys
from pathlib import Path
from typing import Any, Protocol, TypeVar, runtime_checkable

import torch
from tensordict import TensorDict, TensorDictBase

from imitrl.fs.lock import absolute
from imitrl.fs.publish import OLD, publishing
from imitrl.fs.reading import (
    OpenedFolder,
    ReplacedWhileReading,
    check_stored_zip,
    fd_path,
    parse_json,
    read_whole,
)

__all__ = [
    "MANIFEST",
    "MAX_FILES",
    "DeclaresOptimizers",
    "decode_rows",
    "encode_rows",
    "learner_components",
    "read_checkpoint",
    "restore_learner",
    "state_json",
    "write_checkpoint",
]

T = TypeVar("T")

MANIFEST = "manifest.json"
_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}$")  # flat names, no path parts
_MAX_MANIFEST_BYTES = 16 << 20
MAX_FILES = 1024
"""most files a checkpoint's manifest may list (one per key of the rows, the learner and
its optimizers, the state: a few dozen); each is held open while the others are read"""


# ------------------------------------------------------------------------ rows
# the dtypes a column file may hold, by the name the manifest records
_DTYPES = {
    name: getattr(torch, name)
    for name in (
        *("bool", "uint8", "int8", "int16", "int32", "int64"),
        *("float16", "bfloat16", "float32", "float64", "complex64", "complex128"),
    )
}


def encode_rows(rows: TensorDictBase) -> tuple[dict[str, memoryview], list[dict[str, Any]]]:
    """One file per key of ``rows`` [N]: ``(files, columns)``, ``files[name]`` the key's
    N rows as raw bytes (C order, this machine's byte order), ``columns`` the manifest
    entries ``{"key": [parts], "dtype", "shape": trailing shape, "file"}``."""
    files, columns = {}, []
    for i, key in enumerate(rows.keys(include_nested=True, leaves_only=True)):
        value = rows.get(key)
        dtype = str(value.dtype).removeprefix("torch.")
        if _DTYPES.get(dtype) is not value.dtype:
            raise ValueError(f"cannot save {key!r}: dtype {value.dtype} has no file encoding")
        name = f"column_{i:03d}.bin"
        flat = value.detach().cpu().contiguous().reshape(-1)  # no copy for a storage slice
        files[name] = memoryview(flat.view(torch.uint8).numpy())
        parts = [key] if isinstance(key, str) else list(key)
        columns.append({"key": parts, "dtype": dtype, "shape": list(value.shape[1:]), "file": name})
    return files, columns


def decode_rows(content: dict[str, Any], files: dict[str, torch.Tensor]) -> TensorDict:
    """The rows that :func:`encode_rows` wrote, from verified files (views, no copy).

    ``content`` holds ``rows`` (N), ``byteorder`` and ``columns``; raises ``ValueError``
    (or ``KeyError``/``TypeError`` on a malformed entry) if they disagree with the files:
    every column's file must hold its N rows exactly, computed in Python integers before
    any tensor is shaped, and a row must take at least one byte (so N is no more than the
    bytes present).
    """
    if content["byteorder"] != sys.byteorder:
        raise ValueError(f"{content['byteorder']}-endian data on a {sys.byteorder}-endian machine")
    n = content["rows"]
    if type(n) is not int or n < 1:
        raise ValueError(f"rows must be a positive integer, got {n!r}")
    columns = content["columns"]
    if not isinstance(columns, list):
        raise ValueError(f"columns must be a list, got {type(columns).__name__}")
    row_bytes, rows = 0, TensorDict({}, batch_size=[n])
    for column in columns:
        dtype, shape = _DTYPES[column["dtype"]], column["shape"]
        if not isinstance(shape, list) or not all(type(d) is int and 0 <= d < 2**31 for d in shape):
            raise ValueError(f"{column['file']}: shape must be a list of sizes, got {shape!r}")
        raw = files[column["file"]]
        width = math.prod(shape) * torch.empty((), dtype=dtype).element_size()
        if raw.numel() != n * width:  # Python integers: no overflow, nothing allocated
            raise ValueError(f"{column['file']}: {raw.numel()} bytes, {n} rows need {n * width}")
        parts = column["key"]
        rows.set(tuple(parts) if len(parts) > 1 else parts[0], raw.view(dtype).reshape(n, *shape))
        row_bytes += width
    if row_bytes == 0:
        raise ValueError(f"{n} rows declared, and the files hold no byte of any of them")
    return rows


def state_json(state: dict[str, Any] | None) -> str:
    """``state`` as JSON text; refuses what JSON would not give back unchanged."""
    state = {} if state is None else state
    if not isinstance(state, dict):
        raise ValueError(f"state must be a dict of plain JSON values, got {type(state).__name__}")
    try:
        text = json.dumps(state, allow_nan=False)
    except (TypeError, ValueError) as err:
        raise ValueError(
            f"state must be plain JSON (dict, list, str, int, float, bool, None): {err}"
        ) from None
    if json.loads(text) != state:
        raise ValueError("state does not survive a JSON round trip unchanged (tuples? int keys?)")
    return text


# ---------------------------------------------------------------------- learner
@runtime_checkable
class DeclaresOptimizers(Protocol):
    """A module that names its optimizers (:meth:`imitrl.learners.Learner.optimizers`):
    a checkpoint saves and restores them with its weights."""

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        """Every optimizer of the module, by name."""
        ...

    def migrated_state(self, states: dict[str, dict]) -> dict[str, dict]:
        """Saved states as the module holds them (an older checkpoint's, migrated)."""
        ...


def learner_components(learner: torch.nn.Module) -> dict[str, Any]:
    """The learner's weights and every optimizer it declares (:class:`DeclaresOptimizers`:
    an imitrl ``Learner``)."""
    out: dict[str, Any] = {"learner": learner}
    if isinstance(learner, DeclaresOptimizers):
        out.update(learner.optimizers())
    return out


def restore_learner(
    learner: torch.nn.Module,
    saved: dict[str, str] | None,
    files: dict[str, torch.Tensor],
    path: Path,
) -> None:
    """Load the saved weights and optimizers into ``learner``, on whatever device it lives
    (the checkpoint may come from another); all or nothing."""
    components = learner_components(learner)
    if saved is None:
        raise ValueError(f"{path}: cannot load the learner: the checkpoint was saved without one")
    states = {}
    for component, name in saved.items():
        raw = io.BytesIO(bytes(files[name].numpy()))
        check_stored_zip(raw, path / name, len(raw.getbuffer()), what=f"the {component}'s state")
        raw.seek(0)
        try:
            # read onto the CPU whatever device saved it; load_state_dict then copies each
            # tensor to where the learner lives (a GPU checkpoint loads on a CPU machine)
            states[component] = torch.load(raw, weights_only=True, map_location="cpu")
        except Exception as err:  # torch.load raises assorted errors on a bad archive
            raise ValueError(f"{path / name}: cannot load {component} ({err})") from None
    if isinstance(learner, DeclaresOptimizers):
        states = learner.migrated_state(states)  # an older imitrl's checkpoint
    if set(states) != set(components):
        raise ValueError(
            f"{path}: cannot load the learner: the checkpoint holds {sorted(saved)}, "
            f"the given learner has {sorted(components)}"
        )
    backup = {c: copy.deepcopy(obj.state_dict()) for c, obj in components.items()}
    for component, obj in components.items():
        try:
            if isinstance(obj, torch.optim.Optimizer):  # torch checks none of it
                check_optimizer_state(obj, states[component])
            obj.load_state_dict(states[component])
        except (RuntimeError, ValueError, KeyError, TypeError) as err:
            for c, o in components.items():  # leave the caller's learner as it was
                o.load_state_dict(backup[c])
            raise ValueError(
                f"{path / saved[component]}: cannot load {component} into the given learner ({err})"
            ) from None


def check_optimizer_state(opt: torch.optim.Optimizer, saved: Any) -> None:
    """ValueError unless ``saved`` can be ``opt``'s state: per parameter,
    tensors of the parameter's shape (or scalars) of real numbers, finite, a ``step`` not
    below 0; hyperparameters finite, a learning rate not below 0 (a hostile review: an
    ``exp_avg`` viewing one stored value as 2^29 was materialised, 2.5 GB, then a
    traceback; a negative ``step`` was a traceback). Checked before anything is copied."""
    if not (
        isinstance(saved, dict)
        and isinstance(saved.get("state"), dict)
        and isinstance(saved.get("param_groups"), list)
    ):
        raise ValueError("not an optimizer's state (state and param_groups)")
    params = [p for group in opt.param_groups for p in group["params"]]
    for index, entries in saved["state"].items():
        if not (type(index) is int and 0 <= index < len(params) and isinstance(entries, dict)):
            raise ValueError(f"a state of parameter {index!r}, of {len(params)}")
        for name, value in entries.items():
            if isinstance(value, torch.Tensor) and not _plain_state(name, value, params[index]):
                raise ValueError(
                    f"parameter {index}'s {name!r} is {value.dtype} "
                    f"{list(value.shape)} for a parameter of shape {list(params[index].shape)}, "
                    "or not finite, or a negative step"
                )
    for group in saved["param_groups"]:
        if not isinstance(group, dict):
            raise ValueError(f"a parameter group must be a dict, got {group!r}"[:300])
        settings = [v for k, v in group.items() if k != "params"]
        numbers = [x for v in settings for x in (v if isinstance(v, list | tuple) else [v])]
        lr = group.get("lr", 0)
        not_finite = any(isinstance(x, float) and not math.isfinite(x) for x in numbers)
        if not_finite or not (isinstance(lr, int | float) and lr >= 0):
            raise ValueError(f"hyperparameters must be finite, lr >= 0: {group!r}"[:300])


def _plain_state(name: str, value: torch.Tensor, param: torch.Tensor) -> bool:
    """One per-parameter tensor of an optimizer's state, checked without materialising it
    (its shape first)."""
    if value.dim() and value.shape != param.shape:
        return False
    if value.is_complex() or value.dtype == torch.bool:
        return False
    if value.is_floating_point() and not bool(torch.isfinite(value).all()):
        return False
    return not (name == "step" and bool((value < 0).any()))


def _canonical(content: dict[str, Any]) -> bytes:
    return json.dumps(content, sort_keys=True, separators=(",", ":"), allow_nan=False).encode()


# ------------------------------------------------------------------------ write
def write_checkpoint(
    path: str | Path,
    files: dict[str, bytes | memoryview],
    content: dict[str, Any],
    *,
    fmt: str,
    overwrite: bool = False,
) -> Path:
    """Write ``files`` and a manifest (``fmt``, ``content`` plus every file's size and
    SHA-256) as the checkpoint directory ``path``, atomically and exclusively
    (:func:`imitrl.fs.publish.publishing`: one writer per path, an atomic exchange with
    the previous checkpoint); returns the absolute path.

    Args:
        overwrite: replace a checkpoint of format ``fmt`` already at ``path`` (holding
            nothing but its listed files); without it an existing, non-empty ``path`` is
            refused, so of several savers started together exactly one succeeds.

    Raises:
        ValueError: ``path`` exists (without ``overwrite``), is a file, the working
            directory or one of its parents, or a directory that is not a checkpoint of
            format ``fmt`` (it is left untouched); another process is writing it; a file
            name is not a plain name.
        imitrl.fs.DiskFullError: the disk filled up (``path`` keeps what it held).
    """
    for name in files:
        if not _NAME.match(name) or name == MANIFEST:
            raise ValueError(f"checkpoint file name {name!r} must be a plain file name")
    target = absolute(path)

    def replaceable(found: Path) -> None:
        _check_replaceable(found, fmt)

    what = f"a checkpoint ({fmt})"
    with publishing(
        target, overwrite=overwrite, replaceable=replaceable, what=what, empty_ok=True
    ) as tmp:
        listed = {name: _write_file(tmp / name, data) for name, data in files.items()}
        body = {**content, "files": listed}
        manifest = {"format": fmt, "content": body, "content_sha256": _sha256(_canonical(body))}
        text = json.dumps(manifest, indent=1, sort_keys=True, allow_nan=False) + "\n"
        _write_file(tmp / MANIFEST, text.encode())
    return target


def _write_file(path: Path, data: bytes | memoryview) -> dict[str, Any]:
    with open(path, "xb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    return {"bytes": memoryview(data).nbytes, "sha256": _sha256(data)}


def _sha256(data: bytes | memoryview) -> str:
    return hashlib.sha256(data).hexdigest()


def _check_replaceable(target: Path, fmt: str) -> None:
    """Refuse (ValueError) to replace anything at ``target`` but a checkpoint of format
    ``fmt`` holding only its own files."""
    try:
        content = read_whole(
            target, lambda folder: _read_manifest(folder, fmt), what="checkpoint", links=False
        )
    except ValueError as err:
        raise ValueError(
            f"{target} exists and is not a readable checkpoint of format {fmt!r}: refusing "
            f"to replace it ({err})"
        ) from None
    unlisted = sorted(set(os.listdir(target)) - set(content["files"]) - {MANIFEST})
    if unlisted:
        raise ValueError(
            f"{target} holds files its manifest does not list ({unlisted[:5]}): refusing to "
            "replace it"
        )


# ------------------------------------------------------------------------- read
def read_checkpoint(
    path: str | Path, *, fmt: str, map_bytes: int | None = None
) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """Verify and read the checkpoint directory ``path``; returns ``(content, files)``,
    ``files[name]`` the file's bytes as a uint8 tensor ``[size]``.

    Every listed file is checked for presence, size and SHA-256, and the directory for
    unlisted entries, before any of it is returned. Nothing is written. The folder is
    pinned once and each file opened once, by descriptor, inside it: a regular file, never
    a symbolic link or a FIFO (:class:`~imitrl.fs.reading.OpenedFolder`); a load that meets
    a writer's replacement of the folder runs again on the new one
    (:func:`~imitrl.fs.reading.read_whole`), and one that meets it every time says it was
    "replaced while reading" (:class:`~imitrl.fs.reading.ReplacedWhileReading`), never
    that the data is damaged.

    ``map_bytes``: files of at least this many bytes are hashed in a streaming pass and
    returned memory-mapped (copy-on-write, paged in as they are read) instead of read
    into memory: resident memory does not grow with them, at the price of a window
    between the hash and the use in which a change to the file goes unnoticed.

    Raises:
        ValueError: naming the file: no manifest, a manifest of another format or edited,
            a file missing, unlisted, of another size, or with another checksum.
    """
    path = Path(path)
    if not (path / MANIFEST).is_file():
        raise ValueError(_missing_message(path))
    return read_whole(
        path, lambda folder: _read_folder(folder, fmt, map_bytes), what="checkpoint", links=False
    )


def _read_folder(
    folder: OpenedFolder, fmt: str, map_bytes: int | None
) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """:func:`read_checkpoint` on the pinned folder."""
    path = folder.root
    content = _read_manifest(folder, fmt)
    listed = content["files"]
    entries = set(folder.listdir()) - {MANIFEST}  # through the pinned descriptor
    unlisted = sorted(entries - set(listed))
    if unlisted:
        raise ValueError(f"{path / unlisted[0]}: a file the checkpoint's {MANIFEST} does not list")
    opened: dict[str, int] = {}
    try:
        for name, entry in sorted(listed.items()):  # sizes first: cheap, before any hashing
            opened[name] = _open_listed(folder, name, entry["bytes"], name in entries)
        files = {}
        for name, entry in sorted(listed.items()):
            size, sha256 = entry["bytes"], entry["sha256"]
            if map_bytes is not None and size >= max(1, map_bytes):
                files[name] = _map_verified(opened[name], path / name, size, sha256)
            else:
                files[name] = _read_verified(opened[name], path / name, size, sha256)
    finally:
        for fd in opened.values():
            os.close(fd)
    if folder.replaced():  # files found by name (a hub snapshot's): all from one folder
        raise ReplacedWhileReading(f"{path}: replaced while reading it")
    return content, files


def _missing_message(path: Path) -> str:
    hint = ""
    if path.parent.is_dir():
        aside = [e for e in os.listdir(path.parent) if e.startswith(f".{path.name}{OLD}")]
        if aside and not path.exists():
            hint = (
                f"; an interrupted save left the previous checkpoint at {path.parent / aside[0]}"
                f" (rename it to {path.name} to use it)"
            )
    return f"{path} is not a saved DemonstrationBuffer (no {MANIFEST}){hint}"


def _read_manifest(folder: OpenedFolder, fmt: str) -> dict[str, Any]:
    """The manifest's ``content``, checked against its checksum and for its file table."""
    where = folder.root / MANIFEST
    data = folder.read_bytes(MANIFEST, named_by="checkpoint manifest", limit=_MAX_MANIFEST_BYTES)
    manifest = parse_json(data, where=str(where))
    try:
        body, declared = manifest["content"], manifest["content_sha256"]
        found = manifest["format"]
    except (KeyError, TypeError) as err:
        raise ValueError(f"{where}: not a checkpoint manifest (no {err})") from None
    if found != fmt:
        raise ValueError(f"{where}: format {found!r}, expected {fmt!r}")
    try:
        actual = _sha256(_canonical(body))
    except (ValueError, TypeError) as err:
        raise ValueError(f"{where}: content is not plain JSON ({err})") from None
    if actual != declared:
        raise ValueError(f"{where}: edited or damaged (its content does not match its checksum)")
    files = body.get("files") if isinstance(body, dict) else None
    if not isinstance(files, dict) or not all(_valid_entry(n, e) for n, e in files.items()):
        raise ValueError(f"{where}: malformed file table")
    if len(files) > MAX_FILES:
        raise ValueError(f"{where}: lists {len(files)} files, more than the {MAX_FILES} it may")
    return body


def _valid_entry(name: Any, entry: Any) -> bool:
    return (
        isinstance(name, str)
        and bool(_NAME.match(name))
        and name != MANIFEST
        and isinstance(entry, dict)
        and type(entry.get("bytes")) is int
        and entry["bytes"] >= 0
        and isinstance(entry.get("sha256"), str)
        and re.fullmatch(r"[0-9a-f]{64}", entry["sha256"]) is not None
    )


def _open_listed(folder: OpenedFolder, name: str, size: int, present: bool) -> int:
    """A descriptor of the listed file ``name``, a regular file of the manifest's ``size``
    (ValueError naming it otherwise)."""
    where = folder.root / name
    if not present:
        raise ValueError(f"{where}: missing (the checkpoint's {MANIFEST} lists it)")
    fd = folder.open(name, named_by=f"the checkpoint's {MANIFEST}")
    found = os.fstat(fd).st_size
    if found != size:
        os.close(fd)
        raise ValueError(
            f"{where}: {found} bytes, the manifest says {size} (truncated or appended to)"
        )
    return fd


def _read_verified(fd: int, where: Path, size: int, sha256: str) -> torch.Tensor:
    out = torch.empty(size, dtype=torch.uint8)
    view = out.numpy().data  # memoryview(array), typed (numpy types __buffer__ from 3.12)
    with os.fdopen(fd, "rb", buffering=0, closefd=False) as f:
        got = 0
        while got < size:
            n = f.readinto(view[got:])
            if not n:
                break
            got += n
        if got != size or f.read(1):
            raise ValueError(f"{where}: changed size while being read")
    if _sha256(view) != sha256:
        raise ValueError(f"{where}: SHA-256 does not match the manifest (the file was altered)")
    return out


def _map_verified(
    fd: int, where: Path, size: int, sha256: str, block: int = 8 << 20
) -> torch.Tensor:
    """The file as a private (copy-on-write) memory map, after a streaming SHA-256 pass;
    mapped through the descriptor (:func:`~imitrl.fs.reading.fd_path`): the file hashed."""
    digest, buffer = hashlib.sha256(), bytearray(block)
    view = memoryview(buffer)
    with os.fdopen(fd, "rb", buffering=0, closefd=False) as f:
        got = 0
        while True:
            n = f.readinto(view)
            if not n:
                break
            digest.update(view[:n])
            got += n
    if got != size:
        raise ValueError(f"{where}: changed size while being read")
    if digest.hexdigest() != sha256:
        raise ValueError(f"{where}: SHA-256 does not match the manifest (the file was altered)")
    return torch.from_file(fd_path(fd), shared=False, size=size, dtype=torch.uint8)
