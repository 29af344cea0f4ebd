"""Action chunks under inference latency: success and jerk against the delay, four modes.

A chunked flow policy (rectified flow over chunks of ``H`` actions, 16 Euler steps, ``s``
executed per chunk, a fresh noise draw per query: what a robot's sampler does; two
chunkings, ``flow_chunk``'s own ``H = 8, s = 4`` with ``d <= 4`` and ``H = 16, s = 8`` with
``d <= 8``, as asynchronous execution needs ``d <= s <= H - d``) is fitted by BC, then evaluated with an inference delay of ``d`` control steps simulated in
the rollout loop (:class:`~imitrl.policies.latency.DelayedChunkPolicy`), executing its
chunks four ways: ``sync`` (holds still while it waits), ``naive`` asynchronous (the next
chunk takes over at its action ``d``), ``ensemble`` (ACT's temporal ensembling of the chunks
that have arrived, m = 0.01) and ``rtc`` (real-time chunking, Black et al. 2025: the next
chunk inpainted from the current one, guidance weight up to 5). Every mode of a seed plays
the same held-out starts with the same network.

Tasks: the two-way obstacle task (``imitrl.envs.multimodal``: two ways round a disc, the
expert's intent hidden; 50 demonstrations, 10000 steps at batch 256, widths 128-128, 200
held-out episodes per seed and delay) and five MT10 tasks (metaworld_mt10.py's
demonstrations and fit: 5 demonstrations, 320 steps at batch 256, widths 128-128 at lr
3e-3; 20 held-out episodes of at most 150 steps per seed and delay, fewer delays).
Reported: success with Wilson intervals over the pooled episodes, and the jerk at chunk
boundaries: ``|| a_t - 2 a_{t-1} + a_{t-2} ||`` (actions scaled to [-1, 1]) at the steps
where a new chunk takes over (every step of ``ensemble`` once chunks arrive), mean over
those steps with a t interval over episodes.

    python benchmarks/chunk_latency.py            # full run, refreshes the README block
    python benchmarks/chunk_latency.py --quick    # smoke run, into a temporary directory
"""

from __future__ import annotations

import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from torchrl.envs import InitTracker, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

import _report
from chunk_labels import METAWORLD, METAWORLD_STEPS
from imitrl import keys
from imitrl.algorithms import BCConfig, fit_bc
from imitrl.data import DemonstrationBuffer
from imitrl.envs import make_env
from imitrl.envs.multimodal import TwoWayObstacleEnv, two_way_expert
from imitrl.envs.success import SUCCESS
from imitrl.evaluation.evaluate import mean_ci, wilson_interval
from imitrl.learners.chunks import chunked_learner
from imitrl.learners.flow.entries import FLOW_CHUNK_STEPS
from imitrl.learners.flow.loss import FlowMatchingLoss
from imitrl.learners.flow.policy import FlowPolicy
from imitrl.learners.task import TaskSpec
from imitrl.policies.chunking import ChunkExecution, tile_spec
from imitrl.policies.latency import CHUNK_SWITCH, MODES, DelayedChunkPolicy, Latency, hold_action
from imitrl.runtime import rollout_episodes

NAME = "chunk_latency"


@dataclass(frozen=True)
class Config:
    seeds: int = 3
    chunkings: tuple = ((8, 4, (0, 1, 2, 3, 4)), (16, 8, (0, 1, 2, 3, 4, 5, 6, 7, 8)))
    """``(H, s, delays)`` of the two-way task"""
    demos: int = 50
    steps: int = 10_000
    eval: int = 200
    metaworld: tuple = METAWORLD
    mw_seeds: int = 3
    mw_chunkings: tuple = ((8, 4, (0, 2, 4)), (16, 8, (0, 4, 8)))
    mw_eval: int = 20
    quick: bool = False


QUICK = Config(seeds=1, chunkings=((8, 4, (0, 2)),), demos=2, steps=5, eval=4,
               metaworld=("reach-v3",), mw_seeds=1, mw_chunkings=((8, 4, (2,)),), mw_eval=1,
               quick=True)  # fmt: skip


def learner(env, seed: int, hidden: tuple, lr: float, horizon: int, execute: int):
    """A flow policy over chunks of ``horizon``, ``execute`` executed per query, fresh noise."""
    task = TaskSpec.from_env(env)
    policy = FlowPolicy(task.observation_dim, tile_spec(task.action, horizon), hidden=hidden,
                        num_steps=FLOW_CHUNK_STEPS, seed=seed)  # fmt: skip
    loss = FlowMatchingLoss(policy, chunked=True, seed=seed)
    opt = torch.optim.Adam(policy.parameters(), lr=lr)
    return chunked_learner(task, policy, loss, opt, ChunkExecution(horizon, execute=execute),
                           exploration=ExplorationType.RANDOM, normalizer=policy.normalizer)  # fmt: skip


def trained(task: str, seed: int, cfg: Config, horizon: int, execute: int):
    """``(learner, make(seed, lanes) -> env, episode limit)`` of ``task``, fitted by BC."""
    torch.manual_seed(seed)
    if task == "two_way":

        def make(s: int, lanes: int):
            return TwoWayObstacleEnv(seed=s, batch_size=(lanes,) if lanes > 1 else ())

        expert, limit, demos, steps = two_way_expert(), 40, cfg.demos, cfg.steps
        hidden, lr = (128, 128), 1e-3
    else:
        from imitrl.experts import metaworld_expert

        def make(s: int, lanes: int):
            return make_env(task, seed=s, num_envs=lanes, max_episode_steps=METAWORLD_STEPS)

        expert, limit = metaworld_expert(task.removeprefix("metaworld/")), METAWORLD_STEPS
        demos, steps, hidden, lr = (
            (1 if cfg.quick else 5),
            cfg.steps if cfg.quick else 320,
            (128, 128),
            3e-3,
        )
    env = make(seed, 1)
    buffer = DemonstrationBuffer(action_spec=env.action_spec_unbatched)
    buffer.extend(rollout_episodes(env, expert, demos, max_steps=limit))
    fitted = learner(env, seed, hidden, lr, horizon, execute)
    env.close()
    fit_bc(fitted, buffer, BCConfig(num_steps=steps, batch_size=256, seed=seed))
    return fitted, make, limit


def play(fitted, env, limit: int, mode: str, d: int, seed: int) -> dict:
    """``env``'s lanes' held-out episodes (reset from seed ``10_000 + seed``: the same starts
    for every mode and delay) under delay ``d``: successes and each episode's mean jerk at
    its chunk boundaries. One env serves every cell of a seed: Meta-World keeps ~15 MB of
    every env it builds after it is closed (metaworld 3, measured), which thousands of
    20-lane envs would pile up."""
    spec = env.action_spec_unbatched
    policy = DelayedChunkPolicy.wrapping(fitted.policy, Latency(d, mode), hold=hold_action(spec))
    fitted.policy.network.generator.manual_seed(seed)  # the same draws for every mode
    env.set_seed(10_000 + seed)  # (reset(seed=...) does not reach an EnvBase env's generator)
    start = env.reset()
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        td = env.rollout(limit, policy, break_when_any_done=False, auto_cast_to_device=False,
                         auto_reset=False, tensordict=start)  # fmt: skip
    td = td if td.batch_dims == 2 else td.unsqueeze(0)
    done = td.get(("next", keys.DONE)).reshape(td.shape[0], -1)
    first = torch.where(done.any(1), done.float().argmax(1), torch.full((td.shape[0],), limit - 1))
    steps = torch.arange(td.shape[1])[None, :]
    alive = steps <= first[:, None]  # each lane's first episode
    if SUCCESS in td.get("next").keys():
        success = (td.get(("next", SUCCESS)).reshape(td.shape[0], -1) & alive).any(1)
    else:  # the two-way task: reward 1 at the goal
        success = (td.get(("next", keys.REWARD)).reshape(td.shape[0], -1) * alive).sum(1) > 0.5
    low, high = spec.space.low, spec.space.high
    a = 2 * (td.get(keys.ACTION) - low) / (high - low) - 1  # [N, T, m] in [-1, 1]
    jerk = torch.zeros_like(done, dtype=torch.float32)
    jerk[:, 2:] = (a[:, 2:] - 2 * a[:, 1:-1] + a[:, :-2]).norm(dim=-1)
    switch = td.get(CHUNK_SWITCH).reshape(td.shape[0], -1) & alive & (steps >= 2)
    per_episode = (jerk * switch).sum(1) / switch.sum(1).clamp(min=1)
    return {"successes": int(success.sum()), "episodes": int(success.numel()),
            "jerk": per_episode[switch.any(1)].tolist()}  # fmt: skip


def run_task(task: str, cfg: Config, cells: list[dict]) -> None:
    mw = task != "two_way"
    seeds, chunkings = (cfg.mw_seeds, cfg.mw_chunkings) if mw else (cfg.seeds, cfg.chunkings)
    episodes = cfg.mw_eval if mw else cfg.eval
    for horizon, execute, delays in chunkings:
        for seed in range(seeds):
            fitted, make, limit = trained(task, seed, cfg, horizon, execute)
            env = TransformedEnv(make(10_000 + seed, episodes), InitTracker())
            for d in delays:
                for mode in MODES:
                    c = play(fitted, env, limit, mode, d, seed)
                    cells.append(
                        {
                            "task": task,
                            "horizon": horizon,
                            "execute": execute,
                            "seed": seed,
                            "delay": d,
                            "mode": mode,
                            **c,
                        }
                    )
                    print(f"{task} H={horizon} seed {seed} d={d} {mode}: "
                          f"{c['successes']}/{c['episodes']}", file=sys.stderr, flush=True)  # fmt: skip
            env.close()


MT10 = "MT10 (5 tasks)"
"""the MT10 tasks' episodes pooled, a row of its own"""


def _row(task: str, horizon: int, d: int, mode: str, mine: list[dict]) -> dict:
    k, n = sum(c["successes"] for c in mine), sum(c["episodes"] for c in mine)
    lo, hi = wilson_interval(k, n)
    jerk = torch.tensor([j for c in mine for j in c["jerk"]], dtype=torch.float64)
    return {"task": task, "horizon": horizon, "delay": d, "mode": mode, "episodes": n,
            "success": (k / n, lo, hi),
            "jerk": mean_ci(jerk) if jerk.numel() else (float("nan"),) * 3}  # fmt: skip


def _in(cell: dict, task: str) -> bool:
    """``cell`` is one of ``task``'s (of any MT10 task for the pooled row)."""
    return cell["task"].startswith("metaworld/") if task == MT10 else cell["task"] == task


def summarise(cells: list[dict]) -> list[dict]:
    rows = []
    keys_ = dict.fromkeys((c["task"], c["horizon"]) for c in cells)
    mw = [k for k in keys_ if k[0].startswith("metaworld/")]
    several = len({t for t, _ in mw}) > 1
    groups = [*keys_, *dict.fromkeys((MT10, h) for _, h in mw)] if several else list(keys_)
    for task, h in groups:
        mine_h = [c for c in cells if _in(c, task) and c["horizon"] == h]
        for d in sorted({c["delay"] for c in mine_h}):
            for mode in MODES:
                mine = [c for c in mine_h if (c["delay"], c["mode"]) == (d, mode)]
                rows.append(_row(task, h, d, mode, mine))
    return rows


def _at(rows, task, horizon, mode, d):
    return next((r for r in rows
                 if (r["task"], r["horizon"], r["mode"], r["delay"]) == (task, horizon, mode, d)),
                None)  # fmt: skip


def claims(rows: list[dict]) -> list[str]:
    """Issue 48's bar at d = 4: rtc keeps >= 90% of its delay-free success, naive loses >= 20
    points."""
    out = []
    for task, h in dict.fromkeys((r["task"], r["horizon"]) for r in rows):
        base_r, r4 = _at(rows, task, h, "rtc", 0), _at(rows, task, h, "rtc", 4)
        base_n, n4 = _at(rows, task, h, "naive", 0), _at(rows, task, h, "naive", 4)
        if None in (base_r, r4, base_n, n4):
            continue
        keep = r4["success"][0] / base_r["success"][0] if base_r["success"][0] else float("nan")
        drop = base_n["success"][0] - n4["success"][0]
        out.append(f"{task.removeprefix('metaworld/')}, H={h}: rtc at d=4 keeps {keep:.0%} of "
                   f"its d=0 success ({r4['success'][0]:.2f} / {base_r['success'][0]:.2f}); naive "
                   f"loses {100 * drop:.0f} points ({base_n['success'][0]:.2f} -> "
                   f"{n4['success'][0]:.2f})")  # fmt: skip
    return out


def markdown(rows: list[dict], cfg: Config, wall: float) -> str:
    header = ["task", "H, s", "d", *[f"{m}: success" for m in MODES],
              *[f"{m}: jerk" for m in MODES]]  # fmt: skip
    body = []
    for task, h in dict.fromkeys((r["task"], r["horizon"]) for r in rows):
        for d in sorted({r["delay"] for r in rows if (r["task"], r["horizon"]) == (task, h)}):
            cells = [_at(rows, task, h, m, d) for m in MODES]
            body.append([task.removeprefix("metaworld/"), f"{h}, {h // 2}", d,
                         *[f"{c['success'][0]:.2f} [{c['success'][1]:.2f}, {c['success'][2]:.2f}]" for c in cells],
                         *[_report.fmt_ci(tuple(c["jerk"]), digits=3) for c in cells]])  # fmt: skip
    lines = "\n".join(f"* {c}" for c in claims(rows))
    return _report.section(
        "Action chunks under inference latency (`chunk_latency.py`)",
        f"`python benchmarks/chunk_latency.py` ({wall / 60:.1f} min, 1 torch thread): a flow "
        f"policy over chunks of H ({FLOW_CHUNK_STEPS} Euler steps, s = H/2 executed per chunk, "
        "fresh noise per query) fitted by BC; an inference delay of d control steps "
        "simulated in the rollout loop, four executions (`imitrl.policies.latency`). Two-way "
        f"task: {cfg.seeds} seeds x {cfg.eval} held-out episodes, {cfg.demos} demonstrations, "
        f"{cfg.steps} steps at batch 256; MT10 tasks: {cfg.mw_seeds} seeds x {cfg.mw_eval} "
        "episodes, metaworld_mt10.py's demonstrations and fit. Success with 95% Wilson "
        "intervals (pooled episodes); jerk = ||a_t - 2a_{t-1} + a_{t-2}|| at chunk boundaries "
        "(actions in [-1, 1]), mean with a 95% t interval over episodes.\n\n"
        + _report.table(header, body)
        + (f"\n\nAt d = 4 (issue 48's bar: rtc keeps >= 90%, naive loses >= 20 points):\n\n{lines}" if lines else "")
        + f"\n\n![success and jerk against the delay](results/{NAME}.png)\n",
    )  # fmt: skip


def figure(rows: list[dict], path: Path) -> None:
    import matplotlib.pyplot as plt

    groups = [g for g in dict.fromkeys((r["task"], r["horizon"]) for r in rows)
              if g[0] == MT10 or not g[0].startswith("metaworld/")]  # fmt: skip
    fig, axes = _report.panels(2 * len(groups), 2, (4.6, 3.2))
    for i, (task, h) in enumerate(groups):
        ax_s, ax_j = axes[2 * i], axes[2 * i + 1]
        for mode in MODES:
            mine = sorted((r for r in rows if (r["task"], r["horizon"], r["mode"]) == (task, h, mode)),
                          key=lambda r: r["delay"])  # fmt: skip
            d = [r["delay"] for r in mine]
            s = torch.tensor([r["success"] for r in mine])
            ax_s.plot(d, s[:, 0], marker="o", label=mode)
            ax_s.fill_between(d, s[:, 1], s[:, 2], alpha=0.15)
            j = torch.tensor([r["jerk"] for r in mine])
            ax_j.plot(d, j[:, 0], marker="o", label=mode)
        name = f"{task.removeprefix('metaworld/')}, H={h}, s={h // 2}"
        ax_s.set_title(f"{name}: success", fontsize=10)
        ax_s.set_ylim(-0.03, 1.05)
        ax_j.set_title(f"{name}: jerk at chunk boundaries", fontsize=10)
        for ax in (ax_s, ax_j):
            ax.set_xlabel("inference delay d (control steps)")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict:
    p = _report.parser(__doc__)
    p.add_argument("--tasks", nargs="*", default=None, help="two_way and/or MT10 task names")
    args = p.parse_args(argv)
    out_dir = _report.destination(NAME, quick=args.quick, out=args.out)
    cfg = QUICK if args.quick else Config()
    torch.set_num_threads(1)
    tasks = args.tasks or ["two_way", *cfg.metaworld]
    t0 = time.perf_counter()
    cells: list[dict] = []
    for task in tasks:
        run_task(task if task == "two_way" else f"metaworld/{task}", cfg, cells)
    wall = time.perf_counter() - t0
    rows = summarise(cells)
    figure(rows, _report.results_dir(out_dir) / f"{NAME}.png")
    md = markdown(rows, cfg, wall)
    print(md)
    payload = {"config": asdict(cfg), "summary": rows, "cells": cells, "wall_seconds": wall}
    print("results:", _report.write(NAME, payload, md, out_dir=out_dir))
    return payload


if __name__ == "__main__":
    main()
