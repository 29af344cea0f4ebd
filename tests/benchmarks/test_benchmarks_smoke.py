"""Every benchmark script runs end to end on a tiny budget, and ``--quick`` never touches
the committed ``benchmarks/README.md`` or ``benchmarks/results/``."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "benchmarks"
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


# frozenlake_timing --quick runs frozenlake_plain.py --no-exercises (what its --quick is)
RUN_ELSEWHERE = {"frozenlake_plain.py"}
QUICK = [s for s in SCRIPTS if s not in RUN_ELSEWHERE]
PARALLEL = 4
"""scripts run at once: each --quick is mostly imports, process start-up and waiting (Ray,
video encoding), so four share the 2 cores well"""


@pytest.fixture(scope="module")
def quick_runs(tmp_path_factory) -> tuple[dict, dict, dict, dict]:
    """Every script's ``--quick`` run, ``PARALLEL`` at a time, each with its own TMPDIR;
    the committed files before and after all of them."""
    before = committed()
    dirs = {s: tmp_path_factory.mktemp(Path(s).stem) for s in QUICK}

    def run(script: str) -> subprocess.CompletedProcess:
        return subprocess.run(
            [sys.executable, script, "--quick"],
            cwd=BENCH,
            env={**os.environ, "TMPDIR": str(dirs[script])},  # where --quick writes
            capture_output=True,
            text=True,
            timeout=900,
        )

    with ThreadPoolExecutor(PARALLEL) as pool:
        procs = dict(zip(QUICK, pool.map(run, QUICK)))
    return procs, dirs, before, committed()


def test_quick_never_touches_the_committed_results(quick_runs):
    _, _, before, after = quick_runs
    assert after.keys() == before.keys(), "a --quick run added or removed committed files"
    changed = [name for name in before if before[name] != after[name]]
    assert not changed, f"a --quick run rewrote {changed}"


@pytest.mark.parametrize("script", QUICK)
def test_quick_runs_and_writes_to_a_temporary_directory(script, quick_runs):
    procs, dirs, _, _ = quick_runs
    proc = procs[script]
    assert proc.returncode == 0, proc.stderr[-3000:]
    # what it measured went to its temporary directory
    stem = Path(script).stem
    (result,) = dirs[script].rglob(f"{stem}.json")
    data = json.loads(result.read_text())
    assert data["machine"]["torch"].startswith("2.13")


# what two of the --quick runs measured (the smoke run's own output, not a second run)
def _quick_json(quick_runs, script: str) -> dict:
    procs, dirs, _, _ = quick_runs
    assert procs[script].returncode == 0, procs[script].stderr[-3000:]
    (result,) = dirs[script].rglob(f"{Path(script).stem}.json")
    return json.loads(result.read_text())


def test_bc_vs_dagger_quick_records_every_task_and_round(quick_runs):
    saved = _quick_json(quick_runs, "bc_vs_dagger.py")
    (figure,) = quick_runs[1]["bc_vs_dagger.py"].rglob("bc_vs_dagger.png")
    assert figure.stat().st_size > 0
    sys.path.insert(0, str(BENCH))
    try:
        import bc_vs_dagger
    finally:
        sys.path.remove(str(BENCH))
    assert set(saved["tasks"]) == {t.env_id for t in bc_vs_dagger.TASKS}
    for per in saved["tasks"].values():
        (record,) = per["seeds"]
        assert len(record["dagger_scores"]) == 2 and record["bc_matched_rows"] == record["rows"][-1]


def test_continuous_traps_quick_covers_every_trap(quick_runs):
    saved = _quick_json(quick_runs, "continuous_traps.py")
    assert {"float64", "vector_final_obs", "frame_skip", "bang_bang", "startup"} <= set(saved)


def test_bc_vs_dagger_takes_the_flag_its_nan_advice_names():
    """Issue 44: the explanation of a nan score told the user to give a larger
    --max-episode-steps, which bc_vs_dagger.py refused as an unknown flag."""
    source = (BENCH / "bc_vs_dagger.py").read_text()
    assert "give a larger --max-episode-steps" in source
    shown = subprocess.run(
        [sys.executable, "bc_vs_dagger.py", "--help"], cwd=BENCH, capture_output=True, text=True
    )
    assert shown.returncode == 0 and "--max-episode-steps" in shown.stdout
    refused = subprocess.run(
        [sys.executable, "bc_vs_dagger.py", "--max-episode-steps", "0", "--quick"],
        cwd=BENCH, capture_output=True, text=True,
    )  # fmt: skip
    assert refused.returncode != 0 and "--max-episode-steps must be >= 1" in refused.stderr
