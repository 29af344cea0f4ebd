"""save_lerobot(..., video=True): cameras written as LeRobot v3.0 video features.

Checked against what LeRobot's own v3.0 reader reads (lerobot 0.6, ``LeRobotDatasetMetadata``,
``DatasetReader._query_videos`` and ``decode_video_frames_pyav``): ``info.json``'s
``video_path`` and video features, the episode table's ``videos/<feature>/*`` columns,
the data files' ``timestamp``, and frames found by timestamp (``from_timestamp +
timestamp``) within LeRobot's tolerance after seeking to the previous keyframe.
"""

from __future__ import annotations

import inspect
import json
import sys
import warnings

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch
from tensordict import TensorDict

from imitrl import keys
from imitrl.datasets import load_lerobot, save_lerobot

av = pytest.importorskip("av")

FPS = 10
LENGTHS = [5, 1, 7, 4]
TOP, WRIST = "observation.images.top", "observation.images.wrist"
SIZES = {TOP: (32, 48), WRIST: (24, 24)}  # SVT-AV1 in PyAV's wheels takes frames this small
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
TOLERANCE_S = 1e-4  # LeRobotDataset's tolerance_s
MIN_PSNR_DB = 30.0  # measured per frame on these moving gradients: 32.3-37.3 dB (crf 30)
LOADS_VIDEOS = "videos" in inspect.signature(load_lerobot).parameters


def _frames(n: int, height: int, width: int, episode: int) -> torch.Tensor:
    """uint8 ``[n, H, W, 3]``: smooth colour gradients that move a little each frame."""
    y, x = torch.meshgrid(
        torch.arange(height, dtype=torch.float64),
        torch.arange(width, dtype=torch.float64),
        indexing="ij",
    )
    out = []
    for t in range(n):
        phase = 0.3 * t + 1.1 * episode
        out.append(
            torch.stack(
                [
                    128 + 100 * torch.sin(x / 9 + phase),
                    128 + 100 * torch.cos(y / 7 - phase),
                    128 + 80 * torch.sin((x + y) / 13 + 0.5 * phase),
                ],
                dim=-1,
            )
        )
    return torch.stack(out).round().to(torch.uint8)


def _rows(lengths=LENGTHS, cameras=((keys.PIXELS, "top"), (keys.PIXELS, "wrist"))) -> TensorDict:
    """Episodes with a state, an action, and cameras: ``("pixels", "top")`` 32x48 channels
    last and ``("pixels", "wrist")`` 24x24 channels first (``"pixels"`` alone: 32x48)."""
    episodes = []
    for e, n in enumerate(lengths):
        td = TensorDict(
            {
                keys.OBSERVATION: torch.randn(n, 3),
                keys.EXPERT_ACTION: torch.randn(n, 2),
                keys.EPISODE: torch.full((n,), e),
                keys.STEP: torch.arange(n),
            },
            batch_size=[n],
        )
        for cam in cameras:
            if cam == (keys.PIXELS, "wrist"):
                td.set(cam, _frames(n, *SIZES[WRIST], e).permute(0, 3, 1, 2).contiguous())
            else:
                td.set(cam, _frames(n, *SIZES[TOP], e))
        episodes.append(td)
    return torch.cat(episodes)


def _hwc(rows: TensorDict, key) -> np.ndarray:
    value = rows.get(key).numpy()
    return value if value.shape[-1] == 3 else value.transpose(0, 2, 3, 1)


def _episode_table(root) -> list[dict]:
    return pq.read_table(root / "meta/episodes/chunk-000/file-000.parquet").to_pylist()


def _decode(path) -> tuple[list[np.ndarray], list[float], list[bool], object]:
    """Every frame of a file as PyAV gives it: rgb24 arrays, pts in seconds, keyframe flags."""
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        frames, times, key = [], [], []
        for frame in container.decode(stream):
            frames.append(frame.to_ndarray(format="rgb24"))
            times.append(float(frame.pts * stream.time_base))
            key.append(frame.key_frame)
        meta = {
            "codec": stream.codec.canonical_name,
            "pix_fmt": stream.pix_fmt,
            "base_rate": stream.base_rate,
            "average_rate": stream.average_rate,
            "duration_s": float(stream.duration * stream.time_base),
            "audio": len(container.streams.audio),
        }
    return frames, times, key, meta


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float("inf") if mse == 0 else 10 * np.log10(255.0**2 / mse)


def _lerobot_pyav_query(path, timestamps: list[float]) -> np.ndarray:
    """The frames LeRobot's ``decode_video_frames_pyav`` returns for ``timestamps`` (seconds
    into the file): seek to the keyframe at or before the first, decode forward past the
    last, take the nearest frame, refuse one further than ``tolerance_s``. ``[K, H, W, 3]``."""
    first, last = min(timestamps), max(timestamps)
    loaded, loaded_ts = [], []
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        container.seek(
            round(first / stream.time_base) - 1, backward=True, any_frame=False, stream=stream
        )
        for frame in container.decode(stream):
            ts = float(frame.pts * stream.time_base)
            loaded.append(frame.to_ndarray(format="rgb24"))
            loaded_ts.append(ts)
            if ts >= last:
                break
    dist = np.abs(np.asarray(timestamps)[:, None] - np.asarray(loaded_ts)[None, :])
    assert dist.min(axis=1).max() <= TOLERANCE_S, (timestamps, loaded_ts)
    return np.stack([loaded[i] for i in dist.argmin(axis=1)])


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """Two cameras of different sizes, four episodes (one of a single frame), one file each."""
    rows = _rows()
    root = save_lerobot(rows, tmp_path_factory.mktemp("video") / "ds", fps=FPS, video=True)
    return rows, root


def test_files_and_info_are_lerobots(saved):
    _, root = saved
    info = json.loads((root / "meta/info.json").read_text())
    assert info["video_path"] == VIDEO_PATH
    assert info["video_files_size_in_mb"] == 200 and info["chunks_size"] == 1000
    for name, (height, width) in SIZES.items():
        ft = info["features"][name]
        assert ft["dtype"] == "video" and ft["shape"] == [height, width, 3]
        assert ft["names"] == ["height", "width", "channels"]
        assert ft["info"] == {
            "video.height": height,
            "video.width": width,
            "video.codec": "av1",
            "video.pix_fmt": "yuv420p",
            "video.is_depth_map": False,
            "video.fps": FPS,
            "video.channels": 3,
            "has_audio": False,
            "video.g": 2,
            "video.crf": 30,
            "video.preset": 12,
            "video.fast_decode": 0,
            "video.video_backend": "pyav",
            "video.extra_options": {},
            "is_depth_map": False,
        }
    assert sorted(p.relative_to(root).as_posix() for p in root.rglob("*.mp4")) == sorted(
        VIDEO_PATH.format(video_key=name, chunk_index=0, file_index=0) for name in SIZES
    )
    assert not [p for p in root.rglob("*") if "imitrl-video" in p.as_posix()]  # staging gone
    # cameras live in videos/ only: no column in the data files nor in their HF schema
    data = pq.read_table(root / "data/chunk-000/file-000.parquet")
    assert TOP not in data.column_names and WRIST not in data.column_names
    assert TOP not in data.schema.metadata[b"huggingface"].decode()
    sidecar = json.loads((root / "meta/imitrl.json").read_text())
    assert sidecar["columns"][TOP] == {"key": ["pixels", "top"], "shape": [32, 48, 3]}
    assert sidecar["columns"][WRIST] == {"key": ["pixels", "wrist"], "shape": [24, 24, 3]}
    for name in SIZES:  # every video is covered by the checksums
        assert VIDEO_PATH.format(video_key=name, chunk_index=0, file_index=0) in sidecar["files"]


def test_episode_table_locates_each_episode(saved):
    _, root = saved
    table = _episode_table(root)
    for name in SIZES:
        cols = [f"videos/{name}/{c}" for c in ("chunk_index", "file_index")]
        cols += [f"videos/{name}/{c}" for c in ("from_timestamp", "to_timestamp")]
        ends = np.cumsum(LENGTHS) / FPS
        for ep, end, n in zip(table, ends, LENGTHS):
            assert [ep[c] for c in cols[:2]] == [0, 0]
            assert ep[cols[2]] == pytest.approx(end - n / FPS, abs=1e-12)
            assert ep[cols[3]] == pytest.approx(end, abs=1e-12)
    # LeRobot's order: data location, frame range, then each camera, then stats
    names = list(table[0])
    assert names.index("dataset_to_index") < names.index(f"videos/{TOP}/chunk_index")
    assert names.index(f"videos/{WRIST}/to_timestamp") < names.index(f"stats/{TOP}/min")


def test_decoded_frames_sit_at_their_timestamps_close_to_the_source(saved):
    rows, root = saved
    table = _episode_table(root)
    for key, name in (((keys.PIXELS, "top"), TOP), ((keys.PIXELS, "wrist"), WRIST)):
        source = _hwc(rows, key)
        frames, times, keyframe, meta = _decode(
            root / VIDEO_PATH.format(video_key=name, chunk_index=0, file_index=0)
        )
        assert meta["codec"] == "av1" and meta["pix_fmt"] == "yuv420p" and meta["audio"] == 0
        assert meta["base_rate"] == FPS and meta["average_rate"] == FPS  # torchcodec's index
        assert len(frames) == sum(LENGTHS)
        assert meta["duration_s"] == pytest.approx(table[-1][f"videos/{name}/to_timestamp"])
        assert all(f.shape == (*SIZES[name], 3) for f in frames)
        np.testing.assert_allclose(times, np.arange(sum(LENGTHS)) / FPS, atol=1e-9)
        # each episode encoded alone (it starts on a keyframe), with LeRobot's g=2
        offsets = np.concatenate([np.arange(n) for n in LENGTHS])
        assert keyframe == [bool(i % 2 == 0) for i in offsets]
        psnr = [_psnr(f, s) for f, s in zip(frames, source)]
        assert min(psnr) > MIN_PSNR_DB, psnr


def test_lerobots_pyav_query_by_timestamp_finds_each_frame(saved):
    """Each row's frame as LeRobot's reader finds it: the episode's file and
    ``from_timestamp + timestamp`` (the data file's), within ``tolerance_s``."""
    rows, root = saved
    table = _episode_table(root)
    data = pq.read_table(root / "data/chunk-000/file-000.parquet").to_pydict()
    timestamps = np.asarray(data["timestamp"], dtype=np.float64)
    for key, name in (((keys.PIXELS, "top"), TOP), ((keys.PIXELS, "wrist"), WRIST)):
        path = root / VIDEO_PATH.format(video_key=name, chunk_index=0, file_index=0)
        whole, _, _, _ = _decode(path)
        for ep in table:
            lo, hi = ep["dataset_from_index"], ep["dataset_to_index"]
            query = (ep[f"videos/{name}/from_timestamp"] + timestamps[lo:hi]).tolist()
            got = _lerobot_pyav_query(path, query)
            np.testing.assert_array_equal(got, np.stack(whole[lo:hi]))  # the very frames
            assert min(_psnr(g, s) for g, s in zip(got, _hwc(rows, key)[lo:hi])) > MIN_PSNR_DB


def test_video_stats_are_the_image_stats_lerobot_writes(saved, tmp_path):
    """LeRobot computes a video feature's statistics as an image feature's: the same
    numbers as the same rows saved as PNG images."""
    rows, root = saved
    as_images = save_lerobot(rows, tmp_path / "images", fps=FPS)
    video_stats = json.loads((root / "meta/stats.json").read_text())
    image_stats = json.loads((as_images / "meta/stats.json").read_text())
    for name in SIZES:
        assert video_stats[name] == image_stats[name]
        assert np.asarray(video_stats[name]["mean"]).shape == (3, 1, 1)
    video_eps, image_eps = _episode_table(root), _episode_table(as_images)
    for v, i in zip(video_eps, image_eps):
        for name in SIZES:
            assert v[f"stats/{name}/mean"] == i[f"stats/{name}/mean"]


def test_dataset_stats_aggregate_the_episodes_as_lerobot():
    """``meta/stats.json`` from per-episode statistics (lerobot's ``aggregate_feature_stats``):
    min, max, mean, std and count as over all values; quantiles count-weighted."""
    from imitrl.datasets.lerobot._stats import aggregate_stats, feature_stats, image_stats

    rng = np.random.default_rng(0)
    blocks = [rng.normal(size=(n, 2)) * (1 + i) for i, n in enumerate([5, 1, 9])]
    total = aggregate_stats([feature_stats(b) for b in blocks])
    direct = feature_stats(np.concatenate(blocks))
    for stat in ("min", "max", "mean", "std", "count"):
        np.testing.assert_allclose(total[stat], direct[stat], rtol=1e-12)
    q10 = sum(len(b) * np.quantile(b, 0.1, axis=0) for b in blocks) / 15
    np.testing.assert_allclose(total["q10"], q10, rtol=1e-12)
    frames = [rng.integers(0, 256, (n, 3, 4, 5), dtype=np.uint8) for n in (2, 3)]
    total = aggregate_stats([image_stats(f) for f in frames])
    direct = image_stats(np.concatenate(frames))
    assert total["mean"].shape == (3, 1, 1) and total["count"].tolist() == [5]
    np.testing.assert_allclose(total["std"], direct["std"], rtol=1e-12)


def test_files_roll_over_by_size_then_chunk(tmp_path):
    """Past ``video_files_size_in_mb`` the next episode starts the next file, and past
    ``chunks_size`` files the next chunk (lerobot's ``update_chunk_file_indices``)."""
    rows = _rows(cameras=((keys.PIXELS, "top"),))
    root = save_lerobot(
        rows, tmp_path / "ds", fps=FPS, video=True, chunks_size=3, video_files_size_in_mb=1e-4
    )
    table = _episode_table(root)
    places = [(ep[f"videos/{TOP}/chunk_index"], ep[f"videos/{TOP}/file_index"]) for ep in table]
    assert places == [(0, 0), (0, 1), (0, 2), (1, 0)]
    for ep, n, (chunk, file) in zip(table, LENGTHS, places):
        assert ep[f"videos/{TOP}/from_timestamp"] == 0.0
        assert ep[f"videos/{TOP}/to_timestamp"] == pytest.approx(n / FPS)
        path = root / VIDEO_PATH.format(video_key=TOP, chunk_index=chunk, file_index=file)
        frames, _, _, _ = _decode(path)
        assert len(frames) == n
    assert len(list(root.rglob("*.mp4"))) == len(LENGTHS)


def test_one_camera_under_pixels_is_observation_image(tmp_path):
    rows = _rows(lengths=[3, 2], cameras=(keys.PIXELS,))
    root = save_lerobot(rows, tmp_path / "ds", fps=FPS, video=True)
    info = json.loads((root / "meta/info.json").read_text())
    assert info["features"]["observation.image"]["dtype"] == "video"
    frames, _, _, _ = _decode(
        root / VIDEO_PATH.format(video_key="observation.image", chunk_index=0, file_index=0)
    )
    assert len(frames) == 5


@pytest.mark.parametrize("damage", ["flip", "truncate"])
def test_a_changed_video_is_refused_on_load(saved, tmp_path, damage):
    rows, _ = saved
    root = save_lerobot(rows, tmp_path / "ds", fps=FPS, video=True)
    path = root / VIDEO_PATH.format(video_key=WRIST, chunk_index=0, file_index=0)
    data = bytearray(path.read_bytes())
    if damage == "flip":
        data[len(data) // 2] ^= 0xFF
    else:
        del data[-100:]
    path.write_bytes(bytes(data))
    kwargs = {"videos": "skip"} if LOADS_VIDEOS else {}  # refused before any decoding
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the video features skipped, before decoding lands
        with pytest.raises(ValueError, match=r"file-000\.mp4: changed since save_lerobot"):
            load_lerobot(root, **kwargs)


def test_missing_pyav_gives_the_install_command(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "av", None)  # `import av` raises ImportError
    with pytest.raises(ImportError, match=r"pip install 'imitrl\[datasets\]'"):
        save_lerobot(_rows(lengths=[2]), tmp_path / "ds", fps=FPS, video=True)
    assert not (tmp_path / "ds").exists()


def test_video_refuses_what_it_cannot_encode(tmp_path):
    rows = _rows(lengths=[2], cameras=())
    with pytest.raises(ValueError, match="no key is a camera"):
        save_lerobot(rows, tmp_path / "a", fps=FPS, video=True)
    rows.set(keys.PIXELS, torch.rand(2, 8, 8, 3))
    with pytest.raises(ValueError, match=r"'pixels' .*uint8 \[N, H, W, 3\].*got torch.float32"):
        save_lerobot(rows, tmp_path / "b", fps=FPS, video=True)
    rows.set(keys.PIXELS, torch.zeros(2, 3, 8, 3, dtype=torch.uint8))  # SVT-AV1: >= 4x4
    with pytest.raises(ValueError, match=r"'observation.image': frames of 3x8 .* at least 4x4"):
        save_lerobot(rows, tmp_path / "b", fps=FPS, video=True)
    rows.set(keys.PIXELS, torch.zeros(2, 8, 8, 3, dtype=torch.uint8))
    with pytest.raises(ValueError, match="video_files_size_in_mb must be > 0"):
        save_lerobot(rows, tmp_path / "c", fps=FPS, video=True, video_files_size_in_mb=0)
    assert not any(tmp_path.iterdir())


@pytest.mark.skipif(not LOADS_VIDEOS, reason="load_lerobot does not decode videos yet")
def test_load_then_resave_keeps_every_camera(saved, tmp_path):
    """The reader gives back PyAV's own decode of each file; re-saving with video=True
    writes the cameras back (AV1 again: within the PSNR bound of what was loaded)."""
    rows, root = saved
    loaded = load_lerobot(root)
    for key, name in (((keys.PIXELS, "top"), TOP), ((keys.PIXELS, "wrist"), WRIST)):
        whole, _, _, _ = _decode(
            root / VIDEO_PATH.format(video_key=name, chunk_index=0, file_index=0)
        )
        np.testing.assert_array_equal(loaded.rows.get(key).numpy(), np.stack(whole))
    again = save_lerobot(loaded.rows, tmp_path / "again", fps=FPS, video=True)
    reloaded = load_lerobot(again)
    for key in ((keys.PIXELS, "top"), (keys.PIXELS, "wrist")):
        first, second = loaded.rows.get(key).numpy(), reloaded.rows.get(key).numpy()
        assert first.shape == second.shape
        assert min(_psnr(a, b) for a, b in zip(first, second)) > MIN_PSNR_DB
    torch.testing.assert_close(reloaded.rows.get(keys.OBSERVATION), rows.get(keys.OBSERVATION))
