"""Chunk-aware DAgger: a chunked learner's relabelled rows labelled by masking (the
expert's label at each visited state, the rest of the chunk masked) or by the expert's
plan (its own next H actions from each visited state, played on the simulator and
undone: ``imitrl dagger --chunk-labels plan``), issue 46.

Tasks: the two-way obstacle task (``imitrl.envs.multimodal``: an expert with a hidden
intent per episode, whose plan from a visited state follows that intent) and Pendulum
(the scripted swing-up). Per task, learner (``mse_chunk``, ``flow_chunk``), seed and
labelling: ``demos`` expert episodes, then DAgger (round 0 = BC; ``rounds - 1`` relabel
rounds of ``episodes`` learner episodes, beta 0, a fresh learner each round, ``steps``
fit steps at batch 64); the last learner evaluated on ``eval`` held-out episodes (the
same starts for both labellings, and for the expert). Reported: success (two-way) or
mean return (Pendulum) with 95% intervals over the pooled episodes, and the rows each
last fit saw.

    python benchmarks/chunk_labels.py            # full run, refreshes the README block
    python benchmarks/chunk_labels.py --quick    # smoke run, into a temporary directory
"""

from __future__ import annotations

import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from torchrl.envs.utils import ExplorationType

import _report
from imitrl.algorithms import BCConfig, DAggerConfig, dagger
from imitrl.algorithms.dagger import EnvSource
from imitrl.algorithms.expert_plan import with_plans
from imitrl.data import DemonstrationBuffer
from imitrl.envs import make_env
from imitrl.envs.multimodal import TwoWayObstacleEnv, two_way_expert
from imitrl.envs.success import SUCCESS, reported_success
from imitrl.evaluation.evaluate import mean_ci, wilson_interval
from imitrl.experts import pendulum_expert
from imitrl.learners import build
from imitrl.runtime import rollout_episodes

NAME = "chunk_labels"
TASKS = ("two_way", "pendulum")
LEARNERS = ("mse_chunk", "flow_chunk")
LABELS = ("mask", "plan")
METAWORLD = ("reach-v3", "push-v3", "pick-place-v3", "door-open-v3", "drawer-open-v3")
"""MT10 tasks measured (the first five of MT10's list)"""
METAWORLD_STEPS = 150
"""metaworld_mt10.py's episode cut before b0f27fb (it now runs to Meta-World's 500)"""


@dataclass(frozen=True)
class Config:
    """The whole run: the classic tasks' budget, and MT10's protocol for Meta-World's."""

    seeds: int = 5
    demos: int = 3
    rounds: int = 4
    episodes: int = 3
    steps: int = 400
    eval: int = 40
    tasks: tuple = TASKS
    learners: tuple = LEARNERS
    metaworld: tuple = METAWORLD
    mw_seeds: int = 3
    """Meta-World: metaworld_mt10.py's protocol before b0f27fb (beta 0; 5 demonstrations,
    2 relabel rounds of 3 episodes, 320 steps at batch 256, widths 128-128 at lr 3e-3, 5
    held-out episodes of at most 150 steps), a fresh learner each round as above"""


@dataclass(frozen=True)
class Budget:
    """One task's budget."""

    seeds: int
    demos: int
    rounds: int
    episodes: int
    steps: int
    batch: int
    hidden: tuple
    lr: float | None
    eval: int


def budget(task: str, cfg: Config) -> Budget:
    if task.startswith("metaworld/"):
        quick = cfg.steps < 10
        return Budget(cfg.mw_seeds, 1 if quick else 5, cfg.rounds if quick else 3,
                      cfg.episodes, cfg.steps if quick else 320, 256, (128, 128), 3e-3,
                      cfg.eval if quick else 5)  # fmt: skip
    return Budget(cfg.seeds, cfg.demos, cfg.rounds, cfg.episodes, cfg.steps, 64, (64, 64),
                  None, cfg.eval)  # fmt: skip


QUICK = Config(seeds=1, demos=1, rounds=2, episodes=1, steps=5, eval=2, tasks=TASKS,
               learners=("mse_chunk",), metaworld=("reach-v3",), mw_seeds=1)  # fmt: skip


def task_setup(task: str, seed: int):
    """``(env, expert, episode bound, make(seed) -> held-out env)`` of ``task``."""
    if task == "two_way":
        env, expert, limit = TwoWayObstacleEnv(seed=seed), two_way_expert(), 40
        return env, expert, limit, lambda s: TwoWayObstacleEnv(seed=s)
    if task.startswith("metaworld/"):  # MT10's protocol: 150-step episodes, success
        from imitrl.experts import metaworld_expert

        limit = METAWORLD_STEPS
        task_id = task.removeprefix("metaworld/")
    else:
        limit = 100

    def make(s: int):
        return make_env(task if limit == METAWORLD_STEPS else "Pendulum-v1", seed=s,
                        max_episode_steps=limit)  # fmt: skip

    expert = metaworld_expert(task_id) if limit == METAWORLD_STEPS else pendulum_expert()
    return make(seed), expert, limit, make


def cell(task: str, learner: str, labels: str, seed: int, cfg: Config) -> dict:
    """One DAgger run and its last learner's evaluation."""
    b = budget(task, cfg)
    torch.manual_seed(seed)
    env, expert, limit, make = task_setup(task, seed)
    demos = rollout_episodes(env, expert, b.demos, max_steps=limit)
    buffer = DemonstrationBuffer(action_spec=env.action_spec_unbatched)
    plans = labels == "plan"

    def make_learner():
        return build(learner, env, hidden=b.hidden, seed=seed, lr=b.lr)

    buffer.extend(with_plans(demos, make_learner().horizon) if plans else demos)
    source = EnvSource(env, exploration=ExplorationType.DETERMINISTIC, max_steps=limit,
                       plans=plans)  # fmt: skip
    result = dagger(
        source,
        expert,
        make_learner,
        buffer,
        DAggerConfig(rounds=b.rounds, episodes_per_round=b.episodes,
                     bc=BCConfig(num_steps=b.steps, batch_size=b.batch, seed=seed), seed=seed),
    )  # fmt: skip
    returns, successes = held_out_episodes(
        make(10_000 + seed), result.learner.policy, b.eval, seed, limit
    )
    return {"task": task, "learner": learner, "labels": labels, "seed": seed,
            "rows": [r.rows_trained for r in result.rounds], "returns": returns,
            "successes": successes}  # fmt: skip


def expert_cell(task: str, seed: int, cfg: Config) -> dict:
    """The expert on the same held-out starts."""
    _, expert, limit, make = task_setup(task, seed)
    returns, successes = held_out_episodes(
        make(10_000 + seed), expert, budget(task, cfg).eval, seed, limit
    )
    return {"task": task, "learner": "expert", "labels": "-", "seed": seed, "rows": [0],
            "returns": returns, "successes": successes}  # fmt: skip


def held_out_episodes(env, policy, n: int, seed: int, limit: int) -> tuple[list[float], int]:
    """Each held-out episode's return (greedy), and the successes (Meta-World's
    ``info["success"]`` at any step; the two-way task: reward 1)."""
    from imitrl.runtime.returns import episode_returns
    from imitrl.runtime.rollout import rollout_policy

    actor, _ = rollout_policy(env, policy, ExplorationType.DETERMINISTIC)
    reported = SUCCESS in env.observation_spec.keys()  # Meta-World's info["success"]
    summary = episode_returns(env, actor, n, exploration=ExplorationType.DETERMINISTIC,
                              max_steps=limit, seed=10_000 + seed,
                              success_fn=reported_success if reported else None)  # fmt: skip
    returns = summary.returns.double().tolist()
    if summary.success is not None:
        return returns, int(summary.success.sum())
    return returns, sum(1 for r in returns if r > 0.5)  # the two-way task: reward 1


def scored_by_success(task: str) -> bool:
    return task == "two_way" or task.startswith("metaworld/")


def summarise(cells: list[dict]) -> list[dict]:
    rows = []
    for task in dict.fromkeys(c["task"] for c in cells):
        for learner in dict.fromkeys(c["learner"] for c in cells):
            for labels in ("-", *LABELS):
                mine = [c for c in cells if (c["task"], c["learner"], c["labels"]) ==
                        (task, learner, labels)]  # fmt: skip
                if not mine:
                    continue
                returns = torch.tensor([r for c in mine for r in c["returns"]])
                n, k = returns.numel(), sum(c["successes"] for c in mine)
                row = {"task": task, "learner": learner, "labels": labels, "episodes": n,
                       "return": mean_ci(returns), "last_rows": [c["rows"][-1] for c in mine]}  # fmt: skip
                if scored_by_success(task):
                    lo, hi = wilson_interval(k, n)
                    row["success"] = (k / n, lo, hi)
                rows.append(row)
    return rows


def markdown(cfg: Config, rows: list[dict], wall: float) -> str:
    header = ["task", "learner", "chunk labels", "success (95% Wilson)",
              "mean return (95% t)", "rows in the last fit"]  # fmt: skip
    body = []
    for r in rows:
        s = r.get("success")
        body.append([
            r["task"], r["learner"], r["labels"],
            "-" if s is None else f"{s[0]:.2f} [{s[1]:.2f}, {s[2]:.2f}]",
            _report.fmt_ci(tuple(r["return"]), digits=2),
            "-" if r["learner"] == "expert" else ", ".join(map(str, r["last_rows"])),
        ])  # fmt: skip
    return _report.section(
        "Chunk-aware DAgger: masked chunks against the expert's plans (chunk_labels.py)",
        f"`python benchmarks/chunk_labels.py` ({wall / 60:.1f} min, 1 torch thread): "
        f"{cfg.seeds} seeds, {cfg.demos} demonstrations, {cfg.rounds - 1} relabel rounds x "
        f"{cfg.episodes} learner episodes (beta 0), a fresh learner per round "
        f"({cfg.steps} steps x batch 64, widths 64-64), the last learner on {cfg.eval} "
        "held-out episodes per seed (the same starts for both labellings), pooled.\n\n"
        + _report.table(header, body)
        + f"\n\n![success and return](results/{NAME}.png)\n",
    )


def figure(rows: list[dict], path: Path) -> None:
    import matplotlib.pyplot as plt

    tasks = list(dict.fromkeys(r["task"] for r in rows))
    fig, axes = _report.panels(len(tasks), 4, (4.2, 3.2))
    for ax, task in zip(axes, tasks):
        mine = [r for r in rows if r["task"] == task]
        score = "success" if scored_by_success(task) else "return"
        expert = next(r for r in mine if r["learner"] == "expert")
        ax.axhline(expert[score][0], color="grey", ls="--", label="expert")
        learners = list(dict.fromkeys(r["learner"] for r in mine if r["learner"] != "expert"))
        for j, labels in enumerate(LABELS):
            xs, mids, errs = [], [], []
            for i, learner in enumerate(learners):
                r = next(x for x in mine if (x["learner"], x["labels"]) == (learner, labels))
                mid, lo, hi = r[score]
                xs.append(i + (j - 0.5) * 0.25)
                mids.append(mid)
                errs.append((mid - lo, hi - mid))
            ax.errorbar(xs, mids, yerr=list(zip(*errs)), fmt="o", capsize=4, label=labels)
        ax.set_xticks(range(len(learners)), learners)
        ax.set_xlim(-0.6, len(learners) - 0.4)
        ax.set_ylabel("success (95% Wilson)" if score == "success" else "mean return (95% t)")
        ax.set_title(task.replace("_", "-").removeprefix("metaworld/"), fontsize=10)
        if score == "success":
            ax.set_ylim(-0.03, 1.05)
    axes[0].legend(title="chunk labels", fontsize=8)
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
    for task in [*cfg.tasks, *(f"metaworld/{t}" for t in cfg.metaworld)]:
        seeds = budget(task, cfg).seeds
        cells.extend(expert_cell(task, seed, cfg) for seed in range(seeds))
        for learner in cfg.learners:
            for seed in range(seeds):
                for labels in LABELS:
                    cells.append(cell(task, learner, labels, seed, cfg))
                    c = cells[-1]
                    print(f"{task} {learner} {labels} seed {seed}: return "
                          f"{sum(c['returns']) / len(c['returns']):.2f}, successes "
                          f"{c['successes']}/{len(c['returns'])}", file=sys.stderr, flush=True)  # fmt: skip
    wall = time.perf_counter() - t0
    rows = summarise(cells)
    figure(rows, _report.results_dir(out_dir) / f"{NAME}.png")
    md = markdown(cfg, rows, wall)
    print(md)
    payload = {"config": asdict(cfg), "summary": rows, "cells": cells, "wall_seconds": wall}
    print("results:", _report.write(NAME, payload, md, out_dir=out_dir))
    return payload


if __name__ == "__main__":
    main()
