"""Camera decoding: `load_lerobot` on LeRobot v3.0 AV1 video against PyAV's own loop.

A LeRobot v3.0 dataset with one 96x96 camera (`observation.images.cam`), written here as
lerobot 0.4 lays it out: AV1 by PyAV with lerobot's defaults (`libsvtav1`, `yuv420p`,
`g=2`, `crf=30`, `preset=12`), episodes back to back in one mp4 per file, each
episode's `from_timestamp` in the episode table. Measured:

* decode throughput, frames/s: `load_lerobot(root)` (parquet, checks, and every frame
  decoded and placed by timestamp) against the plain PyAV loop over the same files
  (`for frame in container.decode(video=0): frame.to_ndarray(format="rgb24")`), best of
  `repeats`; target: the reader >= 0.8x PyAV.
* resident memory of a fresh process loading a `mem_frames`-frame dataset, with
  `decode_dir` (frames written to a file and memory-mapped) and without (an ordinary
  tensor): peak resident set (`VmHWM`), and anonymous (`RssAnon`) and file-backed
  (`RssFile`) resident memory after the load and after one pass reading every frame
  (`/proc/self/status`). File-backed pages are the page cache's, which the kernel reclaims
  under pressure; anonymous memory cannot be.
* training from the `mem_frames`-frame dataset, in a fresh process: `load_lerobot` with
  `decode_dir`, the rows into a disk-backed `DemonstrationBuffer(path=...)`, then
  `train_steps` minibatch `fit_bc` steps (batch `train_batch`) of `build("for_env", ...)`'s CNN
  (the Nature CNN, a categorical head on the recorded actions) reading
  `("pixels", "cam")`: peak resident set (`VmHWM`) and `RssAnon` / `RssFile` after each
  stage. Target (issue 14): the process stays under 2 GB resident.

    python benchmarks/camera_decode.py            # 20 x 500 frames, 100k frames; refreshes README
    python benchmarks/camera_decode.py --quick    # tiny, into a temporary directory
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import av
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import torch
from torchrl.data import Categorical

import _report
from imitrl import keys
from imitrl.algorithms import BCConfig, fit_bc
from imitrl.data import DemonstrationBuffer
from imitrl.datasets import load_lerobot
from imitrl.learners import TaskSpec, build

NAME = "camera_decode"
CAMERA = "observation.images.cam"
FPS = 50
PIXEL_KEY = (keys.PIXELS, "cam")
"""where ``load_lerobot`` puts ``observation.images.cam``"""
CODEC_OPTIONS = {"g": "2", "crf": "30", "preset": "12"}
"""lerobot 0.4's `encode_video_frames` defaults for libsvtav1 (`_get_codec_options`)"""


@dataclass(frozen=True)
class Config:
    episodes: int = 20
    """episodes of the throughput dataset"""
    length: int = 500
    """frames per episode (both datasets)"""
    size: int = 96
    """frames are size x size RGB"""
    episodes_per_file: int = 10
    """episodes concatenated in one video file"""
    mem_frames: int = 100_000
    """frames of the memory dataset"""
    repeats: int = 3
    """throughput: best of this many"""
    train_steps: int = 200
    """minibatch BC steps of the training phase (on the memory dataset)"""
    train_batch: int = 64
    """minibatch of the training phase"""


QUICK = Config(
    episodes=4, length=50, episodes_per_file=2, mem_frames=1_000, repeats=1, train_steps=3
)


# ------------------------------------------------------------------ the dataset
def frame(t: int, size: int) -> np.ndarray:
    """uint8 ``[size, size, 3]``: smooth gradients drifting with ``t``."""
    y, x = np.mgrid[0:size, 0:size].astype(np.float32) / size
    out = np.stack([np.sin(6 * x + 0.1 * t), np.cos(5 * y - 0.07 * t), np.sin(4 * (x + y))], -1)
    return np.round(127.5 + 120 * out).astype(np.uint8)


def encode_file(path: Path, lengths: list[int], size: int) -> list[float]:
    """Episodes back to back in one AV1 mp4; each episode's ``from_timestamp``."""
    os.environ.setdefault("SVT_LOG", "1")
    path.parent.mkdir(parents=True, exist_ok=True)
    starts, done = [], 0
    with av.open(str(path), "w") as out:
        stream = out.add_stream("libsvtav1", FPS, options=CODEC_OPTIONS)
        stream.pix_fmt, stream.height, stream.width = "yuv420p", size, size
        for n in lengths:
            starts.append(done / FPS)
            for t in range(n):
                image = av.VideoFrame.from_ndarray(frame(done + t, size), format="rgb24")
                out.mux(stream.encode(image))
            done += n
        out.mux(stream.encode())
    return starts


def write_dataset(root: Path, episodes: int, cfg: Config) -> Path:
    """A LeRobot v3.0 directory: one data file, one episode table, the camera's mp4s."""
    n, total = cfg.length, episodes * cfg.length
    per = cfg.episodes_per_file
    video = f"videos/{CAMERA}/chunk-000/file-{{:03d}}.mp4"
    starts = []
    for f in range(0, episodes, per):
        lengths = [n] * min(per, episodes - f)
        starts += encode_file(root / video.format(f // per), lengths, cfg.size)
    step = np.tile(np.arange(n), episodes)
    data = {
        "observation.state": pa.FixedSizeListArray.from_arrays(
            pa.array(np.zeros(total * 2, np.float32)), 2
        ),
        "action": pa.array(np.zeros(total, np.int64)),
        "timestamp": pa.array((step / FPS).astype(np.float32)),
        "frame_index": pa.array(step.astype(np.int64)),
        "episode_index": pa.array(np.repeat(np.arange(episodes), n).astype(np.int64)),
        "index": pa.array(np.arange(total, dtype=np.int64)),
        "task_index": pa.array(np.zeros(total, np.int64)),
    }
    (root / "data/chunk-000").mkdir(parents=True)
    pq.write_table(pa.table(data), root / "data/chunk-000/file-000.parquet")
    cam = f"videos/{CAMERA}"
    table = {
        "episode_index": list(range(episodes)),
        "tasks": [["look"]] * episodes,
        "length": [n] * episodes,
        "data/chunk_index": [0] * episodes,
        "data/file_index": [0] * episodes,
        "dataset_from_index": [e * n for e in range(episodes)],
        "dataset_to_index": [(e + 1) * n for e in range(episodes)],
        f"{cam}/chunk_index": [0] * episodes,
        f"{cam}/file_index": [e // per for e in range(episodes)],
        f"{cam}/from_timestamp": starts,
        f"{cam}/to_timestamp": [s + n / FPS for s in starts],
    }
    (root / "meta/episodes/chunk-000").mkdir(parents=True)
    pq.write_table(pa.table(table), root / "meta/episodes/chunk-000/file-000.parquet")
    tasks = pa.table({"task_index": [0], "__index_level_0__": ["look"]})
    pandas = {"index_columns": ["__index_level_0__"], "columns": []}
    pq.write_table(
        tasks.replace_schema_metadata({b"pandas": json.dumps(pandas).encode()}),
        root / "meta/tasks.parquet",
    )
    scalar = {"shape": [1], "names": None}
    features = {
        "observation.state": {"dtype": "float32", "shape": [2], "names": None},
        "action": {"dtype": "int64", **scalar},
        CAMERA: {
            "dtype": "video",
            "shape": [cfg.size, cfg.size, 3],
            "names": ["height", "width", "channels"],
        },
        "timestamp": {"dtype": "float32", **scalar},
        **{k: {"dtype": "int64", **scalar} for k in ("frame_index", "episode_index", "index")},
        "task_index": {"dtype": "int64", **scalar},
    }
    info = {
        "codebase_version": "v3.0",
        "fps": FPS,
        "total_episodes": episodes,
        "total_frames": total,
        "chunks_size": 1000,
        "data_path": "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet",
        "video_path": "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4",
        "features": features,
    }
    (root / "meta/info.json").write_text(json.dumps(info, indent=2))
    return root


# ------------------------------------------------------------------ throughput
def pyav_loop(files: list[Path]) -> int:
    """Frames decoded by PyAV directly, in the plain loop."""
    count = 0
    for path in files:
        with av.open(str(path)) as container:
            for f in container.decode(video=0):
                f.to_ndarray(format="rgb24")
                count += 1
    return count


def best_rate(fn, frames: int, repeats: int) -> tuple[float, list[float]]:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return frames / min(times), times


def throughput(root: Path, frames: int, cfg: Config) -> dict:
    files = sorted((root / "videos").rglob("*.mp4"))
    assert pyav_loop(files) == frames, "the files hold other frames than the dataset"
    pyav_rate, pyav_s = best_rate(lambda: pyav_loop(files), frames, cfg.repeats)
    reader_rate, reader_s = best_rate(lambda: load_lerobot(root), frames, cfg.repeats)
    skip = lambda: load_lerobot(root, videos="skip", key_map={CAMERA: None})  # noqa: E731
    _, skip_s = best_rate(skip, frames, cfg.repeats)
    return {
        "frames": frames,
        "pyav_fps": pyav_rate,
        "reader_fps": reader_rate,
        "ratio": reader_rate / pyav_rate,
        "parquet_only_s": min(skip_s),
        "pyav_s_all": pyav_s,
        "reader_s_all": reader_s,
    }


# ------------------------------------------------------------------ memory (child)
def status() -> dict[str, int]:
    """``VmHWM``, ``VmRSS``, ``RssAnon``, ``RssFile`` of this process, in kB."""
    fields = ("VmHWM", "VmRSS", "RssAnon", "RssFile")
    out = {}
    for line in Path("/proc/self/status").read_text().splitlines():
        name, _, value = line.partition(":")
        if name in fields:
            out[name] = int(value.split()[0])
    return out


def child(root: Path, decode_dir: Path | None) -> None:
    """Load in this fresh process, then read every frame once; print the memory (JSON)."""
    torch.set_num_threads(1)
    report = {"imported": status()}
    loaded = load_lerobot(root, decode_dir=decode_dir, videos="decode")
    pixels = loaded.rows["pixels", "cam"]
    report["loaded"] = status()
    total = 0
    for i in range(0, len(pixels), 1000):  # one pass, as an epoch of training reads them
        total += int(pixels[i : i + 1000].sum(dtype=torch.int64))
    report["read_once"] = status()
    report["type"] = type(pixels).__name__
    report["checksum"] = total
    print(json.dumps(report))


def train_child(root: Path, scratch: Path, steps: int, batch: int) -> None:
    """Load with ``decode_dir``, extend a disk buffer, fit a CNN by minibatch BC, in this
    fresh process; print the memory after each stage and the peak (JSON)."""
    torch.set_num_threads(1)
    report = {"imported": status()}
    loaded = load_lerobot(root, decode_dir=scratch / "frames", videos="decode")
    report["loaded"] = status()
    buffer = DemonstrationBuffer(path=scratch / "buffer")
    buffer.extend(loaded.rows)
    del loaded  # the rows now live in the buffer's files
    report["buffered"] = status()
    frame = tuple(buffer.data.get(PIXEL_KEY).shape[1:])
    learner = build(
        "for_env",
        TaskSpec.from_specs(None, Categorical(2), pixels=frame, pixel_key=PIXEL_KEY),
        pixel_key=PIXEL_KEY,
        seed=0,
    )
    t0 = time.perf_counter()
    result = fit_bc(learner, buffer, BCConfig(num_steps=steps, batch_size=batch, seed=0))
    report["train_s"] = time.perf_counter() - t0
    report["trained"] = status()
    report["rows"], report["final_loss"] = len(buffer), result.final_loss
    print(json.dumps(report))


def run_child(args: list[str], what: str) -> dict:
    """Run this script in a fresh process with ``args``; its last stdout line (JSON)."""
    proc = subprocess.run(
        [sys.executable, __file__, *args], capture_output=True, text=True, check=False
    )
    if proc.returncode != 0:
        raise RuntimeError(f"{what} child failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def memory(root: Path, scratch: Path) -> dict:
    out = {}
    for mode, extra in (("decode_dir", ["--decode-dir", str(scratch / "frames")]), ("ram", [])):
        out[mode] = run_child(["--child", str(root), *extra], f"memory ({mode})")
    assert out["ram"]["checksum"] == out["decode_dir"]["checksum"], "decode_dir changed frames"
    return out


# ------------------------------------------------------------------ report
def _tables(cfg: Config, speed: dict, mem: dict, train: dict) -> tuple[list, list, list]:
    """The rows of the three tables: decoders, memory per load mode, memory per stage."""
    mb = 1024
    rows = [
        ["PyAV loop (decode + to_ndarray rgb24)", f"{speed['pyav_fps']:,.0f} frames/s", "1.00"],
        [
            "load_lerobot (whole load)",
            f"{speed['reader_fps']:,.0f} frames/s",
            f"{speed['ratio']:.2f}",
        ],
    ]
    mem_rows = []
    for mode, label in (("ram", "decode_dir=None"), ("decode_dir", "decode_dir set")):
        m = mem[mode]
        mem_rows.append(
            [
                label,
                f"{m['loaded']['VmHWM'] / mb:,.0f} MB",
                f"{m['loaded']['RssAnon'] / mb:,.0f} MB",
                f"{m['loaded']['RssFile'] / mb:,.0f} MB",
                f"{m['read_once']['RssAnon'] / mb:,.0f} / {m['read_once']['RssFile'] / mb:,.0f} MB",
                f"{m['imported']['VmRSS'] / mb:,.0f} MB",
            ]
        )
    train_rows = [
        [
            stage,
            f"{train[key]['VmHWM'] / mb:,.0f} MB",
            f"{train[key]['RssAnon'] / mb:,.0f} MB",
            f"{train[key]['RssFile'] / mb:,.0f} MB",
        ]
        for stage, key in (
            ("imports", "imported"),
            ("load_lerobot(decode_dir=...)", "loaded"),
            ("DemonstrationBuffer(path=...).extend", "buffered"),
            (f"fit_bc, {cfg.train_steps} steps of {cfg.train_batch}", "trained"),
        )
    ]
    return rows, mem_rows, train_rows


def _markdown(
    cfg: Config, speed: dict, train: dict, rows: list, mem_rows: list, train_rows: list
) -> str:
    """The README section: the three tables and what each measured."""
    frames_mb = cfg.mem_frames * cfg.size * cfg.size * 3 / 1e6
    return (
        f"One {cfg.size}x{cfg.size} AV1 camera (lerobot's defaults), LeRobot v3.0, "
        f"{cfg.episodes_per_file} episodes per video file. Decode: {cfg.episodes} x "
        f"{cfg.length} frames, best of {cfg.repeats} (the load without decoding takes "
        f"{speed['parquet_only_s']:.2f} s). Target: load_lerobot >= 0.8x PyAV.\n\n"
        + _report.table(["decoder", "throughput", "x PyAV"], rows)
        + f"\n\nResident memory of a fresh process loading {cfg.mem_frames:,} frames "
        f"({frames_mb:,.0f} MB of pixels), after the load and after reading every frame once "
        "(anonymous / file-backed); file-backed pages are reclaimable page cache.\n\n"
        + _report.table(
            ["load", "peak RSS", "RssAnon", "RssFile", "after one pass", "imports alone"],
            mem_rows,
        )
        + f"\n\nTraining from the {cfg.mem_frames:,} frames in a fresh process: decoded into "
        "`decode_dir`, extended into a disk buffer, minibatch `fit_bc` of the Nature CNN "
        f"({train['train_s']:.0f} s for the fit); peak resident set so far and the memory "
        "after each stage. Target: under 2 GB resident.\n\n"
        + _report.table(["stage", "peak RSS", "RssAnon", "RssFile"], train_rows)
    )


def main(argv: list[str] | None = None) -> dict:
    p = _report.parser(__doc__)
    p.add_argument("--child", type=Path, default=None, help=argparse.SUPPRESS)
    p.add_argument("--decode-dir", type=Path, default=None, help=argparse.SUPPRESS)
    p.add_argument("--train-child", type=Path, nargs=2, default=None, help=argparse.SUPPRESS)
    p.add_argument("--train", type=int, nargs=2, default=(200, 64), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child is not None:
        child(args.child, args.decode_dir)
        return {}
    if args.train_child is not None:
        train_child(*args.train_child, *args.train)
        return {}
    out_dir = _report.destination(NAME, quick=args.quick, out=args.out)
    cfg = QUICK if args.quick else Config()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory(prefix=f"{NAME}-") as scratch:
        t0 = time.perf_counter()
        small = write_dataset(Path(scratch) / "small", cfg.episodes, cfg)
        big = write_dataset(Path(scratch) / "big", cfg.mem_frames // cfg.length, cfg)
        encode_s = time.perf_counter() - t0
        speed = throughput(small, cfg.episodes * cfg.length, cfg)
        mem = memory(big, Path(scratch))
        train_args = [str(big), str(Path(scratch) / "train"), str(cfg.train_steps)]
        train = run_child(
            ["--train-child", *train_args[:2], "--train", *train_args[2:], str(cfg.train_batch)],
            "training",
        )
    rows, mem_rows, train_rows = _tables(cfg, speed, mem, train)
    for r in rows + mem_rows + train_rows:
        print(" | ".join(r))
    md = _markdown(cfg, speed, train, rows, mem_rows, train_rows)
    payload = {
        "config": asdict(cfg),
        "encode_s": encode_s,
        "throughput": speed,
        "memory": mem,
        "training": train,
    }
    print("results:", _report.write(NAME, payload, md, out_dir=out_dir))
    return payload


if __name__ == "__main__":
    main()
