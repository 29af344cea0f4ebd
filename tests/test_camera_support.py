"""Library fixes found while writing the README's Cameras section (issue 14)."""

from __future__ import annotations

import torch

from imitrl import keys
from imitrl.data import DemonstrationBuffer, rollout_episodes
from imitrl.data import buffer as buffer_module
from imitrl.envs import episode_limit
from imitrl.envs.pixel_tasks import Hilltop, PixelBalanceEnv, balance_expert


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
