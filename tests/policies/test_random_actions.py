"""Random actions: uniform over the action spec, one draw per lane, from the global RNG
an evaluation seeds (the same seed, the same actions)."""

from __future__ import annotations

import torch
from tensordict import TensorDict
from torchrl.data import Bounded, Categorical

from imitrl import keys
from imitrl.policies.random_actions import RandomActions


def test_draws_are_uniform_in_the_spec_one_per_lane_and_seeded():
    box = RandomActions(Bounded(-2.0, 1.0, (2,)))
    torch.manual_seed(0)
    a = box(TensorDict({}, [4000])).get(keys.ACTION)
    assert a.shape == (4000, 2) and bool((a >= -2.0).all() and (a <= 1.0).all())
    assert abs(a.mean().item() - (-0.5)) < 0.05  # uniform on [-2, 1]: mean -0.5, sd 0.87
    torch.manual_seed(0)
    assert torch.equal(box(TensorDict({}, [4000])).get(keys.ACTION), a)

    counts = torch.bincount(
        RandomActions(Categorical(3))(TensorDict({}, [3000])).get(keys.ACTION), minlength=3
    )
    assert counts.min() > 900 and counts.max() < 1100  # each about 1000 (sd 26)
