"""A feature loaded under its own name never takes one of imitrl's keys, and no two
features land on one key (a hostile review: an image feature renamed ``observation``
replaced the state silently, one renamed ``expert_action`` replaced the labels)."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import pyarrow.parquet as pq
import pytest
import torch

from imitrl import keys
from imitrl.datasets import load_lerobot
from tests._lerobot_files import episodes_data, write_v30

IMAGE = (8, 8)


def _dataset(root: Path, image_name: str) -> Path:
    """A v3.0 dataset whose camera image feature is called ``image_name``."""
    write_v30(root, episodes_data([3, 2], image=IMAGE), files=[(0, 0), (0, 0)], image=IMAGE)
    info = json.loads((root / "meta/info.json").read_text())
    info["features"][image_name] = info["features"].pop("observation.images.cam")
    (root / "meta/info.json").write_text(json.dumps(info))
    for f in (root / "data").rglob("*.parquet"):
        t = pq.read_table(f)
        names = [image_name if c == "observation.images.cam" else c for c in t.column_names]
        pq.write_table(t.rename_columns(names), f)
    return root


def _load(root: Path, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_lerobot(root, images="load", **kwargs)


@pytest.mark.parametrize(
    "name", [keys.OBSERVATION, keys.EXPERT_ACTION, keys.EPISODE, keys.ROUND, keys.STEP]
)
def test_an_image_named_like_one_of_imitrls_keys_is_refused(tmp_path, name):
    root = _dataset(tmp_path / "ds", name)
    with pytest.raises(ValueError, match=rf"feature '{name}' would be loaded under its own name"):
        _load(root)
    rows = _load(root, key_map={name: (keys.PIXELS, name)}).rows  # the way the message gives
    assert rows.get((keys.PIXELS, name)).shape == (5, *IMAGE, 3)
    assert rows.get(keys.OBSERVATION).shape == (5, 4)  # the state, not the image
    assert rows.get(keys.EPISODE).tolist() == [0, 0, 0, 1, 1]
    skipped = _load(root, key_map={name: None}).rows
    assert (keys.PIXELS, name) not in skipped.keys(include_nested=True)


def test_an_image_under_another_name_loads_beside_the_state(tmp_path):
    loaded = _load(_dataset(tmp_path / "ds", "cam_image"))
    assert loaded.loaded["cam_image"] == "cam_image"
    assert loaded.rows.get("cam_image").dtype == torch.uint8
    assert loaded.rows.get(keys.OBSERVATION).shape == (5, 4)


def test_two_features_on_one_key_are_refused_with_the_images_planned(tmp_path):
    root = _dataset(tmp_path / "ds", "cam_image")
    with pytest.raises(
        ValueError, match=r"features \[.cam_image., .next\.reward.\] all map to the buffer key"
    ):
        _load(root, key_map={"next.reward": "cam_image"})
