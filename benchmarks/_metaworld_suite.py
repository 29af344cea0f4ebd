"""What ``metaworld_mt10.py`` and ``metaworld_mt50.py`` share: a suite of Meta-World tasks
with the scripted experts, one cell of ``loss_functions.py``'s machinery per (task,
demonstrations, loss, seed), runs of disjoint cells merged into one report, and the
command line (``--tasks``, ``--losses``, ``--demos``, ``--seeds``, ``--first-seed``,
``--jobs``, ``--merge``, ``--render``)."""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import dataclass, replace
from pathlib import Path

import _report
from _loss_functions.merge import join_cells, with_defaults
from _loss_functions.run import run
from _loss_functions.tasks import Protocol, TaskDef
from _metaworld_report import figure, markdown
from imitrl.envs.metaworld import MAX_STEPS
from imitrl.learners import registry


@dataclass(frozen=True)
class Suite:
    """One benchmark over a Meta-World task set."""

    name: str
    """results' name (``benchmarks/results/<name>.json``, README block)"""
    label: str
    """the task set's name in the report (``MT10``, ``MT50``)"""
    tasks: tuple[str, ...]
    protocol: Protocol
    """every cell's budget; ``demo_episodes`` is replaced by each ``--demos`` entry"""
    losses: tuple[str, ...]
    demos: tuple[int, ...]
    seeds: int
    quick_tasks: tuple[str, ...] = ("reach-v3",)

    @property
    def merged(self) -> str:
        """the merged report's name (its JSON, figure and README block)"""
        return f"{self.name}_merged"


def task_defs(
    protocol: Protocol, tasks: tuple[str, ...], demos: tuple[int, ...], quick: bool
) -> list[TaskDef]:
    """One task definition per (task, number of demonstrations); BC at DAgger's query
    budget runs from the largest number of demonstrations only."""
    out = []
    for task in tasks:
        for n in demos:
            p = replace(protocol, demo_episodes=n, matched=protocol.matched and n == max(demos))
            out.append(metaworld_task(task, f"{task}/{n}demo", p))
    return out


def metaworld_task(task: str, name: str, protocol: Protocol) -> TaskDef:
    """Meta-World's ``task`` (e.g. ``reach-v3``) with its scripted expert, scored by
    success, as ``name`` in the results."""
    return TaskDef(
        name,
        env=f"metaworld/{task}",
        expert="metaworld",
        score="success",
        max_steps=MAX_STEPS,
        protocol=protocol,
    )


def merge(runs: list[dict], demos: tuple[int, ...]) -> dict:
    """One payload of ``runs``' cells with ``demos`` demonstrations (ValueError where two
    runs disagree on a task's protocol, a reference or a cell: the code changed between
    them, or the cells overlap). A cell's digits depend on its seed alone, so cells of
    other tasks, losses or seeds, run apart, join as if run together."""
    if len(runs) < 2:
        raise ValueError("--merge needs at least two results files")
    keep = {f"{t}/{n}demo" for r in runs for t in r["config"]["tasks"] for n in demos}
    protocols: dict = {}
    for k, part in enumerate(runs):
        for name, recorded in part["config"]["protocol"].items():
            protocol = with_defaults(recorded)  # fields a run predates: their defaults
            if name in keep and protocols.setdefault(name, protocol) != protocol:
                raise ValueError(f"run {k} trained {name} with another protocol")
    rows, refs = join_cells(runs, keep=keep.__contains__)
    losses = list(dict.fromkeys(r["loss"] for r in rows))
    seeds = sorted({r["seed"] for r in rows})
    tasks = list(dict.fromkeys(t for r in runs for t in r["config"]["tasks"]))
    for loss in losses:  # every loss at every seed and task: the aggregate compares like with like
        have = sorted({r["seed"] for r in rows if r["loss"] == loss})
        if have != seeds:
            raise ValueError(f"{loss} has seeds {have}, the merge {seeds}")
        done = {r["task"] for r in rows if r["loss"] == loss}  # task/Ndemo: each demo count
        if missing := [t for t in sorted(keep) if t not in done]:
            raise ValueError(f"{loss} has no cells on {missing[:3]}")
    config = {
        **runs[0]["config"],
        "tasks": tasks,
        "losses": losses,
        "demos": list(demos),
        "seeds": len(seeds),
        "jobs": "merged",
        "protocol": protocols,
    }
    return {
        "config": config,
        "rows": rows,
        "references": refs,
        "wall_seconds": sum(r["wall_seconds"] for r in runs),
        "load_average_start": runs[0]["load_average_start"],
        "load_average_end": runs[-1]["load_average_end"],
        "merged_from": [
            _report.portable(r["source"]) if "source" in r else f"run {k}"
            for k, r in enumerate(runs)
        ],
    }


def _report_of(payload: dict, name: str, out: Path | None) -> None:
    """Figure, README block (or ``out``) and JSON of ``payload`` under ``name``."""
    fig = figure(payload, _report.results_dir(out) / f"{name}.png")
    text = markdown(payload, fig.name if out else f"results/{fig.name}")  # README's link
    print(text)
    print(f"results: {_report.write(name, payload, text, out_dir=out)}")


def _of_suite(payload: dict, suite: Suite, path: Path, p: argparse.ArgumentParser) -> dict:
    """``payload`` when it is a results file of ``suite`` (a hostile review: MT50's script
    rendered an MT10 file under MT50's name); one line otherwise. A file that names no
    suite (a part run before it was recorded) must hold tasks of the suite's."""
    config = payload.get("config")
    found = config.get("suite") if isinstance(config, dict) else "no config"
    tasks = config.get("tasks") if isinstance(config, dict) else None
    if found is None and isinstance(tasks, list) and set(map(str, tasks)) <= set(suite.tasks):
        return payload
    if found != suite.label:
        p.error(f"{path}: a results file of {found or 'another script'}, not {suite.label}")
    return payload


def _parser(suite: Suite, doc: str | None) -> argparse.ArgumentParser:
    p = _report.parser(doc)
    p.add_argument("--tasks", nargs="+", default=list(suite.tasks), choices=list(suite.tasks))
    p.add_argument("--losses", nargs="+", default=list(suite.losses))
    p.add_argument("--demos", nargs="+", type=int, default=list(suite.demos))
    p.add_argument("--seeds", type=int, default=suite.seeds)
    p.add_argument(
        "--first-seed",
        type=int,
        default=0,
        help="run seeds first..first+seeds-1 (a cell's digits depend on its seed alone)",
    )
    p.add_argument("--jobs", type=int, default=1, help="worker processes, one thread each")
    p.add_argument(
        "--merge",
        nargs="+",
        type=Path,
        default=None,
        help=f"results files of runs of disjoint cells: one report ({suite.merged}) of their "
        "cells with --demos demonstrations; nothing is run",
    )
    p.add_argument(
        "--render",
        type=Path,
        default=None,
        metavar="JSON",
        help="re-render a results file's report (its README block and figure; a merged one "
        f"as {suite.merged}) from its rows; nothing is run",
    )
    return p


def main(suite: Suite, doc: str | None, argv: list[str] | None = None) -> None:
    """The command line of a suite's script (see the module docstring)."""
    p = _parser(suite, doc)
    args = p.parse_args(argv)
    for flag in ("seeds", "jobs"):
        if getattr(args, flag) < 1:
            p.error(f"--{flag} must be >= 1, got {getattr(args, flag)}")
    if args.first_seed < 0:
        p.error(f"--first-seed must be >= 0, got {args.first_seed}")
    if min(args.demos) < 1:
        p.error(f"--demos must be >= 1, got {min(args.demos)}")
    if len(set(args.demos)) < len(args.demos):  # each count's cells would run twice
        p.error(f"--demos repeats a count: {args.demos}")
    if args.first_seed + args.seeds > 2**31:
        p.error(f"--first-seed {args.first_seed} + --seeds {args.seeds} passes 2^31")
    if unknown := [loss for loss in args.losses if loss not in registry.names()]:
        p.error(f"--losses: {unknown} are not registered losses ({', '.join(registry.names())})")
    out_dir = _report.destination(suite.name, quick=args.quick, out=args.out)  # --quick: scratch
    if args.render is not None:
        payload = _of_suite(_report.read_results(args.render, p.error), suite, args.render, p)
        name = suite.merged if payload["config"].get("jobs") == "merged" else suite.name
        _report.render_safely(
            lambda o: _report_of(payload, name, o), out_dir, p.error, str(args.render)
        )
        return
    if args.merge is not None:
        runs = [
            {**_of_suite(_report.read_results(f, p.error), suite, f, p), "source": str(f)}
            for f in args.merge
        ]
        try:
            merged = merge(runs, tuple(args.demos))
        except (ValueError, KeyError, TypeError) as err:  # parts that do not join: one line
            p.error(_report.merge_refused(err))
        _report.render_safely(
            lambda o: _report_of(merged, suite.merged, o), out_dir, p.error, "--merge"
        )
        return
    out_dir = _report.destination(suite.name, quick=args.quick, out=args.out)
    seeds = 1 if args.quick else args.seeds
    every = args.tasks == list(suite.tasks)
    tasks = suite.quick_tasks if args.quick and every else tuple(args.tasks)
    losses = ["mse"] if args.quick and args.losses == list(suite.losses) else args.losses
    demos = (
        (min(suite.demos),) if args.quick and args.demos == list(suite.demos) else tuple(args.demos)
    )
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    load = os.getloadavg()
    t0 = time.perf_counter()
    raw = run(
        tasks=task_defs(suite.protocol, tasks, demos, args.quick),
        losses=losses,
        seeds=range(args.first_seed, args.first_seed + seeds),
        quick_mode=args.quick,
        jobs=args.jobs,
    )
    config = {
        "suite": suite.label,
        "tasks": list(tasks),
        "losses": losses,
        "demos": list(demos),
        "seeds": seeds,
        "first_seed": args.first_seed,
        "jobs": args.jobs,
        "quick": args.quick,
        "protocol": json.loads(json.dumps(raw["protocols"], default=str)),
    }
    payload = {
        "config": config,
        "rows": raw["rows"],
        "references": raw["references"],
        "wall_seconds": time.perf_counter() - t0,
        "load_average_start": list(load),
        "load_average_end": list(os.getloadavg()),
    }
    _report_of(payload, suite.name, out_dir)
