"""A demonstration buffer bigger than memory: 1e8 CartPole rows on disk, sampled and fitted.

Builds a `DemonstrationBuffer(path=...)` of `rows` CartPole-shaped rows (float32
observations [4], int64 actions, 57 bytes a row with the buffer's own keys) by `extend`
of `chunk` rows at a time (the storage grows by doubling: each growth lengthens the
files and maps them again, timed separately), samples `sample_batches` minibatches from
it, and reads the process's memory from `/proc/self/status` after each phase: VmHWM (peak
resident), RssAnon (the process's own memory) and RssFile (mapped file pages: page
cache, which the kernel reclaims). Then minibatch `fit_bc` throughput (MLP 4-256-256-2,
batch 256) on a disk buffer of `fit_rows` rows against the same fit on an in-memory
buffer of the same rows (target >= 0.8x), best of `repeats`.

The disk buffer goes in a temporary directory under `--scratch` (default: the system's
temporary directory), removed at the end; with less free disk than the rows need (plus
10%), the largest multiple of `chunk` that fits is built and the JSON says so.

    python benchmarks/scale_buffer.py --out benchmarks/results   # 1e8 rows (6.4 GB)
    python benchmarks/scale_buffer.py --quick                     # 2e6 rows, a temp dir
"""

from __future__ import annotations

import logging
import shutil
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from tensordict import TensorDict

import _report
from imitrl import keys
from imitrl.algorithms import BCConfig, fit_bc
from imitrl.data import DemonstrationBuffer
from imitrl.learners import TaskSpec
from imitrl.learners import build as build_learner

NAME = "scale_buffer"


@dataclass(frozen=True)
class Config:
    rows: int = 100_000_000
    """rows of the big disk buffer"""
    chunk: int = 1_000_000
    """rows per `extend`"""
    episode_length: int = 500
    """steps per episode (CartPole-v1's time limit)"""
    sample_batches: int = 1_000
    """minibatches sampled from the big buffer"""
    batch_size: int = 256
    """rows per sampled minibatch and per fit step"""
    fit_rows: int = 1_000_000
    """rows of the disk and in-memory buffers whose fits are compared"""
    fit_steps: int = 1_500
    """gradient steps per timed fit"""
    repeats: int = 2
    """fit timings: best of this many (disk and memory alternate)"""
    seed: int = 0
    """seed of the rows and of the fits"""


QUICK = Config(
    rows=2_000_000, chunk=500_000, sample_batches=50, fit_rows=20_000, fit_steps=30, repeats=1
)


def log(*parts: object) -> None:
    print(*parts, file=sys.stderr, flush=True)


def memory() -> dict[str, int]:
    """VmHWM, VmRSS, RssAnon, RssFile of this process, in bytes."""
    fields = dict(line.split(":", 1) for line in open("/proc/self/status"))
    return {k: int(fields[k].split()[0]) << 10 for k in ("VmHWM", "VmRSS", "RssAnon", "RssFile")}


def chunk_rows(n: int, first_row: int, cfg: Config, g: torch.Generator) -> TensorDict:
    """``n`` CartPole-shaped rows starting at global row ``first_row``."""
    row = first_row + torch.arange(n)
    action = torch.randint(0, 2, (n,), generator=g)
    return TensorDict(
        {
            keys.OBSERVATION: torch.randn(n, 4, generator=g),
            keys.ACTION: action,
            keys.EXPERT_ACTION: action.clone(),
            keys.EXPERT_EXECUTED: torch.ones(n, dtype=torch.bool),
            keys.EPISODE: row // cfg.episode_length,
            keys.ROUND: torch.zeros(n, dtype=torch.long),
            keys.STEP: row % cfg.episode_length,
        },
        [n],
    )


def build(path: Path, rows: int, cfg: Config) -> tuple[DemonstrationBuffer, dict]:
    buf = DemonstrationBuffer(path=path, capacity=cfg.chunk)
    g = torch.Generator().manual_seed(cfg.seed)
    growth, plain = [], []
    t0 = time.perf_counter()
    while len(buf) < rows:
        part = chunk_rows(min(cfg.chunk, rows - len(buf)), len(buf), cfg, g)
        capacity, t = buf.capacity, time.perf_counter()
        buf.extend(part)
        (growth if buf.capacity != capacity else plain).append(time.perf_counter() - t)
        if len(buf) % (10 * cfg.chunk) == 0:
            log(f"  {len(buf):,} rows, {time.perf_counter() - t0:.0f} s, {memory()}")
    return buf, {
        "build_s": time.perf_counter() - t0,
        "growths": len(growth),
        "extend_with_growth_s_mean": sum(growth) / max(1, len(growth)),
        "extend_without_growth_s_mean": sum(plain) / max(1, len(plain)),
    }


def fit_throughput(buf: DemonstrationBuffer, cfg: Config) -> float:
    learner = build_learner(
        "for_env", TaskSpec.from_specs(4, 2), hidden=(256, 256), lr=1e-3, seed=cfg.seed
    )
    config = BCConfig(num_steps=1, batch_size=cfg.batch_size, seed=cfg.seed)
    fit_bc(learner, buf, config)  # prepare (normaliser, checks) outside the timing
    t0 = time.perf_counter()
    fit_bc(learner, buf, BCConfig(num_steps=cfg.fit_steps, batch_size=cfg.batch_size))
    return cfg.fit_steps * cfg.batch_size / (time.perf_counter() - t0)


def compare_fits(scratch: Path, cfg: Config) -> dict:
    rows = chunk_rows(cfg.fit_rows, 0, cfg, torch.Generator().manual_seed(cfg.seed + 1))
    mem = DemonstrationBuffer(capacity=cfg.fit_rows)
    mem.extend(rows)
    disk = DemonstrationBuffer(path=scratch / "fit", capacity=cfg.fit_rows)
    disk.extend(rows)
    del rows
    speeds: dict[str, list[float]] = {"memory": [], "disk": []}
    for r in range(cfg.repeats):
        for name, buf in (("memory", mem), ("disk", disk)):
            speeds[name].append(fit_throughput(buf, cfg))
            log(f"  fit {name} #{r}: {speeds[name][-1]:,.0f} samples/s")
    best = {k: max(v) for k, v in speeds.items()}
    return {
        "fit_samples_per_s": best,
        "fit_all": speeds,
        "fit_ratio": best["disk"] / best["memory"],
    }


def main(argv: list[str] | None = None) -> dict:
    p = _report.parser(__doc__)
    p.add_argument("--scratch", type=Path, default=Path(tempfile.gettempdir()))
    args = p.parse_args(argv)
    out_dir = _report.destination(NAME, quick=args.quick, out=args.out)
    cfg = QUICK if args.quick else Config()
    torch.set_num_threads(1)
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    free = shutil.disk_usage(args.scratch).free
    fits = int(free / 1.1) // (57 * cfg.chunk) * cfg.chunk
    rows = min(cfg.rows, fits)
    log(f"{free / 1e9:.1f} GB free under {args.scratch}: building {rows:,} of {cfg.rows:,} rows")
    scratch = Path(tempfile.mkdtemp(prefix=f"{NAME}-", dir=args.scratch))
    try:
        m: dict = {"rows_wanted": cfg.rows, "rows": rows, "free_disk_bytes": free}
        m["memory_start"] = memory()
        buf, m["build"] = build(scratch / "big", rows, cfg)
        m["row_bytes"] = buf.data.bytes()
        m["memory_after_build"] = memory()
        t0 = time.perf_counter()
        for _ in range(cfg.sample_batches):
            buf.sample(cfg.batch_size)
        m["sample_s_per_batch"] = (time.perf_counter() - t0) / cfg.sample_batches
        m["memory_after_sample"] = memory()
        log(f"built and sampled: {m['memory_after_sample']}")
        del buf
        m.update(compare_fits(scratch, cfg))
        m["memory_end"] = memory()
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    gb, mb = 1e9, 1e6
    s, b = m["memory_after_sample"], m["build"]
    table = [
        ["rows on disk", f"{m['rows']:,} ({m['row_bytes'] / gb:.2f} GB)", ""],
        ["build (extend 1e6 rows at a time)", f"{b['build_s']:.0f} s", f"{b['growths']} growths"],
        [
            "extend with / without growth",
            f"{b['extend_with_growth_s_mean']:.3f} s / {b['extend_without_growth_s_mean']:.3f} s",
            "",
        ],
        [f"sample({cfg.batch_size})", f"{m['sample_s_per_batch'] * 1e3:.2f} ms", ""],
        ["peak resident (VmHWM), build + sample", f"{s['VmHWM'] / mb:,.0f} MB", "target < 1 GB"],
        [
            "RssAnon / RssFile after sampling",
            f"{s['RssAnon'] / mb:,.0f} / {s['RssFile'] / mb:,.0f} MB",
            "",
        ],
        [
            f"fit_bc minibatch, in memory ({cfg.fit_rows:,} rows)",
            f"{m['fit_samples_per_s']['memory']:,.0f} samples/s",
            "1.00",
        ],
        [
            f"fit_bc minibatch, on disk ({cfg.fit_rows:,} rows)",
            f"{m['fit_samples_per_s']['disk']:,.0f} samples/s",
            f"{m['fit_ratio']:.2f} (target >= 0.8)",
        ],
    ]
    for row in table:
        print(" | ".join(row))
    md = (
        f"CartPole-shaped rows in `DemonstrationBuffer(path=...)`; memory from "
        f"/proc/self/status; fits best of {cfg.repeats}.\n\n"
        + _report.table(["what", "value", ""], table)
    )
    payload = {"config": asdict(cfg), **m}
    print("results:", _report.write(NAME, payload, md, out_dir=out_dir))
    return payload


if __name__ == "__main__":
    main()
