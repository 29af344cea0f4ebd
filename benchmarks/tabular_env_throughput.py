"""TabularEnv throughput against a plain gymnasium loop and TorchRL's GymEnv + Collector.

All three play slippery FrozenLake-v1 with the value-iteration expert (a table lookup),
auto-resetting finished episodes, on one CPU thread. Frames/s = env steps per second.

    python benchmarks/tabular_env_throughput.py            # full run, refreshes README
    python benchmarks/tabular_env_throughput.py --quick    # smoke run, into a temporary directory
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import gymnasium as gym
import torch
from torchrl.collectors import Collector
from torchrl.envs import GymEnv

import _report
from _common import lake
from imitrl.envs import TabularEnv
from imitrl.policies import Expert
from imitrl.tabular import greedy

NAME = "tabular_env_throughput"


@dataclass(frozen=True)
class Config:
    gym_steps: int = 300_000
    """steps of the plain gymnasium loop"""
    torchrl_frames: int = 20_000
    """frames through GymEnv + Collector"""
    batch_sizes: tuple[int, ...] = (1, 1_000, 65_536, 1_048_576)
    """TabularEnv lanes"""
    min_frames: int = 5_000_000
    """frames per TabularEnv measurement (at least 50 steps of the batch)"""
    repeats: int = 3
    """best of this many timed repeats"""


QUICK = Config(
    gym_steps=2_000, torchrl_frames=1_000, batch_sizes=(1, 1_000), min_frames=2_000, repeats=1
)


def plain_gym(table: list[int], steps: int) -> float:
    env = gym.make("FrozenLake-v1", is_slippery=True)
    s, _ = env.reset(seed=0)
    t0 = time.perf_counter()
    for _ in range(steps):
        s, _, term, trunc, _ = env.step(table[s])
        if term or trunc:
            s, _ = env.reset()
    return steps / (time.perf_counter() - t0)


def torchrl_gymenv(expert, frames: int) -> float:
    env = GymEnv("FrozenLake-v1", categorical_action_encoding=True)
    env.set_seed(0)
    policy = expert.as_actor()
    collector = Collector(
        env,
        policy,
        frames_per_batch=1000,
        total_frames=frames,
        auto_register_policy_transforms=False,
    )
    t0 = time.perf_counter()
    n = sum(batch.numel() for batch in collector)
    dt = time.perf_counter() - t0
    collector.shutdown()
    return n / dt


def tabular_env(mdp, expert, batch: int, min_frames: int) -> float:
    env = TabularEnv(mdp, batch_size=(batch,), seed=0)
    policy = expert.as_actor()
    steps = max(50, min_frames // batch)
    steps = min(steps, 20_000)
    td = env.reset()
    for _ in range(5):  # warm-up
        td = policy(td)
        _, td = env.step_and_maybe_reset(td)
    t0 = time.perf_counter()
    for _ in range(steps):
        td = policy(td)
        _, td = env.step_and_maybe_reset(td)
    return batch * steps / (time.perf_counter() - t0)


def main(argv: list[str] | None = None) -> list[dict]:
    args = _report.parser(__doc__).parse_args(argv)
    out_dir = _report.destination(NAME, quick=args.quick, out=args.out)
    cfg = QUICK if args.quick else Config()
    torch.set_num_threads(1)
    mdp, Q = lake()
    table = greedy(Q)
    expert = Expert.from_table(table)

    gym_fps = max(plain_gym(table.tolist(), cfg.gym_steps) for _ in range(cfg.repeats))
    trl_fps = max(torchrl_gymenv(expert, cfg.torchrl_frames) for _ in range(cfg.repeats))
    rows = [
        {"simulator": "gymnasium loop", "batch": 1, "frames_per_s": gym_fps},
        {"simulator": "TorchRL GymEnv + Collector", "batch": 1, "frames_per_s": trl_fps},
    ]
    for batch in cfg.batch_sizes:
        fps = max(tabular_env(mdp, expert, batch, cfg.min_frames) for _ in range(cfg.repeats))
        rows.append({"simulator": "imitrl TabularEnv", "batch": batch, "frames_per_s": fps})
    for row in rows:
        row["x_gym_loop"] = row["frames_per_s"] / gym_fps
        print(
            f"{row['simulator']:<28} batch {row['batch']:>9,}: {row['frames_per_s']:>12,.0f} frames/s  ({row['x_gym_loop']:.2f}x gym loop)"
        )
    md = _report.table(
        ["simulator", "lanes", "frames/s", "x plain gymnasium loop"],
        [
            [
                r["simulator"],
                f"{r['batch']:,}",
                f"{r['frames_per_s']:,.0f}",
                f"{r['x_gym_loop']:.2f}",
            ]
            for r in rows
        ],
    )
    path = _report.write(NAME, {"config": cfg.__dict__, "rows": rows}, md, out_dir=out_dir)
    print(f"results: {path}")
    return rows


if __name__ == "__main__":
    main()
