"""LeRobot camera videos (v2.1 and v3.0 layouts, AV1 and H.264) decoded by ``load_lerobot``.

The videos are encoded here with PyAV as lerobot encodes them (``_lerobot_videos``). AV1
at crf 30 is lossy, so loaded frames are compared exactly with PyAV's own decode of the
same files (frame ``t`` of an episode is the file's frame at ``from_timestamp + t / fps``),
and with the source frames within a PSNR: on these smooth synthetic frames the worst frame
measured 34.0 dB with AV1 (crf 30) and 29.2 dB with H.264 (crf 30) when this test was
written; the bounds are 32 and 28 dB.
"""

from __future__ import annotations

import json
import re
import sys
import warnings

import numpy as np
import pytest
import torch
from tensordict import MemoryMappedTensor

from imitrl import keys
from imitrl.datasets import load_lerobot
from tests._lerobot_files import FPS, episodes_data, write_v21, write_v30
from tests._lerobot_videos import (
    add_cameras_v21,
    add_cameras_v30,
    decode_all,
    drop_feature,
    encode,
    psnr,
    smooth_frames,
)

LENGTHS = [4, 3, 5]
SIZES = {"observation.images.top": (32, 48), "observation.images.wrist": (24, 24)}
KEYS = {
    "observation.images.top": (keys.PIXELS, "top"),
    "observation.images.wrist": (keys.PIXELS, "wrist"),
}
MIN_PSNR_DB = {"libsvtav1": 32.0, "libx264": 28.0}


def _cameras(lengths=LENGTHS, sizes=SIZES) -> dict[str, list[np.ndarray]]:
    return {
        name: [smooth_frames(n, h, w, seed=10 * c + e) for e, n in enumerate(lengths)]
        for c, (name, (h, w)) in enumerate(sizes.items())
    }


def _v30(tmp_path, lengths=LENGTHS, sizes=SIZES, codec="libsvtav1"):
    """Data files and video files split differently: episodes 0 and 1 share a video file,
    episode 2 is alone in chunk 1."""
    episodes = episodes_data(lengths)
    root = write_v30(tmp_path / "ds", episodes, files=[(0, 0), (0, 0), (0, 1)])
    cameras = _cameras(lengths, sizes)
    spans = add_cameras_v30(root, cameras, files=[(0, 0), (0, 0), (1, 0)], codec=codec)
    return root, episodes, cameras, spans


def _quiet_load(*args, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return load_lerobot(*args, **kwargs)


def _direct_v30(spans: list[dict], lengths=LENGTHS) -> np.ndarray:
    """PyAV's own decode: episode e is frames ``from_timestamp * fps ..`` of its file."""
    out = []
    for span, n in zip(spans, lengths):
        first = round(span["from_timestamp"] * FPS)
        out.append(decode_all(span["file"])[first : first + n])
    return np.concatenate(out)


def _check_pixels(rows, cameras, direct: dict[str, np.ndarray], codec: str) -> None:
    for name, key in KEYS.items():
        got = rows[key]
        h, w = SIZES[name]
        assert got.dtype == torch.uint8 and got.shape == (sum(LENGTHS), h, w, 3)
        assert np.array_equal(got.numpy(), direct[name])  # frame-exact
        source = np.concatenate(cameras[name])
        worst = min(psnr(got[i].numpy(), source[i]) for i in range(len(source)))
        assert worst >= MIN_PSNR_DB[codec], (name, worst)


# ------------------------------------------------------------------ layouts
def test_v30_two_cameras_several_episodes_per_file(tmp_path):
    root, episodes, cameras, spans = _v30(tmp_path)
    top = spans["observation.images.top"]
    assert top[0]["file"] == top[1]["file"] and top[1]["from_timestamp"] == 4 / FPS
    loaded = _quiet_load(root)
    direct = {name: _direct_v30(spans[name]) for name in SIZES}
    _check_pixels(loaded.rows, cameras, direct, "libsvtav1")
    state = np.concatenate([ep["observation.state"] for ep in episodes])
    assert torch.equal(loaded.rows[keys.OBSERVATION], torch.from_numpy(state))
    assert loaded.loaded["observation.images.top"] == "pixels.top"
    # a frame off by one would not match: consecutive frames differ everywhere
    assert not np.array_equal(
        direct["observation.images.top"][1], direct["observation.images.top"][0]
    )


@pytest.mark.parametrize("codec", ["libsvtav1", "libx264"])
def test_v21_one_file_per_episode_over_chunks(tmp_path, codec):
    episodes = episodes_data(LENGTHS)
    root = write_v21(tmp_path / "ds", episodes, chunks_size=2)
    cameras = _cameras()
    files = add_cameras_v21(root, cameras, chunks_size=2, codec=codec)
    assert files["observation.images.top"][2].parent.parent.name == "chunk-001"
    loaded = _quiet_load(root)
    direct = {name: np.concatenate([decode_all(f) for f in files[name]]) for name in SIZES}
    _check_pixels(loaded.rows, cameras, direct, codec)


def test_v30_h264(tmp_path):
    root, _, cameras, spans = _v30(tmp_path, codec="libx264")
    loaded = _quiet_load(root)
    _check_pixels(loaded.rows, cameras, {n: _direct_v30(spans[n]) for n in SIZES}, "libx264")


# ------------------------------------------------------------------ keys
def test_single_camera_is_pixels_and_key_map_overrides(tmp_path):
    root, _, _, spans = _v30(tmp_path)
    loaded = _quiet_load(
        root, key_map={"observation.images.top": keys.PIXELS, "observation.images.wrist": None}
    )
    assert loaded.rows[keys.PIXELS].shape == (sum(LENGTHS), 32, 48, 3)
    assert np.array_equal(
        loaded.rows[keys.PIXELS].numpy(), _direct_v30(spans["observation.images.top"])
    )
    assert "observation.images.wrist" in loaded.skipped  # the caller's choice: no warning
    assert ("pixels", "wrist") not in loaded.rows.keys(include_nested=True)


def test_observation_image_loads_as_pixels_in_a_camera_only_dataset(tmp_path):
    root, _, _, spans = _v30(tmp_path, sizes={"observation.image": (24, 24)})
    drop_feature(root, "observation.state")
    loaded = _quiet_load(root)
    assert keys.OBSERVATION not in loaded.rows.keys()
    assert np.array_equal(loaded.rows[keys.PIXELS].numpy(), _direct_v30(spans["observation.image"]))
    assert loaded.rows[keys.EXPERT_ACTION].shape == (sum(LENGTHS),)


def test_videos_skip_warns_and_drops(tmp_path):
    root, *_ = _v30(tmp_path)
    with pytest.warns(UserWarning, match=r"observation\.images\.top.*videos='skip'"):
        loaded = load_lerobot(root, videos="skip")
    assert keys.PIXELS not in loaded.rows.keys()
    assert set(SIZES) <= set(loaded.skipped)
    with pytest.raises(ValueError, match="videos must be 'decode' or 'skip'"):
        load_lerobot(root, videos="lazy")


def test_decode_dir_gives_memory_mapped_frames(tmp_path):
    root, *_ = _v30(tmp_path)
    plain = _quiet_load(root)
    mapped = _quiet_load(root, decode_dir=tmp_path / "frames")
    for name, key in KEYS.items():
        value = mapped.rows[key]
        assert isinstance(value, MemoryMappedTensor)
        file = tmp_path / "frames" / f"{name}.uint8"
        assert file.stat().st_size == value.numel()
        assert torch.equal(value, plain.rows[key])


# ------------------------------------------------------------------ bad input
def _edit_info(root, edit) -> None:
    path = root / "meta/info.json"
    info = json.loads(path.read_text())
    edit(info["features"]["observation.images.top"])
    path.write_text(json.dumps(info))


def _truncate(path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def test_missing_truncated_or_corrupt_video_files_are_refused_by_name(tmp_path):
    root, _, _, spans = _v30(tmp_path)
    shared = spans["observation.images.top"][0]["file"]  # episodes 0 and 1
    alone = spans["observation.images.wrist"][2]["file"]
    _truncate(alone)
    with pytest.raises(ValueError, match=re.escape(str(alone))):
        load_lerobot(root)
    alone.write_bytes(b"\x00" * 4096)
    with pytest.raises(ValueError, match=re.escape(str(alone)) + ".*not a readable video"):
        load_lerobot(root)
    shared.unlink()
    with pytest.raises(ValueError, match=re.escape(str(shared)) + r": file not found.*\[0, 1\]"):
        load_lerobot(root)


def test_video_of_another_size_than_declared_is_refused(tmp_path):
    root, _, _, spans = _v30(tmp_path)
    file = spans["observation.images.top"][0]["file"]

    def taller(ft):
        ft["shape"] = [48, 48, 3]
        ft["info"]["video.height"] = 48

    _edit_info(root, taller)
    with pytest.raises(ValueError, match=re.escape(str(file)) + ": frames are 32x48.*48x48"):
        load_lerobot(root)

    def inconsistent(ft):
        ft["shape"] = [32, 48, 3]  # info.json contradicts itself

    _edit_info(root, inconsistent)
    with pytest.raises(ValueError, match=r"info\.json.*video\.height 48"):
        load_lerobot(root)


def test_video_shorter_than_its_episodes_is_refused(tmp_path):
    root, _, cameras, spans = _v30(tmp_path)
    alone = spans["observation.images.top"][2]["file"]  # episode 2, 5 frames
    encode(alone, cameras["observation.images.top"][2][:3])
    message = (
        re.escape(str(alone)) + r": episode 2 .* needs a frame at 0\.06 s.*last frame is at 0\.04"
    )
    with pytest.raises(ValueError, match=message):
        load_lerobot(root)
    with pytest.raises(ValueError, match=message):
        load_lerobot(root, decode_dir=tmp_path / "frames")
    assert list((tmp_path / "frames").iterdir()) == []  # nothing left half-decoded


def test_episode_table_without_camera_columns_is_refused(tmp_path):
    root, *_ = _v30(tmp_path)
    import pyarrow.parquet as pq

    for path in (root / "meta/episodes").glob("*/*.parquet"):
        table = pq.read_table(path)
        pq.write_table(table.drop_columns(["videos/observation.images.top/from_timestamp"]), path)
    with pytest.raises(ValueError, match=r"meta/episodes: episode 0 lacks.*from_timestamp"):
        load_lerobot(root)


def test_missing_pyav_gives_the_install_command(tmp_path, monkeypatch):
    root, *_ = _v30(tmp_path, lengths=[2, 2, 2])
    monkeypatch.setitem(sys.modules, "av", None)  # import av raises ImportError
    with pytest.raises(ImportError, match=re.escape("pip install 'imitrl[datasets]'")):
        load_lerobot(root)
    with pytest.warns(UserWarning, match="videos='skip'"):
        load_lerobot(root, videos="skip")  # no PyAV needed


def test_env_without_a_camera_refuses_pixel_rows(tmp_path):
    from torchrl.envs import GymEnv

    root, *_ = _v30(tmp_path, lengths=[2, 2, 2])
    env = GymEnv("CartPole-v1", categorical_action_encoding=True)
    with pytest.raises(ValueError, match=r"info\.json: the dataset has 'pixels'.*no 'pixels'"):
        load_lerobot(root, env=env)
    drop = dict.fromkeys(SIZES)  # the cameras left out: the state alone fits the env
    loaded = _quiet_load(root, env=env, key_map=drop)
    assert keys.PIXELS not in loaded.rows.keys() and loaded.rows[keys.OBSERVATION].shape == (6, 4)
