"""Every benchmark script runs end to end on a tiny budget, and ``--quick`` never touches
the committed ``benchmarks/README.md`` or ``benchmarks/results/``."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

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
LONGEST = (
    "seam.py",
    "scale_train.py",
    "threads.py",
    "peer_imitation.py",
    "peer_gail.py",
    "camera_decode.py",
    "scale_ray.py",
    "frozenlake_timing.py",
    "scale_datasets.py",
)
"""started first (each --quick alone took 14-24 s of wall on a quiet machine, the rest
4-13 s): the last to finish are short ones"""
QUICK = sorted(
    (s for s in SCRIPTS if s not in RUN_ELSEWHERE),
    key=lambda s: (LONGEST.index(s) if s in LONGEST else len(LONGEST), s),
)
PARALLEL = 4
"""scripts run at once: each --quick is mostly process start-up and waiting (Ray, video
encoding, its own child processes), so four share the 2 cores well"""


@pytest.fixture(scope="module")
def quick_runs(tmp_path_factory) -> tuple[dict, dict, dict, dict]:
    """Every script's ``--quick`` run, ``PARALLEL`` at a time, each with its own TMPDIR
    (each a fork of one process that imported torch, TorchRL and imitrl once:
    ``_preloaded.py``); the committed files before and after all of them."""
    before = committed()
    dirs = {s: tmp_path_factory.mktemp(Path(s).stem) for s in QUICK}
    logs = {s: tmp_path_factory.mktemp(f"{Path(s).stem}-log") for s in QUICK}
    jobs = tmp_path_factory.mktemp("jobs") / "jobs.json"
    jobs.write_text(json.dumps([[s, str(dirs[s]), str(logs[s])] for s in QUICK]))
    subprocess.run(
        [sys.executable, str(Path(__file__).with_name("_preloaded.py")), str(PARALLEL), str(jobs)],
        check=True,
        timeout=1800,
    )
    procs = {
        s: SimpleNamespace(
            returncode=int((logs[s] / "status").read_text()),
            stdout=(logs[s] / "stdout").read_text(),
            stderr=(logs[s] / "stderr").read_text(),
        )
        for s in QUICK
    }
    return procs, dirs, before, committed()


def test_a_preloaded_run_is_the_scripts_own_process(tmp_path):
    """``_preloaded.py`` reports what the script's own process would: its exit status,
    what it printed (its exit handlers' too), a failure's traceback; it sees its TMPDIR."""
    script = tmp_path / "probe.py"  # a path: run as given, in the benchmarks folder
    log, tmp = tmp_path / "log", tmp_path / "tmp"
    log.mkdir()
    tmp.mkdir()
    script.write_text(
        "import atexit, sys, tempfile\n"
        "atexit.register(lambda: print('at exit'))\n"
        "print(sys.argv[1:], tempfile.gettempdir(), __name__, sys.path[0])\n"
        "raise SystemExit(3) if len(sys.argv) > 1 else None\n"
    )
    jobs = tmp_path / "jobs.json"
    jobs.write_text(
        json.dumps([[str(script), str(tmp), str(log)], ["missing.py", str(tmp), str(tmp)]])
    )
    here = Path(__file__).with_name("_preloaded.py")
    subprocess.run([sys.executable, str(here), "2", str(jobs)], check=True, timeout=300)
    assert (log / "status").read_text() == "3"
    said = (log / "stdout").read_text()
    assert said == f"['--quick'] {tmp} __main__ {tmp_path}\nat exit\n"
    assert (tmp / "status").read_text() == "1"  # a script that fails: its traceback
    assert (
        "Traceback" in (tmp / "stderr").read_text() and "missing.py" in (tmp / "stderr").read_text()
    )


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


def test_bc_vs_dagger_takes_the_flag_its_nan_advice_names(capsys):
    """Issue 44: the explanation of a nan score told the user to give a larger
    --max-episode-steps, which bc_vs_dagger.py refused as an unknown flag."""
    source = (BENCH / "bc_vs_dagger.py").read_text()
    assert "give a larger --max-episode-steps" in source
    sys.path.insert(0, str(BENCH))
    try:
        import bc_vs_dagger
    finally:
        sys.path.remove(str(BENCH))
    with pytest.raises(SystemExit) as shown:
        bc_vs_dagger.main(["--help"])
    assert shown.value.code == 0 and "--max-episode-steps" in capsys.readouterr().out
    with pytest.raises(SystemExit) as refused:
        bc_vs_dagger.main(["--max-episode-steps", "0", "--quick"])
    said = f"{capsys.readouterr().err} {refused.value.code}"  # printed, or the exit's message
    assert refused.value.code not in (0, None) and "--max-episode-steps must be >= 1" in said


def test_gpu_benchmark_runs_on_the_machines_device(quick_runs):
    """``gpu.py --quick`` (``--device auto``): pixel BC against a plain torch loop, the
    chunked fits, a DAgger round, on the CPU of a machine without CUDA (CI's)."""
    import torch

    results = _quick_json(quick_runs, "gpu.py")
    assert results["device"] == ("cuda" if torch.cuda.is_available() else "cpu")
    pixel = results["pixel"]
    assert pixel["plain_samples_per_s"] > 0 and pixel["imitrl_samples_per_s"] > 0
    assert set(results["chunks"]) == {"flow_chunk", "diffusion_chunk", "act"}
    assert results["dagger"]["seconds"] > 0
