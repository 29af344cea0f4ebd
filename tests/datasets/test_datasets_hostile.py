"""Hostile datasets and checkpoints stay inside their folder (issue 26, security items).

Every fixture is built by the test: a dataset whose metadata names a path out of its
folder (a camera name with ``/..``, a path template with ``..`` or an absolute path, an
image or checksum entry, a symbolic link), a table declaring ten million episodes over
120 frames, a checkpoint naming a module to import. Beside each dataset lie decoys
outside it (another dataset's parquet files, a video, an empty folder), watched with
inotify: a test fails if anything there was opened, read, created or written, by any
code (pyarrow, PyAV and h5py read files from C).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch

from imitrl.datasets import load_lerobot, load_minari
from tests import _child, _watch
from tests._lerobot_files import episodes_data, write_v21, write_v30
from tests._lerobot_videos import add_cameras_v21, add_cameras_v30, encode

pytestmark = pytest.mark.skipif(not _watch.available(), reason="needs Linux inotify")


def _load(*args, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_lerobot(*args, **kwargs)


@pytest.fixture
def outside(tmp_path) -> Path:
    """Decoys outside every dataset: a LeRobot v2.1 dataset of other values, a video."""
    decoys = tmp_path / "outside"
    write_v21(decoys / "other", episodes_data([5, 6], seed=9))
    encode(decoys / "cam.mp4", np.zeros((11, 16, 16, 3), np.uint8), codec="libx264")
    (decoys / "empty").mkdir()
    return decoys


def _refused_untouched(outside: Path, match: str, load) -> None:
    """``load()`` raises ValueError matching ``match`` and touches nothing in ``outside``."""
    before = sorted(str(p) for p in outside.rglob("*"))
    with _watch.Watch(outside) as watch:
        with pytest.raises(ValueError, match=match):
            load()
        events = watch.events()
    assert events == [], events
    assert sorted(str(p) for p in outside.rglob("*")) == before


def _edit_info(root: Path, **changes) -> None:
    info = json.loads((root / "meta/info.json").read_text())
    info.update(changes)
    (root / "meta/info.json").write_text(json.dumps(info))


# ------------------------------------------------- item 1: where frames are decoded
def test_a_camera_name_cannot_choose_where_decoded_frames_are_written(tmp_path, outside):
    root = write_v21(tmp_path / "ds", episodes_data([5, 6]))
    frames = [np.zeros((5, 16, 16, 3), np.uint8), np.zeros((6, 16, 16, 3), np.uint8)]
    add_cameras_v21(root, {"observation.images.cam": frames}, chunks_size=1000, codec="libx264")
    info = json.loads((root / "meta/info.json").read_text())
    hostile = "observation.images.cam" + "/.." * 16 + str(outside / "empty" / "pwn")
    info["features"][hostile] = info["features"].pop("observation.images.cam")
    info["video_path"] = info["video_path"].replace("{video_key}", "observation.images.cam")
    (root / "meta/info.json").write_text(json.dumps(info))
    decode_dir = tmp_path / "decoded"
    _refused_untouched(
        outside,
        r"feature name .*pwn' is not a LeRobot feature name",
        lambda: load_lerobot(root, decode_dir=decode_dir),
    )
    assert not decode_dir.exists() or list(decode_dir.iterdir()) == []


# ---------------------------------------------- item 2: what path templates may name
def _v21(tmp_path):
    return write_v21(tmp_path / "ds", episodes_data([5, 6]))


def _v30_with_camera(tmp_path):
    root = write_v30(tmp_path / "ds", episodes_data([5, 6]), files=[(0, 0), (0, 0)])
    frames = [np.zeros((5, 16, 16, 3), np.uint8), np.zeros((6, 16, 16, 3), np.uint8)]
    add_cameras_v30(
        root, {"observation.images.cam": frames}, files=[(0, 0), (0, 0)], codec="libx264"
    )
    return root


V21_DATA = "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet"
TEMPLATES = {
    "v2.1 data_path, absolute": (_v21, "data_path", "{outside}/other/" + V21_DATA),
    "v2.1 data_path, ..": (_v21, "data_path", "../outside/other/" + V21_DATA),
    "v2.1 data_path, ../ inside a part": (
        _v21,
        "data_path",
        "data/../../outside/other/" + V21_DATA,
    ),
    "v3.0 video_path, ..": (_v30_with_camera, "video_path", "../outside/cam.mp4"),
    "v3.0 video_path, absolute": (_v30_with_camera, "video_path", "{outside}/cam.mp4"),
}


@pytest.mark.parametrize("case", list(TEMPLATES))
def test_a_path_template_cannot_name_a_file_outside_the_dataset(tmp_path, outside, case):
    make, field, template = TEMPLATES[case]
    root = make(tmp_path)
    _edit_info(root, **{field: template.replace("{outside}", str(outside))})
    _refused_untouched(outside, "outside the dataset folder", lambda: _load(root))
    if field == "data_path":  # streaming into a buffer reads the same names
        from imitrl.data import DemonstrationBuffer

        buffer = DemonstrationBuffer()
        _refused_untouched(outside, "outside the dataset folder", lambda: _load(root, into=buffer))
        assert len(buffer) == 0


def test_an_image_path_cannot_name_a_file_outside_the_dataset(tmp_path, outside):
    root = write_v30(
        tmp_path / "ds", episodes_data([2], image=(4, 4)), files=[(0, 0)], image=(4, 4)
    )
    from PIL import Image

    Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(outside / "empty" / "frame.png")
    path = root / "data/chunk-000/file-000.parquet"
    table = pq.read_table(path)
    kind = table.schema.field("observation.images.cam").type
    stolen = {"bytes": None, "path": str(outside / "empty" / "frame.png")}
    column = pa.array([stolen] * table.num_rows, kind)
    index = table.schema.get_field_index("observation.images.cam")
    pq.write_table(table.set_column(index, "observation.images.cam", column), path)
    _refused_untouched(outside, "outside the dataset folder", lambda: _load(root, images="load"))


def test_a_checksum_list_cannot_make_the_loader_hash_a_file_outside(tmp_path, outside):
    from imitrl.datasets import save_lerobot
    from imitrl.datasets.lerobot._checks import sidecar_digest

    rows = _load(_v21(tmp_path)).rows.exclude("task_index")
    root = save_lerobot(rows, tmp_path / "saved", fps=50)
    sidecar = json.loads((root / "meta/imitrl.json").read_text())
    sidecar["files"]["../outside/other/meta/info.json"] = {"size": 1, "sha256": "0" * 64}
    sidecar["digest"] = sidecar_digest(sidecar)
    (root / "meta/imitrl.json").write_text(json.dumps(sidecar))
    _refused_untouched(outside, "outside the dataset folder", lambda: _load(root))


# ------------------------------------------------------------- symbolic links
def test_a_symbolic_link_out_of_the_dataset_is_refused(tmp_path, outside):
    root = _v21(tmp_path)
    mine = root / V21_DATA.format(episode_chunk=0, episode_index=1)
    mine.unlink()
    mine.symlink_to(outside / "other" / V21_DATA.format(episode_chunk=0, episode_index=1))
    _refused_untouched(outside, "symbolic link out of the dataset folder", lambda: _load(root))


def test_a_minari_dataset_linking_out_is_refused(tmp_path, outside):
    data = tmp_path / "minari" / "data"
    data.mkdir(parents=True)
    (data / "main_data.hdf5").symlink_to(outside / "other" / "meta" / "info.json")
    _refused_untouched(
        outside, "symbolic link out of the dataset folder", lambda: load_minari(data)
    )


def test_an_hdf5_external_link_is_refused(tmp_path, outside):
    h5py = pytest.importorskip("h5py")
    from tests.datasets.minari.test_minari import _episode, _write  # Minari 0.5's layout

    data = _write(tmp_path / "minari", [_episode(3, 0), _episode(4, 1)]) / "data"
    with h5py.File(outside / "empty" / "stolen.hdf5", "w") as f:
        f["actions"] = np.zeros(4, np.int64)
    with h5py.File(data / "main_data.hdf5", "a") as f:
        del f["episode_1/actions"]
        f["episode_1/actions"] = h5py.ExternalLink(
            str(outside / "empty" / "stolen.hdf5"), "actions"
        )
    _refused_untouched(outside, "HDF5 ExternalLink", lambda: load_minari(data))


def _hub_cache(root: Path, cache: Path, repo_id: str) -> Path:
    """``root`` laid out as huggingface_hub caches a dataset: every file a blob named by
    its SHA-256 under ``blobs/``, the snapshot a tree of relative symbolic links to them."""
    import hashlib

    repo = cache / ("datasets--" + repo_id.replace("/", "--"))
    commit = "0123456789abcdef0123456789abcdef01234567"
    snapshot = repo / "snapshots" / commit
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        blob = repo / "blobs" / hashlib.sha256(path.read_bytes()).hexdigest()
        blob.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(path, blob)
        link = snapshot / path.relative_to(root)
        link.parent.mkdir(parents=True, exist_ok=True)
        link.symlink_to(os.path.relpath(blob, link.parent))
    (repo / "refs").mkdir()
    (repo / "refs" / "main").write_text(commit)
    return snapshot


def test_a_hub_snapshot_of_symbolic_links_into_its_blobs_loads(tmp_path):
    root = _v30_with_camera(tmp_path)
    snapshot = _hub_cache(root, tmp_path / "hub", "someone/cams")
    assert all(p.is_symlink() for p in snapshot.rglob("*") if not p.is_dir())
    plain = _load(root).rows
    for loaded in (
        _load(snapshot).rows,
        _load("someone/cams", cache_dir=tmp_path / "hub").rows,
    ):
        assert set(loaded.keys(True, True)) == set(plain.keys(True, True))
        assert all(torch.equal(loaded.get(k), plain.get(k)) for k in plain.keys(True, True))


# ------------------------------------------- item 3: declared sizes beyond the data
_COUNT_SCRIPT = r"""
import resource, sys
resource.setrlimit(resource.RLIMIT_DATA, (3 << 30, 3 << 30))
sys.path[:0] = sys.argv[2:]
from imitrl.datasets import load_lerobot
try:
    load_lerobot(sys.argv[1])
except ValueError as err:
    print("ValueError:", err)
"""


def _declare_episodes(root: Path, count: int, v3: bool) -> None:
    if v3:
        lengths = np.zeros(count, np.int64)
        lengths[:2] = 60
        table = pa.table(
            {
                "episode_index": np.arange(count),
                "length": lengths,
                "data/chunk_index": np.zeros(count, np.int64),
                "data/file_index": np.zeros(count, np.int64),
            }
        )
        pq.write_table(table, root / "meta/episodes/chunk-000/file-000.parquet")
    else:
        with open(root / "meta/episodes.jsonl", "w") as f:
            for e in range(count):
                f.write(f'{{"episode_index": {e}, "tasks": [], "length": {60 if e < 2 else 0}}}\n')
    _edit_info(root, total_episodes=count)


@pytest.mark.parametrize(("version", "count"), [("v3.0", 10_000_000), ("v2.1", 1_000_000)])
def test_an_episode_table_declaring_more_episodes_than_frames_is_refused_at_once(
    tmp_path, version, count
):
    v3 = version == "v3.0"
    episodes = episodes_data([60, 60])
    if v3:
        root = write_v30(tmp_path / "ds", episodes, files=[(0, 0), (0, 0)])
    else:
        root = write_v21(tmp_path / "ds", episodes)
    _declare_episodes(root, count, v3)
    src = next(p for p in sys.path if (Path(p) / "imitrl").is_dir())
    done = _child.run(
        [sys.executable, "-c", textwrap.dedent(_COUNT_SCRIPT), str(root), src],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-2000:]  # a MemoryError under 3 GiB fails here
    held = "120 frames" if v3 else "2 episode files"
    assert f"lists {count} episodes, the data holds {held}" in done.stdout, done.stdout


def test_an_episode_of_no_frames_is_refused(tmp_path):
    root = write_v30(tmp_path / "ds", episodes_data([3, 2]), files=[(0, 0), (0, 0)])
    table = pq.read_table(root / "meta/episodes/chunk-000/file-000.parquet")
    extra = {name: [table.column(name)[0].as_py()] for name in table.column_names}
    extra.update(episode_index=[2], length=[0])
    both = pa.concat_tables([table, pa.Table.from_pydict(extra, table.schema)])
    pq.write_table(both, root / "meta/episodes/chunk-000/file-000.parquet")
    _edit_info(root, total_episodes=3)
    with pytest.raises(ValueError, match="episode 2 has length 0"):
        _load(root)


def test_a_declared_frame_size_is_checked_before_memory_is_taken(tmp_path):
    root = _v30_with_camera(tmp_path)
    info = json.loads((root / "meta/info.json").read_text())
    feature = info["features"]["observation.images.cam"]
    feature["shape"] = [200_000, 200_000, 3]  # 120 GB a frame, were it allocated
    feature["info"]["video.height"] = feature["info"]["video.width"] = 200_000
    (root / "meta/info.json").write_text(json.dumps(info))
    with pytest.raises(ValueError, match=r"frames are 16x16 .* declares .* as 200000x200000"):
        _load(root)


# ------------------------------------------- item 4: a checkpoint names no code to run
def _hostile_checkpoint(folder: Path, env: str, hidden=(8,)) -> Path:
    folder.mkdir()
    config = {"env": env, "loss": "default", "hidden": list(hidden), "lr": 1e-3, "seed": 0,
              "max_episode_steps": 10}  # fmt: skip
    (folder / "config.json").write_text(json.dumps({"command": "bc", "config": config}))
    torch.save({}, folder / "learner.pt")
    marker = folder.parent / "imported"
    (folder / "evilmod.py").write_text(
        f"open({str(marker)!r}, 'w').write('ran')\n"
        "import gymnasium\n"
        "gymnasium.register('Evil-v0', entry_point='gymnasium.envs.classic_control:CartPoleEnv',"
        " max_episode_steps=10)\n"
    )
    return folder


def test_eval_never_imports_a_module_a_checkpoint_names(tmp_path):
    ckpt = _hostile_checkpoint(tmp_path / "downloaded", "evilmod:Evil-v0")
    done = subprocess.run(  # python -m puts the working directory first on sys.path
        [sys.executable, "-m", "imitrl", "eval", "--checkpoint", ".", "--eval-episodes", "1"],
        cwd=ckpt,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert not (tmp_path / "imported").exists(), "the checkpoint's module ran"
    assert done.returncode == 2, done.stderr[-2000:]
    assert "imitrl never imports code a checkpoint names" in done.stderr
    assert "--env evilmod:Evil-v0" in done.stderr  # how to name it, if it is trusted


def test_a_checkpoint_config_cannot_ask_for_any_network_size(tmp_path):
    from imitrl.jobs import EvalJob, run_eval

    ckpt = _hostile_checkpoint(tmp_path / "downloaded", "CartPole-v1", hidden=(1 << 40,))
    with pytest.raises(ValueError, match=r"hidden must be a list of layer widths in \[1, 65536\]"):
        run_eval(EvalJob(checkpoint=ckpt, eval_episodes=1))
