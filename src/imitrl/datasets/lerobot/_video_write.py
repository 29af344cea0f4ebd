"""Camera keys written as LeRobot v3.0 video features (``save_lerobot(..., video=True)``).

Encoding follows LeRobot's own recorder (``lerobot/datasets/video_utils.py``,
``encode_video_frames`` with its default ``RGBEncoderConfig``, and
``dataset_writer._save_episode_video``, lerobot 0.6): each episode of a camera is encoded
on its own with PyAV, ``libsvtav1``, ``yuv420p``, one frame per ``1 / fps`` (PyAV numbers
the frames), options :data:`CODEC_OPTIONS` (``g=2``, ``crf=30``, ``preset=12``,
``svtav1-params=fast-decode=0``; lerobot 0.4 passed the same ``g`` and ``crf`` and left the
preset to SVT-AV1), so every episode starts on a keyframe. The episodes of a camera are
then joined without re-encoding (FFmpeg's concat demuxer, stream copy, ``faststart``: as
``concatenate_video_files``) into ``videos/{video_key}/chunk-XXX/file-YYY.mp4``
(:data:`VIDEO_PATH`) until the next episode would bring the file to
``video_files_size_in_mb`` (the encoded episodes' sizes summed stand for the joined file's,
which lacks only their repeated mp4 headers); then the next file (``chunks_size`` files per
chunk). An
episode's ``from_timestamp`` is the previous episode's ``to_timestamp`` in the same file
(0 in a new one), ``to_timestamp = from_timestamp + length / fps``.

Memory: one episode of one camera is encoded at a time from the rows' own frames (a view,
no copy); the encoded episodes of the file being filled wait on disk in the staging
directory until they are joined.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from imitrl.datasets.lerobot._video import INSTALL_HINT  # one install hint for PyAV

VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
"""LeRobot v3.0's ``video_path`` template (``DEFAULT_VIDEO_PATH`` in ``lerobot/datasets/utils.py``)"""
VCODEC = "libsvtav1"
PIX_FMT = "yuv420p"
CODEC_OPTIONS = {"g": "2", "crf": "30", "preset": "12", "svtav1-params": "fast-decode=0"}
"""``RGBEncoderConfig().get_codec_options(as_strings=True)`` for libsvtav1 (lerobot 0.6)"""
ENCODER_INFO = {
    "video.g": 2,
    "video.crf": 30,
    "video.preset": 12,
    "video.fast_decode": 0,
    "video.video_backend": "pyav",
    "video.extra_options": {},
}
"""the encoder settings lerobot 0.6's ``get_video_info`` records beside the stream's own"""
MIN_SIDE = 4
"""the smallest frame height and width SVT-AV1 encodes (PyAV 18's wheels: 4x4 and 6x6 are
accepted, 3x5, 2x64 and 8x2 refused)"""

_EPISODES_DIR = ".imitrl-video-episodes"
"""staging folder (inside the dataset being written) of the encoded episodes not yet joined"""


def import_av() -> Any:
    """The ``av`` module (PyAV) with an AV1 (SVT-AV1) encoder, imported only when a camera is
    written as video; ImportError with the install command when it is missing."""
    try:
        import av
    except ImportError as err:
        raise ImportError(
            "save_lerobot(video=True) encodes cameras with PyAV (the 'av' package), which is "
            f"not installed: {INSTALL_HINT}; or pass video=False to store frames as images"
        ) from err
    if VCODEC not in av.codecs_available:
        raise ImportError(
            f"this PyAV build has no {VCODEC!r} encoder, which LeRobot's videos use; the "
            f"PyAV wheels bundle it: {INSTALL_HINT}"
        )
    # SVT-AV1 prints its settings (about 50 "Svt[info]" lines per stream) on stdout
    # unless told otherwise; a library call prints nothing the caller did not ask for
    os.environ.setdefault("SVT_LOG", "1")  # 1: errors only
    return av


@dataclass(frozen=True)
class VideoFiles:
    """What :func:`write_videos` wrote, for the episode table and ``info.json``."""

    episode_columns: list[dict[str, Any]]
    """per episode: ``videos/<feature>/{chunk_index, file_index, from_timestamp,
    to_timestamp}`` of every camera, camera after camera"""
    info: dict[str, dict[str, Any]]
    """feature -> the ``info`` LeRobot records for it (``get_video_info`` of its first file)"""


def write_videos(
    root: Path,
    videos: dict[str, np.ndarray],
    starts: list[int],
    lengths: list[int],
    *,
    fps: int,
    chunks_size: int,
    file_size_in_mb: float,
) -> VideoFiles:
    """Every camera's mp4 files under ``root`` (:data:`VIDEO_PATH`).

    Args:
        videos: feature -> uint8 ``[N, H, W, 3]`` frames of all episodes back to back.
        starts, lengths: first frame and number of frames of each episode.
    """
    av = import_av()
    columns: list[dict[str, Any]] = [{} for _ in starts]
    info: dict[str, dict[str, Any]] = {}
    for name, frames in videos.items():
        for i, entry in enumerate(
            _write_camera(
                av, root, name, frames, starts, lengths, fps, chunks_size, file_size_in_mb
            )
        ):
            columns[i].update(entry)
        info[name] = _video_info(
            av, root / VIDEO_PATH.format(video_key=name, chunk_index=0, file_index=0)
        )
    shutil.rmtree(root / _EPISODES_DIR, ignore_errors=True)
    return VideoFiles(columns, info)


def next_file(chunk: int, file: int, chunks_size: int) -> tuple[int, int]:
    """The ``(chunk_index, file_index)`` after a full file (lerobot's
    ``update_chunk_file_indices``)."""
    return (chunk + 1, 0) if file == chunks_size - 1 else (chunk, file + 1)


def _write_camera(
    av: Any,
    root: Path,
    name: str,
    frames: np.ndarray,
    starts: list[int],
    lengths: list[int],
    fps: int,
    chunks_size: int,
    file_size_in_mb: float,
) -> list[dict[str, Any]]:
    """One camera's files, episode by episode; each episode's ``videos/<name>/...`` entries."""
    staging = root / _EPISODES_DIR / name
    staging.mkdir(parents=True, exist_ok=True)
    entries: list[dict[str, Any]] = []
    chunk, file = 0, 0
    pending: list[Path] = []  # encoded episodes of file (chunk, file), in order
    pending_mb, latest = 0.0, 0.0  # their size; the to_timestamp of the last one
    for i, (s, n) in enumerate(zip(starts, lengths)):
        part = staging / f"episode-{i:06d}.mp4"
        _encode_episode(av, part, frames[s : s + n], fps)
        part_mb = part.stat().st_size / 1024**2
        if pending and pending_mb + part_mb >= file_size_in_mb:  # lerobot: the next file
            _join(
                av,
                pending,
                root / VIDEO_PATH.format(video_key=name, chunk_index=chunk, file_index=file),
            )
            chunk, file = next_file(chunk, file, chunks_size)
            pending, pending_mb, latest = [], 0.0, 0.0
        pending.append(part)
        pending_mb += part_mb
        entries.append(
            {
                f"videos/{name}/chunk_index": chunk,
                f"videos/{name}/file_index": file,
                f"videos/{name}/from_timestamp": latest,
                f"videos/{name}/to_timestamp": latest + n / fps,
            }
        )
        latest = latest + n / fps
    _join(av, pending, root / VIDEO_PATH.format(video_key=name, chunk_index=chunk, file_index=file))
    return entries


def _encode_episode(av: Any, path: Path, frames: np.ndarray, fps: int) -> None:
    """uint8 ``[T, H, W, 3]`` frames as one AV1 mp4, as ``encode_video_frames`` writes it
    (frames given as ``rgb24``, converted to ``yuv420p`` by the encoder's reformatter)."""
    with av.open(str(path), "w") as output:
        stream = output.add_stream(VCODEC, fps, options=dict(CODEC_OPTIONS))
        stream.pix_fmt = PIX_FMT
        stream.height, stream.width = frames.shape[1], frames.shape[2]
        for image in frames:
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format="rgb24")
            for packet in stream.encode(frame):
                output.mux(packet)
        for packet in stream.encode():  # flush the encoder
            output.mux(packet)


def _join(av: Any, parts: list[Path], dest: Path) -> None:
    """The encoded episodes ``parts`` as one file ``dest``: moved when alone, else joined
    packet by packet without re-encoding (``concatenate_video_files``)."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    if len(parts) == 1:
        parts[0].replace(dest)
        return
    listing = parts[0].parent / "files.ffconcat"  # names relative to it: no quoting needed
    listing.write_text("ffconcat version 1.0\n" + "".join(f"file '{p.name}'\n" for p in parts))
    with (
        av.open(str(listing), "r", format="concat") as source,
        av.open(str(dest), "w", options={"movflags": "faststart"}) as output,
    ):
        video = source.streams.video[0]
        stream = output.add_stream_from_template(template=video, opaque=True)
        stream.time_base = video.time_base
        for packet in source.demux(video):
            if packet.dts is None:  # the demuxer's flushing packet
                continue
            packet.stream = stream
            output.mux(packet)
    for p in (listing, *parts):
        p.unlink()


def _video_info(av: Any, path: Path) -> dict[str, Any]:
    """The ``info`` of a video feature, read from its first file as LeRobot's
    ``get_video_info`` reads it (lerobot 0.4's keys, then the encoder settings lerobot 0.6
    adds, with its ``is_depth_map``)."""
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        info: dict[str, Any] = {
            "video.height": stream.height,
            "video.width": stream.width,
            "video.codec": stream.codec.canonical_name,
            "video.pix_fmt": stream.pix_fmt,
            "video.is_depth_map": False,
            "video.fps": int(stream.base_rate),
            "video.channels": len(av.VideoFormat(stream.pix_fmt).components),
            "has_audio": bool(container.streams.audio),
        }
    return {**info, **ENCODER_INFO, "is_depth_map": False}
