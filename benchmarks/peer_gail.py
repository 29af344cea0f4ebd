"""GAIL and AIRL in imitrl and in HumanCompatibleAI's imitation 1.0.1, at equal env steps, under two protocols.

Issue 31's harness (the DAgger side is ``peer_imitation.py``): GAIL, and AIRL (tasks
``*_airl``, each library's AIRL tutorial or defaults), on CartPole-v1 (24,576 env
steps, 12 rounds of 2048) and Pendulum-v1 (30,720 steps, 15 rounds; learning rate 1e-3
and gamma 0.9 on both sides, where both libraries' untuned defaults fail), 10 greedy
expert demonstrations (the same scripted experts as ``peer_imitation.py``, checked
there), 8 lanes on both sides, greedy evaluation of 20 episodes on 10 vector envs.

Each (task, seed) runs three fresh processes in turn, 1 torch thread each: imitrl under
the ``own`` protocol, imitation, imitrl under ``matched`` (what each protocol sets:
``_peer_imitation/gail_tasks.py``). Every ratio is imitrl / imitation of the same seed,
whole process (launch to exit, measured here) and by phase (imports, setup, train,
evaluation, measured in the child), labelled with its protocol. The target (issue 31):
imitrl's whole-process wall time <= 0.5x imitation's with returns at least imitation's.

    python benchmarks/peer_gail.py --imitrl-python /work/imitrl_venv/bin/python
                                                    # full run, refreshes the README block
    python benchmarks/peer_gail.py --out /tmp/peer  # full run elsewhere, README untouched
    python benchmarks/peer_gail.py --quick          # imitrl's side, tiny budgets, at once

The peer's venv is ``peer_imitation.py``'s, and so is imitrl's (``--imitrl-python``; its
docstring says how to build both).
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
from _peer_imitation.gail_tasks import PROTOCOLS, TASKS, quick

HERE = Path(__file__).resolve().parent / "_peer_imitation"
CHILD = {"imitrl": HERE / "gail_imitrl.py", "imitation": HERE / "gail_peer.py"}
PEER_PYTHON = "/work/peer_venv/bin/python"


def order(quick_run: bool) -> list[tuple[str, str | None]]:
    """(library, protocol) of one (task, seed), in the order they run."""
    if quick_run:
        return [("imitrl", p) for p in PROTOCOLS]
    return [("imitrl", "own"), ("imitation", None), ("imitrl", "matched")]


def run_one(task, seed, library, protocol, *, peer_python, imitrl_python, workdir, timeout) -> dict:
    spec = json.dumps(task.spec(seed, library, protocol or "own"))
    result = workdir / f"{task.name}-{library}-{protocol}-{seed}.json"
    python = imitrl_python if library == "imitrl" else peer_python
    wall, out = runs._call([python, str(CHILD[library]), spec, str(result)], library, timeout)
    return {"task": task.name, "library": library, "protocol": protocol, "seed": seed,
            "wall": wall, **out}  # fmt: skip


def main(argv: list[str] | None = None) -> None:
    parser = _report.parser(__doc__)
    parser.add_argument("--peer-python", default=PEER_PYTHON)
    parser.add_argument(
        "--imitrl-python", default=sys.executable,
        help="python of the venv that runs imitrl's children (default: this one; see "
        "peer_imitation.py's docstring for the recommended one)",
    )  # fmt: skip
    parser.add_argument("--seeds", type=int, default=None, help="default 3; 1 with --quick")
    parser.add_argument("--tasks", nargs="+", default=list(TASKS), choices=list(TASKS))
    parser.add_argument("--timeout", type=float, default=1800.0)
    args = parser.parse_args(argv)
    out_dir = _report.destination(NAME, quick=args.quick, out=args.out)
    torch.set_num_threads(1)
    seeds = args.seeds if args.seeds is not None else (1 if args.quick else 3)
    tasks = [quick(TASKS[t]) if args.quick else TASKS[t] for t in args.tasks]
    peer_versions = None
    if not args.quick:
        if not Path(args.peer_python).exists():
            raise SystemExit(f"no python at {args.peer_python}: see peer_imitation.py's docstring")
        peer_versions = runs.peer_versions(args.peer_python)
    install = runs.imitrl_install(args.imitrl_python)
    bytecode = None if args.quick else runs.byte_compile_imitrl()
    t0 = time.perf_counter()
    jobs = [(t, s, lib, p) for t in tasks for s in range(seeds) for lib, p in order(args.quick)]
    with tempfile.TemporaryDirectory(prefix="peer-gail-") as tmp:

        def one(job) -> dict:
            task, seed, library, protocol = job
            r = run_one(task, seed, library, protocol, peer_python=args.peer_python,
                        imitrl_python=args.imitrl_python, workdir=Path(tmp),
                        timeout=args.timeout)  # fmt: skip
            print(
                f"{task.name} seed {seed} {library:9s} {protocol or '':7s} wall "
                f"{r['wall']:.2f} s, train {r['phases']['train']:.2f} s, return "
                f"{r['returns']['final']:.1f}",
                file=sys.stderr,
            )
            return r

        if args.quick:  # the smoke run: every process at once (timings moot)
            with ThreadPoolExecutor(len(jobs)) as pool:
                results = list(pool.map(one, jobs))
        else:  # one process at a time, in turn
            results = [one(job) for job in jobs]
    raw = {
        "config": {
            "seeds": seeds,
            "tasks": [task.spec(0, "imitrl", "own") for task in tasks],
            "settings": {
                t.name: {
                    "imitrl own": t.spec(0, "imitrl", "own")["settings"],
                    "imitrl matched": t.spec(0, "imitrl", "matched")["settings"],
                    "imitation": t.spec(0, "imitation", "own")["settings"],
                }
                for t in tasks
            },
            "quick": args.quick,
            "bytecode": bytecode,
            "imitrl_install": install,
            "command": " ".join(["python benchmarks/peer_gail.py", *(argv or sys.argv[1:])]),
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
