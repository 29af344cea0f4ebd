"""Buffer checkpoint size and save/load time: 1e7 CartPole rows on disk are the rows.

A `DemonstrationBuffer` holds one real CartPole-v1 episode (the built-in expert, through
`rollout_episodes`) and then CartPole-shaped rows filled from tensors up to `rows` in
total; the real episode fixes the schema and every filled chunk must match it (the
buffer's `extend` refuses anything else). The buffer grows by doubling, as in a DAgger
run, so its capacity exceeds its rows. Measured: the checkpoint's bytes on disk
against the rows' bytes and the capacity's bytes (what the previous format, a dump of
the whole storage, wrote), and the wall time of `save` (write, SHA-256, fsync, atomic
rename) and `load` (verify every file, read, the buffer's checks), best of `repeats`.
The load runs with the files in the page cache, right after a save.

    python benchmarks/checkpoint_size.py            # 1e7 rows, refreshes README
    python benchmarks/checkpoint_size.py --quick    # 1e5 rows, into a temporary directory
"""

from __future__ import annotations

import logging
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from tensordict import TensorDict
from torchrl.envs import GymEnv

import _report
from _common import DET, rollout
from imitrl import keys
from imitrl.data import DemonstrationBuffer
from imitrl.experts import cartpole_expert

NAME = "checkpoint_size"


@dataclass(frozen=True)
class Config:
    rows: int = 10_000_000
    """rows in the buffer (one real episode, the rest filled from tensors)"""
    chunk: int = 1_000_000
    """rows per filled `extend` (the buffer grows by doubling between them)"""
    episode_length: int = 500
    """steps per filled episode (CartPole-v1's time limit)"""
    repeats: int = 3
    """save/load timings: best of this many"""
    seed: int = 0
    """seed of the env and of the filled values"""


QUICK = Config(rows=100_000, chunk=25_000, repeats=2)
"""two repeats: the smoke run saves twice, as the full run does (a second save into one
folder was refused, and only full runs found it)"""


def filled_rows(n: int, first_episode: int, cfg: Config, g: torch.Generator) -> TensorDict:
    """``n`` CartPole-shaped rows (the keys, dtypes and shapes ``rollout_episodes`` writes)."""
    step = torch.arange(n) % cfg.episode_length
    last = (step == cfg.episode_length - 1)[:, None]
    action = torch.randint(0, 2, (n,), generator=g)
    return TensorDict(
        {
            keys.OBSERVATION: torch.randn(n, 4, generator=g),
            keys.ACTION: action,
            keys.EXPERT_ACTION: action.clone(),
            keys.EXPERT_EXECUTED: torch.ones(n, dtype=torch.bool),
            (keys.NEXT, keys.REWARD): torch.ones(n, 1),
            (keys.NEXT, keys.DONE): last.clone(),
            (keys.NEXT, keys.TERMINATED): torch.zeros(n, 1, dtype=torch.bool),
            (keys.NEXT, keys.TRUNCATED): last.clone(),
            keys.EPISODE: first_episode + torch.arange(n) // cfg.episode_length,
            keys.ROUND: torch.zeros(n, dtype=torch.long),
            keys.STEP: step,
        },
        [n],
    )


def build(cfg: Config) -> DemonstrationBuffer:
    env = GymEnv("CartPole-v1", categorical_action_encoding=True)
    env.set_seed(cfg.seed)
    buf = DemonstrationBuffer(action_spec=env.action_spec_unbatched)
    buf.extend(rollout(env, cartpole_expert(), 1, exploration=DET, max_steps=500))
    g = torch.Generator().manual_seed(cfg.seed)
    while len(buf) < cfg.rows:
        n = min(cfg.chunk, cfg.rows - len(buf))
        buf.extend(filled_rows(n, buf.next_episode, cfg, g))
    return buf


def measure(buf: DemonstrationBuffer, cfg: Config, where: Path) -> dict:
    saves, loads = [], []
    for i in range(cfg.repeats):
        # a save never replaces a folder (overwrite=False): each repeat a fresh one, the
        # one before it removed untimed
        t0 = time.perf_counter()
        path = buf.save(where / f"ckpt{i}", state={"benchmark": NAME})
        saves.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        loaded, _ = DemonstrationBuffer.load(path)
        loads.append(time.perf_counter() - t0)
        del loaded
        if i + 1 < cfg.repeats:
            shutil.rmtree(path)
    loaded, _ = DemonstrationBuffer.load(path)
    assert len(loaded) == len(buf) and bool((loaded.data == buf.data).all()), "rows changed"
    row_bytes = buf.data.bytes()
    return {
        "rows": len(buf),
        "capacity": buf.capacity,
        "bytes_per_row": row_bytes / len(buf),
        "row_bytes": row_bytes,
        "capacity_bytes": row_bytes / len(buf) * buf.capacity,
        "checkpoint_bytes": sum(f.stat().st_size for f in path.iterdir()),
        "checkpoint_files": len(list(path.iterdir())),
        "save_s": min(saves),
        "load_s": min(loads),
        "save_s_all": saves,
        "load_s_all": loads,
    }


def main(argv: list[str] | None = None) -> dict:
    args = _report.parser(__doc__).parse_args(argv)
    out_dir = _report.destination(NAME, quick=args.quick, out=args.out)
    cfg = QUICK if args.quick else Config()
    torch.set_num_threads(1)
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    buf = build(cfg)
    with tempfile.TemporaryDirectory(prefix=f"{NAME}-") as scratch:
        m = measure(buf, cfg, Path(scratch))
    mb = 1e6
    rows = [
        [
            "rows kept (the data)",
            f"{m['row_bytes'] / mb:,.1f} MB",
            f"{m['bytes_per_row']:.0f} B/row",
        ],
        [
            f"storage capacity ({m['capacity']:,} rows; the previous format wrote it all)",
            f"{m['capacity_bytes'] / mb:,.1f} MB",
            "",
        ],
        [
            f"checkpoint on disk ({m['checkpoint_files']} files)",
            f"{m['checkpoint_bytes'] / mb:,.1f} MB",
            f"{m['checkpoint_bytes'] / m['row_bytes']:.4f}x the rows",
        ],
        ["save (write, SHA-256, fsync, atomic rename)", f"{m['save_s']:.2f} s", ""],
        ["load (verify every file, read, check the rows)", f"{m['load_s']:.2f} s", ""],
    ]
    for r in rows:
        print(" | ".join(r))
    md = (
        f"{m['rows']:,} CartPole-v1 rows (one expert episode, the rest filled from tensors), "
        f"saved and loaded best of {cfg.repeats}; the load reads from the page cache.\n\n"
        + _report.table(["what", "size / time", ""], rows)
    )
    payload = {"config": asdict(cfg), **m}
    print("results:", _report.write(NAME, payload, md, out_dir=out_dir))
    return payload


if __name__ == "__main__":
    main()
