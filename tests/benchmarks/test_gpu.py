"""``benchmarks/gpu.py --quick`` runs on the CPU (a CUDA machine runs the full benchmark;
CI has none): pixel BC against a plain torch loop, the chunked fits, a DAgger round."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[2] / "benchmarks"


def test_gpu_benchmark_runs_on_the_cpu(tmp_path):
    done = subprocess.run(
        [
            sys.executable,
            str(BENCH / "gpu.py"),
            "--device",
            "cpu",
            "--quick",
            "--out",
            str(tmp_path),
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    results = json.loads(next(tmp_path.rglob("gpu.json")).read_text())
    assert results["device"] == "cpu"
    assert (
        results["pixel"]["plain_samples_per_s"] > 0 and results["pixel"]["imitrl_samples_per_s"] > 0
    )
    assert set(results["chunks"]) == {"flow_chunk", "diffusion_chunk", "act"}
    assert results["dagger"]["seconds"] > 0
