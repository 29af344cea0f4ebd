"""A hub cache's ``refs/<ref>`` names a snapshot folder, never a path (a second hostile
review: ``refs/main`` holding ``../../../../base`` made ``load_lerobot("org/name")`` load
a folder outside the cache)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from imitrl.datasets import resolve_lerobot_root

COMMIT = "0123456789abcdef0123456789abcdef01234567"


def _cache(tmp_path: Path, ref_text: str | None) -> tuple[Path, Path]:
    """A hub cache holding org/name at COMMIT, its refs/main saying ``ref_text``, and a
    dataset-looking folder outside the cache."""
    cache = tmp_path / "hub"
    repo = cache / "datasets--org--name"
    (repo / "snapshots" / COMMIT / "meta").mkdir(parents=True)
    (repo / "snapshots" / COMMIT / "meta" / "info.json").write_text("{}")
    (repo / "refs").mkdir()
    if ref_text is not None:
        (repo / "refs" / "main").write_text(ref_text)
    outside = tmp_path / "base"
    (outside / "meta").mkdir(parents=True)
    (outside / "meta" / "info.json").write_text("{}")
    return cache, outside


@pytest.mark.parametrize(
    "ref_text",
    ["../../../../base", "../../../base", "/abs/base", "..", "a/b", "x" * 200, "v3.0\n\nmore"],
)
def test_a_ref_that_is_not_a_snapshots_name_is_refused(tmp_path, ref_text):
    cache, _ = _cache(tmp_path, ref_text)
    with pytest.raises(ValueError, match=r"refs/main: revision .* is not a snapshot's name"):
        resolve_lerobot_root("org/name", cache_dir=cache)


def test_a_revision_asked_for_is_held_to_the_same_rule(tmp_path):
    cache, _ = _cache(tmp_path, COMMIT)
    with pytest.raises(ValueError, match=r"revision '../../../base' is not a snapshot's name"):
        resolve_lerobot_root("org/name", revision="../../../base", cache_dir=cache)


def test_a_ref_naming_a_commit_resolves_inside_the_cache(tmp_path):
    cache, _ = _cache(tmp_path, COMMIT + "\n")
    found = resolve_lerobot_root("org/name", cache_dir=cache)
    assert found == cache / "datasets--org--name" / "snapshots" / COMMIT


def test_a_ref_that_is_not_a_regular_file_is_not_read(tmp_path):
    cache, _ = _cache(tmp_path, None)
    os.mkfifo(cache / "datasets--org--name" / "refs" / "main")  # reading it would block
    # not read: "main" is taken as the snapshot's own name, which does not exist; the
    # newest snapshot holding a dataset is found instead
    found = resolve_lerobot_root("org/name", cache_dir=cache)
    assert found == cache / "datasets--org--name" / "snapshots" / COMMIT
