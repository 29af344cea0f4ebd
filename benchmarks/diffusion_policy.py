"""What Diffusion Policy costs on a CPU: a training step, and an action at inference.

For ``diffusion_unet`` (:mod:`imitrl.learners.diffusion_unet`, the registry's CPU
widths 32-64-128) and the paper's widths (256-512-1024), on Meta-World's shapes (39-d
state, 4-d action, ``T_o = 2``, ``T_p = 16``, ``T_a = 8``), one torch thread:

* a training step (forward, backward, AdamW, EMA update) at batch 64 and 256;
* a query (one chunk of 16 actions) at batch 1 (one env) and 10 (ten lanes), sampled by
  DDIM in 10 steps (the registry's) and by DDPM in all 100, and the cost per executed
  action: a query every ``T_a = 8`` steps;
* beside them, the same per-action cost of the other chunked learners the benchmarks
  compare (``flow_chunk``, ``act``, ``mse_chunk``) and of ``mse``.

Each figure is the median of ``repeats`` timed calls after warm-up calls.

    python benchmarks/diffusion_policy.py            # full run, refreshes the README block
    python benchmarks/diffusion_policy.py --quick    # smoke run, into a temporary directory
"""

from __future__ import annotations

import os
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch
from tensordict import TensorDict
from torchrl.data import Bounded
from torchrl.envs.utils import set_exploration_type

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _report
from imitrl import keys
from imitrl.algorithms import BCConfig, fit_bc
from imitrl.data.chunks import IS_INIT
from imitrl.data.history import history_key
from imitrl.learners import TaskSpec, build
from imitrl.learners.diffusion_unet import (
    DIFFUSION_UNET,
    UnetDiffusionConfig,
)

NAME = "diffusion_policy"
TASK = TaskSpec(action=Bounded(-1.0, 1.0, shape=(4,)), observation_dim=39)
FULL = {
    "repeats": 5, "warm": 1, "batches": (64, 256), "lanes": (1, 10), "samplers": ("ddim", "ddpm"),
}  # fmt: skip
QUICK = {"repeats": 1, "warm": 0, "batches": (8,), "lanes": (1,), "samplers": ("ddim",)}
"""the smoke run: every path once, without DDPM's 100 steps at the paper's widths (10 s)"""


def _median_seconds(fn, budget: dict) -> float:
    for _ in range(budget["warm"]):
        fn()
    times = []
    for _ in range(budget["repeats"]):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


CAMERA = (84, 84, 3)
"""the camera learner's images: 84x84 RGB (cropped to 76x76 in training, as the paper)"""


def _rows(n: int, camera: bool = False) -> TensorDict:
    g = torch.Generator().manual_seed(0)
    episode = torch.arange(n) // 50
    rows = TensorDict(
        {
            keys.OBSERVATION: torch.randn(n, 39, generator=g),
            keys.EXPERT_ACTION: torch.rand(n, 4, generator=g) * 2 - 1,
            keys.EPISODE: episode,
            keys.STEP: torch.arange(n) - 50 * episode,
        },
        [n],
    )
    if camera:
        rows.set(keys.PIXELS, torch.randint(0, 256, (n, *CAMERA), dtype=torch.uint8, generator=g))
    return rows


def _unet(widths: str, sampler: str, camera: bool = False):
    unet = DIFFUSION_UNET if widths == "cpu" else UnetDiffusionConfig()
    unet = replace(unet, sampler=sampler)
    pixels = CAMERA if camera else None
    task = (
        TASK
        if pixels is None
        else TaskSpec.from_specs(TASK.observation_dim, TASK.action, pixels=pixels)
    )
    return lambda: build("diffusion_unet", task, options=unet, seed=0)


def _has_camera(learner) -> bool:
    return keys.PIXELS in learner.history_keys


def train_step(make, batch: int, budget: dict) -> float:
    """Seconds per training step at ``batch`` (forward, backward, optimizer, EMA)."""
    learner = make()
    rows = learner.training_rows(_rows(max(4 * batch, 200), camera=_has_camera(learner)))
    steps = budget["warm"] + budget["repeats"]
    t = time.perf_counter()
    fit_bc(learner, rows, BCConfig(num_steps=steps, batch_size=batch))
    return (time.perf_counter() - t) / steps


def query(make, lanes: int, budget: dict) -> float:
    """Seconds per query of the chunk network (a plan of ``T_p`` actions) for ``lanes``."""
    learner = make()
    net = getattr(learner.policy, "network", learner.policy)
    td = TensorDict({k: v for k, v in _inputs(lanes, learner).items()}, [lanes])
    with set_exploration_type(learner.exploration), torch.no_grad():
        return _median_seconds(lambda: net(td.copy()), budget)


def _inputs(lanes: int, learner) -> dict:
    g = torch.Generator().manual_seed(1)
    obs = torch.randn(lanes, 39, generator=g)
    out = {keys.OBSERVATION: obs, IS_INIT: torch.ones(lanes, 1, dtype=torch.bool)}
    if _has_camera(learner):
        out[keys.PIXELS] = torch.randint(0, 256, (lanes, *CAMERA), dtype=torch.uint8, generator=g)
    if learner.history is not None:
        for key in learner.history_keys:
            value = out[key].unsqueeze(1).expand(-1, learner.history, *out[key].shape[1:])
            out[history_key(key)] = value.clone()
    return out


def per_action(make, lanes: int, budget: dict) -> float:
    """Seconds per executed action: the acting policy called step after step (its
    queries every ``k`` steps, or every step for an ensembling or one-step learner)."""
    learner = make()
    inputs = _inputs(lanes, learner)
    calls = 32
    seen = {k: inputs[k] for k in learner.history_keys or (keys.OBSERVATION,)}

    def episode() -> None:  # every lane reset at its first call
        for t in range(calls):
            init = torch.full((lanes, 1), t == 0)
            learner.policy(TensorDict({**seen, IS_INIT: init}, [lanes]))

    with set_exploration_type(learner.exploration), torch.no_grad():
        return _median_seconds(episode, budget) / calls


def measure(budget: dict) -> dict:
    out: dict = {"train": [], "query": [], "action": []}
    for widths in ("cpu", "paper"):
        make = _unet(widths, "ddim")
        for batch in budget["batches"]:
            seconds = train_step(make, batch, budget)
            out["train"].append({"widths": widths, "batch": batch, "seconds": seconds})
            print(f"train {widths} batch {batch}: {seconds * 1e3:.0f} ms", file=sys.stderr)
        for sampler in budget["samplers"]:
            for lanes in budget["lanes"]:
                seconds = query(_unet(widths, sampler), lanes, budget)
                out["query"].append(
                    {"widths": widths, "sampler": sampler, "lanes": lanes, "seconds": seconds}
                )
                print(f"query {widths} {sampler} x{lanes}: {seconds * 1e3:.1f} ms", file=sys.stderr)
    others = {
        name: (
            lambda name=name: build(name, TASK, **({} if name == "act" else {"hidden": (128, 128)}))
        )
        for name in ("mse", "mse_chunk", "flow_chunk", "act")
    }
    camera = _unet("cpu", "ddim", camera=True)  # ResNet-18 (GroupNorm) + spatial softmax
    for batch in budget["batches"]:
        seconds = train_step(camera, batch, budget)
        out["train"].append({"widths": "cpu + camera", "batch": batch, "seconds": seconds})
        print(f"train cpu + camera batch {batch}: {seconds * 1e3:.0f} ms", file=sys.stderr)
    for lanes in budget["lanes"]:
        seconds = query(camera, lanes, budget)
        out["query"].append(
            {"widths": "cpu + camera", "sampler": "ddim", "lanes": lanes, "seconds": seconds}
        )
        print(f"query cpu + camera ddim x{lanes}: {seconds * 1e3:.1f} ms", file=sys.stderr)
    makers = {"diffusion_unet": _unet("cpu", "ddim"), "diffusion_unet + camera": camera}
    for name, make in {**makers, **others}.items():
        for lanes in budget["lanes"]:
            seconds = per_action(make, lanes, budget)
            out["action"].append({"loss": name, "lanes": lanes, "seconds": seconds})
            print(f"action {name} x{lanes}: {seconds * 1e3:.2f} ms", file=sys.stderr)
    return out


def markdown(payload: dict) -> str:
    m = payload["measured"]
    train = _report.table(
        ["U-Net widths", "parameters", "batch", "ms per training step"],
        [[r["widths"], f"{payload['parameters'][r['widths']]:,}", r["batch"],
          f"{r['seconds'] * 1e3:.0f}"] for r in m["train"]],
    )  # fmt: skip
    query = _report.table(
        ["U-Net widths", "sampler", "lanes", "ms per query (16 actions)", "ms per action (T_a = 8)"],
        [[r["widths"], r["sampler"], r["lanes"], f"{r['seconds'] * 1e3:.1f}",
          f"{r['seconds'] / 8 * 1e3:.2f}"] for r in m["query"]],
    )  # fmt: skip
    action = _report.table(
        ["learner", "lanes", "ms per executed action (the acting policy, every step)"],
        [[r["loss"], r["lanes"], f"{r['seconds'] * 1e3:.2f}"] for r in m["action"]],
    )
    return "\n\n".join(
        [
            f"One torch thread, Meta-World's shapes (39-d state, 4-d action); median of "
            f"{payload['budget']['repeats']} timed calls; 1-min load "
            f"{payload['load_average_start'][0]:.2f} at the start; wall time "
            f"{payload['wall_seconds'] / 60:.1f} min. CPU only: no GPU was available. "
            "Parameters: the U-Net's; with the camera, the whole network (the U-Net at CPU "
            f"widths and the ResNet-18 encoder with its spatial softmax, {CAMERA[0]}x"
            f"{CAMERA[1]} images cropped to 76x76 in training).",
            train,
            query,
            action,
        ]
    )


def main(argv: list[str] | None = None) -> None:
    args = _report.parser(__doc__).parse_args(argv)
    out_dir = _report.destination(NAME, quick=args.quick, out=args.out)
    torch.set_num_threads(1)
    budget = QUICK if args.quick else FULL
    load, t0 = os.getloadavg(), time.perf_counter()
    params = {
        w: sum(p.numel() for p in _unet(w, "ddim")().policy.network.unet.parameters())
        for w in ("cpu", "paper")
    }
    camera = _unet("cpu", "ddim", camera=True)().policy.network
    params["cpu + camera"] = sum(p.numel() for p in camera.parameters())
    measured = measure(budget)
    payload = {
        "budget": {k: list(v) if isinstance(v, tuple) else v for k, v in budget.items()},
        "parameters": params,
        "measured": measured,
        "wall_seconds": time.perf_counter() - t0,
        "load_average_start": list(load),
    }
    text = markdown(payload)
    path = _report.write(NAME, payload, text, out_dir=out_dir)
    print(text)
    print(f"results: {path}")


if __name__ == "__main__":
    main()
