"""LeRobot datasets bigger than memory: save_lerobot and a streamed load_lerobot, 1M and 10M frames.

CartPole-shaped rows (float32 observations [4], int64 actions, float32 reward, done /
terminated / truncated flags, episodes of 150-250 steps) are built in a disk buffer
(`DemonstrationBuffer(path=...)`) `chunk` rows at a time; then, each in a fresh
subprocess so that its peak is its own, `save_lerobot(buffer, ...)` writes a v3.0 dataset
from the buffer's memory-mapped files and `load_lerobot(..., into=DemonstrationBuffer(
path=...))` streams it back into another disk buffer. Measured: wall time, and the
process's peak resident memory (VmHWM: its own memory and the pages of the files it has
mapped), its peak own memory (RssAnon, sampled every 5 ms) and its own memory at the end
(RssAnon), above what it held after its imports. Target (issue 15): save <= 5 s and
load <= 3 s for 1M frames on 2 cores, memory independent of the frame count (1M vs
10M). The destination buffer of a load keeps up to 64 MB of the pages it wrote mapped
(``imitrl.data.disk.REMAP_BYTES``): 1M frames (57 MB) stay under that bound, 10M reach
it. Progress goes to stderr.

    python benchmarks/scale_datasets.py            # 1M and 10M frames, results/ and README
    python benchmarks/scale_datasets.py --quick    # 200k frames, into a temporary directory
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import _report

NAME = "scale_datasets"


@dataclass(frozen=True)
class Config:
    frames: tuple[int, ...] = (1_000_000, 10_000_000)
    """dataset sizes measured"""
    chunk: int = 500_000
    """rows per `extend` while building the source buffer"""
    seed: int = 0
    """seed of the rows"""


QUICK = Config(frames=(200_000,), chunk=100_000)


def log(*parts: object) -> None:
    print(*parts, file=sys.stderr, flush=True)


# ----------------------------------------------------------- run in a subprocess
CHILD = r"""
import json, sys, threading, time
import torch
torch.set_num_threads(1)
from imitrl import keys
from imitrl.data import DemonstrationBuffer
from imitrl.datasets import load_lerobot, save_lerobot

def memory():
    fields = dict(line.split(":", 1) for line in open("/proc/self/status"))
    return {k: int(fields[k].split()[0]) << 10 for k in ("VmHWM", "RssAnon")}

task, frames, chunk, seed, src, dst = sys.argv[1:7]
frames, chunk, seed = int(frames), int(chunk), int(seed)
before = memory()
peak_anon, done = [before["RssAnon"]], threading.Event()

def sample():  # the process's own memory, without the mapped files' pages (VmHWM has them)
    while not done.is_set():
        peak_anon[0] = max(peak_anon[0], memory()["RssAnon"])
        time.sleep(0.005)

sampler = threading.Thread(target=sample, daemon=True)
sampler.start()
t0 = time.perf_counter()
if task == "build":
    from tensordict import TensorDict
    g = torch.Generator().manual_seed(seed)
    lengths = torch.randint(150, 251, (frames // 150 + 1,), generator=g)
    ends = torch.cumsum(lengths, 0)
    last_episode = int(torch.searchsorted(ends, frames - 1, right=True))
    lengths[last_episode] -= int(ends[last_episode]) - frames  # the last one ends at frames
    ends = torch.cumsum(lengths, 0)
    buf = DemonstrationBuffer(path=dst, capacity=chunk)
    while len(buf) < frames:  # whole episodes per extend
        stop = int(ends[torch.searchsorted(ends, len(buf) + chunk - 1, right=False).clamp(max=last_episode)])
        row = torch.arange(len(buf), min(stop, frames))
        episode = torch.searchsorted(ends, row, right=True)
        step = row - (ends[episode] - lengths[episode])
        n = len(row)
        last = (step == lengths[episode] - 1)[:, None]
        action = torch.randint(0, 2, (n,), generator=g)
        buf.extend(TensorDict({
            keys.OBSERVATION: torch.randn(n, 4, generator=g),
            keys.ACTION: action, keys.EXPERT_ACTION: action.clone(),
            keys.EXPERT_EXECUTED: torch.ones(n, dtype=torch.bool),
            (keys.NEXT, keys.REWARD): torch.ones(n, 1),
            (keys.NEXT, keys.DONE): last.clone(),
            (keys.NEXT, keys.TERMINATED): last.clone(),
            (keys.NEXT, keys.TRUNCATED): torch.zeros(n, 1, dtype=torch.bool),
            keys.EPISODE: episode, keys.ROUND: torch.zeros(n, dtype=torch.long), keys.STEP: step,
        }, [n]))
    out = {"rows": len(buf)}
elif task == "save":
    buf = DemonstrationBuffer(path=src, resume=True)
    save_lerobot(buf, dst, fps=50, episodes_per_file=1000)
    out = {"rows": len(buf)}
else:
    buf = DemonstrationBuffer(path=dst)
    loaded = load_lerobot(src, into=buf)
    out = {"rows": len(buf)}
seconds = time.perf_counter() - t0
done.set()
sampler.join()
after = memory()
out.update(seconds=seconds, peak_bytes=after["VmHWM"] - before["VmHWM"],
           peak_anon_bytes=max(peak_anon[0], after["RssAnon"]) - before["RssAnon"],
           rss_anon_bytes=after["RssAnon"] - before["RssAnon"], imports_bytes=before["VmHWM"])
print(json.dumps(out))
"""


def run(task: str, frames: int, cfg: Config, src: Path, dst: Path) -> dict:
    """One phase in a fresh interpreter: its wall time and memory (JSON on its last line)."""
    cmd = [sys.executable, "-c", CHILD, task, str(frames), str(cfg.chunk), str(cfg.seed)]
    done = subprocess.run([*cmd, str(src), str(dst)], capture_output=True, text=True, check=False)
    if done.returncode:
        raise RuntimeError(f"{task} of {frames:,} frames failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def measure(frames: int, cfg: Config, scratch: Path) -> dict:
    source, dataset, loaded = scratch / "source", scratch / "dataset", scratch / "loaded"
    log(f"{frames:,} frames: building the source disk buffer")
    built = run("build", frames, cfg, Path("-"), source)
    log(f"  built in {built['seconds']:.1f} s; save_lerobot")
    saved = run("save", frames, cfg, source, dataset)
    size = sum(f.stat().st_size for f in dataset.rglob("*") if f.is_file())
    log(f"  saved in {saved['seconds']:.2f} s ({size / 1e6:.0f} MB); load_lerobot(into=)")
    got = run("load", frames, cfg, dataset, loaded)
    log(f"  loaded in {got['seconds']:.2f} s")
    if got["rows"] != frames or saved["rows"] != frames:
        raise RuntimeError(
            f"rows changed: built {frames}, saved {saved['rows']}, got {got['rows']}"
        )
    for path in (source, dataset, loaded):
        shutil.rmtree(path)
    return {"frames": frames, "dataset_bytes": size, "build": built, "save": saved, "load": got}


def main(argv: list[str] | None = None) -> dict:
    args = _report.parser(__doc__).parse_args(argv)
    out_dir = _report.destination(NAME, quick=args.quick, out=args.out)
    cfg = QUICK if args.quick else Config()
    free = shutil.disk_usage(tempfile.gettempdir()).free
    need = max(cfg.frames) * 150  # two disk buffers (~57 B a row) and the dataset
    if free < need:
        raise SystemExit(f"needs about {need / 1e9:.1f} GB free in {tempfile.gettempdir()}")
    results = []
    with tempfile.TemporaryDirectory(prefix=f"{NAME}-") as scratch:
        for frames in cfg.frames:
            results.append(measure(frames, cfg, Path(scratch)))
    mb = 1e6
    rows = []
    for r in results:
        for phase in ("save", "load"):
            m = r[phase]
            rows.append(
                [
                    f"{r['frames']:,}",
                    f"{phase}_lerobot",
                    f"{m['seconds']:.2f} s",
                    f"{r['frames'] / m['seconds'] / 1e6:.2f} M frames/s",
                    f"{m['peak_bytes'] / mb:,.0f} MB",
                    f"{m['peak_anon_bytes'] / mb:,.0f} MB",
                    f"{m['rss_anon_bytes'] / mb:,.0f} MB",
                ]
            )
    header = [
        "frames",
        "call",
        "wall",
        "throughput",
        "peak RSS above imports",
        "peak RssAnon",
        "RssAnon at end",
    ]
    for row in rows:
        print(" | ".join(row))
    md = (
        "CartPole-shaped rows in a disk buffer -> `save_lerobot` (v3.0, 1000 episodes a file) "
        "-> `load_lerobot(into=DemonstrationBuffer(path=...))`, each call in a fresh process "
        "(1 torch thread); memory above what the process held after its imports "
        "(peak RSS counts the pages of mapped files too, up to 64 MB of the pages a load "
        "writes into its disk buffer) "
        f"({results[0]['save']['imports_bytes'] / mb:,.0f} MB).\n\n" + _report.table(header, rows)
    )
    payload = {"config": asdict(cfg), "results": results}
    print("results:", _report.write(NAME, payload, md, out_dir=out_dir))
    return payload


if __name__ == "__main__":
    t0 = time.perf_counter()
    main()
    log(f"total {time.perf_counter() - t0:.0f} s")
