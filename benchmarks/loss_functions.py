"""Imitation losses compared: every registered loss x task x seed, BC and DAgger, equal budget.

Which loss, on which kind of task, with what uncertainty. For every task, every loss
of :mod:`imitrl.learners.registry` that applies to its action space is trained on
the same expert demonstrations with the same budget (gradient steps x batch size,
network size, optimizer, observation normalisation: the library's default), once
per seed:

* BC: a learner fitted to the demonstrations (DAgger's round 0);
* DAgger: ``rounds - 1`` relabel rounds later (beta = 0, a fresh learner per round,
  same fit), the learner fitted on everything collected.

Tasks (``_loss_functions/tasks.py``, one registry of task definitions): slippery
FrozenLake (score: the exact success probability of the learned policy in 100 steps,
from the MDP, not sampled), CartPole-v1, Pendulum-v1, InvertedPendulum-v5 (score:
mean return over evaluation episodes on held-out seeds), the two-way obstacle task of
:mod:`imitrl.envs.multimodal` (score: success rate; plus the fraction of the learner's
actions near each of the expert's two modes at the decision states, and which side its
successful episodes passed) and the forking corridor of :mod:`imitrl.envs.corridor`
(four routes; success rate, the lane reached or the wall hit, mode fractions at both
forks, turn-backs in the decision windows). ``--task key=value,...`` adds a task from
outside: an env id (or ``module:Id-v0``, or a TorchRL env class ``module:Class``) with
an expert ``module:function`` and a budget, or a recorded LeRobot / Minari dataset
and the env to evaluate in (see ``parse_task`` in ``_loss_functions/parse.py``).

The expert-normalised score is ``(score - random) / (expert - random)``, with the
expert's and a uniformly random policy's scores measured by the same protocol on the
same seeds (averaged over seeds). Intervals are 95% Student-t intervals over seeds.

Every random draw flows from the cell's seed (the learner's initialisation, its
minibatches, its sampling, the envs), so a cell gives the same digits whenever and
wherever (``--jobs``) it runs. The parts: ``_loss_functions/tasks.py`` (the task
table), ``_loss_functions/run.py`` (the cells), ``_loss_functions/report.py``
(statistics, tables, figure).

    python benchmarks/loss_functions.py                      # full run, refreshes the README
    python benchmarks/loss_functions.py --jobs 2             # same results, two processes
    python benchmarks/loss_functions.py --quick              # smoke run, into a temporary dir
    python benchmarks/loss_functions.py --tasks two_way --losses mse diffusion --seeds 3 --out /tmp/x
    python benchmarks/loss_functions.py --merge results/loss_functions.json /tmp/x/loss_functions.json
    python benchmarks/loss_functions.py --quick --losses mse \
        --task name=pend,env=Pendulum-v1,expert=imitrl.experts:pendulum_expert,steps=500

The aggregate statistics (IQM, optimality gap, probability of improvement over MSE
with stratified bootstrap intervals over seeds, performance profiles; Agarwal et al.
2021, :mod:`imitrl.evaluation.aggregate`) are computed over the tasks every
continuous loss applies to.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _report
from _loss_functions.merge import merge
from _loss_functions.parse import parse_task
from _loss_functions.report import NAME, report
from _loss_functions.run import run
from _loss_functions.tasks import TASKS, build
from imitrl.learners import FOR_ENV, registry
from imitrl.system.imports import import_user_module

QUICK_LOSSES = ("cross_entropy", "gaussian_nll", "mse", "flow", "mse_chunk")
"""``--quick``'s default: a loss of each cheap family, one-step and chunked (the smoke run
of the pipeline; ``tests/learners/test_registry.py`` builds and trains every entry)"""


def _parser() -> argparse.ArgumentParser:
    parser = _report.parser(__doc__)
    parser.add_argument(
        "--seeds", type=int, default=None, help="seeds per cell (default 5; 1 with --quick)"
    )
    parser.add_argument(
        "--tasks",
        nargs="+",
        default=None,
        choices=list(TASKS),
        help="built-in tasks (default: all but inverted_pendulum, none when --task is given)",
    )
    parser.add_argument(
        "--task",
        dest="external",
        action="append",
        default=[],
        metavar="KEY=VALUE,...",
        help="a task from outside: name=,env= and expert= (module:function) or dataset= "
        "(a LeRobot or Minari directory), budget keys demos=,rounds=,episodes=,steps=,"
        "batch=,hidden=,lr=,eval= (repeatable)",
    )
    parser.add_argument(
        "--losses",
        nargs="+",
        default=None,
        help="registry names (default: all; with --quick, one of each family: "
        f"{' '.join(QUICK_LOSSES)})",
    )
    parser.add_argument(
        "--import",
        dest="modules",
        nargs="+",
        default=[],
        metavar="MODULE",
        help="import these modules first (their @register entries join the run)",
    )
    parser.add_argument("--jobs", type=int, default=1, help="worker processes (same results)")
    parser.add_argument(
        "--reps",
        type=int,
        default=None,
        help="bootstrap replicates of the aggregate intervals (default 2000; 100 with --quick)",
    )
    parser.add_argument(
        "--merge",
        type=Path,
        nargs="+",
        default=None,
        metavar="JSON",
        help="combine results files of disjoint cells (same seeds and protocols) and render "
        "them as one run (_loss_functions/merge.py)",
    )
    parser.add_argument(
        "--render",
        type=Path,
        default=None,
        metavar="JSON",
        help="re-render the table and figure from a results file instead of running",
    )
    return parser


def _tasks(args: argparse.Namespace) -> list:
    """The run's tasks: ``--tasks`` (default: the default run's) and each ``--task``."""
    external = [parse_task(text) for text in args.external]
    default = [n for n, t in TASKS.items() if t.in_default_run]
    names = args.tasks if args.tasks is not None else ([] if external else default)
    tasks = [TASKS[n] for n in names] + external
    if len({t.name for t in tasks}) != len(tasks):
        raise SystemExit(f"task names must be unique, got {[t.name for t in tasks]}")
    return tasks


def main(argv: list[str] | None = None) -> None:
    p = _parser()
    args = p.parse_args(argv)
    _report.check_least(p, args, seeds=1, jobs=1, reps=2)
    for module in args.modules:  # the user's code, by name: a failure is one line
        try:
            import_user_module(module, f"--import {module}")
        except ValueError as err:
            p.error(str(err))
    tasks = _tasks(args)
    out_dir = _report.destination(NAME, quick=args.quick, out=args.out)
    if args.render is not None:
        raw = _report.read_results(args.render, p.error)
        _report.render_safely(lambda o: report(raw, o), out_dir, p.error, str(args.render))
        return
    if args.merge is not None:
        try:
            raw = merge([_report.read_results(path, p.error) for path in args.merge])
        except (ValueError, KeyError, TypeError) as err:  # parts that do not join: one line
            p.error(_report.merge_refused(err))
        _report.render_safely(lambda o: report(raw, o), out_dir, p.error, "--merge")
        return
    if args.quick and args.losses is None:  # one of each family that applies to a task
        # (a hostile review: --quick --tasks frozenlake cartpole was refused over
        # gaussian_nll, a loss nobody asked for)
        specs = [build(defn, True).spec() for defn in tasks]
        args.losses = [n for n in QUICK_LOSSES if any(n in registry.names(s) for s in specs)]
    for loss in args.losses or []:
        try:
            registry.get(loss)
        except ValueError as err:  # a typo: one line, not a traceback (issue 44)
            raise SystemExit(f"loss_functions.py: --losses: {err}") from None
    torch.set_num_threads(1)
    seeds = args.seeds if args.seeds is not None else (1 if args.quick else 5)
    t0 = time.perf_counter()
    raw = run(
        tasks=tasks,
        losses=args.losses,
        seeds=seeds,
        quick_mode=args.quick,
        jobs=args.jobs,
        modules=tuple(args.modules),
    )
    raw["wall_seconds"] = time.perf_counter() - t0
    raw["config"] = {
        "seeds": seeds,
        "tasks": [t.name for t in tasks],
        "losses": args.losses,
        "quick": args.quick,
        "jobs": args.jobs,
        "bootstrap_reps": args.reps if args.reps is not None else (100 if args.quick else 2000),
        "cpu_count": os.cpu_count(),
        "command": " ".join(["python benchmarks/loss_functions.py", *(argv or sys.argv[1:])]),
    }
    raw["losses"] = {
        e.name: {"actions": e.actions, "summary": e.summary}
        for e in registry.entries()
        if e.name != FOR_ENV  # a network, not an objective: never a cell
    }
    # the raw rows first, so that a failing report can be re-rendered (--render)
    raw_path = _report.results_dir(out_dir) / f"{NAME}.json"
    raw_path.write_text(json.dumps(raw, indent=1, default=str) + "\n")
    report(raw, out_dir)
    print(f"wall time {raw['wall_seconds']:.0f} s")


if __name__ == "__main__":
    main()
