"""imitrl bench's arguments: where a run writes, and --threads after NAME."""

from __future__ import annotations

from pathlib import Path

import pytest

from imitrl.cli import _bench_threads
from imitrl.jobs.bench import script_args
from tests._cli import run_main


def test_a_run_writes_where_it_says_or_under_results_bench():
    cwd = Path("/c")
    assert script_args("x", ("--quick",), cwd) == (["--quick"], None)
    assert script_args("x", ("--out=/o",), cwd) == (["--out=/o"], None)
    assert script_args("x", ("--seeds", "2"), cwd) == (
        ["--seeds", "2", "--out", str(cwd / "results" / "bench" / "x")],
        cwd / "results" / "bench" / "x",
    )


@pytest.mark.parametrize("word", ["--o", "--ou", "--q", "--qui", "--ou=/mine"])
def test_an_abbreviated_out_or_quick_is_refused(word):
    """The script's argparse reads ``--ou X`` as ``--out X``; the command did not, added
    its own ``--out`` after it, and that one won: the run went to results/bench. (Where
    ``--o`` is ambiguous the script's argparse refuses it anyway.)"""
    with pytest.raises(ValueError, match=r"spell --(out|quick) in full"):
        script_args("x", (word, "/mine") if "=" not in word else (word,), Path("/c"))


def test_threads_after_the_name_are_benchs_own():
    """``imitrl bench NAME --threads 2`` handed ``--threads`` to the script, which refused it."""
    assert _bench_threads(["--quick", "--threads", "2"], 1) == (["--quick"], 2)
    assert _bench_threads(["--threads=3", "--seeds", "1"], 1) == (["--seeds", "1"], 3)
    assert _bench_threads(["--quick"], 4) == (["--quick"], 4)
    with pytest.raises(ValueError, match="--threads must be"):
        _bench_threads(["--threads", "two"], 1)


def test_a_bad_thread_count_after_the_name_is_one_line_before_any_script_runs():
    status, _, err = run_main("bench", "chunk_latency", "--quick", "--threads", "0")
    assert status == 2 and "--threads must be" in err and "Traceback" not in err, err
