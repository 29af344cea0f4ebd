"""DAgger relabel rounds on 1 and 2 Ray workers (RaySource) on a costly env.

The env is Pendulum-v1 whose every step also does ``work_ms`` of work (``busy``: a
spinning loop that holds a core, as a slow simulator does; ``sleep``: ``time.sleep``,
as a remote simulator or an expert behind a service does). For each worker count a
fresh local Ray instance (``num_cpus`` = workers) runs DAgger; every relabel round's
wall time is split by :class:`imitrl.algorithms.ray_source.RoundTiming` into the
weight broadcast (liveness ping + ``update_policy_weights_``), the slowest worker's
play time (measured in the worker), and the rest (dispatch + gather: the rows'
transfer and the driver's assembly). Start-up (``ray.init``, the actors, the first
weight sync) is reported apart.

Projection to N workers from the measured per-round overheads, fitted as linear in
the worker count from the 1- and 2-worker runs (``x(N) = x0 + x1 * N``):

    T(N) = broadcast(N) + W / N + gather(N),   speedup(N) = T(1) / T(N)

with ``W`` the play time of a round on one worker (``episodes_per_round`` whole
episodes; it divides evenly only when N divides the episodes: a round needs at least N
episodes to use N workers).

    python benchmarks/scale_ray.py --out benchmarks/results   # full run (README untouched)
    python benchmarks/scale_ray.py --quick                    # smoke run, temporary directory
    python benchmarks/scale_ray.py --work sleep --out DIR     # the work frees the core
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import statistics
import time
from dataclasses import dataclass

import ray
import torch
from torchrl.envs import Transform, TransformedEnv

import _report
from imitrl.algorithms import BCConfig, Constant, DAggerConfig, dagger
from imitrl.algorithms.ray_source import RaySource, init_ray
from imitrl.data import DemonstrationBuffer
from imitrl.envs import make_env
from imitrl.experts import pendulum_expert
from imitrl.learners import build
from imitrl.runtime import rollout_episodes

NAME = "scale_ray"


@dataclass(frozen=True)
class Config:
    env: str = "Pendulum-v1"
    """gymnasium id of the base env (200-step episodes)"""
    work_ms: float = 5.0
    """extra work per env step, in milliseconds"""
    work: str = "busy"
    """busy (a spinning loop: holds a core) or sleep (time.sleep: frees it)"""
    workers: tuple[int, ...] = (1, 2)
    """worker counts measured"""
    episodes_per_round: int = 8
    """episodes per relabel round (divisible by every worker count)"""
    rounds: int = 4
    """relabel rounds timed per worker count (after one untimed round)"""
    fit_steps: int = 50
    """BC steps of each round's fit"""
    project_to: int = 64
    """worker count of the projection"""


QUICK = Config(work_ms=0.5, workers=(1,), episodes_per_round=2, rounds=1, fit_steps=5)


class Work(Transform):
    """``ms`` milliseconds of busy work or sleep after every env step."""

    def __init__(self, ms: float, kind: str) -> None:
        super().__init__()
        self.seconds, self.kind = ms / 1000.0, kind

    def _step(self, tensordict, next_tensordict):
        if self.kind == "sleep":
            time.sleep(self.seconds)
        else:
            end = time.perf_counter() + self.seconds
            while time.perf_counter() < end:
                pass
        return next_tensordict


def costly_env(env_id: str, ms: float, kind: str, *, seed: int):
    return TransformedEnv(make_env(env_id, seed=seed), Work(ms, kind))


def measure(cfg: Config, workers: int) -> dict:
    """One DAgger run on ``workers`` workers of a fresh local Ray: start-up and per-round timings."""
    start = time.perf_counter()
    init_ray(workers)
    ray_init = time.perf_counter() - start
    env = make_env(cfg.env, seed=0)
    expert = pendulum_expert()
    buffer = DemonstrationBuffer(action_spec=env.action_spec_unbatched)
    buffer.extend(rollout_episodes(env, expert, 1))
    timings = []
    env_fn = functools.partial(costly_env, cfg.env, cfg.work_ms, cfg.work, seed=0)
    source = RaySource(env_fn, workers, seed=0)

    def on_fit(k, learner):  # after fit k: round k's collection (k >= 1) is done
        if k >= 2:  # round 1 pays the start-up
            timings.append(source.last_timing)

    config = DAggerConfig(
        rounds=cfg.rounds + 2,
        episodes_per_round=cfg.episodes_per_round,
        beta=Constant(0.5),
        bc=BCConfig(num_steps=cfg.fit_steps, batch_size=256),
    )
    try:
        dagger(source, expert, lambda: build("for_env", env, seed=0), buffer, config, on_fit=on_fit)
        startup = {
            "ray_init": ray_init,
            **{k: v for k, v in source.startup.items() if k != "ray_init"},
        }
    finally:
        source.close()
        ray.shutdown()
    med = lambda xs: statistics.median(xs)  # noqa: E731
    total = med([t.total_s for t in timings])
    broadcast = med([t.broadcast_s for t in timings])
    play = med([t.play_s for t in timings])
    return {
        "workers": workers,
        "startup_s": startup,
        "round_s": total,
        "broadcast_s": broadcast,
        "play_s": play,
        "gather_s": med([t.total_s - t.broadcast_s - t.play_s for t in timings]),
        "rows_per_round": (len(buffer) - rollout_rows(buffer)) / (cfg.rounds + 1),
    }


def rollout_rows(buffer: DemonstrationBuffer) -> int:
    """Rows of round 0 (the demonstrations)."""
    return int((buffer.data["round"] == 0).sum())


def projection(runs: list[dict], n: int) -> dict:
    """``T(n) = broadcast(n) + W / n + gather(n)``, overheads linear in the worker count."""
    one = runs[0]
    work = one["play_s"]  # W: a round's play on one worker

    def linear(key: str) -> float:
        if len(runs) < 2:
            return one[key]  # one point: taken as constant
        x1 = (runs[1][key] - one[key]) / (runs[1]["workers"] - one["workers"])
        return max(0.0, one[key] - x1 * one["workers"] + x1 * n)

    t_n = linear("broadcast_s") + work / n + linear("gather_s")
    return {
        "workers": n,
        "formula": "T(N) = broadcast(N) + W / N + gather(N); x(N) = x0 + x1 * N fitted on the runs",
        "W_s": work,
        "broadcast_s": linear("broadcast_s"),
        "gather_s": linear("gather_s"),
        "round_s": t_n,
        "speedup": one["round_s"] / t_n,
    }


def main(argv: list[str] | None = None) -> dict:
    parser = _report.parser(__doc__)
    parser.add_argument(
        "--work",
        choices=("busy", "sleep"),
        default="busy",
        help="busy: a spinning loop holds a core; sleep: time.sleep frees it",
    )
    args = parser.parse_args(argv)
    out_dir = _report.destination(NAME, quick=args.quick, out=args.out)
    cfg = dataclasses.replace(QUICK if args.quick else Config(), work=args.work)
    torch.set_num_threads(1)
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    runs = [measure(cfg, n) for n in cfg.workers]
    proj = projection(runs, cfg.project_to)
    rows = []
    for r in runs:
        s = r["startup_s"]
        rows.append([
            r["workers"], f"{r['round_s']:.2f} s", f"{runs[0]['round_s'] / r['round_s']:.2f}x",
            f"{r['broadcast_s'] * 1e3:.1f} ms", f"{r['gather_s'] * 1e3:.1f} ms",
            f"{r['play_s']:.2f} s",
            f"{s['ray_init']:.1f} + {s['actors']:.1f} + {s['first_weights']:.1f} s",
        ])  # fmt: skip
    rows.append([
        f"{proj['workers']} (projected)", f"{proj['round_s']:.2f} s", f"{proj['speedup']:.1f}x",
        f"{proj['broadcast_s'] * 1e3:.1f} ms", f"{proj['gather_s'] * 1e3:.1f} ms",
        f"{proj['W_s'] / proj['workers']:.3f} s", "",
    ])  # fmt: skip
    header = [
        "workers", "round", "speedup", "broadcast", "dispatch + gather", "slowest worker",
        "start-up (ray.init + actors + first weights)",
    ]  # fmt: skip
    print(_report.table(header, rows))
    print(proj["formula"])
    md = (
        f"{cfg.env} + {cfg.work_ms} ms of {cfg.work} work per step, {cfg.episodes_per_round} "
        f"episodes per relabel round, median of {cfg.rounds} rounds.\n\n"
        + _report.table(header, rows)
        + f"\n\nProjection: {proj['formula']}.\n"
    )
    payload = {"config": cfg.__dict__, "runs": runs, "projection": proj}
    print("results:", _report.write(NAME, payload, md, out_dir=out_dir))
    return payload


if __name__ == "__main__":
    main()
