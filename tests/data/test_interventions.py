"""intervention_segments (issue 48): the expert's frames kept, each streak an episode."""

from __future__ import annotations

import torch
from tensordict import TensorDict

from imitrl import keys
from imitrl.data.interventions import intervention_segments


def test_each_streak_becomes_an_episode_of_its_own():
    executed = torch.tensor([0, 1, 1, 0, 1, 1, 1, 0, 0, 1], dtype=torch.bool)
    episode = torch.tensor([5, 5, 5, 5, 5, 6, 6, 6, 6, 6])
    step = torch.tensor([0, 1, 2, 3, 4, 0, 1, 2, 3, 4])
    rows = TensorDict({keys.EXPERT_EXECUTED: executed, keys.EPISODE: episode, keys.STEP: step,
                       "x": torch.arange(10)}, batch_size=[10])  # fmt: skip
    out = intervention_segments(rows, 10)
    assert out.get("x").tolist() == [1, 2, 4, 5, 6, 9]
    # episode 5's last frame and episode 6's first are two streaks, not one
    assert out.get(keys.EPISODE).tolist() == [10, 10, 11, 12, 12, 13]
    assert out.get(keys.STEP).tolist() == [0, 1, 0, 0, 1, 0]
    none = intervention_segments(rows[~executed], 3)
    assert none.shape[0] == 0


def test_long_streaks_number_their_steps_from_0_on_several_threads():
    """400,000 rows in two streaks, at 2 threads: each segment's first row was found by
    writing many values to one index, whose winner torch leaves open on several threads
    (steps from -200000 on 12 of 20 calls; 18 of 20 when measured here)."""
    n = 400_000
    executed = torch.ones(n, dtype=torch.bool)
    executed[399_000] = False  # two streaks
    rows = TensorDict(
        {
            keys.EXPERT_EXECUTED: executed,
            keys.EPISODE: torch.zeros(n, dtype=torch.long),
            keys.STEP: torch.arange(n),
        },
        [n],
    )
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        for _ in range(5):
            kept = intervention_segments(rows, 7)
            episode, step = kept.get(keys.EPISODE), kept.get(keys.STEP)
            sizes = [399_000, 999]
            assert torch.equal(
                episode, torch.repeat_interleave(torch.tensor([7, 8]), torch.tensor(sizes))
            )
            assert torch.equal(step, torch.cat([torch.arange(s) for s in sizes]))
    finally:
        torch.set_num_threads(before)
