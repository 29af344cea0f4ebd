"""imitrl side by side with HumanCompatibleAI's imitation 1.0.1 on imitation's own small tasks.

Issue 16's benchmark: the same three tasks, scripted experts and budgets in both
libraries, each (task, library, seed) run as a whole fresh process, one after another,
one torch thread each:

* FrozenLake-v1 (slippery 4x4; expert: value iteration, gamma 0.95): 3 demonstration
  episodes, 4 DAgger rounds x 3 episodes, 1000 evaluation episodes;
* CartPole-v1 (expert ``a = 1[K . obs > 0]``): the first 25 steps of one episode,
  5 rounds x 2 episodes, batch 25, 20 evaluation episodes;
* Pendulum-v1 (expert: energy swing-up + LQR): one episode, 5 rounds x 2 episodes,
  20 evaluation episodes;

a [32, 32] tanh MLP, BC 1000 steps, then 500 steps after each relabel round, batch 32
(see ``_peer_imitation/tasks.py``). Two protocols, each (task, seed) run under both and
named in every row: ``own``, each library with its own defaults (imitrl refits a fresh
learner each round with beta = 0, ``dagger``'s defaults; imitation trains one policy on
with ``LinearBetaSchedule(15)``, ``SimpleDAggerTrainer``'s), and ``matched`` (both train
one policy on with beta = 0). Each evaluates on vector envs as its own code does
(imitrl 16 lanes, imitation 50, as its scripts). What each side does, phase by phase, is
in ``_peer_imitation/imitrl_run.py`` and ``_peer_imitation/peer_run.py``. The experts
are the same functions: the peer's copies (numpy) must label a batch of observations
exactly as imitrl's do, or the run stops.

Both sides run as their users run them: every child is a plain Python script (the
garbage collector as Python starts it, nothing in the process touched). Per (task,
seed) five processes in turn (``runs.PLAN``): imitrl ``own``, imitation ``own``, imitrl
``matched``, imitation ``matched``, then imitrl ``own`` once more with the ``imitrl``
command's collector trick (what the command does in the process it owns,
:mod:`imitrl.system.heap`: the imports with the collector paused, the import-time heap
frozen out of its walks), a row of its own (``cartpole, own, collector trick``) paired
with imitation's ``own`` run of the same seed. The headline ratios are the plain
scripts' ``own`` rows; the collector-trick row says what the trick is worth, not what a
user's script gets.

Recorded: whole-process wall time (launch to exit, measured here) and the child's
phases (imports, setup, BC, DAgger collection + fits without evaluation, evaluation),
per-pair ratios imitrl / imitation and their medians, the BC and final returns of both
(FrozenLake also the exact success of each greedy policy), the peer venv's ``pip list``.
Not run in CI: it needs the peer's venv. ``--quick`` runs imitrl's side only (its plain
and collector-trick processes), on tiny budgets, each process kind on one task and each
task at least once (``runs.order``), ``runs.QUICK_WORKERS`` processes at once (the smoke
test; its timings mean nothing).

The peer's venv, outside the repository (``$PEER_VENV`` stands for a folder of your
choice)::

    python3 -m venv $PEER_VENV
    $PEER_VENV/bin/pip install torch==2.13.0
    $PEER_VENV/bin/pip install imitation torch==2.13.0

(torch first, then pinned again on imitation's line so that pip keeps the CPU build; it
resolves to imitation 1.0.1, stable-baselines3 2.2.1, gymnasium 0.29.1.) A full run
takes its python from ``--peer-python $PEER_VENV/bin/python`` or, without that flag,
from the environment variable ``IMITRL_PEER_PYTHON`` (``runs.PEER_ENV``); with neither
it stops before anything runs. imitrl's side runs likewise from an install of its own
requirements, without the extras of the dev venv (TorchRL imports ray and mujoco
whenever they are installed: ``runs.imitrl_install``), with this checkout's ``src``
first on its path (``--imitrl-python``; the default is the python running the script;
``$IMITRL_VENV`` another folder of your choice)::

    python3 -m venv $IMITRL_VENV
    $IMITRL_VENV/bin/pip install torch==2.13.0
    $IMITRL_VENV/bin/pip install -e .

Then::

    export IMITRL_PEER_PYTHON=$PEER_VENV/bin/python
    python benchmarks/peer_imitation.py --imitrl-python $IMITRL_VENV/bin/python
                                                         # full run, refreshes the README block
    python benchmarks/peer_imitation.py --out /tmp/peer  # full run elsewhere, README untouched
    python benchmarks/peer_imitation.py --quick          # imitrl's side, tiny budgets, temp dir
    python benchmarks/peer_imitation.py --render /tmp/peer/peer_imitation.json --out /tmp/x

The GAIL rows (issue 31: imitrl's ``gail`` against imitation's ``GAIL`` at equal env
steps, under both protocols, beside the shipped ``imitrl gail`` command) have a harness
of their own, ``peer_gail.py``, with its own tasks, budgets, results file and README
block; ``--gail`` runs it from here, with the arguments that follow::

    python benchmarks/peer_imitation.py --gail --seeds 5 --imitrl-python $IMITRL_VENV/bin/python
"""

from __future__ import annotations

import sys
import time
from dataclasses import asdict
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _report
from _peer_imitation import runs
from _peer_imitation.report import NAME, markdown, summarise
from _peer_imitation.tasks import TASKS, quick


def build_parser():
    """The script's flags (``--gail`` is handled before they are read: :func:`main`)."""
    parser = _report.parser(__doc__)
    parser.add_argument(
        "--peer-python",
        default=None,
        help=f"python of the venv with imitation (default: ${runs.PEER_ENV}; one of the two "
        "is needed unless --quick; see the docstring)",
    )
    parser.add_argument(
        "--gail",
        action="store_true",
        help="run the GAIL rows instead (peer_gail.py, given the other arguments)",
    )
    parser.add_argument(
        "--imitrl-python",
        default=sys.executable,
        help="python of the venv that runs imitrl's children (default: this one; see the "
        "docstring for the recommended one)",
    )
    parser.add_argument(
        "--seeds", type=int, default=None, help="seeds per task (default 3; 1 with --quick)"
    )
    parser.add_argument("--tasks", nargs="+", default=list(TASKS), choices=list(TASKS))
    parser.add_argument(
        "--imitrl-loss",
        default="default",
        help="imitrl's learner: default (ActorCritic.for_env) or a loss-registry name "
        "(gaussian_nll: the likelihood learner set beside imitation's Gaussian NLL policy)",
    )
    parser.add_argument(
        "--timeout", type=float, default=3600.0, help="seconds one child process may take"
    )
    parser.add_argument(
        "--render",
        type=Path,
        default=None,
        metavar="JSON",
        help="print the tables of a results file instead of running (and, without --out, "
        "refresh the README block from it)",
    )
    return parser


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else list(argv)
    if "--gail" in argv:  # the GAIL rows: peer_gail.py, given the other arguments
        import peer_gail

        argv.remove("--gail")
        peer_gail.main(argv)
        return
    p = build_parser()
    args = p.parse_args(argv)
    _report.check_least(p, args, seeds=1, timeout=1)
    if args.render is not None:
        payload = _report.read_results(args.render, p.error)

        def render(out: Path | None) -> str:
            text = markdown(payload)
            if out is None:
                _report.update_readme(NAME, text)
            return text

        # only a full render rewrites the README block (it writes no file: printed)
        out = None if args.out is None and not args.quick else Path(args.out or ".")
        print(_report.render_safely(render, out, p.error, str(args.render)))
        return
    # the peer's python first: a full run without one stops before anything is written
    peer_python = None if args.quick else runs.peer_python(args.peer_python)
    out_dir = _report.destination(NAME, quick=args.quick, out=args.out)
    torch.set_num_threads(1)
    raw = measure(args, argv, peer_python)
    text = markdown(raw)
    path = _report.write(NAME, raw, text, out_dir=out_dir)
    print(text)
    print(f"wrote {path}")


def measure(args, argv: list[str], peer_python: str | None) -> dict:
    """Run :func:`runs.plan` on the tasks and seeds ``args`` name; the results file's
    contents (``peer_python`` None: ``--quick``, imitrl's side alone)."""
    seeds = args.seeds if args.seeds is not None else (1 if args.quick else 3)
    tasks = [quick(TASKS[t]) if args.quick else TASKS[t] for t in args.tasks]
    jobs = runs.plan(args.quick)
    t0 = time.perf_counter()

    # -- both venvs and the peer's copies of the experts, before anything is timed
    install = runs.imitrl_install(args.imitrl_python)
    peer_versions, expert_check, bytecode = None, None, None
    if peer_python is not None:
        peer_versions = runs.peer_versions(peer_python)
        expert_check = runs.check_experts(peer_python, timeout=args.timeout)
        print(f"experts agree: {expert_check}")
        bytecode = runs.byte_compile_imitrl()

    # -- the timed runs, one fresh process each
    results = runs.run_all(
        tasks,
        seeds,
        jobs,
        peer_python=peer_python,
        timeout=args.timeout,
        concurrent=args.quick,
        imitrl_loss=args.imitrl_loss,
        imitrl_python=args.imitrl_python,
    )

    # -- untimed: FrozenLake's exact values, the experts' returns
    for r in results:
        if r["greedy_tables"]:
            r["exact_success"] = {
                k: runs.frozenlake_exact(v) for k, v in r["greedy_tables"].items()
            }
    references = {t.name: runs.expert_returns(t, seeds) for t in tasks}
    return {
        "config": {
            "seeds": seeds,
            "tasks": [asdict(t) for t in tasks],
            "libraries": sorted({lib for lib, _, _ in jobs}, key=runs.LIBRARIES.index),
            "plan": [list(job) for job in jobs],
            "imitrl_loss": args.imitrl_loss,
            "quick": args.quick,
            "bytecode": bytecode,
            "peer_python": None if peer_python is None else _report.portable(peer_python),
            "imitrl_install": install,
            "command": " ".join(
                ["python benchmarks/peer_imitation.py", *_report.portable_args(argv)]
            ),
        },
        "imitrl_versions": {
            **{k: v for k, v in _report.machine().items() if k != "platform"},
            **install["versions"],  # the stack of the venv that ran imitrl's children
        },
        "peer_versions": peer_versions,
        "expert_check": expert_check,
        "runs": results,
        "summary": summarise(results, references),
        "wall_seconds": time.perf_counter() - t0,
    }


if __name__ == "__main__":
    main()
