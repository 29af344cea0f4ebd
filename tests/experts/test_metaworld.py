"""The Meta-World expert on LeRobot's observation types: it reads the 39-d state, and a
key holding anything else is refused naming the key to pass (was metaworld's own
``AssertionError: Observation not fully parsed``). Needs the ``metaworld`` extra."""

from __future__ import annotations

import pytest

from imitrl import keys

pytest.importorskip("metaworld")

from imitrl.envs import make_env
from imitrl.experts import metaworld_expert

LEROBOT = {"obs_type": "environment_state_agent_pos"}


def test_on_the_hands_four_numbers_the_expert_names_the_key_of_the_state():
    env = make_env("metaworld/reach-v3", seed=0, env_kwargs=LEROBOT)
    with pytest.raises(ValueError, match=r"holds 4 numbers.*observation_key='environment_state'"):
        metaworld_expert("reach-v3")(env.reset())


def test_given_the_key_of_the_state_it_labels_every_lane():
    env = make_env("metaworld/reach-v3", seed=0, env_kwargs=LEROBOT, num_envs=2)
    out = metaworld_expert("reach-v3", observation_key=keys.ENVIRONMENT_STATE)(env.reset())
    label = out.get(keys.EXPERT_ACTION)
    assert label.shape == (2, 4) and bool(label.abs().le(1.0).all())
