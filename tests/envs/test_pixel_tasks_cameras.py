"""Library fixes found while writing the README's Cameras section (issue 14)."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

from imitrl import keys
from imitrl.data import DemonstrationBuffer
from imitrl.data import buffer as buffer_module
from imitrl.envs import episode_limit
from imitrl.envs.pixel_tasks import Hilltop, PixelBalanceEnv, balance_expert
from imitrl.runtime import rollout_episodes


def test_pixel_balance_env_rollouts_need_no_max_steps():
    env = PixelBalanceEnv(pixels=(8, 8), hill=Hilltop(horizon=12), batch_size=(2,), seed=0)
    assert episode_limit(env) == 12
    rows = rollout_episodes(env, balance_expert(), 3)  # the expert holds the ball: truncated
    assert rows.shape[0] == 3 * 12
    assert int(rows.get(keys.STEP).max()) == 11
    assert bool(rows.get(("next", keys.TRUNCATED))[rows.get(keys.STEP) == 11].all())


def test_a_large_disk_extend_is_written_in_slices_and_keeps_every_row(tmp_path, monkeypatch):
    env = PixelBalanceEnv(pixels=(8, 8), hill=Hilltop(horizon=10), seed=0)
    rows = rollout_episodes(env, balance_expert(), 3)  # 30 rows of 8x8x3 pixels + state
    row_bytes = sum(v[0].nbytes for v in rows.values(include_nested=True, leaves_only=True))
    monkeypatch.setattr(buffer_module, "CHUNK_BYTES", 4 * row_bytes)  # slices of 4 rows
    disk = DemonstrationBuffer(path=tmp_path / "buf", capacity=2)
    index = disk.extend(rows)
    assert torch.equal(index, torch.arange(30))
    # grown slice by slice (2 -> 4 -> 8 -> 16 -> 32), not once to the 30 rows of one write
    assert disk.capacity == 32
    assert (disk.data == rows).all() and disk.num_episodes == 3 and disk.next_episode == 3
    second = DemonstrationBuffer(path=tmp_path / "buf2", capacity=2)
    second.extend(rows[:10])  # episode 0, then the rest in slices after it
    assert torch.equal(second.extend(rows[10:].clone()), torch.arange(10, 30))
    assert (second.data == rows).all()


_SOURCE_SCRIPT = r"""
import os, sys, torch
from tensordict import TensorDict, MemoryMappedTensor
from imitrl import keys
import imitrl.data.buffer as B
if sys.argv[2] == "off":
    B.release_pages = lambda rows: None
def hwm():
    return next(int(l.split()[1]) for l in open("/proc/self/status") if l.startswith("VmHWM")) * 1024
n, root = 36_000, sys.argv[1]
path = os.path.join(root, "frames.uint8")
with open(path, "wb") as f:
    f.truncate(n * 96 * 96 * 3)
pix = MemoryMappedTensor.from_filename(path, dtype=torch.uint8, shape=torch.Size([n, 96, 96, 3]))
z = torch.zeros(n, dtype=torch.int64)
rows = TensorDict({keys.PIXELS: pix, keys.EXPERT_ACTION: z, keys.ACTION: z,
    keys.EXPERT_EXECUTED: torch.ones(n, dtype=torch.bool), keys.EPISODE: torch.arange(n) // 500,
    keys.ROUND: z, keys.STEP: torch.arange(n) % 500}, [n])
before = hwm()
B.DemonstrationBuffer(path=os.path.join(root, "buf")).extend(rows)
print(hwm() - before, pix.numel())
"""


@pytest.mark.parametrize(
    "release", ["on", pytest.param("off", marks=pytest.mark.slow)]
)  # off: the control
def test_extending_from_a_memory_mapped_source_does_not_keep_it_resident(tmp_path, release):
    """Frames decoded into a file (``load_lerobot(decode_dir=...)``) copied into a disk
    buffer: the source's pages are let go slice by slice, so the peak resident set grows
    by a fraction of the 1 GB source (a fixed ~250 MB: the destination pages written between remaps) (without the release, by all of it: the control)."""
    # a fresh interpreter: its resident set is its own (a fork shares the server's pages)
    proc = subprocess.run(
        [sys.executable, "-c", _SOURCE_SCRIPT, str(tmp_path), release],
        capture_output=True, text=True, timeout=300, check=True,
    )  # fmt: skip
    growth, source = map(int, proc.stdout.split()[-2:])
    if release == "on":
        assert growth < source / 2, (
            f"peak grew {growth / 1e6:.0f} MB for a {source / 1e6:.0f} MB source"
        )
    else:
        assert growth > source * 0.9  # the control: the mechanism is what keeps it low
