"""Every benchmark script runs end to end on a tiny budget (results to a temp dir)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.mark.parametrize(
    ("script", "result"),
    [
        ("tabular_env_throughput.py", "tabular_env_throughput.json"),
        ("bc_throughput.py", "bc_throughput.json"),
        ("frozenlake_timing.py", "frozenlake_timing.json"),
    ],
)
def test_benchmark_quick(script, result, tmp_path):
    proc = subprocess.run(
        [sys.executable, script, "--quick", "--out", str(tmp_path)],
        cwd=BENCH,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    data = json.loads((tmp_path / result).read_text())
    assert data["machine"]["torch"].startswith("2.13")
