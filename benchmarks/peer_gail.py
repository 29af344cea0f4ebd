"""GAIL and AIRL in imitrl and in HumanCompatibleAI's imitation 1.0.1, at equal env steps, under two protocols.

Issue 31's harness (the DAgger side is ``peer_imitation.py``): GAIL, and AIRL (tasks
``*_airl``, each library's AIRL tutorial or defaults), on CartPole-v1 (24,576 env
steps, 12 rounds of 2048) and Pendulum-v1 (30,720 steps, 15 rounds; learning rate 1e-3
and gamma 0.9 on both sides, where both libraries' untuned defaults fail), 10 greedy
expert demonstrations (the same scripted experts as ``peer_imitation.py``, checked
there), 8 lanes on both sides, greedy evaluation of 20 episodes on 10 vector envs.

Each (task, seed) runs five fresh processes in turn (:data:`PLAN`), 1 torch thread each:

1. imitrl under the ``own`` protocol, a plain Python script (``_peer_imitation/
   gail_imitrl.py``: the public API as a user's script calls it, the garbage collector
   as Python starts it), the **headline** row;
2. imitation (``_peer_imitation/gail_peer.py``, a plain script too);
3. imitrl under ``matched``, a plain script;
4. imitrl ``own`` with the ``imitrl`` command's collector trick (the imports with the
   collector paused, the import-time heap frozen out of its walks, as the command does in
   the process it owns: :mod:`imitrl.system.heap`), the row ``own, collector trick``;
5. the shipped command itself, ``imitrl gail`` (``imitrl airl``) with the ``own``
   script's settings (``gail_tasks.command_flags``), the row ``own, command as shipped``:
   its wall time is the whole command's, measured here, with all it does beyond the
   script (the expert's and the untrained learner's evaluations, the logger,
   results.json, the checkpoint, curves.png); its return is ``learner.mean_return`` of
   the results.json it writes (evaluated on ``min(episodes, 16)`` lanes, as its own jobs
   evaluate, so not the script's 10).

What each protocol sets: ``_peer_imitation/gail_tasks.py``. Every ratio is imitrl /
imitation of the same seed, whole process (launch to exit, measured here) and by phase
(imports, setup, train, evaluation, measured in the child; the command reports none),
labelled with its protocol and, beside the plain scripts, its process. The target
(issue 31): imitrl's whole-process wall time <= 0.5x imitation's with returns at least
imitation's, judged on the headline rows.

    export IMITRL_PEER_PYTHON=$PEER_VENV/bin/python
    python benchmarks/peer_gail.py --imitrl-python $IMITRL_VENV/bin/python
                                                    # full run, refreshes the README block
    python benchmarks/peer_gail.py --out /tmp/peer  # full run elsewhere, README untouched
    python benchmarks/peer_gail.py --quick          # imitrl's side, tiny budgets, at once

The peer's venv is ``peer_imitation.py``'s, and so is imitrl's (``--peer-python`` or
``$IMITRL_PEER_PYTHON``, ``--imitrl-python``: its docstring says how to build both;
``$PEER_VENV`` and ``$IMITRL_VENV`` stand for folders of your choice). ``--quick`` runs
imitrl's four processes alone, the command's on the same tiny budgets, each process kind
on one task and each task at least once (``runs.order``), ``runs.QUICK_WORKERS`` at once
(timings moot).
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _report
from _peer_imitation import runs
from _peer_imitation.gail_report import NAME, markdown, summarise
from _peer_imitation.gail_tasks import TASKS, GailTask, command_flags, quick
from imitrl.jobs.checkpoint import RESULTS_FILE

HERE = Path(__file__).resolve().parent / "_peer_imitation"
QUICK_TASKS = ("cartpole", "pendulum_airl")
"""the smoke run's tasks (``--quick`` without ``--tasks``): both methods, both action kinds"""
CHILD = {"imitrl": HERE / "gail_imitrl.py", "imitation": HERE / "gail_peer.py"}
PLAN = (
    ("imitrl", "own", "plain"),
    ("imitation", None, "plain"),
    ("imitrl", "matched", "plain"),
    ("imitrl", "own", "collector_trick"),
    ("imitrl", "own", "command"),
)
"""(library, protocol, process) of one (task, seed), in the order they run (imitation's
protocol None: it runs the same under both, once); ``command`` is the shipped ``imitrl
gail`` / ``imitrl airl``, the others scripts (``tasks.PROCESSES``)"""


def plan(quick_run: bool) -> tuple[tuple[str, str | None, str], ...]:
    """:data:`PLAN`, or its imitrl runs alone (``--quick``: no peer venv)."""
    return tuple(job for job in PLAN if job[0] == "imitrl") if quick_run else PLAN


def run_one(
    task: GailTask, seed: int, library: str, protocol: str | None, process: str = "plain",
    *, peer_python: str | None, imitrl_python: str, workdir: Path, timeout: float,
) -> dict:  # fmt: skip
    """One (task, seed, library, protocol, process) as a fresh process: its wall time
    (measured here) and the child's report."""
    if process == "command":
        return run_command(
            task, seed, imitrl_python=imitrl_python, workdir=workdir, timeout=timeout
        )
    spec = json.dumps(task.spec(seed, library, protocol or "own", process))
    result = workdir / f"{task.name}-{library}-{protocol}-{process}-{seed}.json"
    python = imitrl_python if library == "imitrl" else peer_python
    if python is None:
        raise ValueError("imitation's run needs the peer venv's python")
    wall, out = runs._call([python, str(CHILD[library]), spec, str(result)], library, timeout)
    return {"task": task.name, "library": library, "protocol": protocol, "seed": seed,
            "wall": wall, **out, "process": process}  # fmt: skip


def run_command(
    task: GailTask, seed: int, *, imitrl_python: str, workdir: Path, timeout: float
) -> dict:
    """The shipped ``imitrl gail`` (``imitrl airl``) of ``imitrl_python``'s venv with the
    ``own`` script's settings, as a whole process: its wall time measured here, its
    final return, env steps and demonstration rows from the results.json it writes."""
    out_dir = workdir / f"{task.name}-command-{seed}"
    cmd = [*runs.imitrl_command(imitrl_python), *command_flags(task, seed, str(out_dir))]
    wall, results = runs._call(cmd, "imitrl", timeout, result=out_dir / RESULTS_FILE)
    return {
        "task": task.name, "library": "imitrl", "protocol": "own", "seed": seed,
        "wall": wall, "process": "command", "argv": _report.portable_args(cmd),
        "phases": {"job": float(results["seconds"])},  # the job's clock, imports excluded
        "returns": {"final": float(results["learner"]["mean_return"])},
        "env_steps": int(results["env_steps"]),
        "demo_rows": int(results["demonstrations"]["rows"]),
    }  # fmt: skip


def run_jobs(tasks, seeds: int, jobs, args, peer_python: str | None) -> list[dict]:
    """Every (task, seed) and, for each, ``jobs`` in turn, one process at a time;
    ``--quick`` (the smoke run, timings moot): :func:`runs.order`'s quick pairs,
    :data:`runs.QUICK_WORKERS` at once."""
    order = runs.order(tasks, seeds, jobs, quick=args.quick)
    with tempfile.TemporaryDirectory(prefix="peer-gail-") as tmp:

        def one(job) -> dict:
            task, seed, library, protocol, process = job
            r = run_one(task, seed, library, protocol, process, peer_python=peer_python,
                        imitrl_python=args.imitrl_python, workdir=Path(tmp),
                        timeout=args.timeout)  # fmt: skip
            train = r["phases"].get("train")
            print(
                f"{task.name} seed {seed} {library:9s} {protocol or '':7s} {process:15s} wall "
                f"{r['wall']:.2f} s, train {'-' if train is None else f'{train:.2f}'} s, "
                f"return {r['returns']['final']:.1f}",
                file=sys.stderr,
            )
            return r

        if args.quick:
            with ThreadPoolExecutor(min(len(order), runs.QUICK_WORKERS)) as pool:
                return list(pool.map(one, order))
        return [one(job) for job in order]


def build_parser():
    parser = _report.parser(__doc__)
    parser.add_argument(
        "--peer-python", default=None,
        help=f"python of the venv with imitation (default: ${runs.PEER_ENV}; one of the two "
        "is needed unless --quick; see peer_imitation.py's docstring)",
    )  # fmt: skip
    parser.add_argument(
        "--imitrl-python", default=sys.executable,
        help="python of the venv that runs imitrl's children and its command (default: "
        "this one; see peer_imitation.py's docstring for the recommended one)",
    )  # fmt: skip
    parser.add_argument("--seeds", type=int, default=None, help="default 3; 1 with --quick")
    parser.add_argument(
        "--tasks", nargs="+", default=None, choices=list(TASKS),
        help=f"default: all; with --quick {', '.join(QUICK_TASKS)} (GAIL on discrete "
        "actions, AIRL on continuous ones)",
    )  # fmt: skip
    parser.add_argument("--timeout", type=float, default=1800.0)
    return parser


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    # the peer's python first: a full run without one stops before anything is written
    peer_python = None if args.quick else runs.peer_python(args.peer_python)
    out_dir = _report.destination(NAME, quick=args.quick, out=args.out)
    torch.set_num_threads(1)
    seeds = args.seeds if args.seeds is not None else (1 if args.quick else 3)
    names = args.tasks or (list(QUICK_TASKS) if args.quick else list(TASKS))
    tasks = [quick(TASKS[t]) if args.quick else TASKS[t] for t in names]
    peer_versions = None if peer_python is None else runs.peer_versions(peer_python)
    install = runs.imitrl_install(args.imitrl_python)
    bytecode = None if args.quick else runs.byte_compile_imitrl()
    jobs = plan(args.quick)
    t0 = time.perf_counter()
    results = run_jobs(tasks, seeds, jobs, args, peer_python)
    raw = {
        "config": {
            "seeds": seeds,
            "tasks": [task.spec(0, "imitrl", "own") for task in tasks],
            "settings": {
                t.name: {
                    "imitrl own": t.spec(0, "imitrl", "own")["settings"],
                    "imitrl matched": t.spec(0, "imitrl", "matched")["settings"],
                    "imitation": t.spec(0, "imitation", "own")["settings"],
                    "imitrl command (seed 0)": command_flags(t, 0, "OUT"),
                }
                for t in tasks
            },
            "plan": [list(job) for job in jobs],
            "quick": args.quick,
            "bytecode": bytecode,
            "peer_python": None if peer_python is None else _report.portable(peer_python),
            "imitrl_install": install,
            "command": " ".join(
                ["python benchmarks/peer_gail.py", *_report.portable_args(argv or sys.argv[1:])]
            ),
        },
        "imitrl_versions": {
            **{k: v for k, v in _report.machine().items() if k != "platform"},
            **install["versions"],  # the stack of the venv that ran imitrl's children
        },
        "peer_versions": peer_versions,
        "runs": results,
        "summary": summarise(results),
        "wall_seconds": time.perf_counter() - t0,
    }
    text = markdown(raw)
    path = _report.write(NAME, raw, text, out_dir=out_dir)
    print(text)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
