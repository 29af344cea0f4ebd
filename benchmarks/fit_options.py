"""The options of a fit that change its arithmetic: ``BCConfig(precision="bf16")`` and
``BCConfig(compile=True)``, against the default float32 eager fit (issue 28).

Two fits of 200 steps at batch 256 on fixed random rows: a 64-64 tanh MLP on 4-d
observations (CartPole-sized) and the camera benchmark's CNN on 36x36x3 uint8 images,
each on the device given (``--device``, default ``auto``). Reported per option:
samples/s of the timed steps (the compiled fit's first step, where it compiles, timed
apart) and the final training loss beside the float32 one (equal accuracy is the bar
for turning an option on by default). The defaults in ``BCConfig`` follow these numbers.

    python benchmarks/fit_options.py            # full run, refreshes README
    python benchmarks/fit_options.py --quick    # smoke run, into a temporary directory
"""

from __future__ import annotations

import dataclasses
import logging
import os
import sys
import time

import torch
from tensordict import TensorDict

import _report
from camera import ACTION
from imitrl import keys
from imitrl.algorithms import BCConfig, fit_bc
from imitrl.learners import ActorCritic, TaskSpec, build
from imitrl.system.device import resolve_device

NAME = "fit_options"


@dataclasses.dataclass(frozen=True)
class Config:
    steps: int = 200
    """timed steps per fit"""
    batch_size: int = 256
    rows: int = 4096
    image: tuple[int, int] = (36, 36)
    repeats: int = 3
    """runs per option (the best samples/s is kept; the final loss is the same each run)"""
    compiled: tuple[str, ...] = ("mlp", "cnn")
    """the fits also timed under torch.compile (each compilation takes 10-20 s; none in the
    smoke run: ``tests/system/test_device.py`` checks a compiled fit against the eager one)"""


QUICK = Config(steps=3, batch_size=16, rows=64, image=(36, 36), repeats=1, compiled=())
OPTIONS = {"fp32": {}, "bf16": {"precision": "bf16"}, "compile": {"compile": True}}


def _rows(cfg: Config, kind: str) -> TensorDict:
    g = torch.Generator().manual_seed(0)
    n = cfg.rows
    label = torch.rand(n, 2, generator=g) * 2 - 1
    if kind == "mlp":
        return TensorDict(
            {keys.OBSERVATION: torch.randn(n, 4, generator=g), keys.EXPERT_ACTION: label}, [n]
        )
    pixels = torch.randint(0, 256, (n, *cfg.image, 3), generator=g, dtype=torch.uint8)
    return TensorDict({keys.PIXELS: pixels, keys.EXPERT_ACTION: label}, [n])


def _learner(cfg: Config, kind: str, device: torch.device) -> ActorCritic:
    if kind == "mlp":
        return build(
            "for_env", TaskSpec.from_specs(4, ACTION), hidden=(64, 64), seed=0, device=device
        )
    return build(
        "for_env",
        TaskSpec.from_specs(None, ACTION, pixels=(*cfg.image, 3)),
        channels=(16, 32),
        hidden=(64,),
        seed=0,
        device=device,
    )


def _fit(cfg: Config, kind: str, option: dict, device: torch.device) -> dict:
    rows = _rows(cfg, kind)
    learner = _learner(cfg, kind, device)
    first = BCConfig(num_steps=1, batch_size=cfg.batch_size, seed=0, **option)
    t0 = time.perf_counter()
    fit_bc(learner, rows, first)  # warm-up (and the compilation)
    warm = time.perf_counter() - t0
    config = BCConfig(num_steps=cfg.steps, batch_size=cfg.batch_size, seed=1, **option)
    t0 = time.perf_counter()
    result = fit_bc(learner, rows, config)
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    seconds = time.perf_counter() - t0
    return {"samples_per_s": cfg.steps * cfg.batch_size / seconds, "first_step_s": warm,
            "final_loss": result.final_loss}  # fmt: skip


def main(argv: list[str] | None = None) -> dict:
    parser = _report.parser(__doc__)
    parser.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N")
    args = parser.parse_args(argv)
    device = resolve_device(args.device)
    out_dir = _report.destination(NAME, quick=args.quick, out=args.out)
    cfg = QUICK if args.quick else Config()
    torch.set_num_threads(1)
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    results = {"device": str(device), "config": dataclasses.asdict(cfg), "load": os.getloadavg()[0]}
    for kind in ("mlp", "cnn"):
        for name, option in OPTIONS.items():
            if name == "compile" and kind not in cfg.compiled:
                continue
            runs = [_fit(cfg, kind, option, device) for _ in range(cfg.repeats)]
            best = max(runs, key=lambda r: r["samples_per_s"])
            results[f"{kind}/{name}"] = best
            print(f"{kind} {name}: {best}", file=sys.stderr, flush=True)
    lines = [f"Device `{device}`, 1 thread, 1-min load {results['load']:.2f} before the run; "
             f"{cfg.steps} steps at batch {cfg.batch_size}, best of {cfg.repeats}.", "",
             "| fit | option | samples/s | x fp32 | first step (s) | final loss |",
             "|---|---|---|---|---|---|"]  # fmt: skip
    for kind in ("mlp", "cnn"):
        base = results[f"{kind}/fp32"]["samples_per_s"]
        for name in OPTIONS:
            if f"{kind}/{name}" not in results:
                continue
            r = results[f"{kind}/{name}"]
            lines.append(f"| {kind} | {name} | {r['samples_per_s']:,.0f} | {r['samples_per_s'] / base:.2f} "
                         f"| {r['first_step_s']:.2f} | {r['final_loss']:.5f} |")  # fmt: skip
    md = "\n".join(lines)
    print("results:", _report.write(NAME, results, md, out_dir=out_dir))
    print(md)
    return results


if __name__ == "__main__":
    main()
