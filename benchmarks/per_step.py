"""Per-step cost of a rollout: one step = env step + learner forward + expert label.

A DAgger collection step on CartPole-v1 and Pendulum-v1, at 1 lane and at 64 lanes:
the behaviour policy ``TensorDictSequential(expert, learner, BetaMixer(0))`` of an
untrained [32, 32] tanh MLP learner (categorical on CartPole, deterministic on Pendulum)
and the library's expert, whole episodes kept as rows. Three ways of doing that work:

* raw: gymnasium (a ``SyncVectorEnv`` with autoreset DISABLED at 64 lanes) and torch,
  written out: the same network and expert function on ``torch.as_tensor(obs)``, the
  learner's action stepped, every step's observation, actions, label, reward and done
  flags kept, finished lanes reset, everything stacked at the end;
* imitrl: ``rollout_episodes(env, behaviour, n)`` on ``make_env``'s env (its direct path:
  the env stepped directly, the policy called on a dict of tensors);
* TorchRL: the same call inside ``paths.reference("stepper")`` (``env.step_and_maybe_reset`` and
  ``policy(td)`` at every step): the cost of the layers the direct path skips.

Each repeat runs the three back to back; per-step time = wall time / batched steps (the
raw loop runs as many batched steps as imitrl's rollout took), ratios are taken within a
repeat and their median reported. Targets: imitrl <= 3x raw at 1 lane, <= 1.5x at 64.
A second table times a 1000-episode FrozenLake-v1 evaluation through ``make_env`` (the
stream player; the TorchRL path per episode, on fewer episodes).

    python benchmarks/per_step.py            # full run, refreshes README
    python benchmarks/per_step.py --quick    # smoke run, into a temporary directory
"""

from __future__ import annotations

import contextlib
import logging
import os
import statistics
import time
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch
from torchrl.modules import ProbabilisticActor

import _report
from _common import DET, lake
from imitrl.envs import make_env
from imitrl.evaluation import evaluate
from imitrl.experts import cartpole_expert, pendulum_expert
from imitrl.learners import ActorCritic
from imitrl.learners import build as build_learner
from imitrl.policies import BetaMixer, Expert, behaviour_policy
from imitrl.runtime import paths, rollout_episodes
from imitrl.tabular import greedy

NAME = "per_step"
EXPERTS = {"CartPole-v1": cartpole_expert, "Pendulum-v1": pendulum_expert}


@dataclass(frozen=True)
class Config:
    tasks: tuple[str, ...] = ("CartPole-v1", "Pendulum-v1")
    """gymnasium ids (each with its expert from imitrl.experts)"""
    lanes: tuple[int, ...] = (1, 64)
    """envs stepped together"""
    steps: int = 3_000
    """batched steps per measurement at 1 lane (whole episodes: a few more)"""
    steps_batched: int = 400
    """batched steps per measurement at more than 1 lane"""
    repeats: int = 5
    """alternated repeats (raw, imitrl, TorchRL); medians reported"""
    hidden: tuple[int, ...] = (32, 32)
    """the learner's hidden layers"""
    lake_episodes: int = 1_000
    """episodes of the FrozenLake evaluation"""
    lake_torchrl_episodes: int = 100
    """episodes of its TorchRL-path counterpart (reported per episode)"""
    max_episode_steps: int | None = None
    """override the envs' time limits (None: gymnasium's)"""
    seed: int = 0


QUICK = Config(
    lanes=(1, 4),
    steps=60,
    steps_batched=15,
    repeats=1,
    lake_episodes=50,
    lake_torchrl_episodes=2,
    max_episode_steps=40,
)


# ---------------------------------------------------------------------- the task
@dataclass
class Task:
    env_id: str
    lanes: int
    learner: ActorCritic
    expert: Expert
    episodes: int  # episodes per measurement (about steps batched steps)


def build(cfg: Config, env_id: str, lanes: int) -> Task:
    env = make_env(env_id, seed=cfg.seed, num_envs=lanes, max_episode_steps=cfg.max_episode_steps)
    learner = build_learner("for_env", env, seed=cfg.seed, hidden=cfg.hidden)
    expert = EXPERTS[env_id]().bind(env.action_spec_unbatched)
    steps = cfg.steps if lanes == 1 else cfg.steps_batched
    # the episodes that take about `steps` batched steps (measured on a short rollout)
    probe = rollout_episodes(env, behaviour(learner, expert), lanes, exploration=DET)
    mean_length = probe.shape[0] / lanes
    return Task(env_id, lanes, learner, expert, max(lanes, round(steps / mean_length) * lanes))


def behaviour(learner: ActorCritic, expert: Expert):
    return behaviour_policy(expert, learner.policy, BetaMixer(0.0))


def batched_steps(rows, lanes: int) -> int:
    """The steps a rollout took: the lane that finished its episodes last."""
    lane = rows.get("episode") % lanes
    return int(torch.bincount(lane, minlength=lanes).max())


# ------------------------------------------------------------------ three loops
def run_imitrl(task: Task, cfg: Config, fast_path: bool) -> tuple[float, int]:
    env = make_env(
        task.env_id, seed=cfg.seed, num_envs=task.lanes, max_episode_steps=cfg.max_episode_steps
    )
    policy = behaviour(task.learner, task.expert)
    t0 = time.perf_counter()
    with contextlib.nullcontext() if fast_path else paths.reference("stepper"):
        rows = rollout_episodes(env, policy, task.episodes, exploration=DET)
    return time.perf_counter() - t0, batched_steps(rows, task.lanes)


def run_raw(task: Task, cfg: Config, steps: int) -> float:
    """gymnasium + torch doing the same work for ``steps`` batched steps."""
    policy = task.learner.policy
    if isinstance(policy, ProbabilisticActor):  # categorical: logits -> greedy action
        net, greedy_action = policy.module[0].module, True
    else:  # deterministic head: the network writes the action
        net, greedy_action = policy.module, False
    label = task.expert.module
    vector = task.lanes > 1
    limit = cfg.max_episode_steps
    if vector:
        env = gym.vector.SyncVectorEnv(
            [lambda: gym.make(task.env_id, max_episode_steps=limit) for _ in range(task.lanes)],
            autoreset_mode=gym.vector.AutoresetMode.DISABLED,
        )
    else:
        env = gym.make(task.env_id, max_episode_steps=limit)
    obs, _ = env.reset(seed=cfg.seed)
    columns = {k: [] for k in ("obs", "action", "label", "reward", "term", "trunc")}
    t0 = time.perf_counter()
    with torch.no_grad():
        for _ in range(steps):
            o = torch.as_tensor(obs)
            out = net(o)
            a = out.argmax(-1) if greedy_action else out
            y = label(o)
            obs, reward, term, trunc, _ = env.step(
                a.numpy() if vector or not greedy_action else int(a)
            )
            for k, v in zip(columns, (o, a, y, reward, term, trunc)):
                columns[k].append(v)
            done = term | trunc
            if vector and done.any():
                obs, _ = env.reset(options={"reset_mask": done})
            elif not vector and done:
                obs, _ = env.reset()
        rows = {
            k: torch.stack([torch.as_tensor(np.asarray(v)) for v in col])
            for k, col in columns.items()
        }
    dt = time.perf_counter() - t0
    assert rows["obs"].shape[0] == steps
    env.close()
    return dt


def per_step(cfg: Config, env_id: str, lanes: int) -> dict:
    task = build(cfg, env_id, lanes)
    raw, lib, trl = [], [], []
    for _ in range(cfg.repeats):  # alternated, so load on the machine hits all three
        t_lib, steps = run_imitrl(task, cfg, fast_path=True)
        t_raw = run_raw(task, cfg, steps)
        t_trl, steps_trl = run_imitrl(task, cfg, fast_path=False)
        assert steps_trl == steps  # the same episodes on both paths
        raw.append(1e6 * t_raw / steps)
        lib.append(1e6 * t_lib / steps)
        trl.append(1e6 * t_trl / steps)
    med = statistics.median
    row = {
        "task": env_id,
        "lanes": lanes,
        "batched_steps": steps,
        "raw_us": med(raw),
        "imitrl_us": med(lib),
        "torchrl_us": med(trl),
        "imitrl_x_raw": med(b / a for a, b in zip(raw, lib)),
        "torchrl_x_raw": med(c / a for a, c in zip(raw, trl)),
        "target_x_raw": 3.0 if lanes == 1 else 1.5,
        "runs_us": {"raw": raw, "imitrl": lib, "torchrl": trl},
    }
    print(
        f"{env_id:<12} {lanes:>3} lanes: raw {row['raw_us']:8.0f} us, imitrl "
        f"{row['imitrl_us']:8.0f} us ({row['imitrl_x_raw']:.2f}x), TorchRL "
        f"{row['torchrl_us']:8.0f} us ({row['torchrl_x_raw']:.2f}x) per batched step"
    )
    return row


def frozenlake_evaluation(cfg: Config) -> dict:
    """``evaluate(make_env("FrozenLake-v1"), expert, n)``: the stream player and, on fewer
    episodes, the step-by-step TorchRL path (seconds per 1000 episodes)."""
    _, Q = lake()
    expert = Expert.from_table(greedy(Q))
    env = make_env("FrozenLake-v1", seed=cfg.seed)
    fast, slow = [], []
    for _ in range(cfg.repeats):
        t0 = time.perf_counter()
        ev = evaluate(env, expert, cfg.lake_episodes, seed=1)
        fast.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        with paths.reference("stepper", "table_returns"):
            evaluate(env, expert, cfg.lake_torchrl_episodes, seed=1)
        slow.append((time.perf_counter() - t0) * 1000 / cfg.lake_torchrl_episodes)
    row = {
        "episodes": cfg.lake_episodes,
        "imitrl_s": statistics.median(fast),
        "torchrl_s_per_1000": statistics.median(slow),
        "mean_return": ev.mean_return,
        "mean_length": ev.mean_length,
    }
    print(
        f"FrozenLake {cfg.lake_episodes} episodes: {row['imitrl_s']:.3f} s (stream); TorchRL "
        f"path {row['torchrl_s_per_1000']:.1f} s per 1000 episodes"
    )
    return row


def markdown(cfg: Config, rows: list[dict], lake_row: dict, load: float) -> str:
    table = _report.table(
        ["task", "lanes", "raw loop", "imitrl", "x raw", "TorchRL path", "x raw", "target"],
        [
            [
                r["task"],
                r["lanes"],
                f"{r['raw_us']:,.0f} us",
                f"{r['imitrl_us']:,.0f} us",
                f"{r['imitrl_x_raw']:.2f}",
                f"{r['torchrl_us']:,.0f} us",
                f"{r['torchrl_x_raw']:.2f}",
                f"<= {r['target_x_raw']:.1f}",
            ]
            for r in rows
        ],
    )
    head = (
        f"One DAgger collection step (env + [{', '.join(map(str, cfg.hidden))}] tanh MLP "
        f"learner + expert label, rows kept) per batched step, median of {cfg.repeats} "
        f"alternated repeats; ratios within a repeat. Load average over the run: "
        f"{load:.1f} on {os.cpu_count()} cores (compare ratios, not microseconds)."
    )
    lake_line = (
        f"FrozenLake-v1 through `make_env`, the expert, {lake_row['episodes']} episodes: "
        f"`evaluate` {lake_row['imitrl_s']:.3f} s (stream player); the TorchRL path "
        f"{lake_row['torchrl_s_per_1000']:.1f} s per 1000 episodes (measured on "
        f"{cfg.lake_torchrl_episodes})."
    )
    return f"{head}\n\n{table}\n\n{lake_line}"


def main(argv: list[str] | None = None) -> list[dict]:
    args = _report.parser(__doc__).parse_args(argv)
    out_dir = _report.destination(NAME, quick=args.quick, out=args.out)
    cfg = QUICK if args.quick else Config()
    torch.set_num_threads(1)
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    t0, load0 = time.perf_counter(), os.getloadavg()
    rows = [per_step(cfg, env_id, lanes) for env_id in cfg.tasks for lanes in cfg.lanes]
    lake_row = frozenlake_evaluation(cfg)
    # the 15-minute average over a long run, the 1-minute one over a short one
    load = os.getloadavg()[2 if time.perf_counter() - t0 > 600 else 0]
    payload = {
        "config": cfg.__dict__,
        "rows": rows,
        "frozenlake": lake_row,
        "load_average": {"start": load0, "end": os.getloadavg()},
    }
    path = _report.write(NAME, payload, markdown(cfg, rows, lake_row, load), out_dir=out_dir)
    print(f"results: {path}")
    return rows


if __name__ == "__main__":
    main()
