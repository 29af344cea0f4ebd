"""Camera videos added to the LeRobot directories of ``_lerobot_files``, as lerobot lays them out.

Encoding follows lerobot 0.4.4's ``encode_video_frames`` (``lerobot/datasets/video_utils.py``):
PyAV, ``libsvtav1``, ``yuv420p``, options ``g=2``, ``crf=30``, ``preset=12`` (its
``_get_codec_options``; ``h264`` gets the same ``g`` and ``crf``), one frame per
``1 / fps``. v2.1 (lerobot 0.3.3): one mp4 per episode and camera at
``videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4``. v3.0
(lerobot 0.4.4, ``_save_episode_video``): each episode encoded on its own, then appended
to its file by ``concatenate_video_files`` (the concat demuxer, stream copy, ``faststart``);
the episode table gets ``videos/{key}/chunk_index``, ``file_index``, ``from_timestamp`` (the
previous episode's ``to_timestamp`` in the same file, 0 in a new one) and
``to_timestamp = from_timestamp + get_video_duration_in_s(episode video)``.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path

import av
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from ._lerobot_files import FPS

V21_VIDEO_PATH = "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4"
V30_VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
CODECS = {
    "libsvtav1": {"g": "2", "crf": "30", "preset": "12"},
    "libx264": {"g": "2", "crf": "30"},
}


def smooth_frames(length: int, height: int, width: int, *, seed: int) -> np.ndarray:
    """uint8 ``[length, H, W, 3]``: smooth colour gradients that move a little every frame
    (so that consecutive frames differ everywhere, and a lossy codec keeps them well)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    phase = rng.uniform(0, 2 * np.pi, 3)
    out = np.empty((length, height, width, 3), dtype=np.uint8)
    for t in range(length):
        for c in range(3):
            wave = np.sin(x / width * np.pi + phase[c] + 0.3 * t) * np.cos(
                y / height * np.pi / 2 + 0.2 * c * t
            )
            out[t, :, :, c] = np.round(127.5 + 100 * wave).astype(np.uint8)
    return out


def encode(path: Path, frames: np.ndarray, *, codec: str = "libsvtav1", fps: int = FPS) -> None:
    """One mp4 of ``[T, H, W, 3]`` frames, as ``encode_video_frames`` writes it."""
    os.environ.setdefault("SVT_LOG", "1")  # SVT-AV1 prints its settings otherwise
    path.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(path), "w") as out:
        stream = out.add_stream(codec, fps, options=CODECS[codec])
        stream.pix_fmt = "yuv420p"
        stream.height, stream.width = frames.shape[1:3]
        for image in frames:
            out.mux(stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")))
        out.mux(stream.encode())


def concatenate(inputs: list[Path], output: Path) -> None:
    """``concatenate_video_files``: the concat demuxer, packets copied, ``faststart``."""
    with tempfile.TemporaryDirectory() as tmp:
        listing = Path(tmp) / "list.ffconcat"
        listing.write_text(
            "ffconcat version 1.0\n" + "".join(f"file '{p.resolve()}'\n" for p in inputs)
        )
        joined = Path(tmp) / "joined.mp4"
        with (
            av.open(str(listing), "r", format="concat", options={"safe": "0"}) as src,
            av.open(str(joined), "w", options={"movflags": "faststart"}) as dst,
        ):
            into = dst.add_stream_from_template(template=src.streams.video[0], opaque=True)
            into.time_base = src.streams.video[0].time_base
            for packet in src.demux(src.streams.video[0]):
                if packet.dts is None:
                    continue
                packet.stream = into
                dst.mux(packet)
        output.parent.mkdir(parents=True, exist_ok=True)
        shutil.move(joined, output)


def duration(path: Path) -> float:
    """``get_video_duration_in_s``: the stream's duration in seconds."""
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        return float(stream.duration * stream.time_base)


def decode_all(path: Path) -> np.ndarray:
    """Every frame of a file as PyAV decodes it directly, ``[F, H, W, 3]`` uint8."""
    with av.open(str(path)) as container:
        return np.stack([f.to_ndarray(format="rgb24") for f in container.decode(video=0)])


def _declare(root: Path, cameras: dict[str, list[np.ndarray]], video_path: str, codec: str):
    """Add the cameras to ``info.json`` as lerobot does (``shape``, ``names``, ``info``)."""
    info = json.loads((root / "meta/info.json").read_text())
    for name, episodes in cameras.items():
        height, width = episodes[0].shape[1:3]
        info["features"][name] = {
            "dtype": "video",
            "shape": [height, width, 3],
            "names": ["height", "width", "channels"],
            "info": {
                "video.height": height,
                "video.width": width,
                "video.codec": {"libsvtav1": "av1", "libx264": "h264"}[codec],
                "video.pix_fmt": "yuv420p",
                "video.is_depth_map": False,
                "video.fps": FPS,
                "video.channels": 3,
                "has_audio": False,
            },
        }
    info["video_path"] = video_path
    info["total_videos"] = len(cameras) * len(next(iter(cameras.values())))
    (root / "meta/info.json").write_text(json.dumps(info, indent=4))


def add_cameras_v21(
    root: Path, cameras: dict[str, list[np.ndarray]], *, chunks_size: int, codec: str
) -> dict[str, list[Path]]:
    """One file per episode and camera (``cameras[name][e]`` ``[T_e, H, W, 3]``); the files."""
    files: dict[str, list[Path]] = {}
    for name, episodes in cameras.items():
        for e, frames in enumerate(episodes):
            rel = V21_VIDEO_PATH.format(
                episode_chunk=e // chunks_size, video_key=name, episode_index=e
            )
            encode(root / rel, frames, codec=codec)
            files.setdefault(name, []).append(root / rel)
    _declare(root, cameras, V21_VIDEO_PATH, codec)
    return files


def add_cameras_v30(
    root: Path,
    cameras: dict[str, list[np.ndarray]],
    *,
    files: list[tuple[int, int]],
    codec: str = "libsvtav1",
) -> dict[str, list[dict]]:
    """Episodes appended to ``videos/{key}/chunk-{c}/file-{f}.mp4`` (``files[e] = (c, f)``,
    episodes of a file consecutive), the episode table's ``videos/{key}/...`` columns added;
    per camera, each episode's ``{"file", "from_timestamp", "to_timestamp"}``."""
    spans: dict[str, list[dict]] = {}
    columns: dict[str, list] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, episodes in cameras.items():
            end: dict[tuple[int, int], float] = {}
            for e, frames in enumerate(episodes):
                single = Path(tmp) / f"{name}_{e:03d}.mp4"
                encode(single, frames, codec=codec)
                chunk, file = files[e]
                path = root / V30_VIDEO_PATH.format(
                    video_key=name, chunk_index=chunk, file_index=file
                )
                start = end.get(files[e], 0.0)
                if path.exists():
                    concatenate([path, single], path)
                else:
                    path.parent.mkdir(parents=True, exist_ok=True)
                    shutil.copy(single, path)
                end[files[e]] = start + duration(single)
                spans.setdefault(name, []).append(
                    {"file": path, "from_timestamp": start, "to_timestamp": end[files[e]]}
                )
                for field, value in (
                    ("chunk_index", chunk),
                    ("file_index", file),
                    ("from_timestamp", start),
                    ("to_timestamp", end[files[e]]),
                ):
                    columns.setdefault(f"videos/{name}/{field}", []).append(value)
    for table_file in sorted((root / "meta/episodes").glob("*/*.parquet")):
        table = pq.read_table(table_file)
        ids = table.column("episode_index").to_pylist()
        for column, values in columns.items():
            kind = pa.float64() if column.endswith("timestamp") else pa.int64()
            table = table.append_column(column, pa.array([values[e] for e in ids], kind))
        pq.write_table(table, table_file)
    _declare(root, cameras, V30_VIDEO_PATH, codec)
    return spans


def drop_feature(root: Path, name: str) -> None:
    """Remove a parquet feature from every data file and from ``info.json`` (a dataset
    recorded without it)."""
    for path in sorted((root / "data").glob("*/*.parquet")):
        table = pq.read_table(path)
        pq.write_table(table.drop_columns([name]), path)
    info = json.loads((root / "meta/info.json").read_text())
    del info["features"][name]
    (root / "meta/info.json").write_text(json.dumps(info, indent=4))


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """Peak signal-to-noise ratio in dB of two uint8 arrays."""
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float("inf") if mse == 0 else float(10 * np.log10(255.0**2 / mse))
