"""DAgger, a gated expert and HG-DAgger: success against expert labels and interventions.

HG-DAgger (Kelly et al., ICRA 2019) lets a supervisor take over when it judges the
learner unsafe and labels only those frames (LeRobot's DAgger rollouts record them with
``intervention=True``). Three ways to spend an expert, from the same demonstrations:

* ``dagger``: beta 0, the learner drives, the expert labels every visited state;
* ``gated``: the expert takes over where the learner's action is farther than ``tau``
  from its own (:class:`~imitrl.policies.gate.ExpertGate`), every visited state labelled;
* ``hg_dagger``: the same gate, only the frames the expert took over labelled
  (``DAggerConfig(label="interventions")``).

``tau`` is a quarter of the action box's diagonal. Tasks: Pendulum (the scripted swing-up;
mean return) and five MT10 tasks at metaworld_mt10.py's protocol before b0f27fb (beta 0,
150-step episodes; success). A fresh ``mse`` learner each round. Reported per task and
method: success (or return) of the last learner with 95% intervals over the pooled
held-out episodes, the expert labels the relabel rounds added, and the interventions
(frames the expert drove), means over seeds.

    python benchmarks/gated_dagger.py            # full run, refreshes the README block
    python benchmarks/gated_dagger.py --quick    # smoke run, into a temporary directory
"""

from __future__ import annotations

import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from torchrl.envs.utils import ExplorationType

import _report
from chunk_labels import METAWORLD, held_out_episodes, scored_by_success, task_setup
from imitrl.algorithms import BCConfig, DAggerConfig, dagger
from imitrl.algorithms.dagger import EnvSource
from imitrl.data import DemonstrationBuffer
from imitrl.evaluation.evaluate import mean_ci, wilson_interval
from imitrl.learners import build
from imitrl.policies.gate import ExpertGate
from imitrl.runtime import rollout_episodes

NAME = "gated_dagger"
METHODS = ("dagger", "gated", "hg_dagger")


@dataclass(frozen=True)
class Config:
    tasks: tuple = ("pendulum", *(f"metaworld/{t}" for t in METAWORLD))
    seeds: int = 5
    mw_seeds: int = 3
    quick: bool = False


QUICK = Config(tasks=("pendulum", "metaworld/reach-v3"), seeds=1, mw_seeds=1, quick=True)


def _budget(task: str, cfg: Config) -> dict:
    if cfg.quick:
        return dict(seeds=1, demos=1, rounds=2, episodes=1, steps=5, batch=32, hidden=(16,),
                    lr=None, eval=2)  # fmt: skip
    if task.startswith("metaworld/"):  # metaworld_mt10.py's protocol before b0f27fb
        return dict(seeds=cfg.mw_seeds, demos=5, rounds=3, episodes=3, steps=320, batch=256,
                    hidden=(128, 128), lr=3e-3, eval=5)  # fmt: skip
    return dict(seeds=cfg.seeds, demos=3, rounds=4, episodes=3, steps=400, batch=64,
                hidden=(64, 64), lr=None, eval=40)  # fmt: skip


def cell(task: str, method: str, seed: int, cfg: Config) -> dict:
    b = _budget(task, cfg)
    torch.manual_seed(seed)
    env, expert, limit, make = task_setup(task, seed)
    buffer = DemonstrationBuffer(action_spec=env.action_spec_unbatched)
    buffer.extend(rollout_episodes(env, expert, b["demos"], max_steps=limit))
    spec = env.action_spec_unbatched
    tau = 0.25 * float((spec.space.high - spec.space.low).norm())
    gate = None if method == "dagger" else ExpertGate(tau)
    label = "interventions" if method == "hg_dagger" else "all"
    result = dagger(
        EnvSource(env, exploration=ExplorationType.DETERMINISTIC, max_steps=limit),
        expert,
        lambda: build("mse", env, hidden=b["hidden"], seed=seed, lr=b["lr"]),
        buffer,
        DAggerConfig(rounds=b["rounds"], episodes_per_round=b["episodes"], gate=gate, label=label,
                     bc=BCConfig(num_steps=b["steps"], batch_size=b["batch"], seed=seed), seed=seed),
    )  # fmt: skip
    returns, successes = held_out_episodes(
        make(10_000 + seed), result.learner.policy, b["eval"], seed, limit
    )
    rounds = result.rounds[:-1]
    labels = sum(r.rows_collected for r in rounds)
    driven = sum(r.interventions or 0 for r in rounds) if gate is not None else 0
    return {"task": task, "method": method, "seed": seed, "tau": tau, "returns": returns,
            "successes": successes, "labels": labels, "interventions": driven}  # fmt: skip


def summarise(cells: list[dict]) -> list[dict]:
    rows = []
    for task in dict.fromkeys(c["task"] for c in cells):
        for method in METHODS:
            mine = [c for c in cells if (c["task"], c["method"]) == (task, method)]
            if not mine:
                continue
            returns = torch.tensor([r for c in mine for r in c["returns"]])
            n, k = returns.numel(), sum(c["successes"] for c in mine)
            row = {"task": task, "method": method, "episodes": n, "return": mean_ci(returns),
                   "labels": sum(c["labels"] for c in mine) / len(mine),
                   "interventions": sum(c["interventions"] for c in mine) / len(mine)}  # fmt: skip
            if scored_by_success(task):
                lo, hi = wilson_interval(k, n)
                row["success"] = (k / n, lo, hi)
            rows.append(row)
    return rows


def markdown(rows: list[dict], wall: float) -> str:
    header = ["task", "method", "success (95% Wilson)", "mean return (95% t)",
              "expert labels (mean/seed)", "interventions (mean/seed)"]  # fmt: skip
    body = []
    for r in rows:
        s = r.get("success")
        body.append([r["task"], r["method"], "-" if s is None else f"{s[0]:.2f} [{s[1]:.2f}, {s[2]:.2f}]",
                     _report.fmt_ci(tuple(r["return"]), digits=1), f"{r['labels']:.0f}",
                     "-" if r["method"] == "dagger" else f"{r['interventions']:.0f}"])  # fmt: skip
    return _report.section(
        "DAgger, a gated expert and HG-DAgger (gated_dagger.py)",
        f"`python benchmarks/gated_dagger.py` ({wall / 60:.1f} min, 1 torch thread): Pendulum "
        "(5 seeds, 3 demonstrations, 3 relabel rounds x 3 episodes, 400 steps x batch 64, "
        "widths 64-64, 40 held-out episodes per seed) and five MT10 tasks at "
        "metaworld_mt10.py's protocol (3 seeds, 5 demonstrations, 2 relabel rounds x 3 "
        "episodes, 320 steps x batch 256, widths 128-128 at lr 3e-3, 5 held-out episodes of at "
        "most 150 steps); a fresh mse learner each round; gate tau = a quarter of the action "
        "box's diagonal.\n\n"
        + _report.table(header, body)
        + f"\n\n![success against labels](results/{NAME}.png)\n",
    )


def figure(rows: list[dict], path: Path) -> None:
    import matplotlib.pyplot as plt

    tasks = list(dict.fromkeys(r["task"] for r in rows))
    fig, axes = _report.panels(len(tasks), 3, (4.4, 3.3))
    for ax, task in zip(axes, tasks):
        score = "success" if scored_by_success(task) else "return"
        for r in (x for x in rows if x["task"] == task):
            mid, lo, hi = r[score]
            ax.errorbar([r["labels"]], [mid], yerr=[[mid - lo], [hi - mid]], fmt="o", capsize=4,
                        label=r["method"])  # fmt: skip
        ax.set_xlabel("expert labels added (mean per seed)")
        ax.set_ylabel("success (95% Wilson)" if score == "success" else "mean return (95% t)")
        if score == "success":
            ax.set_ylim(-0.03, 1.05)
        ax.set_title(task.removeprefix("metaworld/"), fontsize=10)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict:
    args = _report.parser(__doc__).parse_args(argv)
    out_dir = _report.destination(NAME, quick=args.quick, out=args.out)
    cfg = QUICK if args.quick else Config()
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    cells = []
    for task in cfg.tasks:
        for seed in range(_budget(task, cfg)["seeds"]):
            for method in METHODS:
                c = cell(task, method, seed, cfg)
                cells.append(c)
                print(f"{task} {method} seed {seed}: successes {c['successes']}/{len(c['returns'])}, "
                      f"labels {c['labels']}, interventions {c['interventions']}",
                      file=sys.stderr, flush=True)  # fmt: skip
    wall = time.perf_counter() - t0
    rows = summarise(cells)
    figure(rows, _report.results_dir(out_dir) / f"{NAME}.png")
    md = markdown(rows, wall)
    print(md)
    payload = {"config": asdict(cfg), "summary": rows, "cells": cells, "wall_seconds": wall}
    print("results:", _report.write(NAME, payload, md, out_dir=out_dir))
    return payload


if __name__ == "__main__":
    main()
