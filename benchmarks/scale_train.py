"""Data-parallel fits: samples/s at 1 and 2 CPU ranks, the all-reduce's cost, and the
equivalence of the two.

What ``--nproc`` (:mod:`imitrl.system.ranks`) is for. Two learners, each fitted on the
same synthetic rows with the same global batch, as one process and as two gloo ranks
each holding half of every batch:

* ``cnn``: the camera learner, ``build("for_env", ...)``'s Nature CNN on 84x84x3 uint8
  images (2 bounded actions, MSE), global batch 256 (benchmarks/gpu.py's);
* ``mlp``: ``build("mse", ...)``'s 64-64 MLP on 17-d states (6 bounded actions), global
  batch 256: a step cheaper than an all-reduce.

Each measurement is a fresh process tree: ``python benchmarks/scale_train.py --measure``
for one rank, the same under ``torchrun --standalone --nproc-per-node 2`` for two (a plain
script, as a user runs one), one torch thread per rank. A measurement fits ``warmup``
steps, then times ``steps`` ``fit_bc`` steps (the whole call); it also times
``reduces`` all-reduces of the learner's flat gradient alone. Reported: the median
samples/s (global batch x steps / seconds) over ``repeats`` alternating repeats, the
speed-up of 2 ranks over 1, the all-reduce's milliseconds and its share of a 2-rank step,
the 1-minute load average before each measurement, and the largest relative difference
between the parameters the two runs end with (the equivalence of
``tests/system/test_ranks.py``, at this size).

    python benchmarks/scale_train.py              # full run, refreshes README
    python benchmarks/scale_train.py --quick      # smoke run, into a temporary directory
"""

from __future__ import annotations

import dataclasses
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import _report

NAME = "scale_train"
NETWORKS = ("cnn", "mlp")
GLOBAL_BATCH = {"cnn": 256, "mlp": 256}


@dataclass(frozen=True)
class Config:
    """The whole run."""

    steps: int = 60
    """timed fit_bc steps per measurement"""
    warmup: int = 5
    """fit_bc steps before the timed ones"""
    rows: int = 2048
    """synthetic rows the learner is fitted on"""
    reduces: int = 50
    """timed all-reduces of the flat gradient"""
    repeats: int = 3
    """measurements of each (network, ranks), alternating"""
    image: int = 84
    """the camera's height and width"""
    networks: tuple[str, ...] = NETWORKS
    """the learners measured (of :data:`NETWORKS`)"""


QUICK = Config(steps=4, warmup=1, rows=256, reduces=3, repeats=1, image=36, networks=("cnn",))
"""the smoke run: the CNN alone (the MLP runs the same ranks and all-reduce; each
measurement is a fresh process tree of three interpreters)"""


def _learner_and_rows(network: str, cfg: Config):
    import torch
    from tensordict import TensorDict
    from torchrl.data import Bounded

    from imitrl.learners import TaskSpec, build

    g = torch.Generator().manual_seed(0)
    n = cfg.rows
    if network == "cnn":
        size = (cfg.image, cfg.image, 3)
        task = TaskSpec.from_specs(None, Bounded(-1.0, 1.0, (2,)), pixels=size)
        pixels = torch.randint(0, 256, (n, *size), generator=g, dtype=torch.uint8)
        labels = torch.rand(n, 2, generator=g) * 2 - 1
        rows = TensorDict({"pixels": pixels, "expert_action": labels}, [n])
        learner = build("for_env", task, head="deterministic", loss="mse", seed=0)
    else:
        task = TaskSpec(action=Bounded(-1.0, 1.0, (6,)), observation_dim=17)
        obs = torch.randn(n, 17, generator=g)
        labels = torch.rand(n, 6, generator=g) * 2 - 1
        rows = TensorDict({"observation": obs, "expert_action": labels}, [n])
        learner = build("mse", task, hidden=(64, 64), seed=0)
    return learner, rows


def measure(network: str, cfg: Config, out: str) -> None:
    """One measurement in this process (a rank when ``torchrun`` started it)."""
    import torch

    from imitrl.algorithms import BCConfig, fit_bc
    from imitrl.system import set_threads

    set_threads(1)
    ranked = "RANK" in os.environ
    if ranked:
        import torch.distributed as dist

        dist.init_process_group("gloo")
    rank, world = (dist.get_rank(), dist.get_world_size()) if ranked else (0, 1)
    learner, rows = _learner_and_rows(network, cfg)
    batch = GLOBAL_BATCH[network] // world
    fit_bc(learner, rows, BCConfig(num_steps=cfg.warmup, batch_size=batch, seed=1))
    if ranked:
        dist.barrier()
    t0 = time.perf_counter()
    fit_bc(learner, rows, BCConfig(num_steps=cfg.steps, batch_size=batch, seed=2))
    seconds = time.perf_counter() - t0
    reduce_ms = None
    if ranked:
        flat = torch.cat([p.detach().reshape(-1) for p in learner.policy.parameters()])
        dist.barrier()
        t1 = time.perf_counter()
        for _ in range(cfg.reduces):
            dist.all_reduce(flat.clone())
        reduce_ms = 1000 * (time.perf_counter() - t1) / cfg.reduces
        seconds = max(_gather(seconds, world))  # the step waits for the slowest rank
    if rank == 0:
        params = {k: v.detach() for k, v in learner.policy.state_dict().items()}
        torch.save({"seconds": seconds, "reduce_ms": reduce_ms, "params": params}, out)
    if ranked:
        dist.destroy_process_group()


def _gather(value: float, world: int) -> list[float]:
    import torch
    import torch.distributed as dist

    values = [torch.zeros(1, dtype=torch.float64) for _ in range(world)]
    dist.all_gather(values, torch.tensor([value], dtype=torch.float64))
    return [float(v) for v in values]


def _one(network: str, ranks: int, cfg: Config) -> dict:
    """One measurement in a fresh process tree; its seconds, all-reduce ms and params."""
    import torch

    with tempfile.TemporaryDirectory() as tmp:
        out = str(Path(tmp) / "out.pt")
        script = [str(Path(__file__).resolve()), "--measure", network,
                  "--measure-config", json.dumps(dataclasses.asdict(cfg)), "--measure-out", out]  # fmt: skip
        if ranks == 1:
            cmd = [sys.executable, *script]
        else:
            cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone",
                   f"--nproc-per-node={ranks}", *script]  # fmt: skip
        env = {**os.environ, "OMP_NUM_THREADS": "1"}
        load = os.getloadavg()[0]
        subprocess.run(cmd, check=True, env=env, stdout=subprocess.DEVNULL)
        found = torch.load(out)
    found["load"] = load
    return found


def run(cfg: Config, say) -> tuple[list[dict], dict]:
    rows, drift = [], {}
    for network in cfg.networks:
        last: dict = {}
        for repeat in range(cfg.repeats):
            for ranks in (1, 2) if repeat % 2 == 0 else (2, 1):
                m = _one(network, ranks, cfg)
                last[ranks] = m["params"]
                sps = GLOBAL_BATCH[network] * cfg.steps / m["seconds"]
                rows.append({"network": network, "ranks": ranks, "repeat": repeat,
                             "seconds": m["seconds"], "samples_per_s": sps,
                             "reduce_ms": m["reduce_ms"], "load": m["load"]})  # fmt: skip
                say(f"{network} ranks={ranks} repeat={repeat}: {sps:,.0f} samples/s, "
                    f"load {m['load']:.2f}")  # fmt: skip
        drift[network] = max(
            ((last[2][k] - v).norm() / v.norm().clamp_min(1e-12)).item()
            for k, v in last[1].items()
            if v.is_floating_point()
        )
    return rows, drift


def summary(cfg: Config, rows: list[dict], drift: dict) -> dict:
    out = {}
    for network in cfg.networks:
        mine = [r for r in rows if r["network"] == network]
        sps = {k: statistics.median(r["samples_per_s"] for r in mine if r["ranks"] == k)
               for k in (1, 2)}  # fmt: skip
        reduce_ms = statistics.median(r["reduce_ms"] for r in mine if r["ranks"] == 2)
        step_ms = 1000 * GLOBAL_BATCH[network] / sps[2]
        out[network] = {
            "global_batch": GLOBAL_BATCH[network],
            "samples_per_s_1_rank": sps[1],
            "samples_per_s_2_ranks": sps[2],
            "speedup": sps[2] / sps[1],
            "allreduce_ms": reduce_ms,
            "allreduce_share_of_step": reduce_ms / step_ms,
            "max_relative_param_difference": drift[network],
            "load": [min(r["load"] for r in mine), max(r["load"] for r in mine)],
        }
    return out


def markdown(cfg: Config, summ: dict, wall: float) -> str:
    header = ["learner", "global batch", "1 rank (samples/s)", "2 ranks (samples/s)",
              "2 ranks / 1", "all-reduce (ms)", "of a 2-rank step", "params, max rel. diff",
              "load"]  # fmt: skip
    body = [
        [n, s["global_batch"], f"{s['samples_per_s_1_rank']:,.0f}",
         f"{s['samples_per_s_2_ranks']:,.0f}", f"{s['speedup']:.2f}x",
         f"{s['allreduce_ms']:.2f}", f"{100 * s['allreduce_share_of_step']:.1f}%",
         f"{s['max_relative_param_difference']:.1e}", f"{s['load'][0]:.2f}-{s['load'][1]:.2f}"]
        for n, s in summ.items()
    ]  # fmt: skip
    return _report.section(
        "Data-parallel fits: 1 and 2 CPU ranks (scale_train.py)",
        f"`python benchmarks/scale_train.py` ({wall:.0f} s): {cfg.steps} timed `fit_bc` steps "
        f"after {cfg.warmup}, the same global batch as one process and as two gloo ranks "
        "launched by `torchrun --standalone` (one torch thread each), median of "
        f"{cfg.repeats} alternating repeats, each a fresh process tree; the all-reduce "
        f"timed alone ({cfg.reduces} reduces of the flat gradient); the parameters after "
        "the timed steps compared between the two runs.\n\n"
        + _report.table(header, body)
        + f"\n\n![samples/s](results/{NAME}.png)\n",
    )


def figure(summ: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.4))
    xs = range(len(summ))
    one = [s["samples_per_s_1_rank"] for s in summ.values()]
    two = [s["samples_per_s_2_ranks"] for s in summ.values()]
    ax.bar([x - 0.2 for x in xs], one, 0.4, label="1 rank")
    ax.bar([x + 0.2 for x in xs], two, 0.4, label="2 gloo ranks")
    for x, s in zip(xs, summ.values()):
        ax.annotate(f"{s['speedup']:.2f}x", (x + 0.2, s["samples_per_s_2_ranks"]),
                    ha="center", va="bottom")  # fmt: skip
    ax.set_xticks(list(xs), [f"{n} (batch {s['global_batch']})" for n, s in summ.items()])
    ax.set_yscale("log")
    ax.set_ylabel("samples/s (median)")
    ax.set_title("fit_bc at the same global batch, 2-core CPU")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict | None:
    parser = _report.parser(__doc__)
    parser.add_argument("--measure", default=None, help="(internal) one measurement")
    parser.add_argument("--measure-config", default=None, help="(internal) its config JSON")
    parser.add_argument("--measure-out", default=None, help="(internal) where it writes")
    args = parser.parse_args(argv)
    if args.measure is not None:
        measure(args.measure, Config(**json.loads(args.measure_config)), args.measure_out)
        return None
    out_dir = _report.destination(NAME, quick=args.quick, out=args.out)
    cfg = QUICK if args.quick else Config()
    t0 = time.perf_counter()
    rows, drift = run(cfg, lambda line: print(line, file=sys.stderr, flush=True))
    wall = time.perf_counter() - t0
    summ = summary(cfg, rows, drift)
    figure(summ, _report.results_dir(out_dir) / f"{NAME}.png")
    md = markdown(cfg, summ, wall)
    print(md)
    payload = {"config": dataclasses.asdict(cfg), "summary": summ, "measurements": rows,
               "wall_seconds": wall}  # fmt: skip
    print("results:", _report.write(NAME, payload, md, out_dir=out_dir))
    return payload


if __name__ == "__main__":
    main()
