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


def test_render_safely_rehearses_before_it_writes(tmp_path):
    """A hostile review: a render that failed part-way had already replaced the committed
    figure. The rehearsal fails first, in a scratch folder; the target is never written."""
    import pytest

    target = tmp_path / "committed"
    target.mkdir()
    calls = []

    def render(out):
        calls.append(out)
        (out / "figure.png").write_bytes(b"new")
        raise KeyError("rows")

    def error(message):
        raise SystemExit(message)

    with pytest.raises(
        SystemExit, match=r"x\.json: not a results file this report reads \(KeyError"
    ):
        _report.render_safely(render, target, error, "x.json")
    assert calls and calls[0] != target and not (target / "figure.png").exists()
    assert _report.render_safely(lambda out: f"to {out}", target, error, "x.json") == f"to {target}"


def test_read_results_refuses_what_no_script_wrote(tmp_path):
    import pytest

    def error(message):
        raise SystemExit(message)

    cases = {"a.json": ("{", "JSONDecodeError"), "b.json": ('{"x": Infinity}', "Infinity is not"),
             "c.json": ("null", "a JSON NoneType")}  # fmt: skip
    for name, (text, said) in cases.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(SystemExit, match=said):
            _report.read_results(tmp_path / name, error)
    with pytest.raises(SystemExit, match="IsADirectoryError"):
        _report.read_results(tmp_path, error)
    (tmp_path / "d.json").write_text('{"rows": [1.5]}')
    assert _report.read_results(tmp_path / "d.json", error) == {"rows": [1.5]}


def test_check_least_refuses_counts_below_their_least_and_nan(capsys):
    import argparse

    import pytest

    p = argparse.ArgumentParser(prog="x")
    for given, said in (({"seeds": 0}, "--seeds must be >= 1, got 0"),
                        ({"timeout": float("nan")}, "--timeout must be >= 1, got nan"),
                        ({"reps": 1}, "--reps must be >= 2, got 1")):  # fmt: skip
        with pytest.raises(SystemExit):
            _report.check_least(p, argparse.Namespace(**given), seeds=1, timeout=1, reps=2)
        assert said in capsys.readouterr().err
    _report.check_least(p, argparse.Namespace(seeds=1, timeout=None), seeds=1, timeout=1)
