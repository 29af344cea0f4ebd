"""The README's quick tabular example runs and prints what it promises."""

from __future__ import annotations

from ._readme import assert_prints_what_it_promises, run


def test_pieces_example(tmp_path):
    ns, printed = run("pieces-example", tmp_path)
    assert_prints_what_it_promises("pieces-example", printed)
    assert len(ns["buffer"]) > len(ns["buffer"].data[ns["buffer"].data["round"] == 0])
