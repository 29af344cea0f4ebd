"""``Learner.load_state_dict``: the keys naming one shared weight (the policy's and its
loss's ``actor``, the normaliser's) must hold one value (a hostile review: an edited
checkpoint whose copies disagree loaded, and whichever copy torch loaded last won)."""

from __future__ import annotations

import pytest
import torch

from imitrl.envs import make_env
from imitrl.learners import build


@pytest.fixture
def learner():
    return build("for_env", make_env("CartPole-v1", seed=0), hidden=(8,), seed=0)


def test_copies_that_agree_load(learner):
    state = {k: v.clone() for k, v in learner.state_dict().items()}
    state["policy.module.0.module.1.weight"] += 1.0
    state["loss.actor.module.0.module.1.weight"] += 1.0
    learner.load_state_dict(state)
    assert torch.equal(
        learner.policy.module[0].module[1].weight, state["policy.module.0.module.1.weight"]
    )


@pytest.mark.parametrize(
    ("edited", "other"),
    [
        ("loss.actor.module.0.module.1.weight", "policy.module.0.module.1.weight"),
        ("normalizer.scale", "policy.module.0.module.0.scale"),
    ],
)
def test_copies_that_disagree_are_refused_and_nothing_changes(learner, edited, other):
    before = {k: v.clone() for k, v in learner.state_dict().items()}
    state = {k: v.clone() for k, v in before.items()}
    state[edited] = state[edited] + 1.0
    with pytest.raises(ValueError, match="one weight of the learner but hold different") as err:
        learner.load_state_dict(state)
    assert repr(other) in str(err.value) and repr(edited) in str(err.value)
    after = learner.state_dict()
    assert all(torch.equal(after[k], v) for k, v in before.items())
