"""Camera frames of a LeRobot dataset: where each episode's frames lie in which video file,
and decoding them with PyAV on CPU.

Where (``lerobot/datasets/lerobot_dataset.py``, ``_query_videos`` and
``get_video_file_path``): v2.1 (lerobot 0.3.x) has one mp4 per episode and camera,
``info["video_path"]`` filled with ``episode_chunk = episode_index // chunks_size``,
``video_key`` and ``episode_index``, and frame ``t`` is the video frame at the frame's own
``timestamp``. v3.0 (lerobot 0.4.x) concatenates episodes per file: the episode table's
``videos/<feature>/chunk_index`` and ``file_index`` fill ``video_path`` (with
``video_key``), and frame ``t`` is the video frame at ``videos/<feature>/from_timestamp +
timestamp``.

How (``decode_video_frames_pyav`` in ``lerobot/datasets/video_utils.py``): a wanted
timestamp takes the decoded frame whose ``pts * time_base`` lies within ``tolerance_s``
(``1e-4`` s, :data:`~imitrl.datasets.lerobot._checks.TOLERANCE_S`) of it, else the dataset
is refused. LeRobot seeks to the keyframe before each query; here every file is decoded
once, front to back, and each decoded frame goes to the rows that want it (frames are
at least ``1 / fps`` apart, so at most one frame lies within the tolerance of a
timestamp), which is frame-exact and reads each file once. Frames are ``rgb24`` as
LeRobot converts them (``frame.to_ndarray(format="rgb24")``): uint8 ``[H, W, 3]``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from imitrl.datasets._arrow import MAX_IMAGE_PIXELS
from imitrl.datasets._common import NestedKey
from imitrl.datasets.lerobot._checks import TOLERANCE_S
from imitrl.datasets.lerobot._files import holds, opened
from imitrl.datasets.lerobot._layout import IMAGE_NAMES, fill_template
from imitrl.fs.contained import plain_name
from imitrl.fs.files import create_file, make_folder
from imitrl.fs.reading import OpenedFolder
from imitrl.fs.write_errors import reporting_disk_full

INSTALL_HINT = "pip install 'imitrl[datasets]' (or: pip install av)"


def import_av() -> Any:
    """The ``av`` module (PyAV), imported only when a video is decoded; ImportError with
    the install command when it is missing."""
    try:
        import av
    except ImportError as err:
        raise ImportError(
            f"decoding LeRobot camera videos needs PyAV (the 'av' package): {INSTALL_HINT}; "
            "or pass videos='skip' to load the dataset without its cameras"
        ) from err
    return av


def frame_size(root: Path, name: str, feature: dict) -> tuple[int, int]:
    """``(H, W)`` of a video feature as ``info.json`` declares it: ``shape`` read through its
    ``names`` (``[height, width, channels]``, or channels first), 3 channels, and agreeing
    with the ``info`` LeRobot records beside it (``video.height``, ``video.width``)."""
    where = f"{root / 'meta' / 'info.json'}: video feature {name!r}"
    shape, names = list(feature["shape"]), feature.get("names")
    if names == IMAGE_NAMES["chw"]:
        shape = [*shape[1:], *shape[:1]]
    elif names not in (None, IMAGE_NAMES["hwc"], ["height", "width", "channel"]):
        raise ValueError(f"{where} has names {names}, expected {IMAGE_NAMES['hwc']}")
    if len(shape) != 3 or shape[2] != 3 or min(shape) < 1:
        raise ValueError(f"{where} has shape {feature['shape']}, expected [height, width, 3]")
    height, width = shape[0], shape[1]
    recorded = feature.get("info") or {}
    for field, size in (("video.height", height), ("video.width", width)):
        if field in recorded and recorded[field] != size:
            raise ValueError(
                f"{where} has shape {feature['shape']} but info {field} {recorded[field]!r}"
            )
    return height, width


@dataclass
class _Wanted:
    """The frames one video file must give: ``[K]`` each row's timestamp in the file."""

    rows: list[torch.Tensor]
    """``[T_e]`` output rows of each episode's frames"""
    times: list[torch.Tensor]
    """``[T_e]`` float64 seconds into the file of those frames"""
    episodes: list[int]
    """the episode of each entry above (for messages)"""


def _locate(
    root: Path,
    info: dict,
    major: int,
    name: str,
    episodes: list[dict],
    times: torch.Tensor,
) -> dict[str, _Wanted]:
    """video file (relative to ``root``) -> the rows it fills and their timestamps in it,
    for feature ``name``; ``times`` ``[N]`` is each row's ``timestamp`` (rows are the
    episodes back to back)."""
    files: dict[str, _Wanted] = {}
    begin = 0
    for ep in episodes:
        e, length = int(ep["episode_index"]), int(ep["length"])
        shift = 0.0
        if major == 3:
            cols = [f"videos/{name}/{c}" for c in ("chunk_index", "file_index", "from_timestamp")]
            missing = [c for c in cols if c not in ep]
            if missing:
                raise ValueError(
                    f"{root / 'meta' / 'episodes'}: episode {e} lacks {missing}, needed to find "
                    f"the frames of video feature {name!r}"
                )
            shift = float(ep[cols[2]])
            if not math.isfinite(shift) or shift < 0:
                raise ValueError(
                    f"{root / 'meta' / 'episodes'}: episode {e} has {cols[2]} {shift!r}, "
                    "expected seconds >= 0"
                )
            fields = {"chunk_index": ep[cols[0]], "file_index": ep[cols[1]]}
        else:
            fields = {"episode_chunk": ep["chunk"], "episode_index": e}
        path = fill_template(root, info, "video_path", video_key=name, **fields)
        wanted = files.setdefault(path, _Wanted([], [], []))
        wanted.rows.append(torch.arange(begin, begin + length))
        wanted.times.append(times[begin : begin + length].double() + shift)
        wanted.episodes.append(e)
        begin += length
    return files


class _Frames:
    """Where the decoded uint8 ``[N, H, W, 3]`` frames of one feature go: an ordinary tensor,
    or (``filename`` given) a file written with ``pwrite`` and mapped once complete
    (:meth:`tensor`), so that the frames are never resident in this process while decoded."""

    def __init__(self, shape: tuple[int, ...], filename: Path | None) -> None:
        self.shape, self.filename = shape, filename
        self.frame_bytes = math.prod(shape[1:])
        self.fd: int | None = None
        if filename is None:
            self.array = torch.empty(shape, dtype=torch.uint8).numpy()
            return
        make_folder(filename.parent)
        filename.unlink(missing_ok=True)  # a tensor still mapping an old file keeps it
        # a new file, never through a link planted at its name (imitrl.fs.files)
        self.fd = create_file(filename, what="decoded frames", readable=True)
        os.ftruncate(self.fd, shape[0] * self.frame_bytes)

    def put(self, row: int, image: Any) -> None:
        """Frame ``row`` is ``image`` (uint8 ``[H, W, 3]``)."""
        if self.fd is None:
            self.array[row] = image
        else:
            written = os.pwrite(self.fd, image.data.cast("B"), row * self.frame_bytes)
            if written != self.frame_bytes:
                raise OSError(f"{self.filename}: short write ({written} of {self.frame_bytes} B)")

    def tensor(self) -> torch.Tensor:
        """The frames, once every row is written (a ``MemoryMappedTensor`` over the file)."""
        if self.fd is None:
            return torch.from_numpy(self.array)
        from tensordict import MemoryMappedTensor

        self.close()
        return MemoryMappedTensor.from_filename(self.filename, torch.uint8, self.shape)

    def close(self, *, remove: bool = False) -> None:
        """Close the file (and ``remove`` it: a failed load leaves nothing behind)."""
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None
        if remove and self.filename is not None:
            self.filename.unlink(missing_ok=True)


def _decode_file(
    folder: OpenedFolder,
    relative: str,
    name: str,
    wanted: _Wanted,
    out: _Frames,
    size: tuple[int, int],
) -> None:
    """Decode the video ``relative`` front to back into the frames' rows (uint8
    ``[N, H, W, 3]``), each wanted timestamp taking the frame within :data:`TOLERANCE_S`
    of it."""
    path = folder.root / relative
    times = torch.cat(wanted.times)
    if len(times) == 0:
        return  # empty episodes only
    order = torch.argsort(times, stable=True)
    want = times[order].tolist()
    dest = torch.cat(wanted.rows)[order].tolist()
    owners = [torch.full((len(r),), e) for r, e in zip(wanted.rows, wanted.episodes)]
    owner = torch.cat(owners)[order].tolist()
    j, last, after = 0, None, None
    with _stream(folder, relative, name, size, wanted.episodes) as (container, stream):
        time_base = float(stream.time_base)
        for frame in container.decode(stream):
            if frame.pts is None:
                continue
            t = frame.pts * time_base
            if want[j] < t - TOLERANCE_S:
                after = t  # frames are in time order: want[j] has none
                break
            if want[j] <= t + TOLERANCE_S:
                image = np.ascontiguousarray(frame.to_ndarray(format="rgb24"))
                _check_size(path, name, image.shape[:2], size)
                while j < len(want) and want[j] <= t + TOLERANCE_S:
                    out.put(dest[j], image)
                    j += 1
                if j == len(want):
                    return
            last = t
    if after is not None:
        before = "none" if last is None else f"{last:.6g} s"
        found = f"its frames nearest to it are at {before} and {after:.6g} s"
    else:
        found = "it holds no frame" if last is None else f"its last frame is at {last:.6g} s"
    raise ValueError(
        f"{path}: episode {owner[j]} of video feature {name!r} needs a frame at {want[j]:.6g} s "
        f"(within {TOLERANCE_S} s, LeRobot's tolerance); {found}: the video is shorter than "
        "the episode's timestamps, or they disagree"
    )


@contextmanager
def _stream(
    folder: OpenedFolder, relative: str, name: str, size: tuple[int, int], episodes: list[int]
) -> Iterator[tuple[Any, Any]]:
    """``(container, its first video stream)`` of the video ``relative``, opened by
    descriptor inside the folder (PyAV opens the descriptor's own path, kept open while it
    reads), the stream's frame size checked against ``size`` from its header; PyAV's
    errors become ValueErrors naming it."""
    av = import_av()
    path = folder.root / relative
    if not holds(folder, relative):
        raise ValueError(
            f"{path}: file not found (video feature {name!r} of episode(s) {episodes})"
        )
    named_by = f"meta/info.json's video_path (video feature {name!r})"
    with opened(folder, relative, named_by=named_by) as source:
        try:
            with av.open(source) as container:
                if not container.streams.video:
                    raise ValueError(f"{path}: holds no video stream (video feature {name!r})")
                stream = container.streams.video[0]
                _check_size(path, name, (stream.height, stream.width), size)
                yield container, stream
        except av.error.FFmpegError as err:
            said = str(err).replace(source, str(path))  # the file, not its descriptor
            raise ValueError(
                f"{path}: not a readable video (video feature {name!r}; "
                f"{type(err).__name__}: {said})"
            ) from err


def _probe(
    folder: OpenedFolder, relative: str, name: str, size: tuple[int, int], episodes: list[int]
) -> None:
    """The first video stream of ``relative`` has frames of ``size`` (read from its
    header), at most :data:`~imitrl.datasets._arrow.MAX_IMAGE_PIXELS` of them."""
    with _stream(folder, relative, name, size, episodes):
        pass
    if size[0] * size[1] > MAX_IMAGE_PIXELS:
        raise ValueError(
            f"{folder.root / relative}: frames of {size[0]}x{size[1]} (height x width), more "
            f"than the {MAX_IMAGE_PIXELS:,} pixels a frame may have (video feature {name!r}); "
            "refused before memory is taken for them"
        )


def _check_size(path: Path, name: str, got: tuple[int, int], size: tuple[int, int]) -> None:
    if tuple(got) != tuple(size):
        raise ValueError(
            f"{path}: frames are {got[0]}x{got[1]} (height x width), meta/info.json declares "
            f"video feature {name!r} as {size[0]}x{size[1]}"
        )


def decode_videos(
    folder: OpenedFolder,
    info: dict,
    major: int,
    episodes: list[dict],
    cameras: Mapping[str, NestedKey],
    times: torch.Tensor,
    decode_dir: Path | None,
) -> dict[NestedKey, torch.Tensor]:
    """Buffer key -> uint8 ``[N, H, W, 3]`` frames of each video feature in ``cameras``.

    Args:
        episodes: the episode table in episode order (rows are its episodes back to back).
        cameras: video feature -> buffer key.
        times: ``[N]`` each row's ``timestamp`` within its episode.
        decode_dir: if given, each feature's frames go into the file
            ``<decode_dir>/<feature>.uint8`` (replaced if present; raw uint8 frames, row
            after row), written as they are decoded and returned as tensordict's
            ``MemoryMappedTensor`` over it, so that resident memory stays bounded; else
            into an ordinary tensor. A failed decode removes its file.
    """
    import_av()  # a missing PyAV is reported before anything is decoded
    root = folder.root
    out: dict[NestedKey, torch.Tensor] = {}
    done: list[_Frames] = []
    for name, key in cameras.items():
        size = frame_size(root, name, info["features"][name])
        where = None
        if decode_dir is not None:  # the feature's name, never a path the dataset picks
            where = Path(decode_dir) / plain_name(
                f"{name}.uint8", what="decoded frames of feature", where=str(root)
            )
        located = _locate(root, info, major, name, episodes, times)
        if located:  # the declared size, checked on a file before any memory is taken
            first, wanted = next(iter(located.items()))
            _probe(folder, first, name, size, wanted.episodes)
        frames = _Frames((len(times), *size, 3), where)
        done.append(frames)
        try:
            with reporting_disk_full(
                where or Path("."), what="decoded frames", left="the partial file is removed"
            ):
                for path, wanted in located.items():
                    _decode_file(folder, path, name, wanted, frames, size)
        except BaseException:
            for failed in done:  # nothing is left half-loaded, on disk either
                failed.close(remove=True)
            raise
        out[key] = frames.tensor()
    return out
