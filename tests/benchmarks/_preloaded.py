"""Run benchmark scripts as ``python SCRIPT --quick`` would, each a fork of this one
process, which imported what every script imports (torch, TorchRL, tensordict,
matplotlib, imitrl) once: the smoke run's ~4 s of imports a script, 32 scripts, paid once.

    python _preloaded.py PARALLEL JOBS.json

``JOBS.json``: ``[[script, tmp, log], ...]``. Each script runs in the benchmarks folder
with ``TMPDIR=tmp`` (where its ``--quick`` writes) and ``sys.argv = [script,
"--quick"]``, as ``__main__`` (:func:`runpy.run_path`), its exit handlers run at its end
(:data:`OWN_PROCESS`: a fresh interpreter instead);
``log/stdout``, ``log/stderr`` and ``log/status`` get what the process would print and
its exit status, ``log/cost.json`` its wall and CPU seconds (its own and its children's
that it waited for). ``PARALLEL`` forks at a time. This process starts no thread
before it forks (none of the imports does), so each fork starts as a fresh interpreter
would, with the modules already loaded. What a fork cannot catch: a script reaching a
submodule the preload imported without importing it itself (``imitrl.jobs.bc`` as an
attribute of ``imitrl``), which a fresh interpreter would refuse.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import tempfile
import time
from pathlib import Path

BENCH = Path(__file__).resolve().parents[2] / "benchmarks"
TESTS = Path(__file__).resolve().parents[1]
sys.path.insert(1, str(TESTS))  # for _child (taken off the scripts' sys.path)
from _child import run_program  # noqa: E402  # as python runs a script, to its exit

TIMEOUT = 900
"""seconds a script may run before it is killed (its status then -9)"""
OWN_PROCESS = {"scale_ray.py"}
"""run as a fresh interpreter of their own (the fork execs ``python SCRIPT --quick``): a
Ray driver forked from this process waited on its first actor for minutes"""


def preload() -> None:
    """What the scripts import at their top (each still imports it again: a no-op)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot
    import tensordict  # noqa: F401
    import torch  # noqa: F401
    import torchrl  # noqa: F401

    import imitrl.algorithms
    import imitrl.envs
    import imitrl.jobs.bc
    import imitrl.learners  # noqa: F401


def child(script: str, tmp: Path, log: Path) -> int:
    """Run ``script --quick`` in this (forked) process; its exit status."""
    out = os.open(log / "stdout", os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    err = os.open(log / "stderr", os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    os.dup2(out, 1)
    os.dup2(err, 2)
    os.environ["TMPDIR"] = str(tmp)
    tempfile.tempdir = None  # gettempdir() reads TMPDIR again
    os.chdir(BENCH)
    if Path(script).name in OWN_PROCESS:
        os.execv(sys.executable, [sys.executable, script, "--quick"])
    status = run_program([script, "--quick"], [p for p in sys.path[1:] if p != str(TESTS)])
    sys.stdout.flush()
    sys.stderr.flush()
    return status


def main(parallel: int, jobs: list[tuple[str, str, str]]) -> None:
    preload()
    running: dict[int, tuple[Path, float]] = {}
    queue = [(script, Path(tmp), Path(log)) for script, tmp, log in jobs]
    while queue or running:
        while queue and len(running) < parallel:
            script, tmp, log = queue.pop(0)
            pid = os.fork()
            if pid == 0:
                os._exit(child(script, tmp, log))
            running[pid] = (log, time.monotonic())
        pid, wait_status, usage = os.wait4(-1, os.WNOHANG)
        if pid == 0:  # none ended: stop one past its time, then look again
            for late, (log, start) in running.items():
                if time.monotonic() - start > TIMEOUT:
                    os.kill(late, signal.SIGKILL)
                    with open(log / "stderr", "a") as err:
                        print(f"killed after {TIMEOUT} s", file=err)
            time.sleep(0.2)
            continue
        log, start = running.pop(pid)
        (log / "status").write_text(str(os.waitstatus_to_exitcode(wait_status)))
        cost = {"wall_s": time.monotonic() - start, "cpu_s": usage.ru_utime + usage.ru_stime}
        (log / "cost.json").write_text(json.dumps(cost))


if __name__ == "__main__":
    main(int(sys.argv[1]), json.loads(Path(sys.argv[2]).read_text()))
