"""Every benchmark script runs end to end on a tiny budget, and ``--quick`` never touches
the committed ``benchmarks/README.md`` or ``benchmarks/results/``."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
SCRIPTS = sorted(p.name for p in BENCH.glob("*.py") if not p.name.startswith("_"))
"""every runnable benchmark (helpers are ``_``-prefixed)"""


def committed() -> dict[str, bytes]:
    """``README.md`` and every file under ``results/``, byte for byte."""
    files = [BENCH / "README.md", *(p for p in (BENCH / "results").rglob("*") if p.is_file())]
    return {str(p.relative_to(BENCH)): p.read_bytes() for p in files}


def test_every_script_is_covered():
    assert {
        "bc_throughput.py",
        "bc_vs_dagger.py",
        "camera.py",
        "continuous_traps.py",
        "frozenlake_plain.py",
        "frozenlake_timing.py",
        "loss_functions.py",
        "tabular_env_throughput.py",
    } <= set(SCRIPTS)


# scripts whose --quick run another test already makes (each run is tens of seconds):
# frozenlake_timing --quick runs frozenlake_plain.py --no-exercises (what its --quick is),
# and test_loss_functions_benchmark runs loss_functions.py --quick and checks that
# --quick without --out never writes the committed results
RUN_ELSEWHERE = {"frozenlake_plain.py", "loss_functions.py"}


@pytest.mark.parametrize("script", [s for s in SCRIPTS if s not in RUN_ELSEWHERE])
def test_quick_leaves_the_committed_results_alone(script, tmp_path):
    before = committed()
    proc = subprocess.run(
        [sys.executable, script, "--quick"],
        cwd=BENCH,
        env={**os.environ, "TMPDIR": str(tmp_path)},  # where --quick writes
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    after = committed()
    assert after.keys() == before.keys(), f"{script} --quick added or removed committed files"
    changed = [name for name in before if before[name] != after[name]]
    assert not changed, f"{script} --quick rewrote {changed}"
    # what it measured went to a temporary directory instead
    stem = Path(script).stem
    (result,) = tmp_path.rglob(f"{stem}.json")
    data = json.loads(result.read_text())
    assert data["machine"]["torch"].startswith("2.13")
