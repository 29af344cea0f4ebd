"""Training on the device it is given (issue 28): imitrl's fits against a plain torch loop.

On the device named by ``--device`` (default ``auto``: CUDA when present), with the
learner there and the rows on the CPU as every imitrl fit keeps them:

1. pixel BC, 84x84x3 uint8 images, batch 256, the camera benchmark's Nature CNN
   (32-64-64, MLP 256): ``fit_bc`` with ``build("for_env", ...)``'s CNN against a plain torch
   loop of the same network on the same device (rows moved to the device per step in
   both, samples/s; target: imitrl >= 0.9x);
2. ``flow_chunk``, ``diffusion_chunk`` and ``act`` fits (registry learners, 64-64 MLPs
   or ACT's transformer, CartPole-sized observations, horizon-8 chunk labels):
   samples/s;
3. one CartPole DAgger round (a fit of 200 steps and 4 relabelled episodes) with the
   learner on the device, the env and the expert on the CPU: seconds.

Every timing is the best of ``repeats`` runs after one warm-up, with the device
synchronised before each clock read; the machine's load is recorded beside it.
``--quick`` is a smoke run (tiny images and budgets) that never writes the committed
results. Run::

    python benchmarks/gpu.py                 # auto: CUDA if present
    python benchmarks/gpu.py --device cpu --quick
"""

from __future__ import annotations

import dataclasses
import logging
import os
import sys
import time

import torch
import torch.nn.functional as F

import _report
from camera import ACTION, plain_cnn, throughput_data
from camera import Config as CameraConfig
from imitrl import keys
from imitrl.algorithms import BCConfig, DAggerConfig, EnvSource, dagger, fit_bc
from imitrl.data import DemonstrationBuffer
from imitrl.data.chunks import add_chunk_labels
from imitrl.envs import make_env
from imitrl.experts import cartpole_expert
from imitrl.learners import TaskSpec, build, registry
from imitrl.runtime import rollout_episodes
from imitrl.system.device import resolve_device

NAME = "gpu"


@dataclasses.dataclass(frozen=True)
class Config:
    image: tuple[int, int] = (84, 84)
    """camera size of the pixel fit"""
    rows: int = 4096
    """rows of every fit (kept on the CPU)"""
    batch_size: int = 256
    """rows per step"""
    timed_steps: int = 50
    """timed steps per fit"""
    repeats: int = 3
    """timed runs per measurement (the best is kept), after one warm-up"""
    chunk_losses: tuple[str, ...] = ("flow_chunk", "diffusion_chunk", "act")
    """registry losses of part 2"""
    dagger_fit_steps: int = 200
    """the DAgger round's fit"""


QUICK = Config(image=(36, 36), rows=64, batch_size=16, timed_steps=2, repeats=1, dagger_fit_steps=5)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _timed(fn, repeats: int) -> list[float]:
    """``repeats`` results of ``fn`` after one untimed warm-up (kernels, allocator)."""
    fn()
    return [fn() for _ in range(repeats)]


def pixel_fits(cfg: Config, device: torch.device) -> dict:
    """Part 1: ``fit_bc`` against a plain torch loop, same network, same device."""
    cam = dataclasses.replace(
        CameraConfig(), image=cfg.image, rows=cfg.rows, batch_size=cfg.batch_size
    )
    data = throughput_data(cam)  # uint8 [rows, H, W, 3] on the CPU

    def plain() -> float:
        net = plain_cnn(cam).to(device)
        opt = torch.optim.Adam(net.parameters(), lr=1e-3)
        g = torch.Generator().manual_seed(0)
        pixels, labels = data[keys.PIXELS], data[keys.EXPERT_ACTION]
        _sync(device)
        t0 = time.perf_counter()
        for _ in range(cfg.timed_steps):
            idx = torch.randint(cfg.rows, (cfg.batch_size,), generator=g)
            x = (
                pixels[idx].pin_memory().to(device, non_blocking=True)
                if device.type == "cuda"
                else pixels[idx]
            )
            y = labels[idx].to(device, non_blocking=True)
            loss = F.mse_loss(net(x.float().div(255.0).movedim(-1, -3)), y)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        _sync(device)
        return cfg.timed_steps * cfg.batch_size / (time.perf_counter() - t0)

    def imitrl() -> float:
        learner = build(
            "for_env",
            TaskSpec.from_specs(None, ACTION, pixels=(*cfg.image, 3)),
            lr=1e-3,
            device=device,
        )
        bc = BCConfig(num_steps=cfg.timed_steps, batch_size=cfg.batch_size)
        _sync(device)
        t0 = time.perf_counter()
        fit_bc(learner, data, bc)
        _sync(device)
        return cfg.timed_steps * cfg.batch_size / (time.perf_counter() - t0)

    p, i = max(_timed(plain, cfg.repeats)), max(_timed(imitrl, cfg.repeats))
    return {"plain_samples_per_s": p, "imitrl_samples_per_s": i, "ratio": i / p}


def chunk_fits(cfg: Config, device: torch.device) -> dict:
    """Part 2: samples/s of each chunked loss's fit (labels of horizon 8)."""
    g = torch.Generator().manual_seed(0)
    n = cfg.rows
    rows = {
        keys.OBSERVATION: torch.randn(n, 4, generator=g),
        keys.EXPERT_ACTION: torch.rand(n, 1, generator=g) * 2 - 1,
        keys.EPISODE: torch.arange(n) // 64,
        keys.STEP: torch.arange(n) % 64,
    }
    from tensordict import TensorDict
    from torchrl.data import Bounded

    task = TaskSpec(action=Bounded(-1.0, 1.0, shape=(1,)), observation_dim=4)
    out = {}
    for name in cfg.chunk_losses:
        labelled = add_chunk_labels(TensorDict(rows, [n]), registry.get(name).horizon)

        def fit(name=name, labelled=labelled) -> float:
            learner = build(name, task, seed=0, device=str(device))
            _sync(device)
            t0 = time.perf_counter()
            fit_bc(
                learner, labelled, BCConfig(num_steps=cfg.timed_steps, batch_size=cfg.batch_size)
            )
            _sync(device)
            return cfg.timed_steps * cfg.batch_size / (time.perf_counter() - t0)

        out[name] = {"samples_per_s": max(_timed(fit, cfg.repeats))}
    return out


def dagger_round(cfg: Config, device: torch.device) -> dict:
    """Part 3: seconds of one CartPole DAgger round (a fit, then 4 relabelled episodes)."""
    env = make_env("CartPole-v1", seed=0, num_envs=4)
    expert = cartpole_expert()

    def once() -> float:
        buffer = DemonstrationBuffer(action_spec=env.action_spec_unbatched)
        buffer.extend(rollout_episodes(env, expert, 4))
        config = DAggerConfig(
            rounds=2,
            episodes_per_round=4,
            bc=BCConfig(num_steps=cfg.dagger_fit_steps, batch_size=256),
        )
        _sync(device)
        t0 = time.perf_counter()
        dagger(EnvSource(env), expert, lambda: build("for_env", env, seed=0, device=device),
               buffer, config)  # fmt: skip
        _sync(device)
        return time.perf_counter() - t0

    return {"seconds": min(_timed(once, cfg.repeats))}


def markdown(results: dict) -> str:
    px = results["pixel"]
    lines = [
        f"Device: {results['device_name']} (`--device {results['device']}`), load "
        f"{results['load']:.2f} before the run.",
        "",
        "| fit | samples/s | x plain torch |",
        "|---|---|---|",
        f"| pixel BC, plain torch loop | {px['plain_samples_per_s']:,.0f} | 1.00 |",
        f"| pixel BC, imitrl `fit_bc` | {px['imitrl_samples_per_s']:,.0f} | {px['ratio']:.2f} |",
    ]
    for name, r in results["chunks"].items():
        lines.append(f"| `{name}` | {r['samples_per_s']:,.0f} | |")
    lines.append("")
    lines.append(
        f"One CartPole DAgger round (learner on the device): {results['dagger']['seconds']:.2f} s."
    )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    parser = _report.parser(__doc__)
    parser.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N")
    args = parser.parse_args(argv)
    device = resolve_device(args.device)
    out_dir = _report.destination(NAME, quick=args.quick, out=args.out)
    cfg = QUICK if args.quick else Config()
    torch.set_num_threads(1)  # the CPU side (batches, the env); CUDA kernels are not affected
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    name = (
        torch.cuda.get_device_name(device)
        if device.type == "cuda"
        else f"CPU ({os.cpu_count()} cores, 1 thread)"
    )
    results = {"device": str(device), "device_name": name, "config": dataclasses.asdict(cfg),
               "load": os.getloadavg()[0]}  # fmt: skip
    t0 = time.perf_counter()
    results["pixel"] = pixel_fits(cfg, device)
    print(f"pixel: {results['pixel']}", file=sys.stderr, flush=True)
    results["chunks"] = chunk_fits(cfg, device)
    print(f"chunks: {results['chunks']}", file=sys.stderr, flush=True)
    results["dagger"] = dagger_round(cfg, device)
    results["seconds"] = time.perf_counter() - t0
    md = markdown(results)
    print("results:", _report.write(NAME, results, md, out_dir=out_dir))
    print(md)
    return results


if __name__ == "__main__":
    main()
