"""Each loss at its own budget on Meta-World MT10: BC's fit steps per loss, its training
curve, and success against fit time.

``metaworld_mt10.py`` gives every loss the same 320 fit steps at batch 256, which is a
fair query budget but not a fair training budget: Diffusion Policy's U-Net
(``diffusion_unet``, a denoising loss at a random noise level every step) learns far
slower per step than an MSE regressor. Here each loss trains BC on the same 5
demonstrations of each MT10 task at a ladder of fit steps of its own (:data:`BUDGETS`:
the steps, the batch and why), its recipe's schedule at every rung (Diffusion Policy:
warm-up and cosine decay, its EMA), one cell of ``loss_functions.py``'s machinery per
(task, loss, rung, seed); each fit's training loss is kept as a curve of
:data:`CURVE_POINTS` window means. Reported: success per task (Wilson intervals over the
seeds' pooled episodes, the expert's beside it on the same held-out starts), the
expert-normalised IQM per (loss, rung) with stratified bootstrap intervals against the
median fit seconds, how much the loss still fell over the last fifth of each fit, and
the paired difference of each loss's top rung against ``mse``'s (issue 46: "each loss at
its own budget ... with the loss's training curve showing it has converged").

    python benchmarks/metaworld_budgets.py --jobs 2    # full run, refreshes benchmarks/README.md
    python benchmarks/metaworld_budgets.py --quick     # smoke run, into a temporary directory
    python benchmarks/metaworld_budgets.py --render results/metaworld_budgets.json
    python benchmarks/metaworld_budgets.py --losses diffusion_unet --steps 4000 --out /tmp/r4
    python benchmarks/metaworld_budgets.py --merge results/metaworld_budgets.json \\
        /tmp/r4/metaworld_budgets.json    # one report of runs of disjoint rungs

Runnable in parts (``--losses``, ``--steps``, ``--tasks``) and merged (``--merge``): a cell's digits
depend on its task, loss, rung and seed alone.
"""

from __future__ import annotations

import importlib
import json
import os
import re
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _report
from _loss_functions.merge import join_cells
from _loss_functions.run import execute
from _metaworld_budgets_report import figure, markdown
from _metaworld_suite import metaworld_task
from imitrl.algorithms import BCConfig
from imitrl.envs.metaworld import MT10
from metaworld_mt50 import PROTOCOL as MT50_PROTOCOL

NAME = "metaworld_budgets"
QUICK_LOSSES = ("mse", "diffusion_unet")
"""``--quick``'s losses without ``--losses``: one of each kind of network is the smoke run"""
RECIPES = "_metaworld_recipes"
"""the module whose import registers ``diffusion_unet_mw``: imported by a run alone, so
that importing this script (a test, a merge) leaves the loss registry as it was"""
CURVE_POINTS = 40
"""window means a fit's training loss is kept as (``Protocol.curve_points``)"""


@dataclass(frozen=True)
class Budget:
    """One loss's fits: a ladder of gradient steps at one batch size."""

    steps: tuple[int, ...]
    """the rungs, fewest first; the last is the loss's own budget"""
    batch: int
    """rows a step"""


BUDGETS = {
    "mse": Budget(steps=(320, 2000), batch=256),
    "diffusion_unet": Budget(steps=(500, 2000, 4000, 8000), batch=64),
    "diffusion_unet_mw": Budget(steps=(2000, 4000), batch=64),
}
"""Per loss. ``mse``: ``metaworld_mt10.py``'s 320 steps and ``metaworld_mt50.py``'s 2000
(its network, 256-256 at lr 1e-3, chosen there). ``diffusion_unet``: the registry's CPU
widths (32-64-128, 1.2M parameters, lr 1e-3) at batch 64 (the paper's image configs and
LeRobot's Diffusion Policy recipe; its state configs take 256, 2.5 times the step time on
one CPU thread: ``diffusion_policy.py``), 2000 steps (about 70 ms a step, 2.5 min a fit),
a quarter of it, twice it (its 2000-step training loss still fell 27% over its last
fifth) and four times it (its 4000-step loss still fell 38%). The training curves and
the success at each rung say whether the last rung has converged. ``diffusion_unet_mw``:
the same network, recipe and batch at the horizons of the published Meta-World
Diffusion Policy (``T_p = 4``, executing ``T_a = 3``: :mod:`_metaworld_recipes`), at
``diffusion_unet``'s two rungs that did best."""

PROTOCOL = replace(
    MT50_PROTOCOL,
    demo_episodes=5,
    rounds=1,
    round_steps=None,
    matched=False,
    beta_decay=None,
    eval_episodes=5,
    curve_points=CURVE_POINTS,
)
"""BC alone from 5 demonstrations (``metaworld_mt10.py``'s larger count), episodes at
Meta-World's own 500-step limit (the expert's own success), 5 held-out episodes a seed;
each cell's fit steps and batch from :data:`BUDGETS`."""
SEEDS = 3


def rung_name(task: str, loss: str, steps: int) -> str:
    """A cell's task name: ``<task>/<loss>/<steps>``."""
    return f"{task}/{loss}/{steps}"


def chosen(losses: tuple[str, ...], steps: tuple[int, ...] | None) -> dict[str, Budget]:
    """:data:`BUDGETS` of ``losses``, each with the rungs in ``steps`` alone (all without
    ``steps``; ValueError where a loss keeps none)."""
    out = {}
    for loss in losses:
        budget = BUDGETS[loss]
        kept = budget.steps if steps is None else tuple(s for s in budget.steps if s in steps)
        if not kept:
            raise ValueError(f"{loss} has no rung in --steps {list(steps or ())}: {budget.steps}")
        out[loss] = replace(budget, steps=kept)
    return out


def plan(budgets: dict[str, Budget], tasks: tuple[str, ...], seeds: range, quick: bool):
    """The (task definition, loss, seed, quick) cells, one per rung of ``budgets``, and
    the (task, seed, quick) references, one per task and seed."""
    cells, refs = [], []
    for task in tasks:
        for seed in seeds:
            refs.append((metaworld_task(task, task, PROTOCOL), seed, quick))
        for loss, budget in budgets.items():
            for steps in budget.steps:
                bc = BCConfig(num_steps=steps, batch_size=budget.batch)
                defn = metaworld_task(task, rung_name(task, loss, steps), replace(PROTOCOL, bc=bc))
                cells += [(defn, loss, seed, quick) for seed in seeds]
    return cells, refs


def main(argv: list[str] | None = None) -> None:
    p = _report.parser(__doc__)
    p.add_argument("--tasks", nargs="+", default=list(MT10), choices=list(MT10))
    p.add_argument("--losses", nargs="+", default=None, choices=list(BUDGETS),
                   help="default: every loss (--quick: mse and diffusion_unet, a smoke run "
                   "of the machinery)")  # fmt: skip
    p.add_argument("--steps", nargs="+", type=int, default=None,
                   help="run these rungs of each loss's ladder alone (default: every rung)")  # fmt: skip
    p.add_argument("--seeds", type=int, default=SEEDS)
    p.add_argument("--jobs", type=int, default=1, help="worker processes, one thread each")
    p.add_argument("--render", type=Path, default=None, metavar="JSON",
                   help="re-render a results file's report from its rows; nothing is run")  # fmt: skip
    p.add_argument("--merge", nargs="+", type=Path, default=None, metavar="JSON",
                   help="results files of runs of disjoint rungs: one report of them all")  # fmt: skip
    args = p.parse_args(argv)
    for flag in ("seeds", "jobs"):
        if getattr(args, flag) < 1:
            p.error(f"--{flag} must be >= 1, got {getattr(args, flag)}")
    out = _report.destination(NAME, quick=args.quick, out=args.out)  # --quick: never results/
    if args.render is not None:
        payload = _report.read_results(args.render, p.error)
        _report.render_safely(lambda o: _report_of(payload, o), out, p.error, str(args.render))
        return
    if args.merge is not None:
        runs = [{**_report.read_results(f, p.error), "source": f.name} for f in args.merge]
        try:
            merged = merge(runs)
        except (ValueError, KeyError, TypeError) as err:  # files that do not join: one line
            p.error(_report.merge_refused(err))
        _report.render_safely(lambda o: _report_of(merged, o), out, p.error, "--merge")
        return
    if args.losses is None:
        args.losses = [*QUICK_LOSSES] if args.quick else list(BUDGETS)
    try:
        budgets = chosen(tuple(args.losses), None if args.steps is None else tuple(args.steps))
    except ValueError as err:
        p.error(str(err))
    out_dir = _report.destination(NAME, quick=args.quick, out=args.out)
    every = args.tasks == list(MT10)
    tasks = ("reach-v3",) if args.quick and every else tuple(args.tasks)
    seeds = range(1 if args.quick else args.seeds)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    load, t0 = os.getloadavg(), time.perf_counter()
    cells, refs = plan(budgets, tasks, seeds, args.quick)
    importlib.import_module(RECIPES)  # here, and in every worker: its entry registered
    rows, references = execute(cells, refs, jobs=args.jobs, modules=(RECIPES,))
    payload = {
        "config": {
            "tasks": list(tasks),
            "losses": list(args.losses),
            "seeds": len(seeds),
            "jobs": args.jobs,
            "quick": args.quick,
            "budgets": {k: {"steps": list(b.steps), "batch": b.batch} for k, b in budgets.items()},
            "protocol": json.loads(json.dumps(asdict(PROTOCOL), default=str)),
        },
        "rows": rows,
        "references": references,
        "wall_seconds": time.perf_counter() - t0,
        "load_average_start": list(load),
        "load_average_end": list(os.getloadavg()),
        "command": " ".join(
            ["metaworld_budgets.py", *(argv if argv is not None else sys.argv[1:])]
        ),
    }
    _report_of(payload, out_dir)


def _without_out(command: str) -> str:
    """``command`` without its ``--out`` folder (a path of one machine)."""
    return re.sub(r" --out(=| )\S+", "", command)


def merge(runs: list[dict]) -> dict:
    """One payload of ``runs``' rungs (ValueError where two runs disagree on the tasks,
    the seeds, the protocol, a loss's batch or an expert reference, or run the same cell:
    the code changed between them, or the rungs overlap)."""
    if len(runs) < 2:
        raise ValueError("--merge needs at least two results files")
    first = runs[0]["config"]
    budgets: dict[str, dict] = {}
    for k, part in enumerate(runs):
        config = part["config"]
        for key in ("seeds", "protocol"):
            if config[key] != first[key]:
                raise ValueError(f"run {k} has another {key} than run 0: {config[key]}")
        for loss, b in config["budgets"].items():
            have = budgets.setdefault(loss, {"steps": [], "batch": b["batch"]})
            if have["batch"] != b["batch"]:
                raise ValueError(f"run {k} fits {loss} at batch {b['batch']}, not {have['batch']}")
            have["steps"] = sorted({*have["steps"], *b["steps"]})
    rows, refs = join_cells(runs)
    named = {t for r in runs for t in r["config"]["tasks"]}
    if named - set(MT10):
        raise ValueError(f"tasks outside MT10: {sorted(named - set(MT10))}")
    tasks = [t for t in MT10 if t in named]
    _check_complete(rows, tasks, first["seeds"], budgets)
    losses = [loss for loss in BUDGETS if loss in budgets]
    return {
        "config": {
            **first,
            "tasks": tasks,
            "losses": losses,
            "jobs": "merged",
            "budgets": {loss: budgets[loss] for loss in losses},
        },
        "rows": rows,
        "references": refs,
        "wall_seconds": sum(r["wall_seconds"] for r in runs),
        "load_average_start": runs[0]["load_average_start"],
        "load_average_end": runs[-1]["load_average_end"],
        "merged_from": [line for k, r in enumerate(runs) for line in _parts(k, r)],
    }


def _parts(k: int, run: dict) -> list[str]:
    """How ``run`` (the ``k``-th merged) was made: its command, wall and load, or the parts
    of an earlier merge it holds."""
    if "merged_from" in run:
        return list(run["merged_from"])
    command = _without_out(run.get("command", run.get("source", f"run {k}")))
    load = f"load {run['load_average_start'][0]:.2f} to {run['load_average_end'][0]:.2f}"
    jobs = run["config"]["jobs"]
    return [f"{command}: {run['wall_seconds'] / 60:.1f} min with {jobs} process(es), {load}"]


def _check_complete(rows: list[dict], tasks: list[str], seeds: int, budgets: dict) -> None:
    """ValueError naming the first (task, loss, rung) whose seeds the merged ``rows`` lack:
    parts may split the tasks (``--tasks``) but must together cover every rung on each."""
    have = {(r["task"], r["seed"]) for r in rows}
    for task in tasks:
        for loss, budget in budgets.items():
            for steps in budget["steps"]:
                name = rung_name(task, loss, steps)
                missing = [s for s in range(seeds) if (name, s) not in have]
                if missing:
                    raise ValueError(f"no run holds {name} at seed(s) {missing}")


def _report_of(payload: dict, out: Path | None) -> None:
    fig = figure(payload, _report.results_dir(out) / f"{NAME}.png")
    text = markdown(payload, fig.name if out else f"results/{fig.name}")
    print(text)
    print(f"results: {_report.write(NAME, payload, text, out_dir=out)}")


if __name__ == "__main__":
    main()
