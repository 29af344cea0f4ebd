"""Meta-World MT10: BC and DAgger from 1 and 5 demonstrations, four losses, success rates.

Every task of Meta-World's MT10 (``imitrl.envs.metaworld``: ``metaworld/<task>-v3``, a
new goal and object placement every episode, drawn from the seed) with its scripted
policy as the queryable expert (``--expert metaworld``: labels clipped into the action
bounds, as the env clips what it executes). For each task, number of demonstrations
(1, 5), loss (``mse``, ``flow_chunk``, ``act``, ``diffusion_chunk``) and seed, one cell
of ``loss_functions.py``'s machinery (``_loss_functions/run.py``):

* BC: a learner fitted to the demonstrations (DAgger's round 0);
* DAgger: relabel rounds of the learner's own episodes (beta = 0, warm start: each
  round continues the previous learner), the expert labelling every visited state;
* BC at DAgger's query budget (``bc_matched``): a fresh learner fitted on as many
  expert-driven rows as DAgger's last fit saw, for as many gradient steps (the
  section's exercise 4, at scale): DAgger's rows each cost one expert query, and so do
  the demonstrations'.

Every learner, and the expert, is scored by its success rate over ``eval`` held-out
episodes (Meta-World's measure: ``info["success"]`` at any step; episodes end at the
first success), per task with a Wilson interval over the seeds' pooled episodes, and
across tasks by the aggregate estimators of Agarwal et al. (2021) on the
expert-normalised success (success / the expert's success on the same held-out starts):
IQM, optimality gap and the probability of improvement over MSE, with stratified
bootstrap intervals. The target (issue 29): DAgger reaches >= 0.95 of the expert's
success on at least 8 of the 10 tasks from at most 5 demonstrations.

    python benchmarks/metaworld_mt10.py --jobs 2     # full run, refreshes benchmarks/README.md
    python benchmarks/metaworld_mt10.py --quick      # smoke run, into a temporary directory
    python benchmarks/metaworld_mt10.py --tasks reach-v3 --losses mse --seeds 1 --out /tmp/x
    python benchmarks/metaworld_mt10.py --render results/metaworld_mt10.json  # report only
    python benchmarks/metaworld_mt10.py --merge results/metaworld_mt10.json a.json b.json \
        --demos 5                # one report of runs of disjoint cells (other losses, seeds)
"""

from __future__ import annotations

import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _report
from _loss_functions.run import run
from _loss_functions.tasks import LearnerSettings, Protocol, TaskDef
from _metaworld_mt10_report import figure, markdown
from imitrl.algorithms import BCConfig
from imitrl.envs.metaworld import MT10

NAME = "metaworld_mt10"
"""(not ``metaworld.py``: run as a script, a file of that name would shadow the
``metaworld`` package on ``sys.path``)"""
LOSSES = ("mse", "flow_chunk", "act", "diffusion_chunk")
DEMOS = (1, 5)
PROTOCOL = Protocol(
    demo_episodes=5,
    rounds=3,
    episodes_per_round=3,
    bc=BCConfig(num_steps=320, batch_size=256),
    learner=LearnerSettings(hidden=(128, 128), lr=3e-3),
    eval_episodes=5,
    max_episode_steps=150,
    round_steps=160,
    matched=True,
)
"""every cell's budget, sized so that the full run (10 tasks x 2 demonstration counts x
4 losses x 5 seeds, ``--jobs 2``) fits an hour on 2 cores. Measured: at 400-step fits,
200-step rounds and 6 evaluation episodes the full run took 64.2 min (120 core-minutes of
cells: fits 45, of which ACT's 35; evaluations 37; the rest rollouts and DAgger's
queries), so fits and rounds were cut by a fifth and evaluations by a sixth (about 15
core-minutes); 1000-step fits and 10 episodes had cost three times as much on
pick-place. The demonstrations per task variant (``DEMOS``) replace ``demo_episodes``,
and BC at DAgger's query budget runs from the largest number of demonstrations only.
Episodes are cut at 150 steps: the experts succeed by step 46-98 in the median
(``tests/envs/test_metaworld.py``), and a failing learner's episode would otherwise cost 500
steps of simulation."""


def task_defs(tasks: tuple[str, ...], demos: tuple[int, ...], quick: bool) -> list[TaskDef]:
    """One task definition per (task, number of demonstrations)."""
    out = []
    for task in tasks:
        for n in demos:
            protocol = replace(PROTOCOL, demo_episodes=n, matched=n == max(demos))
            out.append(
                TaskDef(
                    f"{task}/{n}demo",
                    env=f"metaworld/{task}",
                    expert="metaworld",
                    score="success",
                    max_steps=500,
                    protocol=protocol,
                )
            )
    return out


MERGED = f"{NAME}_merged"
"""the merged report's name (its JSON, figure and README block): the full run's own stay"""


def merge(runs: list[dict], demos: tuple[int, ...]) -> dict:
    """One payload of ``runs``' cells with ``demos`` demonstrations (ValueError where two
    runs disagree on a task's protocol, a reference or a cell: the code changed between
    them, or the cells overlap). A cell's digits depend on its seed alone, so cells of
    other losses or seeds, run apart, join as if run together."""
    if len(runs) < 2:
        raise ValueError("--merge needs at least two results files")
    keep = {f"{t}/{n}demo" for r in runs for t in r["config"]["tasks"] for n in demos}
    rows, refs, cells, protocols = [], {}, set(), {}
    for k, part in enumerate(runs):
        for name, protocol in part["config"]["protocol"].items():
            if name in keep and protocols.setdefault(name, protocol) != protocol:
                raise ValueError(f"run {k} trained {name} with another protocol")
        for ref in part["references"]:
            key = (ref["task"], ref["policy"], ref["seed"])
            if ref["task"] in keep and refs.setdefault(key, ref) != ref:
                raise ValueError(f"run {k} measured another {key} reference: the code changed")
        for row in part["rows"]:
            key = (row["task"], row["loss"], row["seed"], row["algorithm"])
            if row["task"] not in keep:
                continue
            if key in cells:
                raise ValueError(f"run {k} repeats the cell {key}")
            cells.add(key)
            rows.append(row)
    losses = list(dict.fromkeys(r["loss"] for r in rows))
    seeds = sorted({r["seed"] for r in rows})
    for loss in losses:  # every loss at every seed: the aggregate compares like with like
        have = sorted({r["seed"] for r in rows if r["loss"] == loss})
        if have != seeds:
            raise ValueError(f"{loss} has seeds {have}, the merge {seeds}")
    config = {
        **runs[0]["config"],
        "losses": losses,
        "demos": list(demos),
        "seeds": len(seeds),
        "jobs": "merged",
        "protocol": protocols,
    }
    return {
        "config": config,
        "rows": rows,
        "references": list(refs.values()),
        "wall_seconds": sum(r["wall_seconds"] for r in runs),
        "load_average_start": runs[0]["load_average_start"],
        "load_average_end": runs[-1]["load_average_end"],
        "merged_from": [r.get("source", f"run {k}") for k, r in enumerate(runs)],
    }


def main(argv: list[str] | None = None) -> None:
    p = _report.parser(__doc__)
    p.add_argument("--tasks", nargs="+", default=list(MT10), choices=list(MT10))
    p.add_argument("--losses", nargs="+", default=list(LOSSES))
    p.add_argument("--demos", nargs="+", type=int, default=list(DEMOS))
    p.add_argument("--seeds", type=int, default=5)
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
        help=f"results files of runs of disjoint cells: one report ({MERGED}) of their "
        "cells with --demos demonstrations; nothing is run",
    )
    p.add_argument(
        "--render",
        type=Path,
        default=None,
        metavar="JSON",
        help="re-render a results file's report (its README block and figure; a merged one "
        f"as {MERGED}) from its rows; nothing is run",
    )
    args = p.parse_args(argv)
    if args.render is not None:
        payload = json.loads(args.render.read_text())
        name = MERGED if payload["config"]["jobs"] == "merged" else NAME
        out_dir = None if args.out is None else Path(args.out)
        fig = figure(payload, _report.results_dir(out_dir) / f"{name}.png")
        text = markdown(payload, fig.name if out_dir else f"results/{fig.name}")
        print(text)
        print(f"results: {_report.write(name, payload, text, out_dir=out_dir)}")
        return
    if args.merge is not None:
        runs = [{**json.loads(f.read_text()), "source": str(f)} for f in args.merge]
        payload = merge(runs, tuple(args.demos))
        out_dir = None if args.out is None else Path(args.out)
        fig = figure(payload, _report.results_dir(out_dir) / f"{MERGED}.png")
        text = markdown(payload, fig.name if out_dir else f"results/{fig.name}")
        print(text)
        print(f"results: {_report.write(MERGED, payload, text, out_dir=out_dir)}")
        return
    out_dir = _report.destination(NAME, quick=args.quick, out=args.out)
    seeds = 1 if args.quick else args.seeds
    tasks = ("reach-v3",) if args.quick and args.tasks == list(MT10) else tuple(args.tasks)
    losses = ["mse"] if args.quick and args.losses == list(LOSSES) else args.losses
    demos = (1,) if args.quick and args.demos == list(DEMOS) else tuple(args.demos)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    load = os.getloadavg()
    t0 = time.perf_counter()
    raw = run(
        tasks=task_defs(tasks, demos, args.quick),
        losses=losses,
        seeds=range(args.first_seed, args.first_seed + seeds),
        quick_mode=args.quick,
        jobs=args.jobs,
    )
    config = {
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
    target = _report.results_dir(out_dir)
    fig = figure(payload, target / f"{NAME}.png")
    text = markdown(payload, fig.name if out_dir else f"results/{fig.name}")  # README's link
    path = _report.write(NAME, payload, text, out_dir=out_dir)
    print(text)
    print(f"results: {path}")


if __name__ == "__main__":
    main()
