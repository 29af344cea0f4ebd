"""fs.contained: a link swapped for a file while it is resolved is refused with the
"changed while" line a loader reports, never an OSError out of realpath (a race that
flipped a data file between a link and a file hit it: EINVAL from readlink)."""

from __future__ import annotations

import errno
import os

import pytest

from imitrl.fs import contained


def test_a_link_turned_into_a_file_as_it_is_resolved_is_refused(tmp_path, monkeypatch):
    (tmp_path / "data.bin").write_bytes(b"x")
    os.symlink(tmp_path / "data.bin", tmp_path / "link.bin")

    real = os.path.realpath

    def swapped(path, *args, **kwargs):
        if str(path).endswith("link.bin"):  # readlink on what is now a file
            raise OSError(errno.EINVAL, "Invalid argument", str(path))
        return real(path, *args, **kwargs)

    monkeypatch.setattr(contained.os.path, "realpath", swapped)
    with pytest.raises(ValueError, match="changed while it was checked"):
        contained.links_stay_inside(tmp_path)


def test_a_link_removed_as_it_is_resolved_is_passed_over(tmp_path, monkeypatch):
    (tmp_path / "data.bin").write_bytes(b"x")
    os.symlink(tmp_path / "data.bin", tmp_path / "link.bin")
    real = os.path.realpath

    def gone(path, *args, **kwargs):
        if str(path).endswith("link.bin"):
            raise FileNotFoundError(errno.ENOENT, "No such file", str(path))
        return real(path, *args, **kwargs)

    monkeypatch.setattr(contained.os.path, "realpath", gone)
    contained.links_stay_inside(tmp_path)  # nothing of it is read later
