"""torch threads: 100 fit_bc steps at 1 and 2 threads, on a quiet machine and beside a busy core.

What ``imitrl.system.threads.DEFAULT_THREADS`` (every command's ``--threads``) rests on.
Two networks, each trained two ways on the same rows:

* MLP 4-64-64-2 (tanh, observations normalised, cross-entropy) on CartPole-sized rows:
  ``build("for_env", TaskSpec.from_specs(4, 2))`` (the library's default MLP) through ``fit_bc``, and the same
  layers in a plain torch loop (Adam, minibatches without replacement);
* the camera study's small CNN on 32x32x3 uint8 images (conv 16 and 32 channels, kernel
  3, stride 2; MLP 64; 2 bounded actions, MSE): ``build("for_env", ...)``'s CNN through
  ``fit_bc``, and the same layers in a plain torch loop.

Each measurement is ``steps`` (100) minibatch steps, wall time of the whole call
(``fit_bc``'s checks and normaliser included), after a 2-step warm-up of each. Every
repeat runs in a fresh process (``--measure``) that sets its thread count with
``set_threads`` before torch computes anything, so torch never starts with another
count. The conditions, repeats alternating 1 and 2 threads:

a. quiet: nothing else is started;
b. busy: one ``python -c 'while True: pass'`` process, pinned to the first core of this
   process's affinity set, runs for the whole block (another job, a test run, the OS).

Reported: the median seconds over ``repeats`` of each (network, loop, threads,
condition), and the 1-minute load average read before each measurement. A repeat that
runs past ``timeout_s`` is stopped; what it finished is kept and the rest is reported as
"> timeout".

    python benchmarks/threads.py              # full run, refreshes README
    python benchmarks/threads.py --quick      # smoke run, into a temporary directory
"""

from __future__ import annotations

import dataclasses
import json
import os
import statistics
import subprocess
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass

import _report
from imitrl.learners import TaskSpec, build

NAME = "threads"
NETWORKS = ("mlp", "cnn")
LOOPS = ("plain", "fit_bc")
CONDITIONS = ("quiet", "busy")


@dataclass(frozen=True)
class Config:
    """The whole run."""

    steps: int = 100
    """timed minibatch steps per measurement"""
    threads: tuple[int, ...] = (1, 2)
    """torch threads compared"""
    repeats: int = 5
    """fresh processes per (threads, condition); medians over them"""
    mlp_rows: int = 4096
    """rows of the MLP task (4 observations, 2 actions)"""
    mlp_batch: int = 256
    """minibatch of the MLP fits"""
    pixels: tuple[int, int] = (32, 32)
    """``(H, W)`` of the CNN task's images"""
    cnn_rows: int = 1024
    """rows of the CNN task"""
    cnn_batch: int = 128
    """minibatch of the CNN fits"""
    timeout_s: float = 90.0
    """a repeat (one process: both networks, both loops) is stopped after this long"""
    conditions: tuple[str, ...] = CONDITIONS
    """the blocks run, in this order (of :data:`CONDITIONS`)"""


QUICK = Config(
    steps=3, repeats=1, mlp_rows=64, mlp_batch=16, pixels=(16, 16), cnn_rows=32, cnn_batch=8,
    conditions=("quiet",),
)  # fmt: skip
"""the smoke run: the quiet block alone (the busy block's spinner would hold a core of the
test run's two for the whole block; ``tests/benchmarks/test_threads.py`` starts and stops
it)"""


# ------------------------------------------------ one measurement (a fresh process)
def mlp_data(cfg: Config):
    """CartPole-sized rows: observations ``[n, 4]``, a linear rule's action in {0, 1}."""
    import torch
    from tensordict import TensorDict

    from imitrl import keys

    g = torch.Generator().manual_seed(0)
    obs = torch.randn(cfg.mlp_rows, 4, generator=g)
    label = (obs @ torch.randn(4, 2, generator=g)).argmax(-1)
    return TensorDict({keys.OBSERVATION: obs, keys.EXPERT_ACTION: label}, [cfg.mlp_rows])


def cnn_data(cfg: Config):
    """uint8 images ``[n, H, W, 3]``, an unread state column, labels in [-1, 1] ``[n, 2]``."""
    import torch
    from tensordict import TensorDict

    from imitrl import keys

    g = torch.Generator().manual_seed(0)
    n = cfg.cnn_rows
    pixels = torch.randint(0, 256, (n, *cfg.pixels, 3), generator=g, dtype=torch.uint8)
    label = 2 * torch.rand(n, 2, generator=g) - 1
    columns = {keys.PIXELS: pixels, keys.OBSERVATION: torch.zeros(n, 2), keys.EXPERT_ACTION: label}
    return TensorDict(columns, [n])


def learner(cfg: Config, network: str):
    """The library's learner of ``network`` (its defaults but the sizes above)."""
    from torchrl.data import Bounded

    if network == "mlp":
        return build("for_env", TaskSpec.from_specs(4, 2), hidden=(64, 64), lr=1e-3)
    action = Bounded(-1.0, 1.0, shape=(2,))
    return build(
        "for_env",
        TaskSpec.from_specs(None, action, pixels=(*cfg.pixels, 3)),
        channels=(16, 32),
        hidden=(64,),
        lr=1e-3,
    )


def plain_net(cfg: Config, network: str, data):
    """The same layers in plain torch, and ``(inputs, labels, loss function)``."""
    import torch
    import torch.nn.functional as F
    from torch import nn

    from imitrl import keys

    torch.manual_seed(0)
    if network == "mlp":
        obs = data[keys.OBSERVATION]
        loc, scale = obs.mean(0), obs.std(0, correction=0)  # the library's normaliser
        net = nn.Sequential(
            nn.Linear(4, 64), nn.Tanh(), nn.Linear(64, 64), nn.Tanh(), nn.Linear(64, 2)
        )
        return net, (obs - loc) / scale, data[keys.EXPERT_ACTION], F.cross_entropy
    h, w = ((cfg.pixels[0] + 3) // 4, (cfg.pixels[1] + 3) // 4)  # two stride-2, padding-1 convs
    net = nn.Sequential(
        nn.Conv2d(3, 16, 3, stride=2, padding=1), nn.ReLU(),
        nn.Conv2d(16, 32, 3, stride=2, padding=1), nn.ReLU(),
        nn.Flatten(), nn.Linear(32 * h * w, 64), nn.ReLU(), nn.Linear(64, 2), nn.Tanh(),
    )  # fmt: skip
    images = data[keys.PIXELS].movedim(-1, -3)  # [n, 3, H, W] uint8, scaled per batch
    return net, images, data[keys.EXPERT_ACTION], F.mse_loss


def plain_loop(cfg: Config, network: str, data, steps: int, batch: int) -> float:
    """Seconds of ``steps`` Adam steps of the plain network (built before the clock)."""
    import torch

    net, inputs, labels, loss_fn = plain_net(cfg, network, data)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    n, g = inputs.shape[0], torch.Generator().manual_seed(0)
    perm, cursor = torch.randperm(n, generator=g), 0
    t0 = time.perf_counter()
    for _ in range(steps):
        if cursor + batch > n:
            perm, cursor = torch.randperm(n, generator=g), 0
        idx = perm[cursor : cursor + batch]
        cursor += batch
        x = inputs[idx]
        x = x.float().div(255.0) if x.dtype == torch.uint8 else x
        loss = loss_fn(net(x), labels[idx])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    return time.perf_counter() - t0


def library_fit(cfg: Config, network: str, data, steps: int, batch: int) -> float:
    """Seconds of one ``fit_bc`` call of ``steps`` steps (the learner built before the clock)."""
    from imitrl.algorithms import BCConfig, fit_bc

    fresh = learner(cfg, network)
    t0 = time.perf_counter()
    fit_bc(fresh, data, BCConfig(num_steps=steps, batch_size=batch))
    return time.perf_counter() - t0


def measure(cfg: Config, threads: int) -> None:
    """One repeat, in this (fresh) process: set the threads, then print one JSON line
    ``{"network/loop": seconds}`` per measurement as it finishes (a stopped repeat
    keeps what it printed)."""
    from imitrl.system import set_threads

    set_threads(threads)  # before torch computes anything in this process
    import logging

    logging.getLogger("torchrl").setLevel(logging.WARNING)
    print(json.dumps({"torch_threads": __import__("torch").get_num_threads()}), flush=True)
    for network in NETWORKS:
        data = mlp_data(cfg) if network == "mlp" else cnn_data(cfg)
        batch = cfg.mlp_batch if network == "mlp" else cfg.cnn_batch
        plain_loop(cfg, network, data, 2, batch)  # warm-up: first-call allocations
        library_fit(cfg, network, data, 2, batch)
        for loop in LOOPS:
            run = plain_loop if loop == "plain" else library_fit
            seconds = run(cfg, network, data, cfg.steps, batch)
            print(json.dumps({f"{network}/{loop}": seconds}), flush=True)


# ------------------------------------------------------------ the driver
@contextmanager
def busy_core(busy: bool):
    """``busy``: a spinning Python process pinned to this process's first core, killed after."""
    if not busy:
        yield None
        return
    pin = ""
    if hasattr(os, "sched_setaffinity"):
        pin = f"os.sched_setaffinity(0, {{{min(os.sched_getaffinity(0))}}})\n"
    # `while True: pass`, but it stops by itself if this process dies without killing it
    code = (
        f"import os\n{pin}while os.getppid() == {os.getpid()}:\n"
        "    for _ in range(1_000_000):\n        pass\n"
    )
    spinner = subprocess.Popen([sys.executable, "-c", code])
    try:
        time.sleep(1.0)  # let it start spinning
        yield spinner
    finally:
        spinner.kill()
        spinner.wait()


def repeat(cfg: Config, threads: int, condition: str) -> dict:
    """One fresh process measuring everything at ``threads``; its seconds and the load."""
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    argv = [sys.executable, __file__, "--measure", json.dumps(dataclasses.asdict(cfg))]
    argv += ["--measure-threads", str(threads)]
    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(argv, capture_output=True, text=True, timeout=cfg.timeout_s, env=env)
        out, timed_out = proc.stdout, False
        if proc.returncode != 0:
            raise RuntimeError(f"--measure failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    except subprocess.TimeoutExpired as err:  # its output so far is bytes, whatever text= says
        stdout = err.stdout or b""
        out, timed_out = stdout.decode() if isinstance(stdout, bytes) else stdout, True
    seconds: dict = {}
    for line in out.splitlines():
        if line.startswith("{"):
            seconds.update(json.loads(line))
    if seconds.get("torch_threads", threads) != threads:
        raise RuntimeError(f"asked for {threads} threads, torch ran {seconds['torch_threads']}")
    return {
        "threads": threads,
        "condition": condition,
        "load_1min": load[0],
        "load_5min": load[1],
        "wall_s": time.perf_counter() - t0,
        "timed_out": timed_out,
        "torch_threads": seconds.pop("torch_threads", None),
        "seconds": seconds,
    }


def run(cfg: Config, log) -> list[dict]:
    """Every repeat of each block of ``cfg.conditions`` in turn (the quiet block, then the
    busy block), 1 and 2 threads alternating."""
    rows = []
    for condition in cfg.conditions:
        with busy_core(condition == "busy"):
            for r in range(cfg.repeats):
                for threads in cfg.threads:
                    row = repeat(cfg, threads, condition)
                    rows.append(row)
                    done = ", ".join(f"{k} {v:.2f} s" for k, v in row["seconds"].items())
                    log(f"{condition} repeat {r} threads {threads} (load {row['load_1min']:.2f}"
                        f"){' TIMED OUT' if row['timed_out'] else ''}: {done}")  # fmt: skip
    return rows


# ------------------------------------------------------------ the report
def summary(cfg: Config, rows: list[dict]) -> dict:
    """Median seconds per (network/loop, condition, threads) (None: a repeat timed out
    before it; then the median is over the finished ones, flagged), and median load."""
    out: dict = {"seconds": {}, "timeouts": {}, "load_1min": {}}
    for condition in cfg.conditions:
        for threads in cfg.threads:
            these = [r for r in rows if r["condition"] == condition and r["threads"] == threads]
            cell = f"{condition}/{threads}"
            out["load_1min"][cell] = statistics.median(r["load_1min"] for r in these)
            for network in NETWORKS:
                for loop in LOOPS:
                    key = f"{network}/{loop}"
                    done = [r["seconds"][key] for r in these if key in r["seconds"]]
                    out["seconds"].setdefault(key, {})[cell] = (
                        statistics.median(done) if done else None
                    )
                    out["timeouts"].setdefault(key, {})[cell] = len(these) - len(done)
    return out


def _cell(cfg: Config, seconds: float | None, missing: int) -> str:
    if seconds is None:
        return f"> {cfg.timeout_s:.0f}"
    return f"{seconds:.2f}" + (f" ({missing} > {cfg.timeout_s:.0f})" if missing else "")


def _ratio(a: float | None, b: float | None) -> str:
    return "-" if a is None or b is None else f"{a / b:.1f}x"


def markdown(cfg: Config, summ: dict, wall: float) -> str:
    """The README block: medians, the 2-thread / 1-thread ratio, the load, the default."""
    from imitrl.system.threads import DEFAULT_THREADS

    names = {"mlp": "MLP 4-64-64-2", "cnn": f"CNN {cfg.pixels[0]}x{cfg.pixels[1]}x3 16-32"}
    loops = {"plain": "plain torch loop", "fit_bc": "imitrl fit_bc"}
    header = ["what"]
    for condition in cfg.conditions:
        header += [f"{condition}, {t} thread{'s' if t > 1 else ''}" for t in cfg.threads]
        header.append(f"{condition}: 2 / 1 threads")
    rows, worst, best = [], 0.0, float("inf")
    for key, cells in summ["seconds"].items():
        network, loop = key.split("/")
        row = [f"{names[network]}, {loops[loop]}"]
        for condition in cfg.conditions:
            row += [
                _cell(cfg, cells[f"{condition}/{t}"], summ["timeouts"][key][f"{condition}/{t}"])
                for t in cfg.threads
            ]
            one, two = cells[f"{condition}/1"], cells[f"{condition}/2"]
            row.append(_ratio(two, one))
            if one and two:
                worst, best = max(worst, two / one), min(best, two / one)
        rows.append(row)
    load = ["machine load (1-min, median before each)"]
    for condition in cfg.conditions:
        load += [f"{summ['load_1min'][f'{condition}/{t}']:.2f}" for t in cfg.threads] + [""]
    rows.append(load)
    return (
        f"Seconds for {cfg.steps} minibatch steps (MLP batch {cfg.mlp_batch}, CNN batch "
        f"{cfg.cnn_batch}), median of {cfg.repeats} fresh processes per cell; busy = one "
        "spinning process pinned to one core. Total wall time "
        f"{wall / 60:.1f} min on {os.cpu_count()} CPU cores.\n\n"
        + _report.table(header, rows)
        + f"\n\n2 threads / 1 thread ranged from {best:.2f}x to {worst:.1f}x the time. "
        f"Default: `DEFAULT_THREADS = {DEFAULT_THREADS}` (every command's `--threads`; "
        "workers of `--jobs` and Ray get one each)."
    )


def main(argv: list[str] | None = None) -> dict | None:
    parser = _report.parser(__doc__)
    parser.add_argument("--measure", default=None, help="(internal) one repeat: the config JSON")
    parser.add_argument("--measure-threads", type=int, default=1, help="(internal) its threads")
    args = parser.parse_args(argv)
    if args.measure is not None:
        fields = json.loads(args.measure)
        measure(Config(**{k: tuple(v) if isinstance(v, list) else v for k, v in fields.items()}),
                args.measure_threads)  # fmt: skip
        return None
    out_dir = _report.destination(NAME, quick=args.quick, out=args.out)
    cfg = QUICK if args.quick else Config()
    t0 = time.perf_counter()
    rows = run(cfg, lambda line: print(line, flush=True))
    wall = time.perf_counter() - t0
    summ = summary(cfg, rows)
    md = markdown(cfg, summ, wall)
    print(md)
    payload = {"config": dataclasses.asdict(cfg), "summary": summ, "repeats": rows,
               "wall_seconds": wall}  # fmt: skip
    print("results:", _report.write(NAME, payload, md, out_dir=out_dir))
    return payload


if __name__ == "__main__":
    main()
