"""The tutorials' examples run and print what they promise (the FrozenLake pieces in
docs/tutorials/frozenlake.md, cameras in docs/tutorials/cameras.md)."""

from __future__ import annotations

from ._readme import assert_prints_what_it_promises, run


def test_pieces_example(tmp_path):
    ns, printed = run("pieces-example", tmp_path)
    assert_prints_what_it_promises("pieces-example", printed)
    assert len(ns["buffer"]) > len(ns["buffer"].data[ns["buffer"].data["round"] == 0])


def test_camera_example(tmp_path):
    """Record pixels to a LeRobot video dataset, load it, BC, privileged-expert DAgger."""
    ns, printed = run("camera-example", tmp_path)
    assert_prints_what_it_promises("camera-example", printed)
    videos = list((tmp_path / "hilltop_demos" / "videos").rglob("*.mp4"))
    assert [v.parent.parent.name for v in videos] == ["observation.image"]  # one camera, one file
    assert set(ns["buffer"].rounds()) == {0, 1, 2}  # the demos and two relabelled rounds
