"""``benchmarks/threads.py``'s busy block, which its ``--quick`` smoke run leaves out: the
spinner holds its core for the block and is gone after it; a run of only some blocks
reports only those."""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

import threads  # noqa: E402


def _cpu_seconds(pid: int) -> float:
    """User + system seconds of process ``pid`` so far (Linux ``/proc``)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def test_the_quiet_block_starts_nothing():
    with threads.busy_core(False) as spinner:
        assert spinner is None


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc")
def test_the_busy_block_spins_pinned_to_one_core_and_stops_after_it():
    with threads.busy_core(True) as spinner:
        assert spinner.poll() is None
        if hasattr(os, "sched_getaffinity"):
            assert os.sched_getaffinity(spinner.pid) == {min(os.sched_getaffinity(0))}
        before = _cpu_seconds(spinner.pid)
        time.sleep(0.5)
        assert _cpu_seconds(spinner.pid) - before > 0.2  # it spins, not sleeps
    assert spinner.returncode is not None  # killed and waited for


def test_a_run_of_some_blocks_reports_those_only():
    cfg = threads.Config(steps=2, repeats=1, conditions=("busy",))
    rows = [
        {"condition": "busy", "threads": t, "load_1min": 0.5, "seconds": {
            f"{n}/{loop}": 0.1 * t for n in threads.NETWORKS for loop in threads.LOOPS}}
        for t in cfg.threads
    ]  # fmt: skip
    summ = threads.summary(cfg, rows)
    assert set(summ["load_1min"]) == {"busy/1", "busy/2"}
    md = threads.markdown(cfg, summ, wall=1.0)
    header = md.split("\n\n")[1].splitlines()[0]
    assert "busy, 1 thread" in header and "quiet" not in header
    assert "2 threads / 1 thread ranged from 2.00x to 2.0x" in md
    assert threads.QUICK.conditions == ("quiet",) and threads.Config().conditions == (
        "quiet",
        "busy",
    )
