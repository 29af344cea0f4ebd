"""benchmarks/_report.py: what a committed report may record of a path (never one
machine's absolute path)."""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

import _report  # noqa: E402


def test_a_path_in_the_checkout_is_relative_to_it():
    assert (
        _report.portable(ROOT / "benchmarks" / "results" / "x.json") == "benchmarks/results/x.json"
    )


def test_a_path_outside_keeps_its_last_parts_and_never_the_root():
    assert _report.portable("/tmp/peer_gail") == "tmp/peer_gail"
    assert _report.portable("/opt/venvs/imitrl_venv/bin/python") == "imitrl_venv/bin/python"
    args = _report.portable_args(["--out", "/tmp/peer_gail", "--seeds", "3"])
    assert args == ["--out", "tmp/peer_gail", "--seeds", "3"]
    assert not any(a.startswith("/") for a in args)
