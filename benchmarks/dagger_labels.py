"""What the expert's labels say at the learner's states: why DAgger trailed BC at equal
labels on Meta-World's object tasks, and the schedule that mends it (issue 46).

On MT10 (``metaworld_mt10.py``, 5 demonstrations, ``mse``) BC given as many expert labels
as DAgger's last fit saw beat DAgger, by most on push and pick-place. This run looks at
the labels themselves. Every cell is ``metaworld_mt10.py``'s (its protocol: the same
demonstrations, fits and held-out starts), once with DAgger's beta at 0 in every relabel
round (the learner drives: that benchmark's protocol) and once with Ross et al.'s schedule
(``beta_i = 0.5 ** (i - 1)``: the expert drives relabel round 1, a fair coin round 2;
``imitrl dagger --beta-decay 0.5``), each with episodes cut at that benchmark's 150 steps
and at Meta-World's own 500 (where the experts' success is their own). DAgger's rows are sorted by where the hand is
against the object (``obs[0:3]`` the hand, ``obs[4:7]`` the first object, as every v3
task lays out its observation):

* near the object: the hand within ``NEAR_XY`` of it across the table and ``NEAR_Z``
  above it, where a push or a grasp begins;
* a retreat: a label there that lifts the hand (``z > RETREAT_Z``) with the gripper open
  (``grip <= 0``): the scripted expert's answer to a hand that came down off its mark,
  "go back up and approach again" (its push and pick-place policies descend only within
  2 cm of the object across the table, ``metaworld/policies/sawyer_push_v3_policy.py``).

Reported: per task, arm and round (0: the demonstrations) the rows, the rows near the object
and the retreats among them, summed over seeds; per task and schedule the success of BC,
DAgger and BC at DAgger's queries (pooled over seeds, 95% Wilson); across MT10 the
expert-normalised IQM of each with stratified bootstrap intervals, and DAgger minus BC at
DAgger's queries paired by task and seed (mean, 95% t interval).

    python benchmarks/dagger_labels.py --jobs 2   # full run, refreshes the README block
    python benchmarks/dagger_labels.py --quick    # smoke run, into a temporary directory
"""

from __future__ import annotations

import os
import sys
import time
from collections import defaultdict
from dataclasses import replace
from pathlib import Path

from tensordict import TensorDictBase

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _metaworld_suite
import _report
from _loss_functions.run import run
from _metaworld_report import against_matched, fmt_rate, groups, normalised, pooled
from imitrl import keys
from imitrl.envs.metaworld import MT10
from imitrl.evaluation.aggregate import iqm, stratified_bootstrap
from metaworld_mt10 import PROTOCOL

NAME = "dagger_labels"
ARMS = {
    "beta 0": (None, 150),
    "Ross et al. (p = 0.5)": (0.5, 150),
    "beta 0, 500 steps": (None, None),
    "Ross et al., 500 steps": (0.5, None),
}
"""each run's label, its ``Protocol.beta_decay`` and its episode cut (None: Meta-World's
own 500 steps)"""
LABELLED = ("reach-v3", "push-v3", "pick-place-v3")
"""the tasks whose labels the first table shows (reach: no object to grasp, the control)"""
SEEDS, DEMOS, REPS = 5, 5, 2000
NEAR_XY, NEAR_Z, RETREAT_Z = 0.06, 0.10, 0.5
"""metres across the table and above the object; a normalised action's z component"""
ALGORITHMS = (("bc", "BC"), ("dagger", "DAgger"), ("bc_matched", "BC at DAgger's queries"))


def label_phases(rows: TensorDictBase) -> dict:
    """Per round: rows, rows near the object, retreats among them (module docstring)."""
    obs, label = rows.get(keys.OBSERVATION), rows.get(keys.EXPERT_ACTION)
    rounds = rows.get(keys.ROUND)
    xy = (obs[:, 0:2] - obs[:, 4:6]).norm(dim=-1)
    near = (xy < NEAR_XY) & (obs[:, 2] - obs[:, 6] < NEAR_Z)
    retreat = near & (label[:, 2] > RETREAT_Z) & (label[:, 3] <= 0)
    return {
        str(r): {"rows": int((rounds == r).sum()), "near": int((near & (rounds == r)).sum()),
                 "retreats": int((retreat & (rounds == r)).sum())}
        for r in rounds.unique().tolist()
    }  # fmt: skip


def _label_rows(label: str, raw: dict) -> list[list]:
    out = []
    for task in (f"{t}/{DEMOS}demo" for t in LABELLED):
        counts: dict = defaultdict(lambda: defaultdict(int))
        for r in raw["rows"]:
            if r["task"] == task and r["algorithm"] == "dagger":
                for rnd, c in r["probe"].items():
                    for k, v in c.items():
                        counts[rnd][k] += v
        for rnd, c in sorted(counts.items(), key=lambda kv: int(kv[0])):
            share = f"{c['retreats'] / c['near']:.2f}" if c["near"] else "-"
            out.append([task.split("/")[0], label, rnd, c["rows"], c["near"],
                        f"{c['retreats']} ({share})"])  # fmt: skip
    return out


def _aggregate(label: str, payload: dict) -> list[list]:
    scores = normalised(payload)
    out = []
    for algorithm, name in ALGORITHMS:
        i = stratified_bootstrap(scores[("mse", DEMOS, algorithm)], iqm, reps=REPS)
        out.append([label, name, f"{i.point:.2f} [{i.low:.2f}, {i.high:.2f}]"])
    (d,) = [f for f in against_matched(payload["rows"]) if f["group"][0] == "DAgger"]
    mean, lo, hi = d["diff"]
    out.append([label, "DAgger - BC at DAgger's queries (paired, 95% t)",
                f"{mean:+.2f} [{lo:+.2f}, {hi:+.2f}] over {d['pairs']} pairs; tasks above / "
                f"below 0: {d['wins']} / {d['losses']}"])  # fmt: skip
    return out


def markdown(
    runs: dict[str, dict], wall: float, load: tuple[float, float], *, quick: bool = False
) -> str:
    """The README block of ``runs``; a ``quick`` one says first that it is a smoke run (a
    review: its header named the full protocol's command, tasks and seeds)."""
    tasks = next(iter(runs.values()))["config"]["tasks"]
    smoke = (
        f"Smoke run (`--quick`: {len(tasks)} task(s), 1 seed, {len(runs)} schedules, the quick "
        "budget): it shows the script runs, nothing more; the committed protocol reads:\n\n"
        if quick
        else ""
    )
    head = smoke + (
        f"`python benchmarks/dagger_labels.py --jobs 2` ({wall / 60:.1f} min, 1 torch thread a "
        f"process, 1-min load {load[0]:.2f} to {load[1]:.2f}): MT10 at `metaworld_mt10.py`'s "
        f"protocol ({DEMOS} demonstrations, 2 relabel rounds x 3 learner episodes, warm start, "
        f"5 held-out episodes), `mse`, {SEEDS} seeds, with DAgger's beta at 0 and with Ross et "
        "al.'s schedule, episodes cut at that benchmark's 150 steps and at Meta-World's own "
        f"500 (the expert's own success). Near the object: the hand within {NEAR_XY} m of "
        f"it across the table and {NEAR_Z} m above it; a retreat: a label there with z > "
        f"{RETREAT_Z} and the gripper open. Round 0: the demonstrations."
    )
    labels = [row for label, raw in runs.items() for row in _label_rows(label, raw)]
    grouped = {label: groups(raw) for label, raw in runs.items()}  # (cells, expert)
    success = [
        [task, label]
        + [fmt_rate(*pooled(cells[(task, DEMOS, "mse", a)])) for a, _ in ALGORITHMS]
        + [fmt_rate(*pooled(expert[(task, DEMOS)]))]
        for task in next(iter(runs.values()))["config"]["tasks"]
        for label, (cells, expert) in grouped.items()
    ]
    aggregate = [row for label, raw in runs.items() for row in _aggregate(label, raw)]
    return "\n\n".join([
        head,
        _report.table(["task", "schedule", "round", "rows", "near the object",
                       "retreats (share of near)"], labels),
        "Success per task (pooled over seeds, 95% Wilson):",
        _report.table(["task", "schedule", *(n for _, n in ALGORITHMS), "expert"], success),
        f"Across MT10: IQM of expert-normalised success (95% stratified bootstrap, {REPS} "
        "replicates), and DAgger against BC at its queries on the same task and seed:",
        _report.table(["schedule", "algorithm", "IQM / paired difference"], aggregate),
    ])  # fmt: skip


def main(argv: list[str] | None = None) -> dict:
    parser = _report.parser(__doc__)
    parser.add_argument("--jobs", type=int, default=1, help="worker processes, one thread each")
    parser.add_argument(
        "--render", type=Path, default=None, metavar="JSON",
        help="re-render a results file's README block from its rows; nothing is run",
    )  # fmt: skip
    args = parser.parse_args(argv)
    if args.jobs < 1:
        parser.error(f"--jobs must be >= 1, got {args.jobs}")
    if args.render is not None:  # --quick or --out: printed only, the README untouched
        payload = _report.read_results(args.render, parser.error)

        def render(out: Path | None) -> str:
            md = markdown(
                payload["runs"], payload["wall_seconds"], tuple(payload["load_average"]),
                quick=bool(payload.get("config", {}).get("quick")),
            )  # fmt: skip
            if out is None:
                _report.update_readme(NAME, md)
            return md

        out = _report.destination(NAME, quick=args.quick, out=args.out)
        print(_report.render_safely(render, out, parser.error, str(args.render)))
        return payload
    out_dir = _report.destination(NAME, quick=args.quick, out=args.out)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    tasks = LABELLED[:1] if args.quick else MT10
    load0, t0 = os.getloadavg()[0], time.perf_counter()
    runs = {}
    # --quick: its protocol cuts every episode at 30 steps, so the 500-step arms would repeat
    arms = {k: ARMS[k] for k in list(ARMS)[:2]} if args.quick else ARMS
    for label, (decay, cut) in arms.items():
        protocol = replace(PROTOCOL, beta_decay=decay, max_episode_steps=cut)
        raw = run(
            tasks=_metaworld_suite.task_defs(protocol, tasks, (DEMOS,), args.quick),
            losses=["mse"], seeds=1 if args.quick else SEEDS, quick_mode=args.quick,
            jobs=args.jobs, probe=label_phases,
        )  # fmt: skip
        runs[label] = {
            "config": {"tasks": list(tasks), "losses": ["mse"], "demos": [DEMOS]},
            "rows": raw["rows"], "references": raw["references"], "beta_decay": decay, "max_episode_steps": cut,
        }  # fmt: skip
    wall = time.perf_counter() - t0
    load = (load0, os.getloadavg()[0])
    md = markdown(runs, wall, load, quick=args.quick)
    print(md)
    payload = {"config": {"seeds": 1 if args.quick else SEEDS, "demos": DEMOS, "quick": args.quick,
                          "protocol": str(PROTOCOL)},
               "runs": runs, "wall_seconds": wall, "load_average": list(load)}  # fmt: skip
    print("results:", _report.write(NAME, payload, md, out_dir=out_dir))
    return payload


if __name__ == "__main__":
    main()
